"""`companion fly`: the companion service flying a scenario against the bundled MAVLink simulator.

Two asyncio endpoints in one process, talking real MAVLink 2 over UDP loopback: the
simulator (ArduPilot or PX4 personality, lockstep, as fast as the machine allows) and the
service (sim-time mode, auto start: arm, take off to the scenario's start height, switch to
GUIDED/OFFBOARD, fly the route). Afterwards the service's flight log and the simulator's true
states become the same trace, metrics and figures as `companion simulate`.

Frames: the simulator's world ENU; the service's ENU is anchored at home (the vehicle's
take-off point), so route points and logged positions are shifted by home's world position.
"""

from __future__ import annotations

import asyncio
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from companion.config import parse_config
from companion.harness import metrics as metrics_mod
from companion.harness.closed_loop import TRACE_COLUMNS, RunResult
from companion.harness.runner import write_outputs
from companion.planner.params import PlannerParams
from companion.service import Service
from companion.service.flightlog import FlightLog, read_flight_log
from companion.service.link import UdpOutLink
from companion.service.notify import SystemdNotifier
from companion.sim.mavlink import SimServer
from companion.sim.scenario import Scenario, load_scenario
from companion.sim.world import World


@dataclass
class FlyResult:
    result: RunResult
    metrics: dict[str, Any]
    counters: dict[str, int]
    lockstep_stalls: int
    log_path: Path | None


def service_config(
    scenario: Scenario, port: int, home_xy: np.ndarray, log_dir: Path, submarine: bool = False
) -> Any:
    """The service configuration that flies `scenario` against the simulator on `port`.

    Air vehicles: auto start (arm, take off to the scenario's start height, GUIDED/OFFBOARD).
    Submarines cannot take off (ArduSub refuses MAV_CMD_NAV_TAKEOFF): the pilot arms and
    selects GUIDED where the vehicle is (see `_pilot_hands_over`), and the service takes over
    at any depth at or above home's, home being where the vehicle armed.
    """
    start_z = scenario.start_position[2] if scenario.start_position else scenario.planner.h_d_m
    points = (np.array(scenario.route.points[1:], dtype=float) - home_xy).tolist()
    control: dict[str, Any] = {
        "time_source": "sim",
        "rate_hz": 1.0 / scenario.dt_s,
        "auto_start": {"enabled": True, "takeoff_alt_m": float(start_z)},
    }
    if submarine:
        control["auto_start"] = {"enabled": False}
        control["min_engage_height_m"] = 0.0
    return parse_config(
        {
            "link": {"connection": f"udpout:127.0.0.1:{port}"},
            "autopilot": {
                "streams_hz": {
                    "ATTITUDE": 50.0,
                    "GLOBAL_POSITION_INT": 50.0,
                    "DISTANCE_SENSOR": 50.0,
                }
            },
            "control": control,
            "route": {
                "source": "config",
                "points": points,
                "arrival_heading_deg": scenario.route.arrival_heading_deg,
            },
            "planner": scenario.planner.model_dump(),
            "sensors": [s.model_dump(exclude_none=True) for s in scenario.sensors],
            "logging": {"flight_log_dir": str(log_dir), "level": "warning"},
        }
    )


async def fly_async(
    scenario: Scenario,
    base_dir: Path,
    out_dir: Path,
    personality: str | None = None,
    progress: Any = None,
) -> FlyResult:
    """Fly the scenario through the service; returns the trace, metrics and link figures."""
    overrides: dict[str, Any] = {
        "port": 0,
        "speedup": math.inf,
        "lockstep": {"enabled": True, "period_s": scenario.dt_s},
        "prearm_delay_s": 0.5,
    }
    if personality is not None:
        overrides["personality"] = personality
    server = SimServer.from_scenario(scenario, base_dir, **overrides)
    await server.start()
    home_xy = np.array(server.autopilot.home_enu[:2], dtype=float)
    log_dir = out_dir / "flightlog"
    submarine = server.personality.is_submarine
    cfg = service_config(scenario, server.port, home_xy, log_dir, submarine)
    service = Service(cfg, UdpOutLink("127.0.0.1", server.port), notifier=SystemdNotifier({}))
    task = asyncio.create_task(service.run())
    goal = np.array(scenario.route.points[-1], dtype=float)
    try:
        t = 0.0
        if submarine:
            t = server.config.prearm_delay_s + 0.5
            await server.run_until(t)
            _pilot_hands_over(server)
        while t < scenario.duration_s and not service.route_finished.is_set():
            t = min(t + 5.0, scenario.duration_s)
            await server.run_until(t)
            if task.done():
                break
            if progress is not None and server.truth:
                pos = server.truth[-1].position_enu
                progress(t, float(np.hypot(*(np.asarray(pos[:2]) - goal))))
    finally:
        service.stop()
        await asyncio.wait_for(task, 10.0)
        await server.close()
    logs = sorted(log_dir.glob("flight-*.jsonl"))
    log = read_flight_log(logs[-1]) if logs else None
    world = World.from_config(scenario.world, base_dir)
    truth_t = np.array([s.t_s for s in server.truth])
    truth_pose = np.array(
        [[*s.position_enu, s.roll_rad, s.pitch_rad, s.yaw_rad] for s in server.truth]
    )
    home = np.array(server.autopilot.home_enu, dtype=float)
    if log is None or len(truth_t) == 0:
        raise RuntimeError("the flight produced no log or no simulator states")
    result = trace_from_log(log, world, home, truth_t, truth_pose)
    result.finished = bool(service.route_finished.is_set())
    m = metrics_mod.for_run(scenario, world, result)
    return FlyResult(result, m, service.counter_values(), server.stats.lockstep_stalls, logs[-1])


def _pilot_hands_over(server: SimServer) -> None:
    """What an ROV pilot does with the joystick before handing over: GUIDED, then arm."""
    ap = server.autopilot
    ap.set_mode(server.personality.mode("GUIDED"), server.t_s, server.state, forced=True)
    if ap.arm(server.t_s, server.state, force=False) != 0:
        raise RuntimeError("the simulated ArduSub refused to arm")


def trace_from_log(
    log: FlightLog,
    world: World | None,
    home_enu: np.ndarray,
    truth_t: np.ndarray | None = None,
    truth_pose: np.ndarray | None = None,
) -> RunResult:
    """A trace (TRACE_COLUMNS) from the planner cycles of a flight log.

    Positions are shifted from the service's home-anchored ENU into the world frame by
    home_enu. With the simulator's true poses (truth_t, truth_pose rows x, y, z, roll,
    pitch, yaw) the vehicle columns are the truth at each cycle's time, else what the
    service received. With a world, clearance and height are the true distances.
    """
    rows = [i for i, kind in enumerate(log.setpoint_kind) if kind == "planner"]
    if not rows:
        raise RuntimeError("the flight log holds no planner cycles")
    idx = np.array(rows)
    t = log.t_s[idx]
    if truth_t is not None and truth_pose is not None:
        j = np.clip(np.searchsorted(truth_t, t - 1e-9), 0, len(truth_t) - 1)
        pose = truth_pose[j]
    else:
        pose = np.column_stack([log.position_enu[idx] + home_enu, log.rpy_rad[idx]])
    sp = log.setpoint_position_enu[idx] + home_enu
    dt = np.diff(t, prepend=t[0] - (t[1] - t[0] if len(t) > 1 else 0.05))
    speed = np.linalg.norm(np.diff(sp, axis=0, prepend=sp[:1]), axis=1) / np.maximum(dt, 1e-9)
    speed[0] = log.speed_ref_mps[idx][0] if len(log.speed_ref_mps) else 0.0
    phi = log.phi_star_rad[idx] if log.phi_star_rad.size else np.zeros((len(idx), 1))
    thr = log.phi_star_threshold_rad[idx] if log.phi_star_threshold_rad.size else phi * 0
    worst = np.argmax(np.nan_to_num(phi - thr, nan=-np.inf), axis=1)
    nan = np.full(len(idx), np.nan)

    def strings(values: list[str | None]) -> np.ndarray:
        return np.array([values[i] or "" for i in idx], dtype=object)

    if world is not None:
        clearance = np.array([world.obstacle_distance(p) for p in pose[:, :3]])
        height = np.array([world.surface_distance(p) for p in pose[:, :3]])
    else:
        clearance, height = nan.copy(), nan.copy()
    trace: dict[str, np.ndarray] = {
        "t": t,
        "x": pose[:, 0],
        "y": pose[:, 1],
        "z": pose[:, 2],
        "roll": pose[:, 3],
        "pitch": pose[:, 4],
        "yaw": pose[:, 5],
        "xd": sp[:, 0],
        "yd": sp[:, 1],
        "zd": sp[:, 2],
        "yaw_d": log.setpoint_yaw_rad[idx],
        "phi_d": log.phi_d_rad[idx] if len(log.phi_d_rad) else nan,
        "phi_star_max": np.nanmax(phi, axis=1) if phi.size else nan,
        "phi_star_threshold": thr[np.arange(len(idx)), worst] if thr.size else nan,
        "decision": strings(log.decision),
        "mode": strings(log.path_mode),
        "side": strings(log.side),
        "min_range": np.nan_to_num(log.min_range_m[idx], nan=0.0),
        "clearance": clearance,
        "height": height,
        "speed_ref": log.speed_ref_mps[idx] if len(log.speed_ref_mps) else nan,
        "speed_xd": speed,
        "segment": nan,
        "parameter": nan,
        "replanned": log.replanned[idx].astype(float) if len(log.replanned) else nan,
    }
    assert set(trace) == set(TRACE_COLUMNS)
    events = [(tt, e) for tt, e in log.events]
    return RunResult(
        trace=trace,
        phi_star=phi,
        thresholds=thr[-1] if thr.size else np.zeros(0),
        events=events,
        finished=bool(log.finished[idx].any()),
        memory_xy=np.empty((0, 2)),
    )


def fly(
    scenario_path: Path,
    out_dir: Path,
    personality: str | None = None,
    plots: bool = True,
    stream: TextIO = sys.stdout,
) -> int:
    """`companion fly`: run, print the metrics table and link figures, write the outputs."""
    scenario = load_scenario(scenario_path)
    interactive = stream.isatty()

    def progress(t: float, to_goal: float) -> None:
        if interactive:
            stream.write(f"\r  simulated t = {t:7.1f} s   distance to goal {to_goal:7.1f} m")
            stream.flush()

    flown = asyncio.run(fly_async(scenario, scenario_path.parent, out_dir, personality, progress))
    if interactive:
        stream.write("\r" + " " * 70 + "\r")
    world = World.from_config(scenario.world, scenario_path.parent)
    written = write_outputs(out_dir, scenario, world, flown.result, flown.metrics, plots)
    c = flown.counters
    stream.write(
        f"scenario {scenario.name} flown through the service over UDP MAVLink "
        f"(lockstep stalls {flown.lockstep_stalls}, setpoints sent "
        f"{c.get('setpoints_sent', c.get('service.setpoints_sent', 0))})\n"
    )
    stream.write(metrics_mod.format_table(flown.metrics) + "\n")
    for t, text in flown.result.events:
        stream.write(f"  {t:8.2f} s  {text}\n")
    if flown.log_path is not None:
        written.append(flown.log_path)
    stream.write("wrote " + ", ".join(str(p) for p in written) + "\n")
    return 0 if flown.metrics["reached_goal"] else 1


def report(
    log_path: Path,
    out_dir: Path,
    scenario_path: Path | None = None,
    plots: bool = True,
    stream: TextIO = sys.stdout,
) -> int:
    """`companion report`: the plots and metrics of a flight log.

    Without a scenario the world is unknown (a real flight): the figures show the flown path,
    the route and the planner's signals over flat ground, and the metrics that need the true
    surface (clearance, height) are not available. With the scenario the log was flown in
    (by `companion fly`), positions are placed in its world and all metrics are computed.
    """
    from companion.planner.route import Route

    log = read_flight_log(log_path)
    if not log.routes:
        stream.write(f"{log_path}: no planner route in this log (the planner never started)\n")
        return 1
    first = log.routes[0]
    points = np.array(first["points"], dtype=float)
    scenario = load_scenario(scenario_path) if scenario_path is not None else None
    if scenario is not None:
        assert scenario_path is not None
        world: World | None = World.from_config(scenario.world, scenario_path.parent)
        # Home is where the vehicle took off: the scenario's first base point, on the ground.
        x0, y0 = scenario.route.points[0]
        home = np.array([x0, y0, float(world.height(x0, y0)) if world else 0.0])
    else:
        world, home = None, np.zeros(3)
    route = Route(
        points + home[:2], first.get("start_heading_rad"), first.get("arrival_heading_rad")
    )
    result = trace_from_log(log, world, home)
    shown_world = world if world is not None else World()
    params = (
        scenario.planner.model_dump()
        if scenario is not None
        else dict(log.header.get("planner") or log.header.get("config", {}).get("planner", {}))
    )
    h_d, v_d = float(params.get("h_d_m", 2.0)), float(params.get("v_d_mps", 1.0))
    source = (
        "the scenario"
        if scenario is not None
        else ("the log" if params else "defaults: the log header has none")
    )
    stream.write(
        f"planner: H_d {h_d:g} m, D_min {float(params.get('d_min_m', 2.0)):g} m, "
        f"v_d {v_d:g} m/s, phi_max {float(params.get('phi_max_rad', 0.6)):g} rad "
        f"(from {source})\n"
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    if world is not None:
        m = metrics_mod.compute(result.trace, route, world, h_d, v_d, result.finished)
        stream.write(metrics_mod.format_table(m) + "\n")
    if plots:
        from companion.harness.plots import PlotParams, write_figures

        written += write_figures(
            out_dir,
            shown_world,
            route,
            result.trace,
            PlotParams.from_planner(
                PlannerParams(
                    h_d_m=h_d,
                    d_min_m=float(params.get("d_min_m", 2.0)),
                    phi_max_rad=float(params.get("phi_max_rad", 0.6)),
                    v_d_mps=v_d,
                )
            ),
            phi_star=result.phi_star,
            thresholds=result.thresholds,
            events=result.events,
            title=log_path.name,
        )
    for t, text in result.events:
        stream.write(f"  {t:8.2f} s  {text}\n")
    stream.write(
        f"{len(result.trace['t'])} planner cycles; wrote " + ", ".join(map(str, written)) + "\n"
    )
    return 0
