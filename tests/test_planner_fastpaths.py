"""The planner's fast paths against their plain references: the same numbers, bit for bit
(a fast path must not change a flight)."""

import math

import numpy as np
import pytest

import companion.planner.avoidance as avoidance
import companion.planner.decision as decision
import companion.planner.path as path
from companion.planner.bezier import CubicBezier, segment_through
from companion.planner.memory import ObstacleMemory
from companion.planner.path import Path
from companion.planner.route import Route


def _array_chords(points: np.ndarray, min_separation_m: float) -> tuple[np.ndarray, np.ndarray]:
    """`chord_steepness` with the plain-float path switched off: the array form."""
    saved = decision._SMALL_CLOUD
    decision._SMALL_CLOUD = 0
    try:
        return decision.chord_steepness(points, min_separation_m)
    finally:
        decision._SMALL_CLOUD = saved


@pytest.mark.parametrize("seed", range(4))
def test_small_cloud_chords_equal_the_array_form(seed: int) -> None:
    rng = np.random.default_rng(seed)
    checked = 0
    for trial in range(1500):
        n = int(rng.integers(2, decision._SMALL_CLOUD + 1))
        points = rng.normal(size=(n, 3)) * float(rng.choice([0.3, 3.0, 30.0]))
        if trial % 3 == 0:
            points[int(rng.integers(n)), 2] = points[0, 2]  # equal heights: no chord
        if trial % 5 == 0:
            points = np.round(points, 1)  # equal chords: the first one wins
        angles, partners = decision.chord_steepness(points, 0.5)
        ref_angles, ref_partners = _array_chords(points, 0.5)
        assert angles.tobytes() == ref_angles.tobytes()
        assert partners.tolist() == ref_partners.tolist()
        checked += int((partners >= 0).sum())
    assert checked > 1000  # most clouds have chords: the comparison is not vacuous


def test_small_cloud_path_is_taken_and_finds_the_steep_chord() -> None:
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 1.0], [0.2, 0.0, 5.0], [0.3, 0.0, 0.3]])
    angles, partners = decision._chord_steepness_small(points, 0.5)
    # Point 3 is 0.3 m from point 0 both ways (too short a chord): no partner. Point 2 lies
    # 0.1 m beside point 3 and 4.7 m above it: a chord tall enough, the steepest. Point 1's
    # chords to points 0 and 3 are equally steep: the first.
    assert partners.tolist() == [-1, 0, 3, -1]
    assert angles[1] == pytest.approx(np.pi / 4)
    assert angles[2] == pytest.approx(np.arctan2(4.7, 0.1))


def _brute_far(points_xy: np.ndarray, position_xy: np.ndarray, radius_m: float) -> int:
    return int((np.hypot(*(points_xy - position_xy).T) > radius_m).sum())


def test_forget_far_with_its_cached_slack_drops_what_a_full_scan_drops() -> None:
    rng = np.random.default_rng(7)
    mem = ObstacleMemory(cell_m=0.25, radius_m=10.0, max_points=10_000)
    position = np.zeros(2)
    dropped = 0
    for cycle in range(400):
        position = position + rng.normal(scale=0.3, size=2)
        if cycle % 7 == 0:
            pts = np.column_stack([position + rng.normal(scale=6.0, size=(5, 2)), np.zeros(5)])
            mem.add(pts, cycle)
        expected = _brute_far(mem.points_xy(), position, mem.radius_m)
        assert mem.forget_far(position) == expected
        dropped += expected
        assert _brute_far(mem.points_xy(), position, mem.radius_m) == 0
    assert dropped > 20


def test_forget_far_sees_a_point_added_far_away_after_a_scan() -> None:
    mem = ObstacleMemory(cell_m=0.25, radius_m=10.0, max_points=64)
    mem.add(np.array([[1.0, 0.0, 0.0]]), 1)
    assert mem.forget_far(np.zeros(2)) == 0  # caches a slack of 9 m
    mem.add(np.array([[12.0, 0.0, 0.0]]), 2)  # beyond the radius already
    assert mem.forget_far(np.zeros(2)) == 1
    assert mem.points_xy().tolist() == [[1.0, 0.0]]


def _reference_curvature(segments: list[CubicBezier]) -> float:
    """The array form of `max_abs_curvature` (stacked control points, numpy's diff)."""
    control = np.stack([seg.control for seg in segments])
    d1 = avoidance._FIRST @ (3.0 * np.diff(control, axis=1))
    d2 = avoidance._SECOND @ (6.0 * np.diff(control, n=2, axis=1))
    cross = d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0]
    speed = np.hypot(d1[..., 0], d1[..., 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        kappa = np.where(speed > 1e-12, cross / speed**3, 0.0)
    return float(np.abs(kappa).max())


def _random_segments(rng: np.random.Generator, m: int) -> list[CubicBezier]:
    scale = float(rng.choice([0.1, 10.0, 300.0]))
    return [
        CubicBezier(rng.normal(size=(4, 2)) * scale + rng.normal(size=2) * 100.0) for _ in range(m)
    ]


def test_curvature_from_the_segments_floats_equals_the_array_form() -> None:
    rng = np.random.default_rng(3)
    for trial in range(2000):
        segs = _random_segments(rng, int(rng.integers(1, 6)))
        if trial % 7 == 0:
            c = rng.normal(size=2)
            segs.append(CubicBezier(np.array([c, c, c + 1.0, c + 1.0])))  # |B'| = 0 at t = 0
        per_segment = avoidance.max_abs_curvatures(segs)
        assert avoidance.max_abs_curvature(segs) == _reference_curvature(segs)
        assert per_segment == [_reference_curvature([seg]) for seg in segs]


def test_segment_through_in_floats_equals_the_array_form() -> None:
    rng = np.random.default_rng(4)
    for _ in range(500):
        p0, p3 = rng.normal(size=2) * 50.0, rng.normal(size=2) * 50.0
        u0, u3 = rng.normal(size=2), rng.normal(size=2)
        u0, u3 = u0 / np.hypot(*u0), u3 / np.hypot(*u3)
        handle = None if rng.random() < 0.5 else float(rng.random() * 10.0)
        dx, dy = float(p3[0]) - float(p0[0]), float(p3[1]) - float(p0[1])
        h0 = math.sqrt(dx * dx + dy * dy) / 3.0 if handle is None else handle
        expected = np.array([p0, p0 + h0 * u0, p3 - h0 * u3, p3])
        seg = segment_through(p0, u0, p3, u3, handle)
        assert seg.control.tobytes() == expected.tobytes()
        assert seg.length == CubicBezier(expected).length


def test_cached_uniform_basis_gives_evaluate_s_points() -> None:
    bases: dict[int, np.ndarray] = {}
    for seg in _random_segments(np.random.default_rng(5), 3):
        for n in (3, 17, 3, 250):
            expected = seg.evaluate(np.linspace(0.0, 1.0, n)).tobytes()
            assert seg.sample(n).tobytes() == expected
            assert seg.sample(n, bases).tobytes() == expected
    assert sorted(bases) == [3, 17, 250]


def test_clearance_memo_measures_as_min_distance_within() -> None:
    rng = np.random.default_rng(6)
    for trial in range(300):
        obstacles = rng.uniform(-30.0, 30.0, size=(int(rng.integers(1, 400)), 2))
        if trial % 4 == 0:
            obstacles[::3, 0] = np.round(obstacles[::3, 0])  # equal x: sorting ties
        inflation = rng.uniform(0.0, 1.5, size=len(obstacles)) * (trial % 3 > 0)
        memo = avoidance.ClearanceMemo(obstacles, inflation)
        samples = rng.uniform(-20.0, 20.0, size=(int(rng.integers(1, 60)), 2))
        samples = samples[:1] + (samples - samples[:1]) * rng.uniform(0.01, 0.5)
        cutoff = float(rng.uniform(0.5, 6.0))
        expected = avoidance.min_distance_within(samples, obstacles, cutoff, inflation)
        assert memo.within(samples, cutoff).tobytes() == expected.tobytes()
    empty = avoidance.ClearanceMemo(np.empty((0, 2)), np.empty(0))
    assert np.isinf(empty.within(np.zeros((2, 2)), 1.0)).all()


def test_clearance_memo_in_chunks_is_exact_below_the_cutoff() -> None:
    """Long runs of samples along a path (more than a chunk of `ClearanceMemo.within`): the
    same numbers below the cutoff, at or above it elsewhere, as `min_distance_within`."""
    rng = np.random.default_rng(11)
    chunk = avoidance._CHUNK_SAMPLES
    seen_below = seen_above = 0
    for _ in range(100):
        obstacles = rng.uniform(-40.0, 40.0, size=(int(rng.integers(50, 600)), 2))
        inflation = rng.uniform(0.0, 1.5, size=len(obstacles))
        memo = avoidance.ClearanceMemo(obstacles, inflation)
        n = int(rng.integers(chunk + 1, 6 * chunk))
        heading = np.cumsum(rng.normal(0.0, 0.05, size=n)) + rng.uniform(0.0, 2.0 * np.pi)
        steps = 0.2 * np.column_stack([np.cos(heading), np.sin(heading)])
        samples = rng.uniform(-20.0, 20.0, size=2) + np.cumsum(steps, axis=0)
        cutoff = float(rng.uniform(0.5, 6.0))
        expected = avoidance.min_distance_within(samples, obstacles, cutoff, inflation)
        got = memo.within(samples, cutoff)
        below = expected < cutoff
        assert got[below].tobytes() == expected[below].tobytes()
        assert np.all(got[~below] >= cutoff)
        seen_below += int(below.sum())
        seen_above += int((~below).sum())
    assert seen_below > 1000 and seen_above > 1000


def test_comes_closer_with_a_memo_decides_as_without() -> None:
    rng = np.random.default_rng(8)
    decided = set()
    for _ in range(200):
        obstacles = rng.uniform(-20.0, 20.0, size=(60, 2))
        inflation = rng.uniform(0.0, 0.5, size=60)
        memo = avoidance.ClearanceMemo(obstacles, inflation)
        shared = _random_segments(rng, 2)
        for _ in range(3):  # the shared segments come back, measured once
            segs = [*_random_segments(rng, 1), *shared]
            limit = float(rng.uniform(0.5, 4.0))
            start = None if rng.random() < 0.5 else float(rng.uniform(0.0, limit))
            plain = avoidance.comes_closer(segs, obstacles, limit, inflation, start)
            assert avoidance.comes_closer(segs, obstacles, limit, inflation, start, memo) == plain
            decided.add(plain)
    assert decided == {True, False}


def test_locate_repeated_gives_the_same_place() -> None:
    path = Path(_random_segments(np.random.default_rng(9), 1))
    for s in (0.3 * path.length, 0.3 * path.length, 0.7 * path.length, 0.3 * path.length):
        k, t = path.locate(s)
        assert (k, t) == (0, path.segments[0].parameter_at(s))


def test_min_distance_is_the_distance_to_the_nearest_inflated_disc() -> None:
    rng = np.random.default_rng(10)
    for _ in range(200):
        samples = rng.uniform(-10.0, 10.0, size=(int(rng.integers(1, 40)), 2))
        points = rng.uniform(-10.0, 10.0, size=(int(rng.integers(1, 80)), 2))
        inflation = rng.uniform(0.0, 1.0, size=len(points))
        rel = samples[:, None, :] - points[None, :, :]
        plain = np.sqrt(rel[..., 0] * rel[..., 0] + rel[..., 1] * rel[..., 1])
        assert avoidance.min_distance(samples, points).tobytes() == plain.min(axis=1).tobytes()
        expected = (plain - inflation[None, :]).min(axis=1)
        assert avoidance.min_distance(samples, points, inflation).tobytes() == expected.tobytes()


@pytest.mark.parametrize("seed", range(3))
def test_nearest_samples_in_groups_equal_the_search_over_every_sample(seed: int) -> None:
    """`path._nearest_samples` (points in groups, each against its own box's samples) gives
    every point the index of the whole search: the nearest sample, the first of equally
    near ones (some points lie on samples, some midway between two)."""
    rng = np.random.default_rng(seed)
    route = Route(np.array([[0.0, 0.0], [40.0, 5.0], [55.0, 40.0], [10.0, 60.0]]), 0.2, 2.5)
    samples = route.polyline().points
    for n in (1, path._GROUP, path._GROUP + 1, 4 * path._GROUP + 17):
        along = samples[rng.integers(len(samples), size=n)]
        points = along + rng.normal(size=(n, 2)) * float(rng.choice([0.5, 4.0, 20.0]))
        if n > 1:
            points[: n // 3] = np.round(points[: n // 3] * 4.0) / 4.0
            points[n // 3 : n // 2] = samples[rng.integers(len(samples), size=n // 2 - n // 3)]
            k = rng.integers(len(samples) - 1, size=n - n // 2)
            points[n // 2 :] = 0.5 * (samples[k] + samples[k + 1])
        dx = points[:, 0, None] - samples[None, :, 0]
        dy = points[:, 1, None] - samples[None, :, 1]
        every = np.argmin(dx * dx + dy * dy, axis=1)  # the first of equal minima
        assert path._nearest_samples(samples, points).tolist() == every.tolist()
