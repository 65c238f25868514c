"""Metrics of a run, as the paper reports them (docs/paper.md, "Metrics").

- min_clearance_m: min over the run of the true shortest distance from the vehicle to any
  obstacle feature (features with obstacle: true).
- max_abs_pitch_rad: max |pitch| of the vehicle; max_abs_phi_d_rad: max |phi_d|, the
  desired pitch of eq. (4) (the paper's Fig. 7c). The two agree for the ideal tracker.
- max_height_error_m: max |H - H_d|, H the true shortest distance from the vehicle to the
  surface, counted once the vehicle has first settled within 0.15 m of H_d (the start height
  is a scenario choice; `height_settle_time_s` says when that happened).
- max_speed_error_mps: max |speed of X_d - reference speed| per cycle. The reference speed is
  v_d except where the planner lowers it on purpose (tight curves, stops, the goal);
  `min_reference_speed_mps` and `time_below_v_d_s` say how much that happened.
- reached_goal, final_position_error_m, final_heading_error_rad: at the last cycle.
- collisions: cycles below the surface or inside an obstacle.
- decisions, replans, max_lateral_deviation_m (per named feature, lateral distance of the
  flown path from the original route where the route passes that feature: its footprint,
  or for a Gaussian hill its core, where it rises more than 5 % of its height).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.planner.frames import wrap_pi
from companion.planner.path import project
from companion.planner.route import Route
from companion.sim.world import World

if TYPE_CHECKING:
    from companion.harness.closed_loop import RunResult
    from companion.sim.scenario import Scenario

SETTLE_BAND_M = 0.15


def feature_sides(
    route: Route, world: World, x: np.ndarray, y: np.ndarray
) -> tuple[dict[str, float], dict[str, str]]:
    """Per feature: max lateral deviation of the flown path (x, y) from the route over the
    stretch of route beside the feature, and the side the path passed an obstacle on."""
    poly = route.polyline()
    s_flown, l_flown = project(poly, np.column_stack([x, y]))
    deviation: dict[str, float] = {}
    sides: dict[str, str] = {}
    for info in world.features:
        if info.polygon is None:
            continue
        outline = info.core if info.core is not None else info.polygon
        s_feat, l_feat = project(poly, outline)
        lo, hi = float(s_feat.min()), float(s_feat.max())
        if hi - lo > 0.9 * route.length:  # a feature the whole route crosses says nothing
            continue
        near = (s_flown >= lo) & (s_flown <= hi)
        if not near.any():
            continue
        deviation[info.name] = float(np.max(np.abs(l_flown[near])))
        if info.obstacle:
            centre = float(np.median(l_feat))
            passed = float(np.median(l_flown[near]))
            sides[info.name] = "left" if passed > centre else "right"
    return deviation, sides


def compute(
    trace: dict[str, np.ndarray],
    route: Route,
    world: World,
    h_d_m: float,
    v_d_mps: float,
    finished: bool,
) -> dict[str, Any]:
    """Metrics dictionary (JSON-ready) of one run."""
    t = trace["t"]
    x, y = trace["x"], trace["y"]
    height_err = np.abs(trace["height"] - h_d_m)
    settled = np.flatnonzero(height_err <= SETTLE_BAND_M)
    first = int(settled[0]) if len(settled) else len(t)
    goal = route.base_points[-1]
    final_err = float(math.hypot(x[-1] - goal[0], y[-1] - goal[1]))
    speed_err = np.abs(trace["speed_xd"] - trace["speed_ref"])
    deviation, sides = feature_sides(route, world, x, y)
    decisions = {
        d: int(np.sum(trace["decision"] == d)) for d in ("vertical", "horizontal", "blocked")
    }
    dt = float(t[1] - t[0]) if len(t) > 1 else 0.0
    collisions = int(
        sum(1 for i in range(len(t)) if trace["height"][i] <= 0.0 or trace["clearance"][i] <= 0.0)
    )
    return {
        "min_clearance_m": float(np.min(trace["clearance"])),
        "max_abs_pitch_rad": float(np.max(np.abs(trace["pitch"]))),
        "max_abs_phi_d_rad": float(np.nanmax(np.abs(trace["phi_d"]))),
        "max_height_error_m": float(np.max(height_err[first:])) if first < len(t) else math.inf,
        "height_settle_time_s": float(t[first]) if first < len(t) else math.inf,
        "initial_height_error_m": float(height_err[0]),
        "max_speed_error_mps": float(np.max(speed_err)),
        "min_reference_speed_mps": float(np.min(trace["speed_ref"])),
        "time_below_v_d_s": float(np.sum(trace["speed_ref"] < v_d_mps - 1e-6) * dt),
        "reached_goal": bool(finished and final_err < 0.5),
        "final_position_error_m": final_err,
        "final_heading_error_rad": abs(
            wrap_pi(float(trace["yaw"][-1]) - route.arrival_heading_rad)
        ),
        "collisions": collisions,
        "duration_s": float(t[-1]),
        "min_range_m": float(np.min(trace["min_range"][trace["min_range"] > 0]))
        if np.any(trace["min_range"] > 0)
        else 0.0,
        "decisions": decisions,
        "replans": int(np.sum(trace["replanned"])),
        "max_lateral_deviation_m": deviation,
        "passed_side": sides,
    }


def steep_clearances(
    scenario: Scenario, trace: Mapping[str, np.ndarray], base_dir: Path | str | None = None
) -> np.ndarray:
    """True clearance (m) at each cycle from the vehicle to the solids the paper's rule goes
    round: every obstacle but a mesa whose flank is no steeper than phi_max. Eq. (7) climbs
    such a mesa, keeping H_d above it, so it is relief: with H_d = D_min a height error
    below H_d would read as a clearance below D_min, and it counts in the height error
    instead. The trace's own clearance where the world has no such mesa. base_dir: where the
    scenario's relative heightmap paths start."""
    limit_deg = math.degrees(scenario.planner.phi_max_rad)
    features = scenario.world.features
    steep = [f for f in features if not (f.type == "mesa" and f.side_slope_deg <= limit_deg)]
    if len(steep) == len(features):  # nothing climbable: the same solids
        return np.asarray(trace["clearance"], dtype=np.float64)
    world = World.from_config(scenario.world.model_copy(update={"features": steep}), base_dir)
    xyz = np.column_stack([trace["x"], trace["y"], trace["z"]])
    return np.array([world.obstacle_distance(p) for p in xyz], dtype=np.float64)


GENTLE_RADIUS_M = 10.0
"""Relief counts as gentle where its radius of curvature is at least this (m): the issue's
0.07 m height target applies there."""
GENTLE_SETTLE_BAND_M = 0.07
"""... counted once the vehicle has first come within this of H_d (the target's own band, as
SETTLE_BAND_M is the 0.15 m target's), m."""
_CURVATURE_STEP_M = 0.25


def principal_curvature_max(z: np.ndarray, step_m: float) -> np.ndarray:
    """max(|k1|, |k2|) (1/m) of the surface z = f(x, y) sampled on a square grid (rows y,
    columns x, step_m apart): the principal curvatures of a graph from its first and second
    differences, (1 + fy^2) fxx - 2 fx fy fxy + (1 + fx^2) fyy over 2 W^3 (mean) and
    (fxx fyy - fxy^2) / W^4 (Gaussian), W = sqrt(1 + fx^2 + fy^2)."""
    fy, fx = np.gradient(z, step_m)
    fxy, fxx = np.gradient(fx, step_m)
    fyy, _ = np.gradient(fy, step_m)
    w2 = 1.0 + fx * fx + fy * fy
    mean = ((1.0 + fy * fy) * fxx - 2.0 * fx * fy * fxy + (1.0 + fx * fx) * fyy) / (2.0 * w2**1.5)
    gauss = (fxx * fyy - fxy * fxy) / (w2 * w2)
    out: np.ndarray = np.abs(mean) + np.sqrt(np.maximum(mean * mean - gauss, 0.0))
    return out


def _window_max(a: np.ndarray, half: int, axis: int) -> np.ndarray:
    """The max of a over [i - half, i + half] along axis (edges repeated), by doubling
    spans: O(n log half) time, O(n) memory."""
    pad = [(0, 0)] * a.ndim
    pad[axis] = (half, half)
    m = np.pad(a, pad, mode="edge")
    k, span = 2 * half + 1, 1
    n = a.shape[axis]

    def part(x: np.ndarray, start: int, length: int) -> np.ndarray:
        out: np.ndarray = np.take(x, np.arange(start, start + length), axis=axis)
        return out

    while 2 * span <= k:
        length = m.shape[axis] - span
        m = np.maximum(part(m, 0, length), part(m, span, length))
        span *= 2
    result: np.ndarray = np.maximum(part(m, 0, n), part(m, k - span, n))
    return result


def gentle_relief(
    world: World, x: np.ndarray, y: np.ndarray, reach_m: float, radius_m: float = GENTLE_RADIUS_M
) -> np.ndarray:
    """Per cycle, (n,) bool: the surface within reach_m of (x, y) (a square of half-side
    reach_m) has a radius of curvature of at least radius_m everywhere (its principal
    curvatures, sampled every 0.25 m, are within 1 / radius_m). Creases (a flank's foot, a
    mesa's rim) and solids' edges are not gentle."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if len(x) == 0:
        return np.zeros(0, dtype=bool)
    step = _CURVATURE_STEP_M
    margin = reach_m + 2.0 * step
    gx = np.arange(float(x.min()) - margin, float(x.max()) + margin + step, step)
    gy = np.arange(float(y.min()) - margin, float(y.max()) + margin + step, step)
    z = world.height(*np.meshgrid(gx, gy))
    kappa = principal_curvature_max(np.asarray(z, dtype=np.float64), step)
    half = math.ceil(reach_m / step)
    near = _window_max(_window_max(kappa, half, 0), half, 1)
    ix = np.clip(np.rint((x - gx[0]) / step).astype(int), 0, len(gx) - 1)
    iy = np.clip(np.rint((y - gy[0]) / step).astype(int), 0, len(gy) - 1)
    out: np.ndarray = near[iy, ix] <= 1.0 / radius_m
    return out


def for_run(scenario: Scenario, world: World, result: RunResult) -> dict[str, Any]:
    """`compute` with the scenario's route, H_d and v_d."""
    return compute(
        result.trace,
        scenario.route_obj(),
        world,
        scenario.planner.h_d_m,
        scenario.planner.v_d_mps,
        result.finished,
    )


METRIC_ROWS = (
    ("min_clearance_m", "min clearance to obstacles", "m"),
    ("max_abs_phi_d_rad", "max |phi_d| (desired pitch)", "rad"),
    ("max_abs_pitch_rad", "max |pitch| of the vehicle", "rad"),
    ("max_height_error_m", "max |H - H_d| (settled)", "m"),
    ("max_speed_error_mps", "max |v(X_d) - v_ref|", "m/s"),
    ("reached_goal", "reached goal", ""),
    ("final_position_error_m", "final position error", "m"),
    ("final_heading_error_rad", "final heading error", "rad"),
    ("collisions", "collisions (cycles)", ""),
    ("replans", "re-plans", ""),
    ("duration_s", "duration", "s"),
)


def format_table(metrics: dict[str, Any]) -> str:
    """A plain-text table of the main metrics."""
    lines = [f"{'metric':<34}{'value':>14}  unit", "-" * 54]
    for key, label, unit in METRIC_ROWS:
        v = metrics[key]
        shown = f"{v:.4f}" if isinstance(v, float) else str(v)
        lines.append(f"{label:<34}{shown:>14}  {unit}")
    d = metrics["decisions"]
    lines.append(
        f"{'decisions v/h/blocked (cycles)':<34}"
        f"{d['vertical']:>5}/{d['horizontal']}/{d['blocked']}".ljust(48)
    )
    for name, dev in metrics["max_lateral_deviation_m"].items():
        side = metrics["passed_side"].get(name)
        extra = f" (passed {side})" if side else ""
        lines.append(f"{'lateral deviation at ' + name:<34}{dev:>14.4f}  m{extra}")
    return "\n".join(lines)
