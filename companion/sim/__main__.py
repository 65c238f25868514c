"""`python -m companion.sim`: the MAVLink vehicle simulator and the SITL sensor bridge.

    python -m companion.sim serve SCENARIO.yaml [--personality px4] [--port 14580] [--speedup 5]
    python -m companion.sim bridge SCENARIO.yaml --connect udpin:127.0.0.1:14550

Options given here override the scenario's `mavlink:` section. See docs/simulator.md.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import csv
import logging
import math
import sys
from pathlib import Path
from typing import Any

from companion.sim.mavlink.config import MavlinkSimConfig, PersonalityName


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m companion.sim",
        description="A MAVLink vehicle simulator that behaves like ArduPilot or PX4 on the "
        "wire, flying a scenario's world; or a bridge adding virtual range sensors to a real "
        "SITL. Options override the scenario's `mavlink:` section.",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    serve = sub.add_parser(
        "serve",
        help="simulate a vehicle on a UDP port",
        description="Simulate an autopilot + vehicle on UDP. The simulator sends to whichever "
        "address last sent it a datagram (or to --target). Connect a companion with e.g. "
        "udpout:127.0.0.1:PORT.",
    )
    serve.add_argument("scenario", type=Path, help="scenario YAML file")
    serve.add_argument(
        "--personality",
        choices=[p.value for p in PersonalityName],
        help="autopilot to imitate (default: scenario, else ardupilot)",
    )
    serve.add_argument("--bind", metavar="HOST", help="address to listen on (127.0.0.1)")
    serve.add_argument("--port", type=int, help="UDP port to listen on (14580; 0 = any)")
    serve.add_argument("--target", metavar="HOST:PORT", help="always send here")
    serve.add_argument(
        "--speedup", type=float, help="simulated s per wall-clock s (1; inf = as fast as possible)"
    )
    serve.add_argument(
        "--lockstep",
        action="store_true",
        help="advance only when the companion answers each TIMESYNC (see docs)",
    )
    serve.add_argument("--lockstep-period", type=float, metavar="S", help="sim s (0.05)")
    serve.add_argument("--lockstep-timeout", type=float, metavar="S", help="wall s (2.0)")
    serve.add_argument("--physics-dt", type=float, metavar="S", help="tick, sim s (0.01)")
    serve.add_argument("--prearm-delay", type=float, metavar="S", help="sim s after boot (2.0)")
    serve.add_argument("--seed", type=int, help="fault seed")
    serve.add_argument(
        "--duration", type=float, metavar="S", help="stop after this much simulated time"
    )
    serve.add_argument(
        "--mission",
        type=Path,
        metavar="FILE",
        help="start with this mission (QGroundControl .plan or QGC WPL 110 waypoint file)",
    )
    serve.add_argument("--truth-csv", type=Path, help="write the true trajectory here on exit")
    serve.add_argument("-v", "--verbose", action="store_true", help="log more")

    bridge = sub.add_parser(
        "bridge",
        help="add the scenario's range sensors to a real SITL",
        description="Read a real autopilot's pose, ray-cast the scenario's world and send "
        "DISTANCE_SENSOR for its sensors, to the autopilot or straight to the companion.",
    )
    bridge.add_argument("scenario", type=Path, help="scenario YAML file")
    bridge.add_argument(
        "--connect",
        metavar="URL",
        help="autopilot stream: udpin:HOST:PORT, udpout:HOST:PORT or tcp:HOST:PORT",
    )
    bridge.add_argument("--send-to", choices=["autopilot", "companion"])
    bridge.add_argument("--companion", metavar="HOST:PORT", help="for --send-to companion")
    bridge.add_argument("--rate", type=float, metavar="HZ", help="wall-clock rate (10)")
    bridge.add_argument("--duration", type=float, metavar="S", help="stop after S wall seconds")
    bridge.add_argument("-v", "--verbose", action="store_true", help="log more")

    return parser


def _config(scenario: Any, overrides: dict[str, Any]) -> MavlinkSimConfig:
    raw = scenario.mavlink or {}
    base = raw.model_dump() if isinstance(raw, MavlinkSimConfig) else dict(raw)
    merged: dict[str, Any] = {**base}
    for key, value in overrides.items():
        if value is None:
            continue
        section, _, field = key.partition(".")
        if field:
            merged[section] = {**merged.get(section, {}), field: value}
        else:
            merged[key] = value
    return MavlinkSimConfig.model_validate(merged)


def _serve(args: argparse.Namespace) -> int:
    from companion.sim.mavlink.server import SimServer
    from companion.sim.scenario import load_scenario

    scenario = load_scenario(args.scenario)
    config = _config(
        scenario,
        {
            "personality": args.personality,
            "bind_host": args.bind,
            "port": args.port,
            "target": args.target,
            "speedup": args.speedup,
            "physics_dt_s": args.physics_dt,
            "prearm_delay_s": args.prearm_delay,
            "lockstep.enabled": True if args.lockstep else None,
            "lockstep.period_s": args.lockstep_period,
            "lockstep.timeout_s": args.lockstep_timeout,
            "faults.seed": args.seed,
        },
    )
    server = SimServer.from_scenario(
        scenario.model_copy(update={"mavlink": config.model_dump()}), args.scenario.parent
    )
    if args.mission is not None:
        from companion.sim.mavlink.missionfile import MissionFileError, load_mission

        try:
            items = load_mission(args.mission, server.personality.has_home_mission_item)
        except MissionFileError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        server.mission.load(items)
        print(f"mission: {len(items)} items from {args.mission}", flush=True)
    duration = args.duration if args.duration is not None else math.inf

    async def main() -> None:
        await server.start()
        print(
            f"{config.personality.value} simulator on udp {config.bind_host}:{server.port} "
            f"(speed-up {config.speedup}, lockstep {'on' if config.lockstep.enabled else 'off'})",
            flush=True,
        )
        try:
            await server.run_until(duration)
        finally:
            await server.close()

    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(main())
    if args.truth_csv is not None:
        _write_truth(server.truth, args.truth_csv)
    s = server.stats
    print(
        f"t = {server.t_s:.2f} s, sent {s.sent}, received {s.received}, "
        f"lockstep stalls {s.lockstep_stalls}"
    )
    return 0


def _write_truth(truth: Any, path: Path) -> None:
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(
            [
                "t_s",
                "x_m",
                "y_m",
                "z_m",
                "roll_rad",
                "pitch_rad",
                "yaw_rad",
                "mode",
                "armed",
                "landed",
            ]
        )
        for s in truth:
            w.writerow(
                [
                    f"{s.t_s:.3f}",
                    *(f"{v:.4f}" for v in s.position_enu),
                    f"{s.roll_rad:.5f}",
                    f"{s.pitch_rad:.5f}",
                    f"{s.yaw_rad:.5f}",
                    s.mode,
                    int(s.armed),
                    int(s.landed),
                ]
            )


def _bridge(args: argparse.Namespace) -> int:
    from companion.sim.mavlink.bridge import SensorBridge
    from companion.sim.scenario import load_scenario
    from companion.sim.world import World

    scenario = load_scenario(args.scenario)
    config = _config(
        scenario,
        {
            "bridge.connect": args.connect,
            "bridge.send_to": args.send_to,
            "bridge.companion_address": args.companion,
            "bridge.rate_hz": args.rate,
        },
    ).bridge
    world = World.from_config(scenario.world, args.scenario.parent)
    bridge = SensorBridge(config, world, [s.to_spec() for s in scenario.sensors])

    async def main() -> None:
        await bridge.start()
        print(f"bridge: reading {config.connect}, DISTANCE_SENSOR to {config.send_to}", flush=True)
        try:
            await bridge.run(args.duration)
        finally:
            await bridge.close()

    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(main())
    print(f"sent {bridge.sent} messages")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )
    try:
        return _serve(args) if args.command == "serve" else _bridge(args)
    except ValueError as exc:  # ScenarioError and config validation: say what is wrong
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
