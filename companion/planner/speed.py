"""The reference speed schedule: how fast X_d may move along the path this cycle.

The speed is v_d lowered by every limit ahead (each the speed from which the vehicle can
still stop, or slow to a curve's speed, braking at accel_max), then ramped from last
cycle's speed. Pure functions of plain numbers and the look-ahead's arrays; metres, seconds,
m/s. `Planner.step` composes them in this order: `reference_speed`, `ramp`,
`step_to_next_stop`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from companion.planner.types import FloatArray

STOPPED_MPS = 1e-3
"""Below this speed X_d counts as at rest."""
_STOP_SHORT_M = 0.05
"""How far short of a place closer than the re-plan distance X_d stops, metres."""
_REST_M = 0.01
"""Closer than this to its stop X_d stops at once (`reacting_speed` would creep), metres."""


def braking_speed(distance_m: float, accel_mps2: float) -> float:
    """The speed from which braking at accel_mps2 stops within distance_m (0 if <= 0)."""
    return math.sqrt(2.0 * accel_mps2 * max(distance_m, 0.0))


def stepped_braking_speed(distance_m: float, accel_mps2: float, dt_s: float) -> float:
    """The speed from which slowing by accel_mps2 dt_s a cycle of dt_s stops within
    distance_m: `braking_speed` less the overshoot of braking in steps, so that a speed
    commanded each cycle does not pass its stop (0 if distance_m <= 0)."""
    step = accel_mps2 * dt_s
    return step * (math.sqrt(2.0 * max(distance_m, 0.0) / (step * dt_s) + 0.25) - 0.5)


def reacting_speed(distance_m: float, accel_mps2: float, reaction_s: float) -> float:
    """The speed v from which a vehicle that keeps v for reaction_s seconds, then brakes at
    accel_mps2, stops within distance_m: v t + v^2 / (2 a) = d (0 if d <= _REST_M)."""
    if distance_m <= _REST_M:
        return 0.0
    a, t = accel_mps2, reaction_s
    return a * (math.sqrt(t * t + 2.0 * distance_m / a) - t)


def rest_margin_m(cruise_mps: float, reaction_s: float) -> float:
    """How far short of the re-plan distance X_d comes to rest before an obstacle, metres:
    the distance flown at the cruise speed in the reaction time. Readings that arrive late
    place the obstacle that much too far while the vehicle approaches at cruise speed, and
    by the time the vehicle has slowed and the readings have caught up, X_d has stopped:
    the vehicle's overshoot of a decelerating setpoint then ends inside the band unless the
    rest point itself is short of it. 0 with reaction_s 0 (the paper's ideal stop)."""
    return max(cruise_mps, 0.0) * max(reaction_s, 0.0)


def leash_limit(lag_m: float, leash_m: float, v_max_mps: float, accel_mps2: float) -> float:
    """The speed X_d may keep with the vehicle lag_m from it (3-D, metres): v_max_mps up to
    half the leash, then the speed from which braking at accel_mps2 stops at the leash
    (0 within _REST_M of it and beyond)."""
    if lag_m <= 0.5 * leash_m:
        return v_max_mps
    room = leash_m - lag_m
    return min(v_max_mps, braking_speed(room, accel_mps2)) if room > _REST_M else 0.0


def next_stop(stops: Sequence[float], s_m: float) -> float | None:
    """The first stop (arc length on the path: a cusp, the end of a retreat) ahead of s_m."""
    for stop in stops:
        if stop > s_m + 1e-9:
            return stop
    return None


def curve_limit(
    curve_s: FloatArray, curve_v_sq: FloatArray, s_m: float, accel_mps2: float
) -> float:
    """The speed from which every curve sample ahead (arc length curve_s, squared curve speed
    curve_v_sq = lat_accel_max / |curvature|) is reached braking at accel_mps2; inf if none."""
    if len(curve_s) == 0:
        return math.inf
    reach_sq = curve_v_sq + 2.0 * accel_mps2 * (curve_s - s_m)
    return math.sqrt(float(reach_sq.min()))


def clearance_limit(
    look_s: FloatArray,
    clearance_m: FloatArray,
    s_m: float,
    accel_mps2: float,
    replan_distance_m: float,
    stop_at_band: bool,
    reaction_s: float = 0.0,
    allowance_m: float = 0.0,
    rest_margin_m: float = 0.0,
) -> float:
    """The speed from which X_d stops _STOP_SHORT_M before the first look-ahead sample
    (arc lengths look_s, clearances clearance_m) closer than the re-plan distance; inf if none.

    reaction_s: the stop is planned as if the vehicle kept its speed that long before braking
    (late readings, a position controller that trails its setpoint), so it brakes v t earlier.
    allowance_m: a further distance short of it (the vehicle measured ahead of X_d).
    rest_margin_m: and a further one for where X_d comes to rest (`rest_margin_m`), when
    stop_at_band (a blocked planner's stop).

    stop_at_band: the planner is blocked or still searching, so it stops before the band
    even when already inside it. Otherwise a path that leads out of the band (an accepted
    correction that starts inside it, a retreat that starts next to the obstacle) is free:
    only places closer than here count, and never "stop where we are" on a path that moves
    away."""
    limit = replan_distance_m
    if not stop_at_band:
        limit = min(limit, float(clearance_m[0]) - _STOP_SHORT_M)
    too_close = (clearance_m < limit).nonzero()[0]
    if len(too_close) == 0:
        return math.inf
    short = _STOP_SHORT_M + max(allowance_m, 0.0)
    if stop_at_band:
        # The rest margin is for the stop of a blocked planner. On a path that is flown
        # (a retreat along the covered track, a correction leaving the band) a place a
        # little closer than the trigger ahead is passed through as before: with the margin
        # X_d would rest short of it for good, neither blocked nor moving.
        short += max(rest_margin_m, 0.0)
    free = float(look_s[too_close[0]] - s_m) - short
    if reaction_s <= 0.0:
        return braking_speed(free, accel_mps2)
    return reacting_speed(free, accel_mps2, reaction_s)


BAND_CREEP_M = 0.1
"""`band_limit`: the distance allowed as if D_min were this much nearer, so that X_d inside
D_min can still creep out, metres."""


def band_limit(
    clearance_m: float,
    floor_m: float,
    replan_distance_m: float,
    accel_mps2: float,
    reaction_s: float,
) -> float:
    """The speed cap of X_d inside the re-plan band (clearance_m, X_d's distance from the
    remembered points, below replan_distance_m): the speed from which the vehicle stops
    before that clearance falls to floor_m (D_min, or lower on a way out from a rest
    inside it), were every metre flown a metre nearer: points seen on the way can be
    that much nearer than the memory has them. BAND_CREEP_M lets X_d creep at the floor.
    inf outside the band."""
    if clearance_m >= replan_distance_m:
        return math.inf
    return reacting_speed(clearance_m - floor_m + BAND_CREEP_M, accel_mps2, reaction_s)


def ramp(v_mps: float, v_target_mps: float, accel_mps2: float, dt_s: float) -> float:
    """Next cycle's reference speed: towards v_target, up at accel_max and down at twice
    that per cycle of dt_s; snapped to 0 when stopping below STOPPED_MPS."""
    step = accel_mps2 * dt_s
    v = min(max(v_target_mps, v_mps - 2.0 * step), v_mps + step)
    if v < STOPPED_MPS and v_target_mps <= 0.0:
        return 0.0
    return v


def step_to_next_stop(step_m: float, s_m: float, stops: Sequence[float], phi_d_rad: float) -> float:
    """The 3-D step of eq. (5), shortened to land exactly on the next stop, never across it
    (the horizontal arc is step cos(phi_d))."""
    stop = next_stop(stops, s_m)
    if stop is None:
        return step_m
    return min(step_m, (stop - s_m) / max(math.cos(phi_d_rad), 1e-6))
