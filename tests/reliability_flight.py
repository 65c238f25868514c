"""Fault flights for the reliability suite: the real service against sim/'s MAVLink simulator.

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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import ServiceConfig
from companion.service import Service
from companion.service.flightlog import iter_records
from companion.service.link import UdpOutLink
from companion.service.notify import SystemdNotifier
from sim.fly import service_config
from sim.mavlink import SimServer
from sim.scenario import Scenario
from sim.world import World

SENSORS_FILE = Path(__file__).resolve().parents[1] / "config" / "sensors" / "paper-11.yaml"

D_MIN_M = 2.0
H_D_M = 2.0
GOAL_X_M = 28.0
DURATION_S = 48.0
"""Take-off (~4 s) plus ~30 m at 1 m/s with a detour round the pillar, and some margin."""
FAULT_AT_S = 14.0
"""Faults start here: the vehicle is in the air, on the route, before the pillar."""
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

T0 = FAULT_AT_S
IN_FLIGHT = [[8.0, DURATION_S]]
"""Link faults from take-over on: the service's command timeouts are wall-clock time, so in a
simulation running ~8x faster than real time a lost ack during start-up costs ~8 simulated
seconds per retry (start-up under loss is tested separately)."""

FAULTS: dict[str, dict[str, Any]] = {
    "none": {},
    "sensor_dropouts": {"sensors": [{"dropout_probability": 0.2}]},
    "sensor_dropout_window": {"sensors": [{"sensor_id": 8, "dropout_windows": [[T0, T0 + 2]]}]},
    "stuck_range": {"sensors": [{"sensor_id": 2, "stuck_windows": [[T0 - 4, T0 + 6]]}]},
    "stuck_surface": {"sensors": [{"sensor_id": 7, "stuck_windows": [[T0 - 8, T0 - 3]]}]},
    "spikes": {"sensors": [{"spike_probability": 0.01}]},
    "spikes_close": {"sensors": [{"spike_probability": 0.005, "spike_range_m": [0.3, 1.0]}]},
    "noise": {"sensors": [{"noise_std_m": 0.05}]},
    "gps_glitch": {
        "position_jumps": [{"at_s": T0, "offset_m": [8.0, -6.0, 3.0], "duration_s": 0.4}]
    },
    "gps_reset": {"position_jumps": [{"at_s": T0, "offset_m": [4.0, 3.0, 0.0]}]},
    "loss_5": {
        "outgoing": {"loss_probability": 0.05, "windows": IN_FLIGHT},
        "incoming": {"loss_probability": 0.05, "windows": IN_FLIGHT},
    },
    "loss_20": {
        "outgoing": {"loss_probability": 0.2, "windows": IN_FLIGHT},
        "incoming": {"loss_probability": 0.2, "windows": IN_FLIGHT},
    },
    "dup_reorder": {
        "outgoing": {
            "duplicate_probability": 0.05,
            "reorder_probability": 0.05,
            "windows": IN_FLIGHT,
        },
        "incoming": {
            "duplicate_probability": 0.05,
            "reorder_probability": 0.05,
            "windows": IN_FLIGHT,
        },
    },
    "link_cut_3s": {"link_cuts": [[T0, T0 + 3]]},
    "reboot": {"reboots": [{"at_s": T0, "duration_s": 1.0}]},
    "mode_change": {"mode_changes": [{"at_s": T0, "mode": "LOITER"}]},
    "companion_restart": {},
}
"""Fault name -> the simulator's `faults:` section (seed added per flight)."""

RANDOM_FAULTS = {
    "sensor_dropouts",
    "spikes",
    "noise",
    "loss_5",
    "loss_20",
    "dup_reorder",
}
"""Faults whose effect depends on the seed; the others are scheduled (the seed still varies
the start heading jitter, see `fly_fault`)."""


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
    for t in svc._tasks:
        t.cancel()
    with contextlib.suppress(Exception):
        await svc.conn.close()
    if svc.flight_log is not None:
        svc.flight_log.close()


async def fly_fault_async(
    fault: str, seed: int, out_dir: Path, personality: str = "ardupilot"
) -> FlightOutcome:
    faults = {**FAULTS[fault], "seed": seed}
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
            if fault == "companion_restart" and restarts == 0 and t + step > FAULT_AT_S:
                await server.run_until(FAULT_AT_S)
                await _kill(svc, task)
                restarts += 1
                lockstep = server._lockstep_ticks
                server._lockstep_ticks = 0  # nobody answers: do not wait for each tick
                await server.run_until(FAULT_AT_S + RESTART_GAP_S)
                server._lockstep_ticks = lockstep
                log_dirs.append(out_dir / f"flightlog-{restarts}")
                cfg = _config(sc, server, log_dirs[-1])
                svc, task = await _start_service(cfg, server.port)
                t = FAULT_AT_S + RESTART_GAP_S
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
