"""Eqs (6)-(7): how steep is what the obstacle sensors see, and which way to avoid it."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from companion.planner.params import PlannerParams
from companion.planner.sensors import Group
from companion.planner.types import BoolArray, Decision, FloatArray, IntArray

_ROWS = np.arange(64, dtype=np.intp)
_SMALL_CLOUD = 10
"""Up to this many points `chord_steepness` loops in plain floats (fewer calls than the
array form's two dozen numpy operations); the numbers are the same (`tests/test_decision`)."""


def steepness(
    obstacle_points: FloatArray, ground_points: FloatArray, detected: BoolArray
) -> FloatArray:
    """Eq. (6): phi_i* = arctan((z_di - z_hj) / |[x_di, y_di] - [x_hj, y_hj]|), radians.

    obstacle_points: X_di, (m, 3) world ENU. ground_points: the paired surface point X_hj of
    each sensor's group, (m, 3) (left group with the left point, forward with forward, right
    with right; docs/paper.md). detected: (m,) bool; phi_i* = 0 where d_i = 0 (nothing seen).
    """
    rel = obstacle_points - ground_points
    horizontal = np.hypot(rel[:, 0], rel[:, 1])
    phi = np.arctan2(rel[:, 2], horizontal)
    return np.where(detected, phi, 0.0)


def thresholds(groups: tuple[Group, ...], params: PlannerParams) -> FloatArray:
    """Eq. (7): phi*_max per obstacle sensor: phi_max for the forward group and
    min(arctan(H_d / D_min), phi_max) for the left and right groups. Radians."""
    side = params.side_threshold_rad
    return np.array([params.phi_max_rad if g is Group.FORWARD else side for g in groups])


def decide(phi_star: FloatArray, threshold: FloatArray) -> Decision:
    """Eq. (7) decision: horizontal if any phi_i* exceeds its threshold, else vertical."""
    return Decision.HORIZONTAL if (phi_star > threshold).any() else Decision.VERTICAL


def decide_rows(phi_star: Sequence[float], threshold: Sequence[float]) -> Decision:
    """`decide` on plain floats (the planner's per-cycle path): the same comparisons."""
    for p, t in zip(phi_star, threshold, strict=True):
        if p > t:
            return Decision.HORIZONTAL
    return Decision.VERTICAL


def chord_steepness(points: FloatArray, min_separation_m: float) -> tuple[FloatArray, IntArray]:
    """The steepest chord from each point down to another, and which one: the project's
    complement to eq. (6).

    points: (n, 3) world ENU, every surface point measured this cycle (obstacle and surface
    sensors, the held ground points). For each point i: max over the points k lower than i
    and at least min_separation_m away from it horizontally or vertically (below it) of
    arctan((z_i - z_k) / |xy_i - xy_k|), radians (pi/2 straight above), and that k; 0 and
    -1 where there is none.

    Why: on a height field the slope of a chord between two surface points is the slope of
    the surface at some point between them (mean value theorem), so the steepest chord is a
    lower bound on how steep the surface is there, never more. Eq. (6) measures one chord,
    from the obstacle point to its group's ground point; seen from afar at a slant, that
    chord is far shallower than the flank it ends on (a 50 degree mesa read as climbable).
    Two rays that hit the same flank measure the flank itself.

    Separation: over a short chord a few centimetres of range noise would tilt the slope a
    lot, so both ends must lie min_separation_m apart. Horizontally or vertically: two rays
    that meet a vertical wall (a level beam and one tilted up above it) hit it at nearly
    the same horizontal place, one above the other, and that chord, the plainest evidence
    of a wall, is steeper than 45 degrees whatever the noise.
    """
    n = len(points)
    if n < 2:
        return np.zeros(n), np.full(n, -1, dtype=np.intp)
    if n <= _SMALL_CLOUD:
        return _chord_steepness_small(points, min_separation_m)
    # About a dozen points a cycle: the number of array operations sets the cost.
    x, y, z = points.T
    dz = np.subtract.outer(z, z)
    dx = np.subtract.outer(x, x)
    dy = np.subtract.outer(y, y)
    h = np.sqrt(dx * dx + dy * dy)
    usable = (dz > 0.0) & ((h >= min_separation_m) | (dz >= min_separation_m))
    # arctan is increasing, so the steepest chord is the one of largest dz / h (inf where
    # h = 0, -1 where not usable); the angle is taken of that chord only.
    ratio = np.divide(dz, h, out=np.full((n, n), -1.0), where=usable & (h > 0.0))
    ratio[usable & (h == 0.0)] = np.inf
    partner = ratio.argmax(axis=1)
    flat = partner + n * (_ROWS[:n] if n <= len(_ROWS) else np.arange(n))  # (i, partner i)
    found = ratio.ravel()[flat] >= 0.0
    best = np.arctan2(dz.ravel()[flat], h.ravel()[flat])
    return np.where(found, best, 0.0), np.where(found, partner, -1)


def chord_steepness_rows(
    points: list[list[float]], min_separation_m: float
) -> tuple[list[float], list[int]]:
    """`chord_steepness` of points given as plain-float rows [x, y, z] (world ENU), its
    results as lists: the same numbers (the planner's per-cycle path, which holds its points
    as floats already)."""
    n = len(points)
    if n < 2:
        return [0.0] * n, [-1] * n
    if n <= _SMALL_CLOUD:
        rises, runs, partners = _chords_small(points, min_separation_m)
        angles: list[float] = np.arctan2(rises, runs).tolist()
        return angles, partners
    phi, partner = chord_steepness(np.array(points, dtype=np.float64), min_separation_m)
    return phi.tolist(), partner.tolist()


def _chord_steepness_small(
    points: FloatArray, min_separation_m: float
) -> tuple[FloatArray, IntArray]:
    """`chord_steepness` in plain floats, for a few points: the same operations (sqrt,
    division; no hypot) in the same order and the first of equal chords, so the same
    numbers; the angles from one numpy arctan2, as the array form takes them."""
    rises, runs, partners = _chords_small(points.tolist(), min_separation_m)
    # arctan2(0, 0) = 0 where there is no chord, as in the array form.
    angles: FloatArray = np.arctan2(rises, runs)
    return angles, np.array(partners, dtype=np.intp)


def _chords_small(
    pts: list[list[float]], min_separation_m: float
) -> tuple[list[float], list[float], list[int]]:
    """The steepest chord down from each point as (rise, run, partner) lists; (0, 0, -1)
    where there is none."""
    sqrt = math.sqrt
    rises: list[float] = []
    runs: list[float] = []
    partners: list[int] = []
    for xi, yi, zi in pts:
        best, k_best, rise, run = -1.0, -1, 0.0, 0.0
        for k, (xk, yk, zk) in enumerate(pts):
            dz = zi - zk
            if dz > 0.0:
                dx, dy = xi - xk, yi - yk
                h = sqrt(dx * dx + dy * dy)
                if h >= min_separation_m or dz >= min_separation_m:
                    q = dz / h if h > 0.0 else math.inf
                    if q > best:
                        best, k_best, rise, run = q, k, dz, h
        rises.append(rise)
        runs.append(run)
        partners.append(k_best)
    return rises, runs, partners
