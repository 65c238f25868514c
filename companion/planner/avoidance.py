"""Horizontal correction: reshape the Bezier path around what is too steep to climb.

Design (docs/avoidance.md has the figure):
1. Obstacle points are expressed in the route's Frenet frame: arc length s along the
   original route and signed lateral offset l (left positive).
2. The points that conflict with the current path are grown into a window [s_a, s_b] by
   adding every remembered point within 2 D_m of it along the route (D_m = D_min + margin).
3. Each point blocks the lateral band [l - D_m, l + D_m]; the gaps between the bands are the
   lateral offsets w at which the path can pass the window. One candidate per gap: the
   offset nearest the current offset l0 and the one nearest the route (l = 0).
4. A candidate is a chain of cubic Beziers P0 -> V1 -> V2 -> R: P0 is the current reference
   point with its tangent (continuity, requirement 1); V1 and V2 sit at offset w at
   s_a - D_m and s_b + D_m, tangent parallel to the route; R rejoins the route before the
   next base point with the route's tangent (requirement 2). V1 is dropped when the window
   has already begun.
5. A candidate is accepted only if its curvature stays within 1 / min_turn_radius and every
   sample of the new curve, and of the route tail it joins, keeps D_m from every remembered
   point (requirement 3; the whole curve is checked, not its control points).
   Around an obstacle that sits across the path, each offset is also offered with an extra
   berth (UNSEEN_BERTH_M), preferred when it fits: the far side has not been seen yet.
6. Candidates are tried cheapest first. Cost: extra length, lateral offset from the route
   (the deviation from the goal direction), a penalty for the side with less free range, and
   a larger one for leaving the side already chosen for this obstacle (hysteresis).
   When the window has already begun (the obstacle is beside the vehicle), V1 is placed a
   few lateral-change lengths ahead instead, so the path moves out promptly.
Mode: AROUND when the obstacle sits across the current line (a conflicting point within
ACROSS_M of it), SHIFT when it is beside the line, closer than D_m.
Pure functions over numpy arrays; frame local ENU x, y metres.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Generator, Sequence
from dataclasses import dataclass

import numpy as np

from companion.planner.bezier import CubicBezier, segment_through
from companion.planner.params import PlannerParams
from companion.planner.path import Path, Polyline, project
from companion.planner.route import Route
from companion.planner.types import BoolArray, FloatArray, IntArray, PathMode, Side

SIDE_SWITCH_PENALTY_M = 4.0
DEAD_END_PENALTY_M = 100.0
LESS_FREE_SIDE_PENALTY_M = 4.0
MAX_LATERAL_OFFSET_M = 40.0
ACROSS_M = 0.5
UNSEEN_BERTH_M = 2.0
"""Extra lateral room taken around an obstacle that sits across the path (its far side
has not been seen yet); dropped when it does not fit."""
"""An obstacle point this close to the current line means the obstacle sits across it."""
TRANSITION_FACTORS = (1.0, 1.5, 2.5, 4.0)
KEEP_ROUTE_FACTOR = 2.0
"""Lengths, in multiples of the shortest S-curve the turn radius allows, over which a
candidate moves to its offset."""
_SAMPLE_SPACING_M = 0.2
BASE_POINT_REACHED_M = 0.5
"""A path that comes this close to a base point passes through it (metres)."""
SKIP_BASE_COST_M = 30.0
"""Extra cost per base point a candidate passes beside instead of through: tried after the
candidates that pass through it, from the route's direction or another one."""
NARROW_COST_M = 200.0
"""Extra cost of a candidate that keeps only the re-plan trigger, not D_min + margin: tried
after every candidate that keeps the margin (see `detour_search`)."""
THROUGH_BASE_COST_M = 20.0
"""Extra cost of a candidate that reaches a base point from another direction than the
route's (see `_with_transitions`)."""
ESCAPE_TOLERANCE_M = 0.05
"""How much nearer than at its start an escape may pass another point (sampling)."""
ESCAPE_SLOPE = 0.3
"""A correction that starts closer than D_min (new points appeared beside the vehicle) must
gain at least this much clearance per metre along it until it is out."""


@dataclass(frozen=True, slots=True)
class Detour:
    """An accepted correction: the new path, where it rejoins the route, and how."""

    path: Path
    rejoin_s: float
    offset_m: float
    side: Side
    mode: PathMode
    cost: float


def min_distance(
    samples_xy: FloatArray, obstacles_xy: FloatArray, inflation_m: FloatArray | None = None
) -> FloatArray:
    """Distance from each sample (n, 2) to the nearest obstacle point (k, 2), less that
    point's inflation (k,) metres when given (the distance to its inflated disc); inf if
    there are no points."""
    if len(obstacles_xy) == 0:
        return np.full(len(samples_xy), np.inf)
    return np.asarray(disc_distances(samples_xy, obstacles_xy, inflation_m).min(axis=1))


def disc_distances(
    samples_xy: FloatArray, obstacles_xy: FloatArray, inflation_m: FloatArray | None = None
) -> FloatArray:
    """Distance from every sample (n, 2) to every obstacle point (k, 2), less that point's
    inflation (k,) when given: (n, k) metres."""
    # Per coordinate, not a sum over a length-2 axis: numpy reduces short axes slowly.
    dx = samples_xy[:, 0, None] - obstacles_xy[None, :, 0]
    dy = samples_xy[:, 1, None] - obstacles_xy[None, :, 1]
    # In place (the same operations, without an (n, k) array per step).
    np.multiply(dx, dx, out=dx)
    np.multiply(dy, dy, out=dy)
    np.add(dx, dy, out=dx)
    np.sqrt(dx, out=dx)
    if inflation_m is not None:
        np.subtract(dx, inflation_m[None, :], out=dx)
    return dx


def min_distance_within(
    samples_xy: FloatArray,
    obstacles_xy: FloatArray,
    cutoff_m: float,
    inflation_m: FloatArray | None = None,
) -> FloatArray:
    """`min_distance` where it is below cutoff_m (the same numbers); elsewhere some value
    >= cutoff_m, possibly inf. Obstacles outside the samples' bounding box grown by
    cutoff_m (plus the largest inflation) cannot come closer than that and are left out
    before the (n, k) distances."""
    if len(samples_xy) == 0 or len(obstacles_xy) == 0:
        return np.full(len(samples_xy), np.inf)
    inside = _in_reach(samples_xy, obstacles_xy, cutoff_m, inflation_m)
    infl = inflation_m[inside] if inflation_m is not None else None
    return min_distance(samples_xy, obstacles_xy[inside], infl)


def _in_reach(
    samples_xy: FloatArray,
    obstacles_xy: FloatArray,
    cutoff_m: float,
    inflation_m: FloatArray | None,
) -> BoolArray:
    """Mask (k,) of the obstacle points in the samples' bounding box grown by cutoff_m plus
    the largest inflation: the only ones whose inflated disc can come nearer than cutoff_m."""
    grow = cutoff_m + (float(inflation_m.max()) if inflation_m is not None else 0.0)
    lo = samples_xy.min(axis=0) - grow
    hi = samples_xy.max(axis=0) + grow
    return np.asarray(np.all((obstacles_xy >= lo) & (obstacles_xy <= hi), axis=1), dtype=np.bool_)


_FEW_POINTS = 3
"""`min_distance_to` measures up to this many points one at a time."""
_BOX_SLACK_M = 1e-6
"""Widens `within_reach`'s box far beyond the rounding of the distances compared."""


def min_distance_to(
    samples_xy: FloatArray, points: Sequence[tuple[float, float, float]]
) -> FloatArray:
    """`min_distance` from the samples (n, 2) to points given as (x, y, inflation) tuples,
    metres: the same per-pair expression (so the same numbers), a few points one at a time
    (numpy reduces a short axis slowly)."""
    if len(points) > _FEW_POINTS:
        arr = np.array(points, dtype=np.float64)
        return min_distance(samples_xy, arr[:, :2], arr[:, 2])
    out = np.full(len(samples_xy), np.inf)
    sx = samples_xy[:, 0]
    sy = samples_xy[:, 1]
    for x, y, e in points:
        dx = sx - x
        dy = sy - y
        np.multiply(dx, dx, out=dx)
        np.multiply(dy, dy, out=dy)
        np.add(dx, dy, out=dx)
        np.sqrt(dx, out=dx)
        np.subtract(dx, e, out=dx)
        np.minimum(out, dx, out=out)
    return out


def within_reach(
    box: tuple[float, float, float, float],
    cutoff_m: float,
    points: Sequence[tuple[float, float, float]],
) -> list[tuple[float, float, float]]:
    """The points (x, y, inflation) that may come closer than cutoff_m to some sample in
    the box (x_lo, y_lo, x_hi, y_hi), metres: those in the box grown by cutoff_m plus their
    inflation. Every other point's distance less its inflation exceeds cutoff_m at every
    sample in the box."""
    x_lo, y_lo, x_hi, y_hi = box
    out = []
    for p in points:
        x, y, e = p
        g = cutoff_m + e + _BOX_SLACK_M
        if x_lo - g <= x <= x_hi + g and y_lo - g <= y <= y_hi + g:
            out.append(p)
    return out


def min_distance_within_updated(
    samples_xy: FloatArray,
    values: FloatArray,
    cutoff_m: float,
    box: tuple[float, float, float, float],
    removed: Sequence[tuple[float, float, float]],
    added: Sequence[tuple[float, float, float]],
) -> tuple[FloatArray, IntArray]:
    """`min_distance_within` after the obstacle points changed, from `values`, measured by
    it (or by this) against the points before: now those less `removed`, plus `added`, as
    (x, y, inflation) metres. box: the samples' bounding box (x_lo, y_lo, x_hi, y_hi).
    Returns the new values (`values` itself if no change could reach below cutoff_m), the
    same numbers below cutoff_m (elsewhere >= cutoff_m), except at the returned sample
    indices: there a removed point was the nearest, and the caller must measure against
    every point afresh.

    A sample's value is a minimum over pairs, and a pair's value does not depend on the
    other points: a sample below the cutoff whose removed pairs are all farther than its
    value keeps that value's point, so its new value is the least of the old one and the
    added pairs'. A sample at or beyond the cutoff had no point nearer, nor has it now but
    among the added ones."""
    removed = within_reach(box, cutoff_m, removed)
    added = within_reach(box, cutoff_m, added)
    stale = np.empty(0, dtype=np.intp)
    if removed:
        near = np.flatnonzero(values < cutoff_m)
        if len(near):
            was = values[near]
            stale = near[min_distance_to(samples_xy[near], removed) <= was]
    if added:
        values = np.minimum(values, min_distance_to(samples_xy, added))
    elif len(stale):
        values = values.copy()
    return values, stale


def sample_segments(
    segments: list[CubicBezier], bases: dict[int, FloatArray] | None = None
) -> FloatArray:
    """Points along the segments at roughly _SAMPLE_SPACING_M, (n, 2). bases: as in
    `CubicBezier.sample`."""
    parts = [
        seg.sample(max(3, math.ceil(seg.length / _SAMPLE_SPACING_M) + 1), bases) for seg in segments
    ]
    return np.concatenate(parts) if parts else np.empty((0, 2))


_CURVATURE_T = np.linspace(0.0, 1.0, 33)
_FIRST = np.stack(  # Bernstein basis of B' at _CURVATURE_T, against the hodograph (33, 3)
    [(1.0 - _CURVATURE_T) ** 2, 2.0 * _CURVATURE_T * (1.0 - _CURVATURE_T), _CURVATURE_T**2], 1
)
_SECOND = np.stack([1.0 - _CURVATURE_T, _CURVATURE_T], 1)  # B'' against its (33, 2) points


def max_abs_curvature(segments: list[CubicBezier]) -> float:
    """Largest |curvature| (1/m) at 33 evenly spaced t of each segment (`curvature`, for
    all the segments at once)."""
    return max(max_abs_curvatures(segments))


def max_abs_curvatures(segments: list[CubicBezier]) -> list[float]:
    """`max_abs_curvature` of each segment, (len(segments),) 1/m, in one pass: callers that
    compare several options build them all, then measure them together."""
    # The hodograph's control points 3 diff(control) (each segment keeps them as floats)
    # and 6 diff(control, n=2), computed as numpy's diff computes them: the same numbers
    # as the array forms, without stacking and differencing (m, 4, 2) arrays.
    first = []
    second = []
    for seg in segments:
        x0, y0, x1, y1, x2, y2, x3, y3 = seg.control_floats
        d = seg.hodograph_floats
        first.append(((d[0], d[1]), (d[2], d[3]), (d[4], d[5])))
        a0, b0, a1, b1, a2, b2 = x1 - x0, y1 - y0, x2 - x1, y2 - y1, x3 - x2, y3 - y2
        second.append(((6.0 * (a1 - a0), 6.0 * (b1 - b0)), (6.0 * (a2 - a1), 6.0 * (b2 - b1))))
    d1 = _FIRST @ np.array(first)  # (m, 33, 2)
    d2 = _SECOND @ np.array(second)
    cross = d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0]
    speed = np.hypot(d1[..., 0], d1[..., 1])
    kappa = np.divide(cross, speed**3, out=np.zeros_like(speed), where=speed > 1e-12)
    per_segment: list[float] = np.abs(kappa).max(axis=1).tolist()
    return per_segment


def free_intervals(
    lateral: FloatArray,
    half_width_m: float | FloatArray,
    limit_m: float = MAX_LATERAL_OFFSET_M,
) -> list[tuple[float, float]]:
    """Gaps between the bands [l - half_width, l + half_width] within [-limit, limit];
    half_width is one number or one per point."""
    if len(lateral) == 0:
        return [(-limit_m, limit_m)]
    half = np.broadcast_to(np.asarray(half_width_m, dtype=np.float64), lateral.shape)
    bands = sorted(zip((lateral - half).tolist(), (lateral + half).tolist(), strict=True))
    gaps: list[tuple[float, float]] = []
    cursor = -limit_m
    for lo, hi in bands:
        if lo > cursor:
            gaps.append((cursor, lo))
        cursor = max(cursor, hi)
    if cursor < limit_m:
        gaps.append((cursor, limit_m))
    return [(a, b) for a, b in gaps if b - a > 1e-6]


def _route_frame(poly: Polyline, s: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Point, unit tangent and left normal of the dense route polyline at arc length s."""
    s_list = poly.s_list
    j = min(bisect.bisect_left(s_list, s), len(s_list) - 1)
    if j > 0 and (s - s_list[j - 1]) < (s_list[j] - s):
        j -= 1
    t = poly.tangents[j]
    p = poly.points[j] + t * (s - s_list[j])
    return p, t, poly.normals[j]


@dataclass(frozen=True, slots=True)
class AvoidanceRequest:
    """Everything a re-plan needs, in the world frame (x, y metres).

    start_xy / start_dir: current reference point and unit tangent; start_dir None means the
    vehicle is at rest and may leave in any direction. conflict_xy: remembered points that
    the current path comes too close to. obstacles_xy: all remembered points nearby.
    committed_side: side already chosen for this obstacle (hysteresis). free_left_m /
    free_right_m: how much free range the side sensors report. avoid_side: a side that was
    found to be a dead end. obstacles_inflation: per point of obstacles_xy, metres to keep
    beyond D_min + margin (None: 0).
    """

    start_xy: FloatArray
    start_dir: FloatArray | None
    conflict_xy: FloatArray
    obstacles_xy: FloatArray
    committed_side: Side = Side.NONE
    free_left_m: float = 0.0
    free_right_m: float = 0.0
    avoid_side: Side = Side.NONE
    obstacles_inflation: FloatArray | None = None


def plan_detour(route: Route, request: AvoidanceRequest, params: PlannerParams) -> Detour | None:
    """Best feasible correction of the path (see the module docstring), or None (blocked):
    `detour_search` run to its end."""
    search = detour_search(route, request, params)
    while True:
        try:
            next(search)
        except StopIteration as done:
            result: Detour | None = done.value
            return result


@dataclass(slots=True)
class SearchFrame:
    """What a correction search computes from the route, the obstacle points and the
    conflict alone, not from where it starts: the points in the route's Frenet frame, the
    window [s_a, s_b] they grow the conflict into, the lateral offsets and inflations that
    block it, the clearance memo and the route tails it has measured. `retreat_search` tries
    many starts against the same points and shares one frame among them (the same numbers
    as a frame made afresh for each)."""

    poly: Polyline
    obstacles_xy: FloatArray
    inflation_m: FloatArray
    l_seed: FloatArray
    s_a: float
    s_b: float
    l_window: FloatArray
    infl_window: FloatArray
    memo: ClearanceMemo
    tails: dict[float, list[CubicBezier]]
    """The route after each rejoin point tried (candidates share them), filled in by
    `_build`; the memo measures each tail segment once."""

    @classmethod
    def of(cls, route: Route, request: AvoidanceRequest, params: PlannerParams) -> SearchFrame:
        """The frame of the request's obstacle points and conflict (not empty) on route."""
        d_m = params.d_min_m + params.clearance_margin_m
        poly = route.polyline()
        obstacles = request.obstacles_xy
        inflation = request.obstacles_inflation
        if inflation is None:
            inflation = np.zeros(len(obstacles))
        s_obs, l_obs = project(poly, obstacles)
        s_seed, l_seed = project(poly, request.conflict_xy)
        s_a, s_b = float(s_seed.min()), float(s_seed.max())
        lat_limit = float(np.max(np.abs(l_seed))) + 2.0 * d_m + 2.0
        window = np.zeros(len(s_obs), dtype=bool)
        # An inflated point reaches e farther along and across the route than the point.
        s_lo, s_hi, l_abs = s_obs - inflation, s_obs + inflation, np.abs(l_obs) + inflation
        for _ in range(20):
            window = (s_hi >= s_a - 2.0 * d_m) & (s_lo <= s_b + 2.0 * d_m)
            window &= np.abs(l_obs) - inflation <= lat_limit
            if not window.any():
                break
            new_a, new_b = float(s_lo[window].min()), float(s_hi[window].max())
            new_limit = max(lat_limit, float(np.max(l_abs[window])) + 2.0 * d_m)
            if new_a == s_a and new_b == s_b and new_limit == lat_limit:
                break
            s_a, s_b, lat_limit = min(s_a, new_a), max(s_b, new_b), new_limit
        if window.any():
            l_window, infl_window = l_obs[window], inflation[window]
        else:
            l_window, infl_window = l_seed, np.zeros(len(l_seed))
        return cls(
            poly=poly,
            obstacles_xy=obstacles,
            inflation_m=inflation,
            l_seed=l_seed,
            s_a=s_a,
            s_b=s_b,
            l_window=l_window,
            infl_window=infl_window,
            memo=ClearanceMemo(obstacles, inflation),  # sorted once; tails measured once
            tails={},
        )


def detour_search(
    route: Route,
    request: AvoidanceRequest,
    params: PlannerParams,
    frame: SearchFrame | None = None,
) -> Generator[None, None, Detour | None]:
    """`plan_detour` in work units: yields once after the set-up (the projections and the
    candidate list) and once after each candidate tried and rejected, and returns the
    Detour or None.
    A caller with a budget of units per cycle can resume it next cycle (the search is
    deterministic and clock-free); run to its end it is exactly `plan_detour`.
    frame: `SearchFrame.of(route, request, params)`, or one made for another request with
    the same obstacle points, inflations and conflict (made here when None)."""
    d_m = params.d_min_m + params.clearance_margin_m
    if len(request.conflict_xy) == 0:
        return None
    if frame is None:
        frame = SearchFrame.of(route, request, params)
    poly, obstacles, inflation = frame.poly, frame.obstacles_xy, frame.inflation_m
    l_seed, s_a, s_b = frame.l_seed, frame.s_a, frame.s_b
    l_window, infl_window = frame.l_window, frame.infl_window
    s0_arr, l0_arr = project(poly, request.start_xy[None, :])
    s0, l0 = float(s0_arr[0]), float(l0_arr[0])

    start_clear = float(min_distance(request.start_xy[None, :], obstacles, inflation)[0])
    seed_mid = _median(l_seed)
    across = float(np.min(np.abs(l_seed - l0))) < ACROSS_M
    mode = PathMode.AROUND if across else PathMode.SHIFT
    on_route = abs(l0) < 0.05 and request.start_dir is not None

    # Every offset and transition keeping D_m, cheapest first; then, where the margin leaves
    # room, the same keeping only the re-plan trigger (D_min + margin / 2) plus a little: a
    # passage narrower than 2 D_m is still one to pass. Paths at the trigger are not in
    # conflict with it, so the re-plan does not come back every cycle.
    narrow_m = params.d_min_m + 0.5 * params.clearance_margin_m + 0.05
    options: list[tuple[float, float, Side, float | None, float, bool, float]] = []
    for keep_m, extra in ((d_m, 0.0), (narrow_m, NARROW_COST_M)):
        if extra > 0.0 and d_m - keep_m < 0.1:
            break
        candidates = _offsets(
            free_intervals(l_window, keep_m + 0.05 + infl_window), l0, mode, seed_mid, request
        )
        options += [
            (cost + extra, w, side, leave, at, through, keep_m)
            for cost, w, side, leave, at, through in _with_transitions(
                candidates, l0, s0, s_a, s_b, keep_m, params, on_route, route
            )
        ]

    tails, memo = frame.tails, frame.memo
    yield
    for cost, w, side, leave, transition, through_base, keep_m in options:
        built = _build(
            route, poly, request, params, s0, leave, transition, s_b, w, keep_m, tails, through_base
        )
        if built is None:
            yield
            continue
        detour_segments, rejoin_s, tail = built
        if max_abs_curvature(detour_segments) > 1.0 / params.min_turn_radius_m * 1.001:
            yield
            continue
        if not keeps_clear(
            detour_segments, tail, obstacles, inflation, keep_m, start_clear, params, memo
        ):
            yield
            continue
        extra = sum(seg.length for seg in detour_segments) - (rejoin_s - s0)
        return Detour(
            path=Path([*detour_segments, *tail]),
            rejoin_s=rejoin_s,
            offset_m=w,
            side=side,
            mode=mode,
            cost=cost + max(extra, 0.0),
        )
    return None


def _offsets(
    gaps: list[tuple[float, float]],
    l0: float,
    mode: PathMode,
    seed_mid: float,
    request: AvoidanceRequest,
) -> list[tuple[float, float, Side]]:
    """Candidate offsets (cost, w, side), cheapest first: per gap between the blocked bands,
    the offset nearest the current one (l0) and the one nearest the route, and around an
    obstacle across the path each with an extra berth (see the module docstring)."""
    candidates: list[tuple[float, float, Side]] = []
    for lo, hi in gaps:
        offsets: list[tuple[float, float]] = []  # (w, cost adjustment)
        for target in (l0, 0.0):
            w = min(max(target, lo + 1e-3), hi - 1e-3)
            offsets.append((w, 0.0))
            if mode is PathMode.AROUND:
                # Seen from the front, an obstacle's far extent is unknown: prefer a berth.
                berth = w + UNSEEN_BERTH_M if w <= lo + 1e-2 else w - UNSEEN_BERTH_M
                if lo < berth < hi and (w <= lo + 1e-2 or w >= hi - 1e-2):
                    offsets.append((berth, -1.6 * UNSEEN_BERTH_M - 0.1))
        for w, adjust in offsets:
            side = Side.LEFT if w > seed_mid else Side.RIGHT
            cost = abs(w - l0) + 0.5 * abs(w) + adjust
            if request.committed_side is not Side.NONE and side is not request.committed_side:
                cost += SIDE_SWITCH_PENALTY_M
            if side is request.avoid_side:
                cost += DEAD_END_PENALTY_M
            less_free = Side.LEFT if request.free_left_m < request.free_right_m else Side.RIGHT
            if request.free_left_m != request.free_right_m and side is less_free:
                cost += LESS_FREE_SIDE_PENALTY_M
            if not any(abs(w - c[1]) < 1e-6 for c in candidates):
                candidates.append((cost, w, side))
    candidates.sort(key=lambda c: (c[0], c[1]))
    return candidates


def keeps_clear(
    segments: list[CubicBezier],
    tail: list[CubicBezier],
    obstacles_xy: FloatArray,
    inflation_m: FloatArray,
    keep_m: float,
    start_clear_m: float,
    params: PlannerParams,
    memo: ClearanceMemo | None = None,
) -> bool:
    """The clearance check of a new path (`comes_closer`): its own segments, then the route
    tail it joins as far as the look-ahead, keep keep_m - 0.05 (at least D_min) from every
    point; a start already closer than that (start_clear_m) must move out. memo: as in
    `comes_closer`."""
    required = min(keep_m - 0.05, max(params.d_min_m, start_clear_m - 0.05))
    floor = start_clear_m - 0.05 if start_clear_m - 0.05 < required else None
    ahead: list[CubicBezier] = []
    along = 0.0
    for seg in tail:
        if along > params.lookahead_m:
            break
        ahead.append(seg)
        along += seg.length
    return not comes_closer([*segments, *ahead], obstacles_xy, required, inflation_m, floor, memo)


_CHUNK_SAMPLES = 64
"""`ClearanceMemo.within` measures a path's samples this many at a time (consecutive, so a
chunk spans about 13 m of path at _SAMPLE_SPACING_M)."""


class ClearanceMemo:
    """A search's obstacle points (fixed for the search) prepared for many clearance checks,
    and what `comes_closer` measured of each segment it saw (its samples, their clearance
    below a limit), kept for the segments that come back: the route tail that many
    candidates rejoin. The points are sorted by x once, so that a segment's bounding box
    takes its points by two binary searches instead of a test of every point; the points
    inside the box are the same as `min_distance_within` takes, so the numbers are the
    same. The segments are held, so an id is never reused while its entry lives."""

    def __init__(self, obstacles_xy: FloatArray, inflation_m: FloatArray | None) -> None:
        order = np.argsort(obstacles_xy[:, 0], kind="stable")
        self._xy = obstacles_xy[order]
        self._x = self._xy[:, 0]
        self._inflation = None if inflation_m is None else inflation_m[order]
        self._max_inflation = (
            float(inflation_m.max()) if inflation_m is not None and len(inflation_m) else 0.0
        )
        self._entries: dict[tuple[int, float], tuple[CubicBezier, FloatArray, FloatArray]] = {}
        self._bases: dict[int, FloatArray] = {}  # `CubicBezier.sample`'s, by sample count

    def within(self, samples_xy: FloatArray, cutoff_m: float) -> FloatArray:
        """`min_distance_within(samples_xy, obstacles, cutoff_m, inflation)`: the same
        numbers below cutoff_m (elsewhere >= cutoff_m). Samples along a path are taken
        _CHUNK_SAMPLES at a time, each run with the points of its own box: a long segment's
        box holds many points that none of its stretches comes near."""
        n = len(samples_xy)
        if n <= _CHUNK_SAMPLES:
            return self._within_box(samples_xy, cutoff_m)
        out = np.empty(n)
        for a in range(0, n, _CHUNK_SAMPLES):
            out[a : a + _CHUNK_SAMPLES] = self._within_box(
                samples_xy[a : a + _CHUNK_SAMPLES], cutoff_m
            )
        return out

    def _within_box(self, samples_xy: FloatArray, cutoff_m: float) -> FloatArray:
        """`within` against the points in the samples' box grown by cutoff_m plus the
        largest inflation (the only points that can come nearer than cutoff_m)."""
        if len(samples_xy) == 0 or len(self._xy) == 0:
            return np.full(len(samples_xy), np.inf)
        grow = cutoff_m + self._max_inflation
        lo = samples_xy.min(axis=0) - grow
        hi = samples_xy.max(axis=0) + grow
        i0 = int(np.searchsorted(self._x, lo[0], side="left"))
        i1 = int(np.searchsorted(self._x, hi[0], side="right"))
        xy = self._xy[i0:i1]
        inside = (xy[:, 1] >= lo[1]) & (xy[:, 1] <= hi[1])
        infl = None if self._inflation is None else self._inflation[i0:i1][inside]
        return min_distance(samples_xy, xy[inside], infl)

    def measure(self, seg: CubicBezier, limit_m: float) -> tuple[FloatArray, FloatArray]:
        """The segment's samples (`sample_segments`) and their clearance below limit_m."""
        key = (id(seg), limit_m)
        entry = self._entries.get(key)
        if entry is None:
            samples = sample_segments([seg], self._bases)
            entry = self._entries[key] = (seg, samples, self.within(samples, limit_m))
        return entry[1], entry[2]


def comes_closer(
    segments: list[CubicBezier],
    obstacles_xy: FloatArray,
    limit_m: float,
    inflation_m: FloatArray | None = None,
    start_m: float | None = None,
    memo: ClearanceMemo | None = None,
) -> bool:
    """True if a sample of the segments (spaced as `sample_segments` spaces them) is closer
    than limit_m to an obstacle point's inflated disc. A path that starts closer (start_m,
    below limit_m) must move out: at a sample s metres along, the limit is
    min(limit_m, start_m + ESCAPE_SLOPE * s), and no other point may come nearer than
    it was at the start (`_approaches_another`). Segment by segment, stopping at the first
    that fails: most rejected candidates fail early, and a segment's bounding box leaves out
    most points. memo: a search's `ClearanceMemo`, made of these obstacles and inflations
    (it measures against its own copy, each segment once)."""
    along = 0.0
    for seg in segments:
        if memo is not None:
            samples, near = memo.measure(seg, limit_m)
        else:
            samples = sample_segments([seg])
            near = min_distance_within(samples, obstacles_xy, limit_m, inflation_m)
        if start_m is None or start_m >= limit_m or along > (limit_m - start_m) / ESCAPE_SLOPE:
            if float(near.min()) < limit_m:
                return True
        else:
            step = np.hypot(*np.diff(samples, axis=0).T)
            s = along + np.concatenate([[0.0], np.cumsum(step)])
            if np.any(near < np.minimum(limit_m, start_m + ESCAPE_SLOPE * s)):
                return True
            start_xy = segments[0].control[0]
            if _approaches_another(samples, start_xy, obstacles_xy, inflation_m, limit_m):
                return True
        along += seg.length
    return False


def _approaches_another(
    samples_xy: FloatArray,
    start_xy: FloatArray,
    obstacles_xy: FloatArray,
    inflation_m: FloatArray | None,
    limit_m: float,
) -> bool:
    """True if a sample of a path that moves out from inside limit_m comes nearer to some
    point's inflated disc than min(limit_m, that point's distance from the path's start) -
    ESCAPE_TOLERANCE_M.

    The escape's own floor rises from the nearest point's distance; measured as a minimum
    over all points, it lets the path close on any other point down to that floor. From
    deep inside one point's inflation (a disc the memory widened for a flank's foot) the
    floor is below 0, and a way out of that disc could lead into another solid."""
    if len(obstacles_xy) == 0:
        return False
    inside = _in_reach(samples_xy, obstacles_xy, limit_m, inflation_m)
    if not inside.any():
        return False
    pts = obstacles_xy[inside]
    infl = None if inflation_m is None else inflation_m[inside]
    floor = np.minimum(disc_distances(start_xy[None, :], pts, infl)[0], limit_m)
    near = disc_distances(samples_xy, pts, infl)
    return bool(np.any(near < floor[None, :] - ESCAPE_TOLERANCE_M))


def _hold_and_rejoin(
    route: Route, params: PlannerParams, hold_start: float, s_b: float, w: float, d_m: float
) -> tuple[float, float, float | None]:
    """Where a candidate at offset w stops holding it (route arc length, m), where it would
    like to be back on the route (a return S-curve later), and the arc length of the base
    point that cuts that return short (None: none does; the route's end counts as one)."""
    hold_end = max(s_b + d_m, hold_start + params.min_turn_radius_m)
    ret = max(
        1.3 * math.sqrt(6.0 * abs(w) * params.min_turn_radius_m),
        2.0 * params.min_turn_radius_m,
        4.0,
    )
    base_s = route.base_s_list  # the first base point beyond hold_end (ascending)
    i = bisect.bisect_right(base_s, hold_end + 1e-6)
    limit = base_s[i] if i < len(base_s) else route.length
    return hold_end, hold_end + ret, limit if hold_end + ret > limit else None


def passed_beside(
    route: Route, path: Path, start_xy: FloatArray, rejoin_s: float
) -> list[tuple[int, float]]:
    """Base points that a correction from start_xy, rejoining the route at rejoin_s, passes
    beside instead of through: (index into route.base_points, distance in metres) for each
    base point ahead of start_xy and before rejoin_s that the path misses by more than
    BASE_POINT_REACHED_M."""
    s0 = float(project(route.polyline(), np.asarray(start_xy, dtype=np.float64)[None, :])[0][0])
    ahead = np.flatnonzero((route.base_s > s0 + 0.5) & (route.base_s < rejoin_s - 1e-6))
    if len(ahead) == 0:
        return []
    points = path.polyline().points
    out: list[tuple[int, float]] = []
    for k in ahead.tolist():
        miss = float(np.min(np.hypot(*(points - route.base_points[k]).T)))
        if miss > BASE_POINT_REACHED_M:
            out.append((k, miss))
    return out


def _skipped(route: Route, leave_s: float, hold_end: float) -> int:
    """How many base points a candidate that leaves the route at leave_s and holds its
    offset to hold_end (route arc lengths, m) passes at that offset instead of through."""
    base_s = route.base_s_list  # ascending: those in (leave_s + 0.5, hold_end]
    first = bisect.bisect_right(base_s, leave_s + 0.5)
    return max(bisect.bisect_right(base_s, hold_end) - first, 0)


def _with_transitions(
    candidates: list[tuple[float, float, Side]],
    l0: float,
    s0: float,
    s_a: float,
    s_b: float,
    d_m: float,
    params: PlannerParams,
    on_route: bool,
    route: Route,
) -> list[tuple[float, float, Side, float | None, float, bool]]:
    """Each candidate offset with the route positions at which it may reach that offset:
    the window's start (s_a - D_m) when that is ahead, else a few lengths ahead of here.
    Later transitions cost a little more (they stay longer on the old line). A vehicle on
    the route first tries to stay on it until KEEP_ROUTE_FACTOR S-curve lengths before
    the offset is reached (the `leave` position; None: leave now): an obstacle seen from
    afar does not bend the path over terrain long before it.

    Where a base point comes before the return to the route is complete, each option is
    also offered through that base point from another direction (the last flag;
    THROUGH_BASE_COST_M more): rejoining before it along the route's own tangent can need a
    sharper S-curve than the turn radius allows."""
    out: list[tuple[float, float, Side, float | None, float, bool]] = []
    for cost, w, side in candidates:
        # A cubic S-curve shifting sideways by c over a length L curves at about 6 c / L^2.
        shortest = max(1.0, 1.1 * math.sqrt(6.0 * abs(w - l0) * params.min_turn_radius_m))
        # Reach the offset D_m before the window, or at its start (the clearance check of
        # the whole curve decides whether cutting in diagonally is safe), or a few S-curve
        # lengths ahead; later transitions cost a little more.
        options = [s_a - d_m, s_a - 0.5 * d_m, s_a]
        options += [s0 + factor * shortest for factor in TRANSITION_FACTORS]
        for i, at in enumerate(options):
            if at > s0 + 0.5:
                leave = at - KEEP_ROUTE_FACTOR * shortest
                hold_end, _, base_cut = _hold_and_rejoin(route, params, at, s_b, w, d_m)
                for through, extra in ((False, 0.0), (True, THROUGH_BASE_COST_M)):
                    if through and base_cut is None:
                        continue
                    if on_route and i < 3 and leave > s0 + 1.0:
                        skip = SKIP_BASE_COST_M * _skipped(route, leave, hold_end)
                        out.append(
                            (cost + extra + skip + 0.1 * i - 0.05, w, side, leave, at, through)
                        )
                    skip = SKIP_BASE_COST_M * _skipped(route, s0, hold_end)
                    out.append((cost + extra + skip + 0.1 * i, w, side, None, at, through))
    out.sort(key=lambda c: (c[0], c[1], c[5]))
    return out


def _build(
    route: Route,
    poly: Polyline,
    request: AvoidanceRequest,
    params: PlannerParams,
    s0: float,
    leave: float | None,
    hold_start: float,
    s_b: float,
    w: float,
    d_m: float,
    tails: dict[float, list[CubicBezier]],
    through_base: bool = False,
) -> tuple[list[CubicBezier], float, list[CubicBezier]] | None:
    """The Bezier chain of one candidate: reach offset w at route position hold_start, hold
    it to s_b + D_m, then rejoin the route; plus the route tail it rejoins. tails: the
    route split at rejoin points already tried (candidates share them), filled in here.

    The return to the route ends no later than the next base point, along the route's
    tangent there; with through_base it instead passes through that base point along the
    line from the hold's end to the rejoin point beyond it (Catmull-Rom), and rejoins the
    route one return length past the base point (or ends there, at the goal)."""
    hold_end, rejoin_s, base_s = _hold_and_rejoin(route, params, hold_start, s_b, w, d_m)
    ret = rejoin_s - hold_end
    if base_s is not None:
        rejoin_s = base_s
    if rejoin_s <= hold_end + 0.5:
        return None
    via_base: FloatArray | None = None
    base_t = np.zeros(2)
    if through_base:
        if base_s is None:
            return None
        if base_s >= route.length - 1e-9 and route.arrival_heading_given:
            return None  # the goal is to be reached along the heading asked for
        base_t = _route_frame(poly, base_s)[1]
        via_base = route.base_points[int(np.argmin(np.abs(route.base_s - base_s)))]
        later = route.base_s[route.base_s > base_s + 1e-6]
        rejoin_s = min(base_s + ret, float(later[0]) if len(later) else base_s)
        if base_s < rejoin_s <= base_s + 0.5:
            return None
    via: list[tuple[FloatArray, FloatArray]] = []
    if leave is not None:
        p, t, _ = _route_frame(poly, leave)
        via.append((p, t))
    if hold_start > s0 + 0.5:
        p, t, n = _route_frame(poly, hold_start)
        via.append((p + w * n, t))
    p, t, n = _route_frame(poly, hold_end)
    hold_p = p + w * n
    via.append((hold_p, t))
    rejoin_p, rejoin_t, _ = _route_frame(poly, rejoin_s)
    if via_base is not None:
        at_end = base_s is not None and base_s >= route.length - 1e-9  # the goal: arrive there
        base_dir = _base_direction(
            hold_p, t, via_base, base_t, None if at_end else rejoin_p, rejoin_t
        )
        if base_dir is None:
            return None
        via.append((via_base, base_dir))
        if at_end:
            rejoin_p, rejoin_t = via_base, base_dir
    via.append((rejoin_p, rejoin_t))

    start = np.asarray(request.start_xy, dtype=np.float64)
    first_target = via[0][0]
    start_dir = request.start_dir
    first_handle: float | None = None  # (None: a third of the chord)
    if start_dir is None:
        leaving = _start_direction(start, first_target, via[0][1])
        if leaving is None:
            return None
        start_dir, first_handle = leaving
    segments: list[CubicBezier] = []
    cur, cur_dir = start, np.asarray(start_dir, dtype=np.float64)
    for point, direction in via:
        if float(np.hypot(*(point - cur))) < 0.3:
            continue
        if float(np.dot(point - cur, cur_dir)) <= 0.0:
            return None  # the next via point is behind us: no smooth way to it
        handle = first_handle if not segments else None
        segments.append(segment_through(cur, cur_dir, point, direction, handle))
        cur, cur_dir = point, direction
    if not segments:
        return None
    if rejoin_s not in tails:
        tails[rejoin_s] = route.tail_from(rejoin_s)
    tail = tails[rejoin_s]
    # The route tail starts exactly at the rejoin point; snap the last segment's end to it.
    if tail:
        x0, y0, x1, y1, x2, y2, x3, y3 = segments[-1].control_floats
        tx, ty = tail[0].control_floats[:2]
        dx, dy = tx - x3, ty - y3
        segments[-1] = CubicBezier.from_floats([x0, y0, x1, y1, x2 + dx, y2 + dy, tx, ty])
    return segments, rejoin_s, tail


def _unit_or_none(v: FloatArray) -> FloatArray | None:
    norm = float(np.hypot(v[0], v[1]))
    return None if norm < 1e-9 else np.asarray(v / norm, dtype=np.float64)


def _base_direction(
    hold_p: FloatArray,
    hold_t: FloatArray,
    base_p: FloatArray,
    route_t: FloatArray,
    rejoin_p: FloatArray | None,
    rejoin_t: FloatArray,
) -> FloatArray | None:
    """Unit direction in which a correction passes a base point (`_build`'s through_base):
    of a few directions (the Catmull-Rom line from the hold's end to the rejoin point, the
    route's tangent at the base point, the hold's tangent mirrored about the chord, and
    halfway between the first and each of the others), the one whose segments into and out
    of the base point curve least. rejoin_p None: the base point is the route's end."""
    chord = _unit_or_none(base_p - hold_p)
    if chord is None:
        return None
    line = _unit_or_none((rejoin_p if rejoin_p is not None else base_p) - hold_p)
    assert line is not None
    mirrored = 2.0 * float(np.dot(hold_t, chord)) * chord - hold_t
    options = [line, route_t, mirrored]
    options += [v for v in (_unit_or_none(line + o) for o in options[1:]) if v is not None]
    # The options' segments first, then their curvature in one pass.
    kept: list[FloatArray] = []
    segs: list[CubicBezier] = []
    for d in options:
        if float(np.dot(d, chord)) <= 0.0:
            continue
        if rejoin_p is not None and float(np.dot(rejoin_p - base_p, d)) <= 0.0:
            continue
        kept.append(d)
        segs.append(segment_through(hold_p, hold_t, base_p, d))
        if rejoin_p is not None:
            segs.append(segment_through(base_p, d, rejoin_p, rejoin_t))
    if not kept:
        return None
    per_segment = max_abs_curvatures(segs)
    per_option = 1 if rejoin_p is None else 2
    best, best_kappa = None, math.inf
    for i, d in enumerate(kept):
        kappa = max(per_segment[per_option * i : per_option * (i + 1)])
        if kappa < best_kappa:
            best, best_kappa = d, kappa
    return best


def _start_direction(
    start: FloatArray, target: FloatArray, target_dir: FloatArray
) -> tuple[FloatArray, float | None] | None:
    """Unit direction in which a vehicle at rest (free to turn on the spot) leaves towards a
    point it must pass along target_dir, and the handle length of that first segment (None:
    a third of the chord). Of the chord (the default handles), target_dir mirrored about the
    chord (a circular arc: handles 4/3 tan(theta/4) r for a turn theta of radius r) and
    halfway between, the one whose segment curves least."""
    chord = _unit_or_none(target - start)
    if chord is None:
        return None
    length = float(np.hypot(*(target - start)))
    mirrored = 2.0 * float(np.dot(target_dir, chord)) * chord - target_dir
    half_turn = math.acos(min(1.0, max(-1.0, float(np.dot(target_dir, chord)))))
    arc_handle = None
    if half_turn > 1e-6:
        radius = length / (2.0 * math.sin(half_turn))
        arc_handle = 4.0 / 3.0 * math.tan(half_turn / 2.0) * radius
    options: list[tuple[FloatArray, float | None]] = [(chord, None), (mirrored, arc_handle)]
    halfway = _unit_or_none(chord + mirrored)
    if halfway is not None:
        options.append((halfway, None))
    kappas = max_abs_curvatures(
        [segment_through(start, d, target, target_dir, h, h) for d, h in options]
    )
    return options[int(np.argmin(kappas))]


def _median(values: FloatArray) -> float:
    """The median of a 1-D array, as `np.median` gives it (the mean of the two middle values
    when their number is even). np.median's first call in a process imports numpy.ma (about
    10 ms): a re-plan cycle must not pay that in flight."""
    v = np.sort(values)
    n = len(v)
    if n % 2:
        return float(v[n // 2])
    return float((v[n // 2 - 1] + v[n // 2]) / 2.0)
