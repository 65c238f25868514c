"""Fault flights for the reliability suite: the real service against the bundled MAVLink simulator.

`fly_fault(name, seed)` flies a short scenario (a hill and a pillar beside the route) through
the companion service over UDP loopback in lockstep with one fault from `FAULTS` injected, and
returns what happened: the true trajectory's minimum clearance to obstacles and height above
the surface (sampled at every physics tick, not only at planner cycles), the service's
counters, and per flight-log cycle its verdict and setpoint kind, so a test can assert what
the service did (continue, hold, stop commanding, release, resume).

Fault "companion_restart" kills the service mid-flight (its task is cancelled, as SIGKILL
would leave things: no POWEROFF heartbeat, nothing saved) and starts a new Service instance
on a new socket after `RESTART_GAP_S` of simulated time. While no companion answers, the
simulator runs without lockstep (otherwise each tick would wait `lockstep.timeout_s`).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import ServiceConfig
from companion.harness.fly import service_config
from companion.service import Service
from companion.service.flightlog import iter_records
from companion.service.link import UdpOutLink
from companion.service.notify import SystemdNotifier
from companion.sim.mavlink import SimServer
from companion.sim.scenario import Scenario
from companion.sim.world import World

SENSORS_FILE = Path(__file__).resolve().parents[1] / "config" / "sensors" / "paper-11.yaml"

D_MIN_M = 2.0
H_D_M = 2.0
GOAL_X_M = 28.0
DURATION_S = 48.0
"""Take-off (~4 s) plus ~30 m at 1 m/s with a detour round the pillar, and some margin."""
RESTART_GAP_S = 3.0


def scenario(mavlink: dict[str, Any] | None = None) -> Scenario:
    """A 28 m route over a small hill, with a pillar 0.5 m left of the route at x = 17 m."""
    import yaml

    sensors = yaml.safe_load(SENSORS_FILE.read_text())
    return Scenario.model_validate(
        {
            "name": "reliability",
            "description": "short route: a hill, then a pillar just left of the route",
            "duration_s": DURATION_S,
            "dt_s": 0.05,
            "world": {
                "features": [
                    {
                        "type": "gaussian_hill",
                        "name": "hill",
                        "center": [8.0, -3.0],
                        "height_m": 1.5,
                        "sigma_m": 4.0,
                    },
                    {
                        "type": "cylinder",
                        "name": "pillar",
                        "center": [17.0, 0.5],
                        "radius_m": 1.0,
                        "height_m": 8.0,
                    },
                ]
            },
            "route": {
                "points": [[0.0, 0.0], [GOAL_X_M, 0.0]],
                "start_heading_deg": 0.0,
                "arrival_heading_deg": 0.0,
            },
            "vehicle": {"model": "ideal"},
            "sensors": sensors,
            "planner": {"h_d_m": H_D_M, "d_min_m": D_MIN_M, "phi_max_rad": 0.6, "v_d_mps": 1.0},
            "mavlink": mavlink,
        }
    )


# --- the faults ----------------------------------------------------------------------------

IN_FLIGHT = [[8.0, DURATION_S]]
"""Link faults from take-over on: the service's command timeouts are wall-clock time, so in a
simulation running ~8x faster than real time a lost ack during start-up costs ~8 simulated
seconds per retry (start-up under loss is tested separately)."""


def fault_time(seed: int) -> float:
    """When a scheduled fault strikes: 10-24 s, i.e. before, at and after the pillar
    (passed at ~17-25 s), varied with the seed."""
    return 10.0 + (seed * 3.7) % 14.0


def _link(**probabilities: float) -> dict[str, Any]:
    one = {**probabilities, "windows": IN_FLIGHT}
    return {"outgoing": one, "incoming": one}


FAULTS: dict[str, Callable[[float], dict[str, Any]]] = {
    "none": lambda t0: {},
    "sensor_dropouts": lambda t0: {"sensors": [{"dropout_probability": 0.2}]},
    "sensor_dropout_window": lambda t0: {
        "sensors": [{"sensor_id": 8, "dropout_windows": [[t0, t0 + 2.0]]}]
    },
    "stuck_range": lambda t0: {"sensors": [{"sensor_id": 2, "stuck_windows": [[t0 - 4, t0 + 6]]}]},
    "stuck_surface": lambda t0: {
        "sensors": [{"sensor_id": 7, "stuck_windows": [[t0 - 4, t0 + 1]]}]
    },
    "spikes": lambda t0: {"sensors": [{"spike_probability": 0.01}]},
    "spikes_close": lambda t0: {
        "sensors": [{"spike_probability": 0.005, "spike_range_m": [0.3, 1.0]}]
    },
    "noise": lambda t0: {"sensors": [{"noise_std_m": 0.05}]},
    "gps_glitch": lambda t0: {
        "position_jumps": [{"at_s": t0, "offset_m": [8.0, -6.0, 3.0], "duration_s": 0.4}]
    },
    "gps_reset": lambda t0: {"position_jumps": [{"at_s": t0, "offset_m": GPS_RESET_M}]},
    "loss_5": lambda t0: _link(loss_probability=0.05),
    "loss_20": lambda t0: _link(loss_probability=0.2),
    "dup_reorder": lambda t0: _link(duplicate_probability=0.05, reorder_probability=0.05),
    "link_cut_3s": lambda t0: {"link_cuts": [[t0, t0 + 3.0]]},
    "reboot": lambda t0: {"reboots": [{"at_s": t0, "duration_s": 1.0}]},
    "mode_change": lambda t0: {"mode_changes": [{"at_s": t0, "mode": "LOITER"}]},
    "companion_restart": lambda t0: {},
}
"""Fault name -> the simulator's `faults:` section for a fault at t0 (seed added per flight)."""

GPS_RESET_M = (4.0, 3.0, 0.0)

RANDOM_FAULTS = {
    "sensor_dropouts",
    "spikes",
    "spikes_close",
    "noise",
    "loss_5",
    "loss_20",
    "dup_reorder",
}
"""Faults whose draws depend on the seed; for the others the seed moves the fault's time."""


@dataclass
class Cycle:
    t: float
    verdict: str
    sp_kind: str | None
    own: str


@dataclass
class FlightOutcome:
    fault: str
    seed: int
    personality: str
    min_clearance_m: float
    """True 3-D distance to the nearest obstacle over the flight (every physics tick)."""
    min_height_m: float
    """True distance to the surface (terrain or obstacle) once airborne."""
    reached_goal: bool
    final_distance_m: float
    lockstep_stalls: int
    counters: dict[str, int]
    cycles: list[Cycle]
    t0: float = 0.0
    restarts: int = 0
    wall_s: float = 0.0
    truth_t: np.ndarray = field(default_factory=lambda: np.zeros(0))
    truth_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    modes: list[str] = field(default_factory=list)

    @property
    def safe(self) -> bool:
        return self.min_clearance_m >= D_MIN_M - 1e-6 and self.min_height_m > 0.0

    def cycles_between(self, t0: float, t1: float) -> list[Cycle]:
        return [c for c in self.cycles if t0 <= c.t < t1]

    def kinds_between(self, t0: float, t1: float) -> set[str | None]:
        return {c.sp_kind for c in self.cycles_between(t0, t1)}

    def summary(self) -> dict[str, Any]:
        return {
            "fault": self.fault,
            "seed": self.seed,
            "personality": self.personality,
            "min_clearance_m": round(self.min_clearance_m, 3),
            "min_height_m": round(self.min_height_m, 3),
            "reached_goal": self.reached_goal,
            "safe": self.safe,
            "stalls": self.lockstep_stalls,
            "wall_s": round(self.wall_s, 2),
        }


def _config(sc: Scenario, server: SimServer, log_dir: Path) -> ServiceConfig:
    home_xy = np.array(server.autopilot.home_enu[:2], dtype=float)
    return service_config(sc, server.port, home_xy, log_dir)


async def _start_service(cfg: ServiceConfig, port: int) -> tuple[Service, asyncio.Task[int]]:
    svc = Service(cfg, UdpOutLink("127.0.0.1", port), notifier=SystemdNotifier({}))
    return svc, asyncio.create_task(svc.run())


async def _kill(svc: Service, task: asyncio.Task[int]) -> None:
    """As SIGKILL: nothing more is sent, the socket just goes away."""
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError, Exception):
        await task
    await svc.abandon()


async def fly_fault_async(
    fault: str, seed: int, out_dir: Path, personality: str = "ardupilot"
) -> FlightOutcome:
    t0 = fault_time(seed)
    faults = {**FAULTS[fault](t0), "seed": seed}
    sc = scenario({"faults": faults})
    wall0 = time.monotonic()
    server = SimServer.from_scenario(
        sc,
        ".",
        port=0,
        speedup=math.inf,
        lockstep={"enabled": True, "period_s": sc.dt_s},
        prearm_delay_s=0.5,
        personality=personality,
    )
    await server.start()
    log_dirs = [out_dir / "flightlog-0"]
    cfg = _config(sc, server, log_dirs[0])
    svc, task = await _start_service(cfg, server.port)
    restarts = 0
    goal = np.array([GOAL_X_M, 0.0])
    try:
        t = 0.0
        while t < sc.duration_s and not svc.route_finished.is_set():
            step = 1.0
            if fault == "companion_restart" and restarts == 0 and t + step > t0:
                await server.run_until(t0)
                await _kill(svc, task)
                restarts += 1
                lockstep = server._lockstep_ticks
                server._lockstep_ticks = 0  # nobody answers: do not wait for each tick
                await server.run_until(t0 + RESTART_GAP_S)
                server._lockstep_ticks = lockstep
                log_dirs.append(out_dir / f"flightlog-{restarts}")
                cfg = _config(sc, server, log_dirs[-1])
                svc, task = await _start_service(cfg, server.port)
                t = t0 + RESTART_GAP_S
                continue
            t = min(t + step, sc.duration_s)
            await server.run_until(t)
            if task.done():
                break
    finally:
        svc.stop()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(task, 10.0)
        await server.close()
    if task.done() and not task.cancelled() and task.exception() is not None:
        raise RuntimeError(f"service crashed in fault {fault}") from task.exception()

    world = World.from_config(sc.world, ".")
    truth = server.truth
    t_arr = np.array([s.t_s for s in truth])
    xyz = np.array([s.position_enu for s in truth])
    # The surface counts from take-off (first 1.5 m above the terrain) on.
    above = xyz[:, 2] - np.array([float(world.height(x, y)) for x, y in xyz[:, :2]])
    lifted = np.flatnonzero(above >= 1.5)
    airborne = np.zeros(len(xyz), dtype=bool)
    if lifted.size:
        airborne[lifted[0] :] = True
    airborne &= np.array([not s.landed for s in truth])
    clear = np.array([world.obstacle_distance(p) for p in xyz[::2]])
    heights = np.array([world.surface_distance(p) for p in xyz[airborne][::2]])
    cycles: list[Cycle] = []
    for d in log_dirs:
        for path in sorted(d.glob("flight-*.jsonl")):
            cycles += [
                Cycle(float(r["t"]), str(r["verdict"]), r.get("sp_kind"), str(r["own"]))
                for r in iter_records(path)
                if r.get("type") == "cycle"
            ]
    final_xy = xyz[-1, :2]
    return FlightOutcome(
        fault=fault,
        seed=seed,
        personality=personality,
        min_clearance_m=float(clear.min()) if clear.size else math.inf,
        min_height_m=float(heights.min()) if heights.size else math.inf,
        reached_goal=bool(np.hypot(*(final_xy - goal)) < 1.0),
        final_distance_m=float(np.hypot(*(final_xy - goal))),
        lockstep_stalls=server.stats.lockstep_stalls,
        counters=svc.counter_values(),
        cycles=cycles,
        t0=t0,
        restarts=restarts,
        wall_s=time.monotonic() - wall0,
        truth_t=t_arr,
        truth_xyz=xyz,
        modes=[s.mode for s in truth],
    )


def fly_fault(
    fault: str, seed: int, out_dir: Path, personality: str = "ardupilot"
) -> FlightOutcome:
    return asyncio.run(fly_fault_async(fault, seed, out_dir, personality))


# --- the sweep (long run) -------------------------------------------------------------------


def classify(o: FlightOutcome) -> str:
    """What the service did, in a word or two, from its log and counters."""
    c = o.counters
    kinds = {x.sp_kind for x in o.cycles if x.own == "engaged"}
    released = any(x.own == "released" for x in o.cycles)
    parts = []
    if o.restarts:
        parts.append("restarted")
    if "hold" in kinds:
        parts.append("hold")
    if any(x.verdict == "stop" and x.own == "engaged" for x in o.cycles):
        parts.append("stop")
    if c.get("input.position_jump_accepted", 0):
        parts.append("replan")
    if released:
        parts.append("released")
    elif o.reached_goal:
        parts.append("resume" if parts else "continue")
    else:
        parts.append("not finished")
    return "+".join(parts)


def sweep(
    personality: str, seeds: range, out_dir: Path, faults: list[str] | None = None
) -> list[dict[str, Any]]:
    """Every fault x every seed; one summary row per flight (also written as JSON lines)."""
    import json
    import tempfile

    rows = []
    out_dir.mkdir(parents=True, exist_ok=True)
    with (out_dir / f"sweep-{personality}.jsonl").open("w") as f:
        for fault in faults or list(FAULTS):
            for seed in seeds:
                with tempfile.TemporaryDirectory() as d:
                    try:
                        o = fly_fault(fault, seed, Path(d), personality)
                        row = {**o.summary(), "behaviour": classify(o), "t0": o.t0}
                    except Exception as exc:  # a crash is a result too
                        row = {
                            "fault": fault,
                            "seed": seed,
                            "personality": personality,
                            "error": repr(exc),
                            "safe": False,
                        }
                rows.append(row)
                f.write(json.dumps(row) + "\n")
                f.flush()
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    """Markdown: per fault, flights, safe, min clearance, min height, reached, behaviours."""
    from collections import Counter, defaultdict

    by: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        by[r["fault"]].append(r)
    lines = [
        "| fault | flights | safe | min clearance m | min height m | reached goal | "
        "service did (flights) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for fault, rs in by.items():
        ok = [r for r in rs if "error" not in r]
        beh = Counter(r.get("behaviour", "crash") for r in rs)
        lines.append(
            f"| {fault} | {len(rs)} | {sum(bool(r['safe']) for r in rs)} | "
            f"{min((r['min_clearance_m'] for r in ok), default=float('nan')):.2f} | "
            f"{min((r['min_height_m'] for r in ok), default=float('nan')):.2f} | "
            f"{sum(bool(r.get('reached_goal')) for r in ok)} | "
            + ", ".join(f"{k} ({v})" for k, v in beh.most_common())
            + " |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    import argparse
    import logging

    ap = argparse.ArgumentParser(
        description="fault sweep against the bundled simulator (see docs/reliability.md)"
    )
    ap.add_argument("--personality", default="ardupilot")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--faults", default="")
    ap.add_argument("--out", type=Path, default=Path("out/reliability"))
    args = ap.parse_args()
    logging.disable(logging.WARNING)
    result = sweep(
        args.personality,
        range(1, args.seeds + 1),
        args.out,
        args.faults.split(",") if args.faults else None,
    )
    print(table(result))
