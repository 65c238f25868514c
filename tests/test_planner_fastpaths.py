"""The planner's fast paths against their plain references: the same numbers, bit for bit
(a fast path must not change a flight)."""

import numpy as np
import pytest

import companion.planner.decision as decision
from companion.planner.memory import ObstacleMemory


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
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 1.0], [0.2, 0.0, 5.0]])
    angles, partners = decision._chord_steepness_small(points, 0.5)
    # Point 2 is 0.2 m from point 0 (too short a chord): its partner is point 1.
    assert partners.tolist() == [-1, 0, 1]
    assert angles[1] == pytest.approx(np.pi / 4)
    assert angles[2] == pytest.approx(np.arctan2(4.0, 0.8))


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
