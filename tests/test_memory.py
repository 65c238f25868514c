"""ObstacleMemory: binning, bounds, inflation and the change counters."""

import math

import numpy as np

from companion.planner.memory import ObstacleMemory


def test_one_point_per_cell_newest_wins_with_its_inflation() -> None:
    mem = ObstacleMemory(cell_m=0.25, radius_m=40.0, max_points=64)
    assert mem.add(np.array([[1.01, 1.01, 0.0]]), cycle=1, inflation_m=np.array([0.5])) == 1
    assert mem.add(np.array([[1.2, 1.2, 0.0]]), cycle=2, inflation_m=np.array([0.1])) == 0
    assert len(mem) == 1
    assert mem.points_xy().tolist() == [[1.2, 1.2]]
    assert mem.inflation_m().tolist() == [0.1]


def test_a_cells_slope_only_rises() -> None:
    """A measured slope shallower than the steepest the cell has had brings that one's
    inflation; a steeper one its own; a reading without a slope (NaN: no short chord) is
    taken as it is, and the steepest stays for the next measured one. The position is
    always the newest."""
    mem = ObstacleMemory(0.25, 40.0, 64)
    p = np.array([[2.01, 0.01, 3.0]])
    mem.add(p, 1, np.array([0.9]), np.array([0.7]))
    mem.add(p, 2, np.array([0.2]), np.array([1.1]))  # steeper: its own
    assert mem.inflation_m().tolist() == [0.2]
    mem.add(p, 3, np.array([0.8]), np.array([0.75]))  # shallower: the steepest's
    assert mem.inflation_m().tolist() == [0.2]
    mem.add(p + 0.05, 4, np.array([0.0]), np.array([np.nan]))  # a long chord: as seen
    assert mem.inflation_m().tolist() == [0.0]
    mem.add(p + 0.1, 5, np.array([0.8]), np.array([0.75]))  # the steepest is still kept
    assert mem.inflation_m().tolist() == [0.2]
    assert mem.points_xy().tolist() == [[2.11, 0.11]]
    # A cell with no slope yet takes the first measured one.
    q = np.array([[5.01, 0.01, 3.0]])
    mem.add(q, 6, np.array([0.0]), np.array([np.nan]))
    mem.add(q, 7, np.array([0.6]), np.array([0.8]))
    assert mem.inflation_m().tolist() == [0.2, 0.6]


def test_a_dropped_cells_slope_is_forgotten_with_it() -> None:
    mem = ObstacleMemory(0.25, 10.0, 64)
    mem.add(np.array([[1.0, 0.0, 3.0]]), 1, np.array([0.1]), np.array([1.5]))
    assert mem.forget_far(np.array([50.0, 0.0])) == 1
    mem.add(np.array([[1.0, 0.0, 3.0]]), 2, np.array([0.7]), np.array([0.6]))
    assert mem.inflation_m().tolist() == [0.7]


def test_inflation_defaults_to_zero_and_is_never_negative_or_nan() -> None:
    mem = ObstacleMemory(0.25, 40.0, 64)
    mem.add(np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]]), 1)
    mem.add(np.array([[10.0, 0.0, 0.0], [15.0, 0.0, 0.0]]), 2, np.array([-1.0, np.nan]))
    assert mem.inflation_m().tolist() == [0.0, 0.0, 0.0, 0.0]


def test_non_finite_points_are_dropped() -> None:
    mem = ObstacleMemory(0.25, 40.0, 64)
    assert mem.add(np.array([[np.nan, 0.0, 0.0], [0.0, np.inf, 0.0]]), 1) == 0
    assert len(mem) == 0


def test_generation_counts_added_and_dropped_cells_only() -> None:
    mem = ObstacleMemory(0.25, 10.0, 64)
    mem.add(np.array([[1.0, 1.0, 0.0]]), 1)
    g, v = mem.generation, mem.version
    mem.add(np.array([[1.05, 1.05, 0.0]]), 2)  # the same cell seen again
    assert mem.generation == g and mem.version > v
    mem.add(np.array([[3.0, 1.0, 0.0]]), 3)
    assert mem.generation == g + 1
    assert mem.forget_far(np.array([100.0, 0.0])) == 2
    assert mem.generation == g + 2 and len(mem) == 0


def test_oldest_go_first_beyond_max_points_and_near_filters_by_radius() -> None:
    mem = ObstacleMemory(0.25, 1000.0, 16)
    pts = np.array([[float(i), 0.0, 0.0] for i in range(20)])
    mem.add(pts, 1, np.arange(20, dtype=float))
    assert len(mem) == 16
    assert mem.points_xy()[0].tolist() == [4.0, 0.0]  # 0..3 dropped
    xy, infl = mem.near_with_inflation(np.array([10.0, 0.0]), 2.0)
    assert xy[:, 0].tolist() == [8.0, 9.0, 10.0, 11.0, 12.0]
    assert infl.tolist() == [8.0, 9.0, 10.0, 11.0, 12.0]


def _contents_of(xy: np.ndarray, inflation: np.ndarray) -> dict[tuple[float, float], float]:
    """Points (k, 2) and inflation (k,) as {(x, y): inflation}, exact floats."""
    return {(x, y): e for (x, y), e in zip(xy.tolist(), inflation.tolist(), strict=True)}


def _contents(mem: ObstacleMemory) -> dict[tuple[float, float], float]:
    """The stored points as {(x, y): inflation}."""
    return _contents_of(mem.points_xy(), mem.inflation_m())


def _random_change(mem: ObstacleMemory, rng: np.random.Generator, cycle: int) -> None:
    """One of the memory's changes at random: new cells, re-seen cells (moved within the
    cell or not, inflation up or down, with or without a slope), forgetting, carving."""
    kind = int(rng.integers(0, 6))
    if kind <= 2 or len(mem) == 0:
        k = int(rng.integers(1, 6))
        if kind == 0 and len(mem):  # re-seen cells: the same or a nearby position
            pts = mem.points_xy()[rng.integers(0, len(mem), k)]
            jitter = rng.choice([0.0, 0.05], size=(k, 1)) * rng.uniform(-1, 1, (k, 2))
            xy = pts + jitter
        else:
            xy = rng.uniform(-12.0, 12.0, (k, 2))
        xyz = np.column_stack([xy, rng.uniform(0.0, 3.0, k)])
        infl = rng.choice([0.0, 0.3, 0.6], size=k)
        slope = np.where(rng.random(k) < 0.5, rng.uniform(0.5, 1.5, k), np.nan)
        mem.add(xyz, cycle, infl, slope)
    elif kind == 3:
        mem.forget_far(rng.uniform(-8.0, 8.0, 2))
    elif kind == 4:
        dirs = rng.normal(size=(5, 3))
        dirs /= np.linalg.norm(dirs, axis=1)[:, None]
        mem.carve(np.array([*rng.uniform(-5, 5, 2), 1.5]), dirs, np.full(5, 10.0), 0.5)
    else:
        mem.add(np.array([[np.nan, 0.0, 0.0]]), cycle)  # a version with nothing stored


def test_changes_since_lead_from_each_earlier_version_to_the_points_now() -> None:
    """Property: for every earlier version still in the log, the points then less
    `removed`, plus `added`, are the points now; a point in `added` only (not removed)
    kept its position and its inflation rose. Older versions get None."""
    rng = np.random.default_rng(5)
    mem = ObstacleMemory(0.25, 14.0, 48)
    history: dict[int, dict[tuple[float, float], float]] = {mem.version: _contents(mem)}
    nones, forgotten = 0, -1
    for cycle in range(1, 400):
        _random_change(mem, rng, cycle)
        now = _contents(mem)
        history[mem.version] = now
        slot_xy, slot_inflation = mem.slot_points()  # the stored points, inf elsewhere
        stored = np.isfinite(slot_xy[:, 0])
        assert np.all(np.isinf(slot_xy[~stored]))
        assert _contents_of(slot_xy[stored], slot_inflation[stored]) == now
        versions = sorted(history)
        for version in versions[-6:] + versions[:-6:15]:  # the recent ones and a few older
            then = history[version]
            changes = mem.changes_since(version)
            if changes is None:
                nones += 1
                assert all(mem.changes_since(v) is None for v in versions if v < version)
                forgotten = max(forgotten, version)
                continue
            rebuilt = dict(then)
            for x, y, e in changes.removed:
                assert rebuilt.pop((x, y)) == e  # removed: stored then, as it was
            for x, y, e in changes.added:
                assert (x, y) in now and now[(x, y)] == e
                if (x, y) in rebuilt:
                    assert e > rebuilt[(x, y)]  # kept in place: only a rise
                rebuilt[(x, y)] = e
            assert rebuilt == now
        history = {v: h for v, h in history.items() if v > forgotten}
    assert nones > 0, "the log never reached its bound"
    assert len(history) > 10
    assert mem.changes_since(mem.version) == ([], [])
    assert mem.changes_since(mem.version + 1) is None


def test_a_reach_is_bounded_by_rays_that_pass_below_its_height() -> None:
    """A point 5 m up whose reach (2 m, down to z = 2 m) is on top of its inflation (0.3 m):
    a ray above that height bounds nothing; one at it, passing 0.8 m from the point, bounds
    the reach to 0.8 m; the inflation never goes below the one without the reach. The bound
    stays with the cell: a new reading there keeps it (plus the distance moved)."""
    mem = ObstacleMemory(0.25, 40.0, 64)
    p = np.array([[5.1, 0.1, 5.0]])
    for cycle in (1, 2):  # (a reach is taken from the second cycle that sees one there)
        mem.add(p, cycle, np.array([0.3]), np.array([np.nan]), np.array([2.0]), np.array([2.0]))
        assert mem.inflation_m().tolist() == [0.3 if cycle == 1 else 2.3]
    east = np.array([[1.0, 0.0, 0.0]])
    assert mem.bound_reach(np.array([0.0, 0.9, 2.5]), east, np.array([10.0]), 0.3) == 0
    assert mem.bound_reach(np.array([0.0, 0.9, 2.2]), east, np.array([3.0]), 0.3) == 0  # short
    assert mem.bound_reach(np.array([0.0, 0.9, 2.2]), east, np.array([10.0]), 0.3) == 1
    assert np.allclose(mem.inflation_m(), [0.3 + 0.8])
    down = np.array([[0.0, 0.0, -1.0]])  # straight down beside the point: 0.1 m from it
    assert mem.bound_reach(np.array([5.1, 0.2, 6.0]), down, np.array([5.0]), 0.3) == 1
    assert np.allclose(mem.inflation_m(), [0.3 + 0.1])
    q = p + np.array([0.1, 0.0, 0.0])
    mem.add(q, 3, np.array([0.3]), np.array([np.nan]), np.array([2.0]), np.array([2.0]))
    assert np.allclose(mem.inflation_m(), [0.3 + 0.2])


def test_a_reach_is_bounded_by_a_ray_from_afar_only_where_it_comes_near() -> None:
    """A ray from 30 m away bounds a reach only when its free stretch comes within the
    current bound of the point: the cheap test that skips far points (`bound_reach`) lets
    through every ray that the full one would use."""
    mem = ObstacleMemory(0.25, 60.0, 64)
    p = np.array([[5.0, 0.0, 5.0]])
    for cycle in (1, 2):
        mem.add(p, cycle, np.array([0.3]), np.array([np.nan]), np.array([2.0]), np.array([2.0]))
    west = np.array([[-1.0, 0.0, 0.0]])
    origin = np.array([35.0, 1.0, 2.2])  # the ray passes 1.0 m from the point
    assert mem.bound_reach(origin, west, np.array([30.0]), 0.3) == 1
    assert np.allclose(mem.inflation_m(), [0.3 + 1.0])
    origin = np.array([35.0, 0.5, 2.2])  # 0.5 m from it, but its stretch ends 1.0 m short:
    assert mem.bound_reach(origin, west, np.array([29.0]), 0.3) == 0  # 1.12 m at the least
    assert np.allclose(mem.inflation_m(), [0.3 + 1.0])
    # ends 0.3 m short: 0.58 m from the point, within the bound of 1.0 m
    assert mem.bound_reach(origin, west, np.array([29.7]), 0.3) == 1
    assert np.allclose(mem.inflation_m(), [0.3 + math.hypot(0.3, 0.5)])


def test_a_reach_takes_the_steepest_slope_measured_near_its_point() -> None:
    """A point 4 m above its reach height reaching 2.5 m (a long chord's shallow slope):
    a slope of 80 degrees measured by a short chord within slope_share_m (1.5 m) caps it at
    4 / tan(80 degrees), whichever came first; one farther away does not."""
    theta = np.radians(80.0)
    for order in ("reach first", "slope first"):
        mem = ObstacleMemory(0.25, 40.0, 64, slope_share_m=1.5)
        pts = np.array([[5.1, 0.1, 6.0], [9.1, 0.1, 6.0]])
        extra = (np.zeros(2), np.full(2, np.nan), np.array([2.5, 2.5]), np.array([2.0, 2.0]))
        slope = (np.array([[6.1, 0.6, 7.0]]), 3, np.array([0.01]), np.array([theta]))
        if order == "slope first":
            mem.add(*slope)
        for cycle in (1, 2):
            mem.add(pts, cycle, *extra)
        if order == "reach first":
            mem.add(*slope)
        xy, e = mem.points_xy().tolist(), mem.inflation_m().tolist()
        infl = dict(zip(map(tuple, xy), e, strict=True))
        assert np.isclose(infl[(5.1, 0.1)], 4.0 / np.tan(theta))
        assert infl[(9.1, 0.1)] == 2.5


def test_a_reach_waits_for_a_second_cycle_and_takes_the_chords_between_points() -> None:
    """A reach seen in one cycle only widens nothing; the next cycle's reading in the cell
    next to it takes both. Two such points 1.5 m apart in height and 0.3 m apart across (a
    wall met by a beam tilted up at two heights) are a chord of 79 degrees: each point
    reaches its rise (4 m, 2.5 m) over the tangent of its steepest chord, not the long
    chord's 2.5 m."""
    mem = ObstacleMemory(0.25, 40.0, 64, slope_share_m=2.5, min_chord_m=0.5)
    extra = (np.zeros(1), np.full(1, np.nan), np.array([2.5]), np.array([2.0]))
    mem.add(np.array([[5.1, 0.1, 6.0]]), 1, *extra)
    assert mem.inflation_m().tolist() == [0.0]
    mem.add(np.array([[5.1, 0.4, 6.0]]), 2, *extra)  # the next cell, the same height
    assert mem.inflation_m().tolist() == [2.5, 2.5]
    mem.add(np.array([[5.4, 0.1, 4.5]]), 3, *extra)  # 1.5 m lower, 0.3 m across
    steep = 0.3 / 1.5  # 1 / tan of the chord from the first point, the steepest
    across = np.hypot(0.3, 0.3) / 1.5  # from the second
    assert np.allclose(mem.inflation_m(), [4.0 * steep, 4.0 * across, 2.5 * steep])


def test_a_row_of_reach_points_takes_the_slope_measured_at_its_end() -> None:
    """A beam tilted up leaves a row of points 4 m up along a face as the vehicle passes it,
    one cell a cycle; a short chord measured the face vertical under the row's first point.
    Each point of the row takes the slope that capped the one before it (within 0.5 m), so
    the row keeps no reach 4 m on, beyond the 2.5 m that a measured slope is shared over;
    a row with no slope measured keeps its reach."""
    for measured in (True, False):
        mem = ObstacleMemory(0.25, 40.0, 64, slope_share_m=2.5, min_chord_m=0.5)
        if measured:
            mem.add(np.array([[5.1, 0.1, 2.0]]), 0, np.zeros(1), np.array([np.pi / 2]))
        extra = (np.zeros(1), np.full(1, np.nan), np.array([2.5]), np.array([2.0]))
        for k in range(17):  # x from 5.1 to 9.1 m
            mem.add(np.array([[5.1 + 0.25 * k, 0.1, 4.0]]), k + 1, *extra)
        row = mem.inflation_m()  # (the measured cell is the row's first)
        assert len(row) == 17
        assert (row < 0.01).all() if measured else (row == 2.5).all()
