"""Eqs (6)-(7): steepness, thresholds and the vertical/horizontal decision."""

import math

import numpy as np
import pytest

from companion.planner.decision import decide, steepness, thresholds
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
