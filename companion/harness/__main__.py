"""`python -m companion.harness`: flights that need more than the simulator.

    python -m companion.harness sitl SCENARIO.yaml [--sensors-to autopilot] --out out/sitl

`sitl` starts the real ArduCopter SITL of `../shared/sitl/`, the sensor bridge and the
companion service, flies the scenario's route and prints the metrics (docs/simulator.md,
"Real SITL in the tests").
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m companion.harness", description=__doc__.split("\n")[0]
    )
    sub = parser.add_subparsers(dest="command", required=True)
    sitl = sub.add_parser(
        "sitl",
        help="fly a scenario with the companion service on the real ArduCopter SITL",
        description="Start ../shared/sitl/arducopter-sitl, the sensor bridge and the service "
        "(auto start), fly the scenario's route and print the metrics, the truth being the "
        "pose SITL reports.",
    )
    sitl.add_argument("scenario", type=Path, help="scenario YAML file")
    sitl.add_argument(
        "--sensors-to",
        choices=["companion", "autopilot"],
        default="companion",
        help="bridge sends DISTANCE_SENSOR to the companion (default) or feeds SITL's MAVLink "
        "rangefinders/proximity, the companion reading SITL's re-reports",
    )
    sitl.add_argument(
        "--sensors", type=Path, metavar="FILE", help="sensor table replacing the scenario's"
    )
    sitl.add_argument(
        "--autopilot",
        choices=["arducopter", "px4"],
        default="arducopter",
        help="which SITL: ../shared/sitl/arducopter-sitl (default) or PX4 with SIH physics "
        "(../shared/sitl/px4/px4-sitl)",
    )
    sitl.add_argument(
        "--instance",
        type=int,
        default=0,
        help="SITL instance (ArduCopter: TCP 5762+10*I; PX4: 0-9, UDP 14540+I)",
    )
    sitl.add_argument("--speedup", type=float, default=1.0, help="SITL speed-up (1)")
    sitl.add_argument("--default-ekf", action="store_true", help="EKF3 as shipped (no --fast-ekf)")
    sitl.add_argument("--out", type=Path, default=Path("out/sitl"), help="output directory")
    sitl.add_argument("-v", "--verbose", action="store_true", help="log more")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )
    from companion.harness.sitl import run_cli

    try:
        return run_cli(
            args.scenario,
            args.out,
            args.sensors_to,
            args.instance,
            args.speedup,
            not args.default_ekf,
            args.sensors,
            autopilot=args.autopilot,
        )
    except ValueError as exc:  # ScenarioError and config validation: say what is wrong
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
