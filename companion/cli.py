"""The `companion` command: run the service, check a config, simulate or fly a scenario,
sweep random worlds.

Bad input is refused before any work starts, with one line naming the problem and exit code 2.
Arguments say what they hold through their `type=` (`InputFile`, `ScenarioFile`, `OutputDir`,
`Connection`, ...): the type checks the text when the command line is parsed, and types with a
`preflight(value)` check more (load a scenario and its world, create the output directory)
once parsing is done, before the command runs. A subcommand with a `no_plots` option gets
the matplotlib check. New subcommands get all of this by using the same types.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import os
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

LOG_LEVELS = ("debug", "info", "warning", "error")


class CliError(Exception):
    """Bad input: one line for stderr, exit code 2."""


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line (and exit 2)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


# --- argument types ------------------------------------------------------------------------


class InputFile:
    """A file that must exist and be readable (checked at parse time)."""

    what = "file"

    def __call__(self, text: str) -> Path:
        path = Path(text)
        if not path.exists():
            raise argparse.ArgumentTypeError(f"{self.what} {text}: no such file")
        if not path.is_file():
            raise argparse.ArgumentTypeError(f"{self.what} {text}: not a file")
        if not os.access(path, os.R_OK):
            raise argparse.ArgumentTypeError(f"{self.what} {text}: not readable")
        return path

    def __repr__(self) -> str:  # argparse names the type in some messages
        return self.what


class ConfigFile(InputFile):
    """A service config file (validated by the command itself, with every problem listed)."""

    what = "config file"


class ScenarioFile(InputFile):
    """A scenario YAML file; before the command runs, the scenario and its world are loaded
    (so a bad key, a missing, corrupt, 1-D or NaN height map is refused up front)."""

    what = "scenario"

    def preflight(self, path: Path) -> None:
        from companion.sim.scenario import ScenarioError, load_scenario
        from companion.sim.world import World

        try:
            scenario = load_scenario(path)
            World.from_config(scenario.world, path.parent)
        except ScenarioError as exc:
            raise CliError(str(exc)) from None
        except (ValueError, OSError, EOFError) as exc:
            raise CliError(f"{path}: {exc}") from None


class FlightLogFile(InputFile):
    """A flight log (.jsonl) written by the service: its first record must be the header."""

    what = "flight log"

    def preflight(self, path: Path) -> None:
        try:
            with path.open(encoding="utf-8") as f:
                first = next((line for line in f if line.strip()), "")
            rec = json.loads(first) if first else None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise CliError(f"flight log {path}: not a flight log ({exc})") from None
        if not isinstance(rec, dict) or rec.get("type") != "header":
            raise CliError(f"flight log {path}: not a flight log (no header record)")


class OutputDir:
    """A directory to write into. At parse time: not an existing file, and its nearest
    existing parent is a directory. Before the command runs: created and a file written and
    removed there (catches read-only places and /proc as root too)."""

    def __call__(self, text: str) -> Path:
        path = Path(text)
        if path.exists() and not path.is_dir():
            raise argparse.ArgumentTypeError(
                f"output directory {text}: exists and is not a directory"
            )
        parent = path.absolute().parent
        while not parent.exists():
            parent = parent.parent
        if not parent.is_dir():
            raise argparse.ArgumentTypeError(f"output directory {text}: {parent} is a file")
        return path

    def __repr__(self) -> str:
        return "output directory"

    def preflight(self, path: Path) -> None:
        try:
            path.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryFile(dir=path):
                pass
        except OSError as exc:
            raise CliError(
                f"output directory {path}: cannot write there ({exc.strerror or exc})"
            ) from None


class Connection:
    """A connection string (pymavlink or MAVSDK form), parsed by the service's one parser."""

    def __call__(self, text: str) -> str:
        from companion.service.link import parse_connection

        try:
            return str(parse_connection(text))
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    def __repr__(self) -> str:
        return "connection"


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("terrain-companion")
    except PackageNotFoundError:
        return "unknown (not installed)"


# --- the parser ----------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="companion",
        description="Terrain-following, obstacle-avoiding path planning for ArduPilot and PX4.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser("run", help="run the companion service against an autopilot")
    run.add_argument("--config", type=ConfigFile(), required=True, help="service YAML file")
    run.add_argument(
        "--connection", type=Connection(), help="override the config's link.connection"
    )
    run.add_argument(
        "--quiet",
        action="store_true",
        help="no live status line (there is none when stderr is not a terminal)",
    )
    run.add_argument(
        "--persist-params",
        action="store_true",
        help="write parameter changes made in flight (PARAM_SET) back into the config file",
    )

    check = sub.add_parser("check-config", help="validate a service config file and exit")
    check.add_argument("config", type=ConfigFile())
    check.add_argument(
        "--connection", type=Connection(), help="override the config's link.connection"
    )

    simulate = sub.add_parser(
        "simulate", help="fly a scenario in process (no MAVLink) and write metrics and plots"
    )
    simulate.add_argument("scenario", type=ScenarioFile(), help="scenario YAML file")
    simulate.add_argument("--out", type=OutputDir(), required=True, help="output directory")
    simulate.add_argument("--no-plots", action="store_true", help="skip the figures")
    simulate.add_argument(
        "--json", action="store_true", help="print the metrics as JSON on stdout (text: stderr)"
    )

    fly = sub.add_parser(
        "fly",
        help="fly a scenario through the service against the MAVLink simulator over UDP",
    )
    fly.add_argument("scenario", type=ScenarioFile(), help="scenario YAML file")
    fly.add_argument("--out", type=OutputDir(), required=True, help="output directory")
    fly.add_argument(
        "--autopilot",
        choices=("ardupilot", "px4", "ardusub"),
        default=None,
        help="simulator personality (default: the scenario's, else ardupilot)",
    )
    fly.add_argument("--no-plots", action="store_true", help="skip the figures")
    fly.add_argument(
        "--json", action="store_true", help="print the metrics as JSON on stdout (text: stderr)"
    )

    sweep = sub.add_parser(
        "sweep",
        help="fly many seeded random worlds (seeds x layouts x vehicles) and summarise",
        description="Fly seeded random worlds (companion.sim.worldgen) in process, in parallel, "
        "and write results.csv (row by row), summary.txt, failures.txt and, per failure, its "
        "scenario file and figures. See docs/scenarios.md.",
    )
    sweep.add_argument(
        "--seeds", required=True, help="N, A:B (A..B-1) or a comma list of those, e.g. 0:100"
    )
    sweep.add_argument(
        "--layout",
        action="append",
        default=None,
        help="sensor layout: a name in config/sensors (paper-11, horizontal-7, ring-8) or a "
        "YAML file; repeat or comma-separate (default: those three)",
    )
    sweep.add_argument(
        "--vehicle",
        action="append",
        default=None,
        help="vehicle model: ideal, multicopter; repeat or comma-separate (default: both)",
    )
    sweep.add_argument(
        "--fault",
        action="append",
        default=None,
        help="sensor fault on every sensor: none, noise, dropout, spikes (default: none)",
    )
    sweep.add_argument("--out", type=Path, default=Path("out/sweep"), help="output directory")
    sweep.add_argument(
        "--workers", type=int, default=2, help="parallel processes (default 2; 1: in process)"
    )
    sweep.add_argument(
        "--ray",
        nargs="?",
        const="local",
        default=None,
        metavar="ADDRESS",
        help="run on Ray: a local instance, or the cluster at ADDRESS (HOST:PORT, "
        "ray://HOST:PORT or auto); needs the [ray] extra",
    )
    sweep.add_argument(
        "--resume", action="store_true", help="keep DIR/results.csv and skip the runs in it"
    )
    sweep.add_argument("--no-figures", action="store_true", help="no figures of failures")
    sweep.add_argument(
        "--write-scenarios",
        action="store_true",
        help="only write each world as a scenario file in DIR (no flight)",
    )

    report = sub.add_parser("report", help="plots (and metrics) of a flight log")
    report.add_argument(
        "log", type=FlightLogFile(), help="flight log (.jsonl) written by the service"
    )
    report.add_argument("--out", type=OutputDir(), required=True, help="output directory")
    report.add_argument(
        "--scenario", type=ScenarioFile(), default=None, help="the scenario it was flown in"
    )
    report.add_argument("--no-plots", action="store_true", help="skip the figures")

    for command in sub.choices.values():  # every subcommand, present and future
        command.add_argument(
            "-v", "--verbose", action="count", default=0, help="log more (-v info, -vv debug)"
        )
        command.add_argument(
            "--log-level", choices=LOG_LEVELS, default=None, help="log at this level"
        )
    parser.set_defaults(_subparsers=sub)
    return parser


def preflight(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Check the chosen subcommand's arguments before any work; CliError names the problem."""
    sub = getattr(args, "_subparsers", None)
    command = sub.choices.get(args.command) if sub is not None else None
    if command is None:
        return
    for action in command._actions:
        check = getattr(action.type, "preflight", None)
        value = getattr(args, action.dest, None)
        if check is not None and value is not None:
            check(value)
    if getattr(args, "no_plots", True) is False and importlib.util.find_spec("matplotlib") is None:
        raise CliError(
            "figures need matplotlib: pip install 'terrain-companion[plots]', or add --no-plots"
        )


def _print_metrics_json(out_dir: Path) -> None:
    """The metrics document the command wrote (DIR/metrics.json), on stdout."""
    sys.stdout.write((out_dir / "metrics.json").read_text(encoding="utf-8"))
    sys.stdout.flush()


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        preflight(parser, args)
    except CliError as exc:
        print(f"companion {args.command}: error: {exc}", file=sys.stderr)
        return 2
    if args.log_level is None and args.verbose:
        args.log_level = "debug" if args.verbose > 1 else "info"
    if args.command != "run":
        logging.basicConfig(
            level=(args.log_level or "warning").upper(),
            format="%(levelname)s %(name)s: %(message)s",
            stream=sys.stderr,
        )
    text: Any = sys.stderr if getattr(args, "json", False) else sys.stdout
    try:
        if args.command == "run":
            from companion.service import main as service_main

            return service_main(
                args.config,
                args.connection,
                args.log_level,
                quiet=args.quiet,
                persist_params=args.persist_params,
            )
        if args.command == "check-config":
            from companion.config import check_config

            return check_config(args.config, connection=args.connection)
        if args.command == "simulate":
            from companion.harness.runner import simulate
            from companion.sim.scenario import ScenarioError

            try:
                code = simulate(args.scenario, args.out, plots=not args.no_plots, stream=text)
            except ScenarioError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 2
            if args.json:
                _print_metrics_json(args.out)
            return code
        if args.command == "sweep":
            from companion.harness.sweep import (
                DEFAULT_LAYOUTS,
                VEHICLES,
                SweepError,
                SweepOptions,
                sweep,
            )

            def items(values: list[str] | None, default: tuple[str, ...]) -> tuple[str, ...]:
                if not values:
                    return default
                return tuple(v.strip() for arg in values for v in arg.split(",") if v.strip())

            opts = SweepOptions(
                seeds=args.seeds,
                layouts=items(args.layout, DEFAULT_LAYOUTS),
                vehicles=items(args.vehicle, VEHICLES),
                faults=items(args.fault, ("none",)),
                out=args.out,
                workers=args.workers,
                ray=args.ray,
                resume=args.resume,
                figures=not args.no_figures,
                write_scenarios=args.write_scenarios,
            )
            try:
                return sweep(opts)
            except SweepError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 2
        if args.command == "report":
            from companion.harness.fly import report

            return report(args.log, args.out, args.scenario, plots=not args.no_plots)
        if args.command == "fly":
            from companion.harness.fly import fly
            from companion.sim.scenario import ScenarioError

            try:
                code = fly(
                    args.scenario,
                    args.out,
                    args.autopilot,
                    plots=not args.no_plots,
                    stream=text,
                )
            except ScenarioError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 2
            if args.json:
                _print_metrics_json(args.out)
            return code
    except KeyboardInterrupt:
        return 130
    except RuntimeError as exc:  # the run itself failed (e.g. the flight produced no log)
        print(f"companion {args.command}: failed: {exc}", file=sys.stderr)
        return 1
    return 2


if __name__ == "__main__":
    sys.exit(main())
