"""The `companion` command: run the service, check a config, simulate or fly a scenario."""

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
