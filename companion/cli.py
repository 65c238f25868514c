"""The `companion` command: run the service, check a config, simulate or fly a scenario,
sweep random worlds."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="companion",
        description="Terrain-following, obstacle-avoiding path planning for ArduPilot and PX4.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser("run", help="run the companion service against an autopilot")
    run.add_argument("--config", type=Path, required=True, help="service YAML file")

    check = sub.add_parser("check-config", help="validate a service config file and exit")
    check.add_argument("config", type=Path)

    simulate = sub.add_parser(
        "simulate", help="fly a scenario in process (no MAVLink) and write metrics and plots"
    )
    simulate.add_argument("scenario", type=Path, help="scenario YAML file")
    simulate.add_argument("--out", type=Path, required=True, help="output directory")
    simulate.add_argument("--no-plots", action="store_true", help="skip the figures")

    fly = sub.add_parser(
        "fly",
        help="fly a scenario through the service against the MAVLink simulator over UDP",
    )
    fly.add_argument("scenario", type=Path, help="scenario YAML file")
    fly.add_argument("--out", type=Path, required=True, help="output directory")
    fly.add_argument(
        "--autopilot",
        choices=("ardupilot", "px4", "ardusub"),
        default=None,
        help="simulator personality (default: the scenario's, else ardupilot)",
    )
    fly.add_argument("--no-plots", action="store_true", help="skip the figures")

    sweep = sub.add_parser(
        "sweep",
        help="fly many seeded random worlds (seeds x layouts x vehicles) and summarise",
        description="Fly seeded random worlds (sim/worldgen) in process, in parallel, and "
        "write results.csv (row by row), summary.txt, failures.txt and, per failure, its "
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
    report.add_argument("log", type=Path, help="flight log (.jsonl) written by the service")
    report.add_argument("--out", type=Path, required=True, help="output directory")
    report.add_argument(
        "--scenario", type=Path, default=None, help="the scenario it was flown in (from fly)"
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if args.command == "run":
            from companion.service import main as service_main

            return service_main(args.config)
        if args.command == "check-config":
            from companion.config import check_config

            return check_config(args.config)
        if args.command == "simulate":
            from sim.runner import simulate
            from sim.scenario import ScenarioError

            try:
                return simulate(args.scenario, args.out, plots=not args.no_plots)
            except ScenarioError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 2
        if args.command == "sweep":
            from sim.sweep import DEFAULT_LAYOUTS, VEHICLES, SweepError, SweepOptions, sweep

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
            from sim.fly import report

            return report(args.log, args.out, args.scenario)
        if args.command == "fly":
            from sim.fly import fly
            from sim.scenario import ScenarioError

            try:
                return fly(args.scenario, args.out, args.autopilot, plots=not args.no_plots)
            except ScenarioError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 2
    except KeyboardInterrupt:
        return 130
    return 2


if __name__ == "__main__":
    sys.exit(main())
