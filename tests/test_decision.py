"""Eqs (6)-(7): steepness, thresholds and the vertical/horizontal decision."""

import math

import numpy as np
import pytest

from companion.planner.decision import chord_steepness, decide, steepness, thresholds
from companion.planner.params import PlannerParams
from companion.planner.sensors import Group
from companion.planner.types import Decision

PARAMS = PlannerParams(h_d_m=2.0, d_min_m=2.0, phi_max_rad=0.6)


def test_thresholds_per_group() -> None:
    thr = thresholds((Group.LEFT, Group.FORWARD, Group.RIGHT), PARAMS)
    assert thr.tolist() == [0.6, 0.6, 0.6]  # atan(2/2) = 0.785 > phi_max
    narrow = PlannerParams(h_d_m=1.0, d_min_m=3.0, phi_max_rad=0.6)
    thr = thresholds((Group.LEFT, Group.FORWARD, Group.RIGHT), narrow)
    assert thr[1] == 0.6
    assert thr[0] == thr[2] == pytest.approx(math.atan(1.0 / 3.0))


def test_nothing_detected_gives_zero() -> None:
    phi = steepness(np.array([[5.0, 0, 9]]), np.array([[2.0, 0, 0]]), np.array([False]))
    assert phi.tolist() == [0.0]


def test_gentle_hill_ahead_is_vertical() -> None:
    """A point on a 15-degree slope 6 m ahead of the forward ground point: climb over."""
    ground = np.array([[2.0, 0.0, 0.0]])
    obstacle = np.array([[8.0, 0.0, 6.0 * math.tan(math.radians(15))]])
    phi = steepness(obstacle, ground, np.array([True]))
    assert phi[0] == pytest.approx(math.radians(15))
    assert decide(phi, thresholds((Group.FORWARD,), PARAMS)) is Decision.VERTICAL


def test_wall_ahead_is_horizontal() -> None:
    ground = np.array([[2.0, 0.0, 0.0]])
    obstacle = np.array([[4.0, 0.0, 2.0]])  # a wall face 2 m beyond the ground point, 2 m up
    phi = steepness(obstacle, ground, np.array([True]))
    assert decide(phi, thresholds((Group.FORWARD,), PARAMS)) is Decision.HORIZONTAL


def test_side_slope_steeper_than_atan_hd_over_dmin_is_horizontal() -> None:
    """Fig. 4b: beside a slope steeper than atan(H_d / D_min) the side threshold trips."""
    params = PlannerParams(h_d_m=1.0, d_min_m=3.0, phi_max_rad=0.6)
    side = math.atan(1.0 / 3.0)  # 0.32 rad
    groups = (Group.LEFT,)
    ground = np.array([[0.0, 2.0, 0.0]])
    steeper = np.array([[0.0, 5.0, 3.0 * math.tan(side + 0.05)]])
    gentler = np.array([[0.0, 5.0, 3.0 * math.tan(side - 0.05)]])
    thr = thresholds(groups, params)
    assert decide(steepness(steeper, ground, np.array([True])), thr) is Decision.HORIZONTAL
    assert decide(steepness(gentler, ground, np.array([True])), thr) is Decision.VERTICAL
    # The same slope ahead (forward group, threshold phi_max) is climbed.
    fwd = thresholds((Group.FORWARD,), params)
    assert decide(steepness(steeper, ground, np.array([True])), fwd) is Decision.VERTICAL


def test_chord_steepness_measures_a_flank_seen_at_a_slant() -> None:
    """Eq. (6) pairs a level hit on a 50-degree flank with the ground point far in front and
    reads it as climbable; two hits on the flank itself measure the flank."""
    flank = math.radians(50.0)
    ground = np.array([2.0, 0.0, 0.0])  # the forward ground point
    foot = 6.0  # the flank starts 6 m ahead
    hits = np.array([[foot + z / math.tan(flank), 0.0, z] for z in (2.0, 3.5)])
    eq6 = steepness(hits[:1], ground[None, :], np.array([True]))
    assert eq6[0] < PARAMS.phi_max_rad  # the paper's test alone: climbable
    phi, partner = chord_steepness(np.vstack([hits, ground]), min_separation_m=0.5)
    assert phi[1] == pytest.approx(flank)  # the upper hit, against the lower one
    assert partner[1] == 0
    assert phi[2] == 0.0 and partner[2] == -1  # nothing lower than the ground point


def test_chord_steepness_never_exceeds_the_steepest_slope() -> None:
    """Mean value theorem: on a height field no chord is steeper than the surface."""
    rng = np.random.default_rng(7)
    xy = rng.uniform(-20.0, 20.0, size=(60, 2))
    z = 3.0 * np.exp(-(xy**2).sum(axis=1) / (2 * 6.0**2))  # a Gaussian hill
    max_slope = math.atan(3.0 / 6.0 * math.exp(-0.5))
    phi, _ = chord_steepness(np.column_stack([xy, z]), min_separation_m=0.1)
    assert float(phi.max()) <= max_slope + 1e-9


def test_chord_steepness_ignores_short_chords() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.3]])
    phi, partner = chord_steepness(pts, min_separation_m=0.5)
    assert phi.tolist() == [0.0, 0.0] and partner.tolist() == [-1, -1]


def test_chord_steepness_counts_a_short_run_under_a_tall_rise() -> None:
    """A level beam and a beam tilted up meet a vertical wall one above the other: the
    chord between them is the wall's slope (pi/2 straight above), though its horizontal
    run is far below the separation."""
    pts = np.array([[10.0, 0.0, 2.0], [10.02, 0.0, 4.7], [10.0, 0.0, 7.0]])
    for form in (pts, np.tile(pts, (4, 1)) + np.repeat(np.arange(4.0), 3)[:, None] * 100.0):
        phi, partner = chord_steepness(form, min_separation_m=0.5)
        assert phi[0] == 0.0 and partner[0] == -1
        assert math.degrees(phi[1]) > 89.0 and partner[1] == 0
        assert phi[2] == math.pi / 2 and partner[2] == 0  # the first of the vertical chords


def test_chord_steepness_on_float_rows_equals_the_array_form() -> None:
    """The planner's plain-float entry (`chord_steepness_rows`) gives chord_steepness's
    numbers bit for bit, on both sides of the small-cloud switch and for 0 or 1 point."""
    from companion.planner.decision import chord_steepness_rows

    rng = np.random.default_rng(11)
    partners_found = 0
    for trial in range(600):
        n = trial % 15
        points = rng.normal(size=(n, 3)) * float(rng.choice([0.5, 5.0]))
        if trial % 4 == 0:
            points = np.round(points, 1)  # equal heights and equal chords
        phi, partner = chord_steepness(points, 0.5)
        phi_rows, partner_rows = chord_steepness_rows(points.tolist(), 0.5)
        assert np.array(phi_rows, dtype=np.float64).tobytes() == phi.tobytes()
        assert partner_rows == partner.tolist()
        partners_found += sum(p >= 0 for p in partner_rows)
    assert partners_found > 1000


def test_decide_on_float_rows_equals_decide() -> None:
    from companion.planner.decision import decide_rows

    rng = np.random.default_rng(12)
    seen = set()
    for _ in range(500):
        phi = rng.uniform(-1.0, 1.0, 7)
        thr = rng.uniform(0.3, 1.0, 7)
        expected = decide(phi, thr)
        assert decide_rows(phi.tolist(), thr.tolist()) is expected
        seen.add(expected)
    assert seen == {Decision.VERTICAL, Decision.HORIZONTAL}
