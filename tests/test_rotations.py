"""R_G, R_MR, R_psi and body <-> world rotations."""

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from companion.planner import frames
from companion.planner.frames import flu_to_frd, ned_to_enu
from companion.planner.rotations import (
    body_to_world,
    euler_zyx,
    r_g,
    r_mr,
    r_psi,
    rot_x,
    rot_y,
    rot_z,
    world_to_body,
)

angle = st.floats(-math.pi, math.pi, allow_nan=False)


@given(angle, angle, angle)
def test_r_g_is_a_rotation(roll: float, pitch: float, yaw: float) -> None:
    r = r_g(roll, pitch, yaw)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert math.isclose(float(np.linalg.det(r)), 1.0, abs_tol=1e-12)


@given(angle, angle, angle)
def test_r_mr_is_a_rotation(a: float, b: float, c: float) -> None:
    r = r_mr(a, b, c)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert math.isclose(float(np.linalg.det(r)), 1.0, abs_tol=1e-12)


def test_r_g_conventions() -> None:
    fwd = np.array([1.0, 0.0, 0.0])
    # Yaw 90 deg (ENU, CCW from east): nose points north.
    np.testing.assert_allclose(r_g(0, 0, math.pi / 2) @ fwd, [0, 1, 0], atol=1e-12)
    # Nose up is positive pitch.
    np.testing.assert_allclose(r_g(0, 0.3, 0) @ fwd, [math.cos(0.3), 0, math.sin(0.3)], atol=1e-12)
    # Positive roll lowers the right wing: body left (+y FLU) rises.
    assert (r_g(0.2, 0, 0) @ np.array([0.0, 1.0, 0.0]))[2] > 0


@given(angle, st.floats(-1.5, 1.5), angle)
def test_r_g_matches_mavlink_ned_frd(roll: float, pitch: float, yaw_ned: float) -> None:
    """R_G(ENU<-FLU) equals the aerospace NED<-FRD matrix seen through the frame swaps."""
    yaw_enu = math.pi / 2 - yaw_ned
    r_ned = euler_zyx(roll, pitch, yaw_ned)
    v_flu = np.array([0.3, -0.5, 0.8])
    via_ned = ned_to_enu(r_ned @ flu_to_frd(v_flu))
    np.testing.assert_allclose(r_g(roll, pitch, yaw_enu) @ v_flu, via_ned, atol=1e-12)


@given(angle, angle, angle)
def test_euler_zyx_is_the_product_of_the_axis_rotations(
    roll: float, pitch: float, yaw: float
) -> None:
    expected = rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)
    np.testing.assert_allclose(euler_zyx(roll, pitch, yaw), expected, atol=1e-12)
    np.testing.assert_allclose(
        r_g(roll, pitch, yaw), rot_z(yaw) @ rot_y(-pitch) @ rot_x(roll), atol=1e-12
    )


def test_one_rotation_matrix() -> None:
    """The Euler matrix has one owner (`rotations.euler_zyx`); frames keeps no copy."""
    assert not hasattr(frames, "euler_frd_matrix")


def test_r_mr_boresight_is_z_column() -> None:
    # Tilting the z boresight by -90 deg about y points it forward.
    np.testing.assert_allclose(r_mr(0, math.pi / 2, 0) @ [0, 0, 1], [1, 0, 0], atol=1e-12)


@given(angle)
def test_r_psi_turns_forward_ground_direction_up(psi: float) -> None:
    fwd = np.array([math.cos(psi), math.sin(psi), 0.0])
    np.testing.assert_allclose(r_psi(psi) @ fwd, [0, 0, 1], atol=1e-12)
    # A rising ground direction turns to its upward normal: perpendicular, pointing up.
    up_slope = np.array([math.cos(psi), math.sin(psi), 1.0]) / math.sqrt(2)
    n = r_psi(psi) @ up_slope
    assert n[2] > 0
    assert abs(float(np.dot(n, up_slope))) < 1e-12


@given(angle, angle, angle)
def test_body_world_round_trip(roll: float, pitch: float, yaw: float) -> None:
    r = r_g(roll, pitch, yaw)
    v = np.array([[1.0, 2.0, -3.0], [0.1, 0.0, 5.0]])
    np.testing.assert_allclose(world_to_body(body_to_world(v, r), r), v, atol=1e-12)
