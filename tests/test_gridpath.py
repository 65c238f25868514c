"""The last resort when blocked at rest: straight legs over a grid of the memory."""

import itertools

import numpy as np
import pytest

from companion.planner import gridpath
from companion.planner.avoidance import AvoidanceRequest, min_distance, plan_detour
from companion.planner.gridpath import grid_search
from companion.planner.params import PlannerParams
from companion.planner.route import Route

PARAMS = PlannerParams(d_min_m=2.0, clearance_margin_m=0.6, min_turn_radius_m=2.0)
D_M = PARAMS.d_min_m + PARAMS.clearance_margin_m


def _run(search):  # type: ignore[no-untyped-def]
    units = 0
    while True:
        try:
            next(search)
            units += 1
        except StopIteration as done:
            return done.value, units


def _line(a: tuple[float, float], b: tuple[float, float], step: float = 0.25) -> np.ndarray:
    n = int(np.hypot(b[0] - a[0], b[1] - a[1]) / step) + 1
    return np.linspace(a, b, n)


def _at_rest(start: tuple[float, float], points: np.ndarray) -> AvoidanceRequest:
    return AvoidanceRequest(
        start_xy=np.array(start), start_dir=None, conflict_xy=points, obstacles_xy=points
    )


def test_a_base_point_behind_a_wall_end_is_reached_round_the_end() -> None:
    """The route crosses a long wall (y from -30 to 3) just before base point W2, 3 m behind
    it. No correction reaches W2 (they hold an offset along the route); the grid finds legs
    round the wall's end to W2 that keep D_m from every point, stopping at each corner."""
    wall = _line((20.0, -30.0), (20.0, 3.0))
    route = Route(np.array([[0.0, 0.0], [23.0, 0.0], [50.0, 0.0]]), 0.0, 0.0)
    start = (15.0, 0.0)
    plan, units = _run(grid_search(route, _at_rest(start, wall), PARAMS))
    assert plan is not None and units >= 2  # set-up and check at least: it is resumable
    assert plan.base_index == 1 and plan.rejoin_s == route.base_s[1]
    legs = plan.path.segments[: len(plan.stops)]
    np.testing.assert_allclose(legs[0].evaluate(0.0), start, atol=1e-12)
    np.testing.assert_allclose(legs[-1].evaluate(1.0), route.base_points[1], atol=1e-12)
    for a, b in itertools.pairwise(legs):
        np.testing.assert_allclose(a.evaluate(1.0), b.evaluate(0.0), atol=1e-12)
    # The stops are the corners' arc lengths, the last one at the base point.
    np.testing.assert_allclose(plan.stops, np.cumsum([leg.length for leg in legs]))
    assert plan.legs_length_m == plan.stops[-1]
    # Every leg is straight and keeps D_m; the way goes round the wall's upper end.
    samples = np.vstack([leg.sample(200) for leg in legs])
    assert float(min_distance(samples, wall).min()) >= D_M - 0.05
    assert float(samples[:, 1].max()) > 3.0 + D_M - 0.1
    # The tail after the base point is the route's own.
    tail = plan.path.segments[len(plan.stops) :]
    np.testing.assert_allclose(tail[-1].evaluate(1.0), route.base_points[-1], atol=1e-9)


def test_no_way_over_the_grid_is_none() -> None:
    """A closed ring round the vehicle: no way out, the search ends with None."""
    ang = np.linspace(0.0, 2.0 * np.pi, 240, endpoint=False)
    ring = np.column_stack([10.0 + 5.0 * np.cos(ang), 5.0 * np.sin(ang)])
    route = Route(np.array([[0.0, 0.0], [30.0, 0.0]]), 0.0, 0.0)
    plan, _ = _run(grid_search(route, _at_rest((10.0, 0.0), ring), PARAMS))
    assert plan is None


def test_a_passage_narrower_than_the_cells_margin_is_found() -> None:
    """A corridor 5 m wide: its middle is 2.5 m from both walls, more than the re-plan
    distance plus 5 cm (2.35 m) but less than that plus half a cell diagonal, so no cell is
    free at the first two levels (the start's own cell not either). The last level tests
    cell centres only; the legs it gives keep their own check (>= 2.3 m)."""
    # The walls 2.5 m from the start and from the row of cell centres at y = 0.25 (the grid
    # starts 15 m below the base point).
    walls = np.vstack([_line((0.0, 2.75), (24.0, 2.75)), _line((0.0, -2.25), (24.0, -2.25))])
    route = Route(np.array([[0.0, 0.0], [34.0, 0.0], [60.0, 0.0]]), 0.0, 0.0)
    plan, _ = _run(grid_search(route, _at_rest((10.0, 0.25), walls), PARAMS))
    assert plan is not None and plan.base_index == 1
    legs = plan.path.segments[: len(plan.stops)]
    np.testing.assert_allclose(legs[-1].evaluate(1.0), route.base_points[1], atol=1e-12)
    samples = np.vstack([leg.sample(200) for leg in legs])
    narrow = PARAMS.d_min_m + 0.5 * PARAMS.clearance_margin_m + 0.05
    assert float(min_distance(samples, walls).min()) >= narrow - 0.05


def test_where_corrections_skip_the_base_point_the_grid_reaches_it() -> None:
    """4 m behind a wall across the route the base point is out of the corrections' reach
    (the one found passes beside it); the grid's legs end exactly on it."""
    wall = _line((20.0, -3.0), (20.0, 1.0))
    route = Route(np.array([[0.0, 0.0], [24.0, 0.0], [60.0, 0.0]]), 0.0, 0.0)
    request = _at_rest((10.0, 0.0), wall)
    detour = plan_detour(route, request, PARAMS)
    assert detour is not None
    miss = float(np.min(np.hypot(*(detour.path.polyline().points - [24.0, 0.0]).T)))
    assert miss > 1.0
    plan, _ = _run(grid_search(route, request, PARAMS))
    assert plan is not None
    end = plan.path.segments[len(plan.stops) - 1].evaluate(1.0)
    np.testing.assert_allclose(end, [24.0, 0.0], atol=1e-12)


def test_the_grid_blocks_exactly_the_cells_within_reach() -> None:
    """The rasterised memory (row intervals) against every cell centre measured to every
    point: the same cells, with inflations of several sizes and points off the grid."""
    from companion.planner.gridpath import CELL_M, _Grid

    rng = np.random.default_rng(5)
    pts = rng.uniform([-12.0, -9.0], [14.0, 11.0], size=(300, 2))
    inflation = np.where(rng.random(300) < 0.3, rng.uniform(0.0, 1.8, 300), 0.0)
    start, goal = np.array([-3.0, 0.0]), np.array([4.0, 2.0])
    grid = _Grid.around(start, goal, pts, inflation, D_M, np.inf)
    ny, nx = grid.blocked.shape
    iy, ix = np.mgrid[0:ny, 0:nx]
    centres = np.stack(
        [grid.origin[0] + (ix + 0.5) * CELL_M, grid.origin[1] + (iy + 0.5) * CELL_M], -1
    )
    d = np.hypot(centres[..., None, 0] - pts[:, 0], centres[..., None, 1] - pts[:, 1])
    reach = D_M + inflation + CELL_M * np.sqrt(0.5)
    expected = (d <= reach).any(axis=-1)
    assert grid.blocked.any()
    assert np.array_equal(grid.blocked, expected)


def test_sight_lines_in_one_array_are_the_sight_lines_one_by_one() -> None:
    from companion.planner.gridpath import _Grid

    rng = np.random.default_rng(11)
    pts = rng.uniform([-12.0, -9.0], [14.0, 11.0], size=(40, 2))
    grid = _Grid.around(np.array([-3.0, 0.0]), np.array([4.0, 2.0]), pts, np.zeros(40), 1.0, np.inf)
    seen = []
    for _ in range(20):
        a = rng.uniform([-20.0, -17.0], [21.0, 19.0])
        ends = rng.uniform([-22.0, -19.0], [23.0, 21.0], size=(25, 2))  # some off the grid
        one_by_one = [grid.clear_line(a, b) for b in ends]
        assert grid.clear_lines(a, ends).tolist() == one_by_one
        seen += one_by_one
    assert 0 < sum(seen) < len(seen)  # clear and blocked lines both met


def _reference_astar(blocked: np.ndarray, s: tuple[int, int], g: tuple[int, int]):  # type: ignore[no-untyped-def]
    """A* as written plainly: (ix, iy) cells in dicts, the bounds checked per neighbour,
    ties broken on insertion order; (cells or None, expansions)."""
    import heapq
    import math

    ny, nx = blocked.shape
    best, parent = {s: 0.0}, {}
    frontier, count, expanded, done = [(0.0, 0, s)], 1, 0, set()
    while frontier:
        _, _, here = heapq.heappop(frontier)
        if here in done:
            continue
        if here == g:
            path = [here]
            while path[-1] in parent:
                path.append(parent[path[-1]])
            return path[::-1], expanded
        done.add(here)
        expanded += 1
        hx, hy = here
        for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1)):
            cx, cy = hx + dx, hy + dy
            if not (0 <= cx < nx and 0 <= cy < ny) or blocked[cy, cx]:
                continue
            if dx and dy and (blocked[hy, cx] or blocked[cy, hx]):
                continue
            cost = best[here] + (math.sqrt(2.0) if dx and dy else 1.0)
            if cost < best.get((cx, cy), math.inf):
                best[(cx, cy)], parent[(cx, cy)] = cost, here
                heapq.heappush(frontier, (cost + math.hypot(g[0] - cx, g[1] - cy), count, (cx, cy)))
                count += 1
    return None, expanded


def test_the_grid_search_is_a_plain_a_star() -> None:
    """The search over flat cell indices finds the same cells as a plain A* over (ix, iy)
    tuples, ties included, and yields once per EXPANSIONS_PER_UNIT expansions; on grids
    with a walled-off goal, random clutter, points off the grid and a blocked start."""
    from companion.planner.gridpath import EXPANSIONS_PER_UNIT, _astar, _Grid

    rng = np.random.default_rng(7)
    found = none = 0
    for trial in range(40):
        pts = rng.uniform(-8.0, 48.0, size=(int(rng.integers(0, 300)), 2))
        if trial % 4 == 0:  # a wall across, with a gap, or closed
            gap = 4.0 if trial % 8 else 0.0
            wall = [[20.0, y] for y in np.arange(-25.0, 25.0, 0.25) if abs(y - 5.0) > gap]
            pts = np.concatenate([pts, np.array(wall)])
        start, goal = rng.uniform(-3.0, 3.0, 2), rng.uniform(36.0, 42.0, 2)
        grid = _Grid.around(start, goal, pts, np.zeros(len(pts)), D_M, rng.uniform(0.0, 4.0))
        if grid.blocked_at(goal):
            continue
        cells, units = _run(_astar(grid, start, goal))
        expected, expanded = _reference_astar(grid.blocked, grid.cell(start), grid.cell(goal))
        assert cells == expected
        assert units == expanded // EXPANSIONS_PER_UNIT
        found += cells is not None
        none += cells is None
    assert found > 10 and none > 0


def test_a_pocket_deeper_than_the_first_margin_is_left_over_a_wider_grid(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The vehicle stands at the back of a U 10 m wide whose sides run 23 m back from its
    back wall; the base point is 5 m behind that wall. The way out goes round the end of a
    side, 18 m and more from both start and base point: past the first grid's margin (15 m),
    where no way is found, so a wider grid is searched and its legs leave by the U's mouth."""
    back = _line((35.0, -5.0), (35.0, 5.0))
    sides = np.vstack([_line((12.0, 5.0), (35.0, 5.0)), _line((12.0, -5.0), (35.0, -5.0))])
    walls = np.vstack([back, sides])
    route = Route(np.array([[0.0, 0.0], [40.0, 0.0], [70.0, 0.0]]), 0.0, 0.0)
    request = _at_rest((30.0, 0.0), walls)
    monkeypatch.setattr(gridpath, "MARGINS_M", gridpath.MARGINS_M[:1])
    assert _run(grid_search(route, request, PARAMS))[0] is None
    monkeypatch.undo()
    plan, _ = _run(grid_search(route, request, PARAMS))
    assert plan is not None and plan.base_index == 1
    legs = plan.path.segments[: len(plan.stops)]
    np.testing.assert_allclose(legs[-1].evaluate(1.0), route.base_points[1], atol=1e-12)
    samples = np.vstack([leg.sample(200) for leg in legs])
    assert float(min_distance(samples, walls).min()) >= D_M - 0.05
    assert float(samples[:, 0].min()) < 12.0 - D_M + 0.1  # round a side's end, out of the mouth
