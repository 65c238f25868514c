"""MAVLink NED/FRD <-> planner ENU/FLU conversions round-trip."""

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from companion.planner.frames import (
    attitude_enu_to_ned,
    attitude_ned_to_enu,
    enu_to_ned,
    flu_to_frd,
    frd_to_flu,
    matrix_to_quaternion,
    ned_to_enu,
    quaternion_to_matrix,
    wrap_pi,
    yaw_enu_to_ned,
    yaw_ned_to_enu,
)

finite = st.floats(-1e4, 1e4, allow_nan=False)
angle = st.floats(-math.pi, math.pi, allow_nan=False)


@given(finite, finite, finite)
def test_vectors_round_trip(a: float, b: float, c: float) -> None:
    v = np.array([a, b, c])
    np.testing.assert_allclose(enu_to_ned(ned_to_enu(v)), v)
    np.testing.assert_allclose(flu_to_frd(frd_to_flu(v)), v)


def test_ned_to_enu_axes() -> None:
    np.testing.assert_allclose(ned_to_enu([1.0, 0.0, 0.0]), [0, 1, 0])  # north
    np.testing.assert_allclose(ned_to_enu([0.0, 1.0, 0.0]), [1, 0, 0])  # east
    np.testing.assert_allclose(ned_to_enu([0.0, 0.0, 1.0]), [0, 0, -1])  # down
    np.testing.assert_allclose(frd_to_flu([0.0, 1.0, 0.0]), [0, -1, 0])  # right is -left


def test_yaw_conventions() -> None:
    assert math.isclose(yaw_ned_to_enu(0.0), math.pi / 2)  # north
    assert math.isclose(yaw_ned_to_enu(math.pi / 2), 0.0, abs_tol=1e-12)  # east
    assert math.isclose(abs(yaw_ned_to_enu(-math.pi / 2)), math.pi)  # west


@given(angle, st.floats(-1.5, 1.5), angle)
def test_attitude_round_trip(roll: float, pitch: float, yaw: float) -> None:
    r2, p2, y2 = attitude_enu_to_ned(*attitude_ned_to_enu(roll, pitch, yaw))
    assert math.isclose(r2, roll) and math.isclose(p2, pitch)
    assert abs(wrap_pi(y2 - yaw)) < 1e-9
    assert abs(wrap_pi(yaw_enu_to_ned(yaw_ned_to_enu(yaw)) - yaw)) < 1e-9


@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4))
def test_quaternion_round_trip(q: list[float]) -> None:
    qa = np.array(q)
    if np.linalg.norm(qa) < 1e-3:
        return
    r = quaternion_to_matrix(qa)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(r)), r, atol=1e-9)
