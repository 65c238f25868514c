"""How far ahead a sensor layout can flag a wall as too steep, and the speed that allows a
stop within that distance.

A planner can only avoid what it has judged steep. Whether a reading is steep is decided
from chords between measured points (eq. 6 and `decision.chord_steepness`), and a layout of
level obstacle sensors with down-tilted surface sensors cannot tell a wall from climbable
relief until it is close: the chord from the ground point in front (H_d below, g ahead) to
the level hit on the wall, d ahead, is steeper than phi*_max only when
d < g + H_d / tan(phi*_max). Whatever the layout, the reference speed must let the vehicle
stop before it comes within the re-plan distance of a wall first flagged there, including
the reaction allowance of the stop (`PlannerParams.reaction_time_s`): what the sensors can
confirm must cover the reaction distance as well as the braking distance.

`level_gaps_deg` says where a layout has no obstacle sensor looking level ahead: a solid
approached from such a bearing is seen only when a surface sensor reaches it or a ray at the
gap's edge meets it, whatever the speed. `sweep_amplitude_rad` is how far the heading must
swing either way for the rays to cross every bearing ahead (the planner's yaw sweep).

All lengths in metres, angles in radians (degrees where a name says so), body FLU with the
vehicle level.
"""

from __future__ import annotations

import math

import numpy as np

from companion.planner.sensors import Group, Role, SensorTable

_AHEAD_COS = math.cos(math.radians(35.0))
"""Obstacle sensors within this angle of the nose (horizontally) look where the vehicle goes."""
_LEVEL_TOLERANCE_RAD = math.radians(10.0)
"""Obstacle sensors whose boresight is within this of the horizontal look at flight height."""
_SWEEP_ELEVATION_RAD = math.radians(35.0)
"""Obstacle sensors within this of the horizontal count for the yaw sweep's gaps: a beam
tilted up 25 degrees meets a solid at least d tan(25 deg) tall d away, which a pole or a
wall standing on the ground is, and one that is not is flown over."""
SWEEP_AMPLITUDE_MAX_RAD = math.radians(30.0)
"""The yaw sweep swings at most this far either side of the path's heading: farther, the
surface sensors' ground points leave the path's line by more than half H_d."""


def forward_depression_rad(sensors: SensorTable) -> float:
    """How far below the horizontal the forward surface sensor looks, radians (<= 0: it
    does not look down): over level ground at height h it lands h / tan(this) ahead."""
    fwd = sensors.specs[sensors.surface_index[Group.SURFACE_FORWARD]].boresight_flu
    return -math.atan2(float(fwd[2]), math.hypot(float(fwd[0]), float(fwd[1])))


def wall_flag_distance_m(sensors: SensorTable, h_d_m: float, threshold_rad: float) -> float:
    """Horizontal distance ahead at which the layout first flags a vertical wall across the
    path as steeper than threshold_rad, flying level at H_d over flat ground. 0 if it never
    does (no forward-looking obstacle sensor, or no forward surface reading to pair with)."""
    depression = forward_depression_rad(sensors)
    if depression <= 0.0:
        return 0.0
    ground_ahead = h_d_m / math.tan(depression)  # g: where the forward surface ray lands
    if ground_ahead >= sensors.specs[sensors.surface_index[Group.SURFACE_FORWARD]].max_range_m:
        return 0.0
    tan_thr = math.tan(threshold_rad)
    best = 0.0
    for spec in sensors.specs:
        u = spec.boresight_flu
        horizontal = math.hypot(float(u[0]), float(u[1]))
        if spec.role is not Role.OBSTACLE or horizontal < 1e-6:
            continue
        if float(u[0]) / horizontal < _AHEAD_COS:
            continue
        # A wall d ahead (across the path) is hit at (d, d u1/u0, H_d + d u2/u0) from the
        # ground point's foot; the chord to the ground point (g, 0, 0) is steep while its
        # rise exceeds tan(threshold) times its horizontal length.
        d = np.arange(ground_ahead + 0.05, spec.max_range_m * float(u[0]), 0.05)
        rise = h_d_m + d * float(u[2]) / float(u[0])
        run = np.hypot(d - ground_ahead, d * float(u[1]) / float(u[0]))
        flagged = d[rise > tan_thr * run]
        if len(flagged):
            best = max(best, float(flagged.max()))
    return best


def layout_speed_limit_mps(
    flag_distance_m: float,
    replan_distance_m: float,
    accel_mps2: float,
    dt_s: float,
    reaction_s: float = 0.0,
    allowance_m: float = 0.0,
) -> float:
    """Largest speed v from which the vehicle stops (braking at accel_mps2) before it comes
    within replan_distance_m of a wall first flagged flag_distance_m ahead, as the stop is
    planned (`speed.clearance_limit`): one cycle of dt_s at v before the wall is seen, then
    reaction_s at v before braking, and the rest point a further v * reaction_s short (the
    readings of the approach place the wall that much too far, `speed.rest_margin_m`), and
    allowance_m short (the vehicle measured ahead of X_d):
    v (dt + 2 t) + v^2 / (2 a) <= flag - replan - allowance. 0 if there is no room."""
    room = flag_distance_m - replan_distance_m - max(allowance_m, 0.0)
    if room <= 0.0:
        return 0.0
    a = accel_mps2
    lag = dt_s + 2.0 * max(reaction_s, 0.0)
    # v^2 / (2a) + v lag - room = 0
    return -a * lag + math.sqrt((a * lag) ** 2 + 2.0 * a * room)


def level_gaps_deg(
    sensors: SensorTable, tolerance_rad: float = _LEVEL_TOLERANCE_RAD
) -> list[tuple[float, float]]:
    """Bearing intervals of the half ahead (degrees, body frame, clockwise from the nose as
    MAVLink's yaw: -90 left to 90 right) that no obstacle sensor looking level covers (its
    boresight within tolerance_rad of the horizontal; a beam covers its bearing, a sector
    its field of view), widest first. Empty when the level sensors cover the half."""
    covered: list[tuple[float, float]] = []
    for spec in sensors.specs:
        u = spec.boresight_flu
        horizontal = math.hypot(float(u[0]), float(u[1]))
        if spec.role is not Role.OBSTACLE or horizontal < 1e-9:
            continue
        if abs(math.atan2(float(u[2]), horizontal)) > tolerance_rad:
            continue
        bearing = -math.degrees(math.atan2(float(u[1]), float(u[0])))
        half = 0.5 * math.degrees(spec.fov_rad)
        covered.append((bearing - half, bearing + half))
    gaps: list[tuple[float, float]] = []
    edge = -90.0
    for lo, hi in sorted(covered):
        if lo > edge:
            gaps.append((edge, min(lo, 90.0)))
        edge = max(edge, hi)
        if edge >= 90.0:
            break
    if edge < 90.0:
        gaps.append((edge, 90.0))
    # Rounded to a micro-degree, so that equal gaps are equal and order by bearing (+ 0.0:
    # no -0.0).
    gaps = [(round(a, 6) + 0.0, round(b, 6) + 0.0) for a, b in gaps if b - a > 1e-6]
    return sorted(gaps, key=lambda g: (g[0] - g[1], g[0]))


def sweep_amplitude_rad(sensors: SensorTable) -> float:
    """Half the widest bearing gap ahead between the obstacle sensors within
    _SWEEP_ELEVATION_RAD of the horizontal (`level_gaps_deg`), at most SWEEP_AMPLITUDE_MAX_RAD:
    how far the heading must swing either way for the rays at a gap's edges to cross every
    bearing of it (`Planner`'s yaw sweep). 0 when those sensors cover the half ahead.
    Radians."""
    gaps = level_gaps_deg(sensors, _SWEEP_ELEVATION_RAD)
    if not gaps:
        return 0.0
    lo, hi = gaps[0]
    return min(0.5 * math.radians(hi - lo), SWEEP_AMPLITUDE_MAX_RAD)


def describe_sweep(amplitude_rad: float, period_m: float) -> str:
    """The yaw sweep for a person: "the heading swings A deg either way over P m of
    travel" (`sweep_amplitude_rad`, `PlannerParams.yaw_sweep_period_m`)."""
    swing = math.degrees(amplitude_rad)
    return f"the heading swings {swing:.0f} deg either way over {period_m:g} m of travel"


def describe_level_gaps(sensors: SensorTable) -> str:
    """One line for a person: the widest bearing gap ahead without a level obstacle sensor
    (`level_gaps_deg`) and what it means, or that there is none."""
    gaps = level_gaps_deg(sensors)
    if not gaps:
        return "level obstacle sensors cover the half ahead"
    lo, hi = gaps[0]
    widest = hi - lo
    # A solid of width w between two rays `widest` apart meets one within w / (2 sin(gap/2)).
    reach = 1.0 / (2.0 * math.sin(math.radians(widest) / 2.0))
    return (
        f"{len(gaps)} bearing gap(s) ahead without a level obstacle sensor, the widest "
        f"{widest:.0f} deg ({_side(lo)} to {_side(hi)}): a solid in a gap meets a level ray "
        f"only within {reach:.1f} m per metre of its width"
    )


def _side(bearing_deg: float) -> str:
    """'the nose', or 'N deg left/right' for a body bearing (degrees, right positive)."""
    if abs(bearing_deg) < 0.5:
        return "the nose"
    side = "right" if bearing_deg > 0.0 else "left"
    return f"{abs(bearing_deg):.0f} deg {side}"
