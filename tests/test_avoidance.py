"""Horizontal correction: continuity, clearance over the whole curve, curvature, route."""

import itertools
import math
import subprocess
import sys

import numpy as np
import pytest

from companion.planner.avoidance import (
    AvoidanceRequest,
    _median,
    _start_direction,
    comes_closer,
    free_intervals,
    max_abs_curvature,
    min_distance,
    passed_beside,
    plan_detour,
    sample_segments,
)
from companion.planner.bezier import segment_through
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


def _nearest_to(detour_path_points: np.ndarray, point: np.ndarray) -> float:
    return float(np.min(np.hypot(*(detour_path_points - point).T)))


def test_a_base_point_close_behind_an_obstacle_is_reached_from_another_direction() -> None:
    """The base point 7 m behind the wall is too close for the return S-curve to meet the
    route before it along the route's tangent; the correction passes through it at an angle
    and rejoins the route after it, keeping D_m and the turn radius."""
    route = Route(np.array([[0.0, 0.0], [27.0, 0.0], [60.0, 0.0]]), 0.0, 0.0)
    pts = wall(20.0, -3.0, 1.0)
    detour = plan_detour(route, request(pts), PARAMS)
    assert detour is not None
    assert detour.rejoin_s > route.base_s[1] + 1.0  # rejoins after the base point...
    poly = detour.path.polyline(0.05)
    assert _nearest_to(poly.points, route.base_points[1]) < 0.05  # ...having passed through it
    segs = list(detour.path.segments)
    assert max_abs_curvature(segs) <= 1.0 / PARAMS.min_turn_radius_m * 1.001
    for a, b in itertools.pairwise(segs):
        np.testing.assert_allclose(a.tangent(1.0), b.tangent(0.0), atol=1e-6)
    assert float(min_distance(sample_segments(segs), pts).min()) >= D_M - 0.05 - 1e-9


def test_through_a_base_point_just_before_the_goal_the_path_still_ends_at_the_goal() -> None:
    """A base point 7 m behind the wall and the goal 8 m after it, less than a return
    S-curve: the correction passes through the base point and ends at the goal. (It used to
    end at the base point, claiming to rejoin at the goal, and the vehicle stopped there for
    good: random world 241, ring-8.)"""
    route = Route(np.array([[0.0, 0.0], [27.0, 0.0], [35.0, 0.0]]), 0.0, None)
    detour = plan_detour(route, request(wall(20.0, -3.0, 1.0)), PARAMS)
    assert detour is not None
    np.testing.assert_allclose(detour.path.end, route.base_points[-1], atol=1e-9)
    assert _nearest_to(detour.path.polyline(0.05).points, route.base_points[1]) < 0.05


def test_passing_a_base_point_through_costs_less_than_passing_beside_it() -> None:
    """Of the corrections that exist, one through the base point wins over one that holds
    its offset past it (skipping it), though the skip is shorter."""
    route = Route(np.array([[0.0, 0.0], [28.0, 0.0], [60.0, 0.0]]), 0.0, 0.0)
    detour = plan_detour(route, request(wall(20.0, -3.0, 1.0)), PARAMS)
    assert detour is not None
    assert _nearest_to(detour.path.polyline(0.05).points, route.base_points[1]) < 0.05


def test_the_goal_is_reached_along_the_arrival_heading_asked_for() -> None:
    """A goal just behind an obstacle: with no arrival heading asked for, a correction may
    arrive from another direction; with one, it never does (here: no correction)."""
    pts = wall(20.0, -3.0, 1.0)
    free = Route(np.array([[0.0, 0.0], [27.0, 0.0]]), 0.0, None)
    asked = Route(np.array([[0.0, 0.0], [27.0, 0.0]]), 0.0, 0.0)
    for route in (free, asked):
        detour = plan_detour(route, request(pts), PARAMS)
        if detour is None:
            continue
        end = detour.path.segments[-1]
        np.testing.assert_allclose(end.evaluate(1.0), [27.0, 0.0], atol=1e-9)
        if route is asked:
            np.testing.assert_allclose(end.tangent(1.0), [1.0, 0.0], atol=1e-6)
    assert plan_detour(free, request(pts), PARAMS) is not None


def test_a_passage_narrower_than_two_d_m_is_passed_at_the_replan_distance() -> None:
    """Two long walls leave a 5 m gap: too narrow to keep D_min + margin (2.6 m) from both,
    wide enough for the re-plan distance D_min + margin / 2 (2.3 m). The correction goes
    through it, keeping at least that."""
    pts = np.vstack([wall(20.0, -45.0, 1.5), wall(20.0, 6.5, 45.0)])
    detour = plan_detour(ROUTE, request(pts), PARAMS)
    assert detour is not None
    assert 3.5 < detour.offset_m < 4.5
    trigger = PARAMS.d_min_m + 0.5 * PARAMS.clearance_margin_m
    clearance = float(min_distance(sample_segments(list(detour.path.segments)), pts).min())
    assert trigger <= clearance < D_M


def test_from_rest_the_first_segment_leaves_in_the_least_curving_direction() -> None:
    """At rest the vehicle may turn on the spot: to reach a point 2 m ahead and 2 m to the
    left along the route's heading it leaves to the left, on a quarter circle (curvature
    near 1/2), where leaving along the chord would curve twice as much."""
    start, target, heading = np.zeros(2), np.array([2.0, 2.0]), np.array([1.0, 0.0])
    leaving = _start_direction(start, target, heading)
    assert leaving is not None
    direction, handle = leaving
    np.testing.assert_allclose(direction, [0.0, 1.0], atol=1e-9)
    arc = segment_through(start, direction, target, heading, handle, handle)
    chord = segment_through(start, np.array([1.0, 1.0]) / math.sqrt(2.0), target, heading)
    assert max_abs_curvature([arc]) < 0.52
    assert max_abs_curvature([chord]) > 2.0 * max_abs_curvature([arc]) * 0.9


def test_a_base_point_out_of_reach_is_reported_with_the_distance_it_is_missed_by() -> None:
    """4 m behind the wall the base point cannot be passed through at the turn radius: the
    correction passes beside it, and `passed_beside` names it and the miss; 7 m behind,
    the correction goes through it and nothing is reported."""
    pts = wall(20.0, -3.0, 1.0)
    for behind, missed in ((4.0, True), (7.0, False)):
        route = Route(np.array([[0.0, 0.0], [20.0 + behind, 0.0], [60.0, 0.0]]), 0.0, 0.0)
        detour = plan_detour(route, request(pts), PARAMS)
        assert detour is not None
        beside = passed_beside(route, detour.path, np.zeros(2), detour.rejoin_s)
        if missed:
            assert [k for k, _ in beside] == [1]
            miss = _nearest_to(detour.path.polyline().points, route.base_points[1])
            assert beside[0][1] == pytest.approx(miss) and miss > 1.0
        else:
            assert beside == []


def test_the_first_search_in_a_process_imports_nothing() -> None:
    """A module imported on first use inside a re-plan is paid for in flight (numpy.ma, behind
    np.median's first call, cost about 10 ms): a fresh process's first search imports none."""
    code = """
import sys
import numpy as np
from companion.planner.avoidance import AvoidanceRequest, plan_detour
from companion.planner.params import PlannerParams
from companion.planner.route import Route
ys = np.arange(-3.0, 1.0 + 1e-9, 0.25)
pts = np.column_stack([np.full_like(ys, 15.0), ys])
route = Route(np.array([[0.0, 0.0], [60.0, 0.0]]), 0.0, 0.0)
req = AvoidanceRequest(start_xy=np.zeros(2), start_dir=np.array([1.0, 0.0]),
                       conflict_xy=pts, obstacles_xy=pts)
before = set(sys.modules)
assert plan_detour(route, req, PlannerParams(d_min_m=2.0, clearance_margin_m=0.6)) is not None
print(sorted(set(sys.modules) - before))
"""
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("n", [1, 2, 5, 6, 17])
def test_median_is_numpys(n: int) -> None:
    values = np.random.default_rng(n).normal(size=n)
    assert _median(values) == float(np.median(values))


def test_an_escape_from_inside_one_disc_may_not_close_on_another_point() -> None:
    """A path out of a point's inflated disc (the vehicle 2 m inside it) gains clearance from
    that point as an escape must, but runs at a wall point 4 m ahead, 0.2 m beside its
    line: measured as a minimum over all points, its floor (below 0 for the first 7 m) let
    it pass 0.2 m from that point."""
    east = np.array([1.0, 0.0])
    path = [segment_through(np.zeros(2), east, np.array([8.0, 0.0]), east)]
    inflated = np.array([[-2.0, 0.0]])
    inflation = np.array([4.0])  # the start is 2 m inside its disc
    assert not comes_closer(path, inflated, 2.0, inflation, -2.0)
    wall = np.array([[4.0, 0.2]])  # 4.0 m from the start, 0.2 m beside the path
    both = np.vstack([inflated, wall])
    assert comes_closer(path, both, 2.0, np.array([4.0, 0.0]), -2.0)
    # A point the path moves away from, or passes no nearer than it started, does not count.
    behind = np.array([[-1.0, 1.5]])
    assert not comes_closer(path, np.vstack([inflated, behind]), 2.0, np.array([4.0, 0.0]), -2.0)
