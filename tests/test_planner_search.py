"""The re-plan search in work units: the same answer whether it runs in one go or over
cycles, a bound per cycle, and the exact rewrites behind its speed (same numbers)."""

import copy
import itertools
import math

import numpy as np
import pytest

import companion.planner.planner as planner_mod
from companion.planner import (
    SEARCH_BUDGET_UNITS,
    SEARCH_BUDGET_UNITS_AT_REST,
    Planner,
    PlannerParams,
    Route,
    VehicleState,
)
from companion.planner.avoidance import (
    AvoidanceRequest,
    SearchFrame,
    detour_search,
    plan_detour,
)
from companion.planner.bezier import CubicBezier, _real_roots_quadratic
from companion.planner.decision import chord_steepness
from companion.planner.retreat import (
    RETREAT_STEPS_M,
    backwards_track,
    retreat_search,
    split_at_turns,
)
from companion.planner.speed import STOPPED_MPS
from companion.planner.types import Side
from tests.test_planner import SENSORS, flat_ranges

PARAMS = PlannerParams(d_min_m=2.0, clearance_margin_m=0.6, min_turn_radius_m=2.0)
ROUTE = Route(np.array([[0.0, 0.0], [60.0, 0.0]]), 0.0, 0.0)


def wall(x: float, y0: float, y1: float, step: float = 0.25) -> np.ndarray:
    ys = np.arange(y0, y1 + 1e-9, step)
    return np.column_stack([np.full_like(ys, x), ys])


def request(points: np.ndarray, start=(0.0, 0.0), direction=(1.0, 0.0)) -> AvoidanceRequest:  # type: ignore[no-untyped-def]
    return AvoidanceRequest(
        start_xy=np.array(start),
        start_dir=None if direction is None else np.array(direction),
        conflict_xy=points,
        obstacles_xy=points,
    )


def run_to_end(search):  # type: ignore[no-untyped-def]
    units = 0
    while True:
        try:
            next(search)
        except StopIteration as done:
            return done.value, units
        units += 1


def same_path(a, b) -> bool:  # type: ignore[no-untyped-def]
    return len(a.segments) == len(b.segments) and all(
        np.array_equal(x.control, y.control) for x, y in zip(a.segments, b.segments, strict=True)
    )


@pytest.mark.parametrize(
    "points",
    [
        wall(15.0, -3.0, 1.0),
        wall(20.0, -1.0, 1.0),
        np.vstack([wall(12.0, -40.0, 40.0)]),
    ],
)
def test_search_in_units_is_plan_detour(points: np.ndarray) -> None:
    whole = plan_detour(ROUTE, request(points), PARAMS)
    stepped, units = run_to_end(detour_search(ROUTE, request(points), PARAMS))
    assert units >= 1  # the set-up is a unit
    if whole is None:
        assert stepped is None
    else:
        assert stepped is not None
        assert same_path(whole.path, stepped.path)
        assert (whole.side, whole.mode, whole.offset_m) == (
            stepped.side,
            stepped.mode,
            stepped.offset_m,
        )


def test_one_frame_shared_by_searches_from_many_starts_changes_no_answer() -> None:
    """`retreat_search` shares one `SearchFrame` (projections, window, clearance memo, route
    tails) among its trials from different starts: each answer is the one a search with a
    frame of its own finds, candidate for candidate."""
    along = np.arange(10.0, 23.0, 0.25)
    pts = np.vstack([wall(23.0, -1.0, 8.0), np.column_stack([along, np.full(len(along), 3.0)])])
    shared = SearchFrame.of(ROUTE, request(pts), PARAMS)
    found = 0
    for x, y, direction in [
        (18.0, 0.0, None),
        (15.0, 0.5, None),
        (12.0, -0.5, None),
        (8.0, 0.0, (1.0, 0.0)),
        (2.0, 0.0, (1.0, 0.0)),
    ]:
        req = request(pts, start=(x, y), direction=direction)
        alone, units_alone = run_to_end(detour_search(ROUTE, req, PARAMS))
        with_shared, units_shared = run_to_end(detour_search(ROUTE, req, PARAMS, shared))
        assert units_alone == units_shared
        assert (alone is None) == (with_shared is None)
        if alone is not None:
            found += 1
            assert same_path(alone.path, with_shared.path)
            assert (alone.side, alone.mode, alone.offset_m, alone.cost) == (
                with_shared.side,
                with_shared.mode,
                with_shared.offset_m,
                with_shared.cost,
            )
    assert found >= 2  # the comparison saw accepted corrections, not only failures
    assert shared.tails  # and the shared route tails were filled in and used again


def test_a_pocket_fails_after_trying_every_candidate() -> None:
    sides = np.arange(0.0, 14.0, 0.25)
    pocket = np.vstack(
        [
            wall(14.0, -10.0, 10.0),
            np.column_stack([sides, np.full(len(sides), 10.0)]),
            np.column_stack([sides, np.full(len(sides), -10.0)]),
        ]
    )
    result, units = run_to_end(detour_search(ROUTE, request(pocket, direction=None), PARAMS))
    assert result is None
    assert units > 5  # every candidate tried, one unit each


def at_rest_before_a_wall() -> tuple[Planner, np.ndarray, VehicleState]:
    """A planner at rest at the route's start, flat ground, and a wall across the route 6 m
    ahead in its memory: its first cycle searches for a correction."""
    route = Route(np.array([[0.0, 0.0], [60.0, 0.0]]), 0.0, 0.0)
    planner = Planner(PARAMS, SENSORS, route, np.array([0.0, 0.0, 2.0]))
    pts = wall(6.0, -4.0, 3.0)
    planner._memory.add(np.column_stack([pts, np.full(len(pts), 2.0)]), 0)
    state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    return planner, flat_ranges(2.0), state


def test_a_search_resumed_over_cycles_finds_what_one_cycle_finds(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    whole, ranges, state = at_rest_before_a_wall()
    monkeypatch.setattr(planner_mod, "SEARCH_BUDGET_UNITS_AT_REST", 10**9)
    first = whole.step(state, ranges, 0.05)
    assert first.diagnostics.replanned

    stepped, ranges, state = at_rest_before_a_wall()
    monkeypatch.setattr(planner_mod, "SEARCH_BUDGET_UNITS_AT_REST", 1)
    cycles = 0
    while True:
        cycles += 1
        result = stepped.step(state, ranges, 0.05)
        d = result.diagnostics
        assert d.search_units <= 1
        if d.replanned:
            break
        assert d.searching
        assert result.setpoint.velocity_enu.tolist() == [0.0, 0.0, 0.0]  # waits at rest
        assert np.array_equal(result.setpoint.position_enu, first.setpoint.position_enu)
        # A copy (a pending search cannot be copied) starts the search afresh.
        copy.deepcopy(stepped)
        assert cycles < 200
    assert cycles > 1
    assert same_path(whole.path, stepped.path)


def test_no_cycle_spends_more_than_the_budget() -> None:
    planner, ranges, state = at_rest_before_a_wall()
    for _ in range(40):
        d = planner.step(state, ranges, 0.05).diagnostics
        assert 0 <= d.search_units <= SEARCH_BUDGET_UNITS_AT_REST <= SEARCH_BUDGET_UNITS


def at_rest_in_a_pocket() -> tuple[Planner, np.ndarray, VehicleState]:
    """A planner at rest at the route's start with walls ahead and on both sides in its
    memory: every correction is tried and fails before the way out is found."""
    route = Route(np.array([[0.0, 0.0], [60.0, 0.0]]), 0.0, 0.0)
    planner = Planner(PARAMS, SENSORS, route, np.array([0.0, 0.0, 2.0]))
    sides = np.arange(-6.0, 14.0, 0.25)
    pocket = np.vstack(
        [
            wall(14.0, -8.0, 8.0),
            np.column_stack([sides, np.full(len(sides), 8.0)]),
            np.column_stack([sides, np.full(len(sides), -8.0)]),
        ]
    )
    planner._memory.add(np.column_stack([pocket, np.full(len(pocket), 2.0)]), 0)
    return planner, flat_ranges(2.0), VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)


def test_a_search_at_rest_goes_on_over_memory_changes() -> None:
    """A vehicle at rest sees its surroundings change every few cycles; a search restarted
    at each change would never finish. It finishes on the points it started with, spending
    what it would have spent, and gives the same path."""
    calm, ranges, state = at_rest_in_a_pocket()
    busy, _, _ = at_rest_in_a_pocket()
    spent_calm: list[int] = []
    spent_busy: list[int] = []
    for cycle in range(200):
        a = calm.step(state, ranges, 0.05).diagnostics
        spent_calm.append(a.search_units)
        if cycle % 2 == 0:  # a new cell far away every other cycle: the memory changes
            far = np.array([[-40.0 - cycle, 30.0, 2.0]])
            busy._memory.add(far, cycle)
        generation = busy._memory.generation
        b = busy.step(state, ranges, 0.05).diagnostics
        spent_busy.append(b.search_units)
        assert busy._memory.generation >= generation
        if a.replanned or b.replanned:
            break
    assert a.replanned and b.replanned
    assert sum(spent_busy) == sum(spent_calm) > SEARCH_BUDGET_UNITS_AT_REST
    assert same_path(calm.path, busy.path)


def test_a_long_search_at_rest_is_spread_over_cycles_of_the_rest_budget() -> None:
    """At rest in a pocket (walls ahead and on both sides), every correction is tried and
    fails before the way out is found: more units than one cycle at rest may spend, spent
    over several cycles of at most SEARCH_BUDGET_UNITS_AT_REST while X_d waits."""
    planner, ranges, state = at_rest_in_a_pocket()
    spent: list[int] = []
    for _ in range(200):
        result = planner.step(state, ranges, 0.05)
        d = result.diagnostics
        spent.append(d.search_units)
        assert d.search_units <= SEARCH_BUDGET_UNITS_AT_REST
        if d.replanned:
            break
        assert result.setpoint.velocity_enu.tolist() == [0.0, 0.0, 0.0]  # waits at rest
    busy = [u for u in spent if u > 0]
    assert sum(busy) > SEARCH_BUDGET_UNITS_AT_REST and len(busy) >= 2


def test_retreat_needs_a_track_and_finds_the_other_side() -> None:
    # Covered track: 20 m along y = 0 up to x = 20; a wall closes the left and the front.
    track = [(float(x), 0.0) for x in np.arange(0.0, 20.01, 0.5)]
    here = np.array([20.0, 0.0])
    back = backwards_track(here, track)
    assert np.array_equal(back[0], here) and np.array_equal(back[-1], [0.0, 0.0])
    along = np.arange(10.0, 23.0, 0.25)
    pts = np.vstack([wall(23.0, -1.0, 8.0), np.column_stack([along, np.full(len(along), 3.0)])])
    req = request(pts, start=tuple(here), direction=None)
    assert run_to_end(retreat_search(ROUTE, req, PARAMS, back[:2], 0.5, Side.LEFT))[0] is None
    assert plan_detour(ROUTE, req, PARAMS) is None  # blocked where it stands
    plan, units = run_to_end(retreat_search(ROUTE, req, PARAMS, back, 0.5, Side.LEFT))
    assert plan is not None and units >= 1
    assert plan.back_m in RETREAT_STEPS_M
    assert plan.failed_side is Side.LEFT
    assert plan.detour.side is Side.RIGHT
    # It starts here, backs out along the covered track, then takes the correction.
    assert np.allclose(plan.path.segments[0].control[0], here)
    assert plan.back_length_m == pytest.approx(plan.back_m, abs=0.6)
    turn = plan.detour.path.segments[0].control[0]  # where it stops and turns
    assert turn[1] == 0.0 and 0.0 <= (here[0] - turn[0]) - plan.back_m <= 0.5


def test_way_back_stops_where_the_track_doubles_back() -> None:
    """The vehicle went east along y = 0 to x = 20, turned on the spot and came back west
    along y = 1 (a way 1 m beside the first, so the track does not unwind). Backing out from
    x = 17.5 retraces that hairpin: the way back is cut at its two sharp corners, where the
    vehicle stops and turns, instead of one spline that loops round them at speed."""
    track = [(float(x), 0.0) for x in np.arange(0.0, 20.01, 0.5)] + [(20.0, 0.5)]
    track += [(float(x), 1.0) for x in np.arange(20.0, 17.99, -0.5)]
    here = np.array([17.5, 1.0])
    along = np.arange(10.0, 23.0, 0.25)
    pts = np.vstack([wall(23.0, -1.0, 8.0), np.column_stack([along, np.full(len(along), 3.0)])])
    req = request(pts, start=tuple(here), direction=None)
    plan, _ = run_to_end(
        retreat_search(ROUTE, req, PARAMS, backwards_track(here, track), 0.5, Side.LEFT)
    )
    assert plan is not None and plan.back_m > 3.0
    assert len(plan.turns_m) == 2
    assert all(0.0 < a < b < plan.back_length_m for a, b in itertools.pairwise(plan.turns_m))
    # Between the stops the way back bends gently: no loop round a corner.
    stops = [0.0, *plan.turns_m, plan.back_length_m]
    for a, b in itertools.pairwise(stops):
        s = np.linspace(a + 1e-6, b - 1e-6, 50)
        headings = np.unwrap([plan.path.heading(v) for v in s])
        assert np.ptp(headings) < math.radians(60.0)


def test_split_at_turns_keeps_gentle_bends_whole() -> None:
    gentle = np.array([[0.0, 0.0], [2.0, 0.0], [3.9, 0.6], [5.6, 1.7]])  # 17 and 15 degrees
    assert [len(p) for p in split_at_turns(gentle)] == [4]
    corner = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0], [-2.0, 2.0]])
    pieces = split_at_turns(corner)
    assert [p.tolist() for p in pieces] == [
        [[0.0, 0.0], [2.0, 0.0]],
        [[2.0, 0.0], [2.0, 2.0]],
        [[2.0, 2.0], [0.0, 2.0], [-2.0, 2.0]],
    ]


def test_real_roots_quadratic_matches_numpy() -> None:
    rng = np.random.default_rng(3)
    cases = [(1.0, -2.0, 1.0), (0.0, 2.0, -1.0), (1.0, 0.0, 1.0), (2.0, -3.0, 1.0), (0.0, 0.0, 1.0)]
    cases += [tuple(rng.normal(size=3) * rng.choice([1e-6, 1.0, 1e3])) for _ in range(500)]
    for c2, c1, c0 in cases:
        mine = sorted(_real_roots_quadratic(c2, c1, c0))
        if abs(c2) + abs(c1) == 0.0:
            assert mine == []
            continue
        ref = sorted(float(r.real) for r in np.roots([c2, c1, c0]) if abs(r.imag) < 1e-12)
        assert len(mine) == len(ref) or (len(ref) == 2 and len(mine) == 1 and math.isclose(*ref))
        for r in mine:
            assert min(abs(r - q) for q in ref) <= 1e-9 * (1.0 + abs(r))


def test_bezier_scalar_set_up_is_the_array_form() -> None:
    rng = np.random.default_rng(5)
    for _ in range(200):
        c = rng.normal(size=(4, 2)) * rng.choice([1e-3, 1.0, 100.0])
        seg = CubicBezier(c)
        d = 3.0 * np.diff(seg.control, axis=0)
        assert seg._d == tuple(map(float, d.ravel()))
        h = (d[0], 2.0 * (d[1] - d[0]), d[0] - 2.0 * d[1] + d[2])
        assert seg._h == tuple((float(x), float(y)) for x, y in h)
    with pytest.raises(ValueError, match="finite"):
        CubicBezier(np.array([[0.0, 0.0], [1.0, np.nan], [2.0, 0.0], [3.0, 0.0]]))


def test_chord_steepness_is_the_steepest_chord() -> None:
    rng = np.random.default_rng(7)
    for _ in range(50):
        pts = rng.uniform(-5.0, 5.0, size=(rng.integers(0, 16), 3))
        phi, partner = chord_steepness(pts, 0.5)
        for i, p in enumerate(pts):
            best, arg = -1.0, -1
            for k, q in enumerate(pts):
                h = math.hypot(p[0] - q[0], p[1] - q[1])
                if p[2] - q[2] > 0.0 and (h >= 0.5 or p[2] - q[2] >= 0.5):
                    a = math.atan2(p[2] - q[2], h)
                    if a > best:
                        best, arg = a, k
            assert phi[i] == pytest.approx(max(best, 0.0), abs=1e-12)
            assert partner[i] == arg


def test_route_tail_is_kept_and_equals_the_split() -> None:
    route = Route(np.array([[0.0, 0.0], [20.0, 5.0], [40.0, 0.0]]), 0.0, 0.0)
    for s in (0.0, 3.3, 20.6, route.length - 0.1):
        tail = route.tail_from(s)
        split = route.split_at(s)[1]
        assert len(tail) == len(split)
        assert all(np.array_equal(a.control, b.control) for a, b in zip(tail, split, strict=True))
        assert route.tail_from(s) is tail


def test_blocked_on_the_move_searches_again_only_at_rest() -> None:
    """A search from a moving X_d that fails stops the vehicle; while it stops, no cycle
    searches again (each would start afresh from a new point and spend a whole budget);
    at rest it does."""
    planner = Planner(PARAMS, SENSORS, ROUTE, np.array([0.0, 0.0, 2.0]))
    ranges = flat_ranges(2.0)
    state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    for _ in range(80):  # up to speed on flat ground
        state = VehicleState(
            planner.step(state, ranges, 0.05).setpoint.position_enu.copy(), 0, 0, 0
        )
    assert planner._v > 0.5
    x = float(state.position_enu[0])
    sides = np.arange(x - 10.0, x + 8.0, 0.25)
    pocket = np.vstack(  # too narrow to pass keeping D_min, closed 8 m ahead
        [
            wall(x + 8.0, -12.0, 12.0),
            np.column_stack([sides, np.full(len(sides), 2.5)]),
            np.column_stack([sides, np.full(len(sides), -2.5)]),
        ]
    )
    planner._memory.add(np.column_stack([pocket, np.full(len(pocket), 2.0)]), 0)
    stopping = searched_at_rest = 0
    for _ in range(400):
        was_blocked, v_before = planner._blocked, planner._v
        d = planner.step(state, ranges, 0.05).diagnostics
        state = VehicleState(planner._xd_prev.copy(), 0.0, 0.0, 0.0)
        if was_blocked and v_before > STOPPED_MPS:
            stopping += 1
            assert d.search_units == 0
        elif v_before <= STOPPED_MPS and d.search_units > 0:
            searched_at_rest += 1
            break
    assert stopping >= 5
    assert searched_at_rest == 1
