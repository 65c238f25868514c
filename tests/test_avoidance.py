"""Horizontal correction: continuity, clearance over the whole curve, curvature, route."""

import itertools
import math

import numpy as np
import pytest

from companion.planner.avoidance import (
    AvoidanceRequest,
    free_intervals,
    max_abs_curvature,
    min_distance,
    plan_detour,
    sample_segments,
)
from companion.planner.params import PlannerParams
from companion.planner.route import Route
from companion.planner.types import PathMode, Side

PARAMS = PlannerParams(d_min_m=2.0, clearance_margin_m=0.6, min_turn_radius_m=2.0)
D_M = PARAMS.d_min_m + PARAMS.clearance_margin_m


def wall(x: float, y0: float, y1: float, step: float = 0.25) -> np.ndarray:
    ys = np.arange(y0, y1 + 1e-9, step)
    return np.column_stack([np.full_like(ys, x), ys])


def request(points: np.ndarray, start=(0.0, 0.0), direction=(1.0, 0.0), **kw) -> AvoidanceRequest:  # type: ignore[no-untyped-def]
    return AvoidanceRequest(
        start_xy=np.array(start),
        start_dir=None if direction is None else np.array(direction),
        conflict_xy=points,
        obstacles_xy=points,
        **kw,
    )


ROUTE = Route(np.array([[0.0, 0.0], [60.0, 0.0]]), 0.0, 0.0)


def test_free_intervals() -> None:
    gaps = free_intervals(np.array([0.0, 1.0]), 2.0, limit_m=10.0)
    assert gaps == [(-10.0, -2.0), (3.0, 10.0)]
    assert free_intervals(np.array([]), 2.0, 10.0) == [(-10.0, 10.0)]


def test_detour_around_a_wall_keeps_every_requirement() -> None:
    pts = wall(15.0, -3.0, 1.0)  # longer to the right (negative y): left is the short way
    detour = plan_detour(ROUTE, request(pts), PARAMS)
    assert detour is not None
    assert detour.side is Side.LEFT and detour.mode is PathMode.AROUND
    segs = list(detour.path.segments)
    # Continuity: starts at the reference point with the same tangent.
    np.testing.assert_allclose(segs[0].evaluate(0.0), [0, 0], atol=1e-12)
    np.testing.assert_allclose(segs[0].tangent(0.0), [1, 0], atol=1e-12)
    # Tangent-continuous joins.
    for a, b in itertools.pairwise(segs):
        np.testing.assert_allclose(a.tangent(1.0), b.tangent(0.0), atol=1e-6)
    # Clearance over the whole new curve, not its control points.
    samples = sample_segments(segs)
    assert float(min_distance(samples, pts).min()) >= D_M - 0.05
    # Curvature bound.
    assert max_abs_curvature(segs[:-1]) <= 1.0 / PARAMS.min_turn_radius_m * 1.001
    # Rejoins the route and ends at the last base point with the arrival heading.
    np.testing.assert_allclose(detour.path.end, [60, 0], atol=1e-9)
    assert detour.path.heading(detour.path.length) == pytest.approx(0.0, abs=1e-9)


def test_side_hysteresis_keeps_the_committed_side() -> None:
    pts = wall(15.0, -2.0, 2.0)  # symmetric: either side works
    free = plan_detour(ROUTE, request(pts, free_left_m=30.0, free_right_m=10.0), PARAMS)
    assert free is not None and free.side is Side.LEFT  # more free range on the left
    kept = plan_detour(
        ROUTE,
        request(pts, committed_side=Side.RIGHT, free_left_m=30.0, free_right_m=10.0),
        PARAMS,
    )
    assert kept is not None and kept.side is Side.RIGHT


def test_obstacle_beside_the_path_shifts_it() -> None:
    pts = wall(15.0, 1.0, 1.0)  # a single point 1 m left of the route
    pts = np.vstack([np.column_stack([np.arange(10, 20, 0.25), np.full(40, 1.0)])])
    detour = plan_detour(ROUTE, request(pts), PARAMS)
    assert detour is not None
    assert detour.mode is PathMode.SHIFT and detour.side is Side.RIGHT
    assert detour.offset_m == pytest.approx(1.0 - D_M - 0.05, abs=0.01)


def test_no_way_through_is_none() -> None:
    """A closed pocket around the vehicle: every candidate breaks D_min."""
    ang = np.linspace(-math.pi / 2, math.pi / 2, 60)
    pocket = np.column_stack([3.5 * np.cos(ang), 3.5 * np.sin(ang)])
    assert plan_detour(ROUTE, request(pocket), PARAMS) is None


def test_route_base_points_are_kept() -> None:
    route = Route(np.array([[0.0, 0.0], [30.0, 0.0], [60.0, 10.0]]), 0.0, 0.0)
    detour = plan_detour(route, request(wall(12.0, -1.0, 1.0)), PARAMS)
    assert detour is not None
    assert detour.rejoin_s <= route.base_s[1] + 1e-9
    poly = detour.path.polyline(0.05)
    for w in route.base_points[1:]:
        assert float(np.min(np.hypot(*(poly.points - w).T))) < 0.05


def test_inflated_points_are_passed_farther_out() -> None:
    """A correction keeps D_m + e from a point inflated by e (a flank inclined under it)."""
    route = Route(np.array([[0.0, 0.0], [60.0, 0.0]]), 0.0, 0.0)
    wall = np.array([[30.0, y] for y in np.arange(-6.0, 1.01, 0.25)])
    infl = np.full(len(wall), 1.0)
    base = AvoidanceRequest(
        start_xy=np.array([10.0, 0.0]),
        start_dir=np.array([1.0, 0.0]),
        conflict_xy=wall,
        obstacles_xy=wall,
    )
    plain = plan_detour(route, base, PARAMS)
    wide = plan_detour(
        route,
        AvoidanceRequest(
            start_xy=base.start_xy,
            start_dir=base.start_dir,
            conflict_xy=wall,
            obstacles_xy=wall,
            obstacles_inflation=infl,
        ),
        PARAMS,
    )
    assert plain is not None and wide is not None
    for detour, extra in ((plain, 0.0), (wide, 1.0)):
        samples = detour.path.polyline().points
        assert float(min_distance(samples, wall).min()) >= D_M + extra - 0.05 - 1e-9
    assert wide.offset_m > plain.offset_m
    assert float(min_distance(np.array([[0.0, 0.0]]), wall, infl)[0]) == (
        float(min_distance(np.array([[0.0, 0.0]]), wall)[0]) - 1.0
    )
