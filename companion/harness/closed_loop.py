"""The in-process closed loop: world -> range sensors -> planner -> vehicle model, per cycle.

No MAVLink here; `companion fly` runs the same scenario over UDP. The trace holds one row
per cycle (columns in TRACE_COLUMNS); metrics are computed from it by `companion.harness.metrics`.
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from companion.planner import Planner, StepResult, VehicleState
from companion.planner.decision import thresholds as eq7_thresholds
from companion.planner.rotations import r_g
from companion.planner.sensors import SensorTable
from companion.sim.scenario import Scenario
from companion.sim.sensing import SensorFan
from companion.sim.vehicle import make_vehicle
from companion.sim.world import World

TRACE_COLUMNS = (
    "t",
    "x",
    "y",
    "z",
    "roll",
    "pitch",
    "yaw",
    "xd",
    "yd",
    "zd",
    "yaw_d",
    "phi_d",
    "phi_star_max",
    "phi_star_threshold",
    "decision",
    "mode",
    "side",
    "min_range",
    "clearance",
    "height",
    "speed_ref",
    "speed_xd",
    "segment",
    "parameter",
    "replanned",
)


STALL_BOX_M = 1.0
"""`run(stall_stop_s=...)`: a vehicle that stays within a box this wide (m) has stalled."""


@dataclass
class RunResult:
    trace: dict[str, np.ndarray]
    phi_star: np.ndarray
    """(cycles, obstacle sensors) phi_i* per sensor, radians."""
    thresholds: np.ndarray
    events: list[tuple[float, str]]
    finished: bool
    memory_xy: np.ndarray
    step_time_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """(cycles,) CPU time of each planner.step call (thread time: other load on the machine
    does not count), seconds; not deterministic."""


def sense(
    world: World, sensors: SensorTable, state: VehicleState, fan: SensorFan | None = None
) -> np.ndarray:
    """True ranges of every sensor at the vehicle pose, metres; max range where nothing hit
    (what an autopilot reports for "out of range"). A sensor with a field of view reads the
    nearest hit across it (`companion.sim.sensing`); fan: the table's rays, made once per
    flight by the caller (made here if None)."""
    rot = r_g(state.roll_rad, state.pitch_rad, state.yaw_rad)
    if fan is None:
        fan = SensorFan(sensors.boresights_flu, sensors.fov_rad)
    ranges = fan.ranges(world.raycast, state.position_enu, rot, sensors.max_range_m)
    return np.where(np.isfinite(ranges), ranges, sensors.max_range_m)


def run(
    scenario: Scenario,
    world: World,
    progress: Callable[[float, float], None] | None = None,
    sensor_filter: Callable[[float, np.ndarray, VehicleState], np.ndarray] | None = None,
    stall_stop_s: float | None = None,
) -> RunResult:
    """Fly the scenario in process until the goal is reached or duration_s has passed.

    sensor_filter(t_s, true_ranges_m, state) -> ranges_m: what the planner reads instead of
    the true ranges (sensor faults), given the vehicle state they were sensed from; None: the
    true ranges. stall_stop_s: also stop once the vehicle
    has stayed within a 1 m box for this long (s) (None: never).
    """
    params = scenario.params()
    sensors = scenario.sensor_table()
    route = scenario.route_obj()
    start = scenario.start(world)
    planner = Planner(params, sensors, route, start)
    fan = SensorFan(sensors.boresights_flu, sensors.fov_rad)
    initial = VehicleState(start, 0.0, 0.0, route.start_heading_rad)
    vehicle = make_vehicle(scenario.vehicle, initial)
    dt = scenario.dt_s
    rows: dict[str, list[float | str]] = {c: [] for c in TRACE_COLUMNS}
    columns = [rows[c] for c in TRACE_COLUMNS]
    phi_rows: list[np.ndarray] = []
    events: list[tuple[float, str]] = []
    step_times: list[float] = []
    state = vehicle.state
    prev_xd = np.array(start)
    finished = False
    steps = round(scenario.duration_s / dt)
    goal = route.base_points[-1]
    for k in range(steps):
        t = (k + 1) * dt
        ranges = sense(world, sensors, state, fan)
        if sensor_filter is not None:
            ranges = sensor_filter(t, ranges, state)
        t0 = time.thread_time()
        result: StepResult = planner.step(state, ranges, dt)
        step_times.append(time.thread_time() - t0)
        sp, diag = result.setpoint, result.diagnostics
        state = vehicle.step(sp, dt)
        events.extend((t, e) for e in diag.events)
        pos = state.position_enu
        x_d = sp.position_enu
        phi_star = diag.phi_star_rad
        step_xd = x_d - prev_xd
        # One list per column, appended in TRACE_COLUMNS order (a dict per row cost more
        # than the rest of the bookkeeping).
        for column, value in zip(
            columns,
            (
                t,
                pos[0],
                pos[1],
                pos[2],
                state.roll_rad,
                state.pitch_rad,
                state.yaw_rad,
                x_d[0],
                x_d[1],
                x_d[2],
                sp.yaw_rad,
                sp.pitch_rad,
                float(phi_star.max()),
                float(diag.threshold_rad[int((phi_star - diag.threshold_rad).argmax())]),
                diag.decision.value,
                diag.mode.value,
                diag.side.value,
                diag.min_range_m,
                world.obstacle_distance(pos),
                world.surface_distance(pos),
                diag.speed_ref_mps,
                math.sqrt(float(step_xd.dot(step_xd))) / dt,  # (np.linalg.norm's sum)
                diag.segment,
                diag.parameter,
                float(diag.replanned),
            ),
            strict=True,
        ):
            column.append(value)
        phi_rows.append(phi_star.copy())
        prev_xd = x_d
        if progress is not None and k % 200 == 0:
            progress(t, float(np.hypot(*(pos[:2] - goal))))
        if diag.finished:
            finished = True
            break
        if stall_stop_s is not None and k % 20 == 0 and t >= stall_stop_s:
            window = rows["x"][-round(stall_stop_s / dt) :], rows["y"][-round(stall_stop_s / dt) :]
            if np.ptp(window[0]) < STALL_BOX_M and np.ptp(window[1]) < STALL_BOX_M:
                break
    trace = {
        c: np.array(v) if c not in ("decision", "mode", "side") else np.array(v, dtype=object)
        for c, v in rows.items()
    }
    return RunResult(
        trace=trace,
        phi_star=np.array(phi_rows),
        thresholds=eq7_thresholds(sensors.obstacle_groups, params),
        events=events,
        finished=finished,
        memory_xy=planner.memory_points_xy,
        step_time_s=np.array(step_times),
    )


def write_trace(path: Path, trace: dict[str, np.ndarray]) -> None:
    """trace.csv: one row per cycle, columns TRACE_COLUMNS."""
    n = len(trace["t"])
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(TRACE_COLUMNS)
        for i in range(n):
            writer.writerow(
                [
                    v if isinstance(v := trace[c][i], str) else f"{float(v):.6g}"
                    for c in TRACE_COLUMNS
                ]
            )
