"""Rotation matrices of eqs (1)-(3).

World frame ENU (z up), body frame FLU (x forward, y left, z up). With body angles
(roll, pitch, yaw) in the ENU/FLU convention of `companion.planner.types`:

    R_G(roll, pitch, yaw) = Rz(yaw) @ Ry(-pitch) @ Rx(roll)

maps body vectors to world vectors. (Nose-up pitch is a negative rotation about the FLU
y axis, which points left.)
"""

from __future__ import annotations

import math

import numpy as np

from companion.planner.types import FloatArray


def rot_x(angle_rad: float) -> FloatArray:
    """Right-handed rotation about x by angle_rad."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_rad: float) -> FloatArray:
    """Right-handed rotation about y by angle_rad."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> FloatArray:
    """Right-handed rotation about z by angle_rad."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_zyx(roll_rad: float, pitch_rad: float, yaw_rad: float) -> FloatArray:
    """Rz(yaw) @ Ry(pitch) @ Rx(roll): the 3-2-1 Euler rotation, the one rotation matrix of
    the project. In a z-down frame (MAVLink's body FRD in NED, aerospace angles) it maps body
    vectors to the parent frame as it stands; `r_g` is the same matrix for ENU/FLU angles."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def r_g(roll_rad: float, pitch_rad: float, yaw_rad: float) -> FloatArray:
    """R_G of eqs (1)-(2): body (FLU) to world (ENU) rotation from the vehicle attitude.

    Angles in radians: roll right-wing-down positive, pitch nose-up positive, yaw from +x
    (east) counter-clockwise. Nose-up is a negative rotation about the FLU y axis (it points
    left): `euler_zyx(roll, -pitch, yaw)`.
    """
    return euler_zyx(roll_rad, -pitch_rad, yaw_rad)


def r_mr(a_rad: float, b_rad: float, c_rad: float) -> FloatArray:
    """R_MR of eqs (1)-(2): a sensor's mounting rotation in the body frame (FLU).

    a, b, c are rotations about the body x, y and z axes (radians), applied x first:
    R_MR = Rz(c) @ Ry(b) @ Rx(a). The sensor's boresight is its own z axis, so
    R_MR @ [0, 0, 1] is the boresight's body-frame unit vector.
    """
    return rot_z(c_rad) @ rot_y(b_rad) @ rot_x(a_rad)


def r_psi(yaw_rad: float) -> FloatArray:
    """R_psi of eq. (3): turns a ground direction in the heading's vertical plane up by pi/2.

    R_psi = R_G(0,0,psi) R_G(0,-pi/2,0) R_G(0,0,-psi) as printed in the paper; a forward
    ground direction (cos psi, sin psi, 0) becomes (0, 0, 1). World frame ENU.
    """
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array(
        [
            [s * s, -c * s, -c],
            [-c * s, c * c, -s],
            [c, s, 0.0],
        ]
    )


def body_to_world(vectors_body: FloatArray, r_world_body: FloatArray) -> FloatArray:
    """Rotate body (FLU) vectors, shape (3,) or (n, 3), into the world (ENU) frame."""
    return np.asarray(vectors_body, dtype=np.float64) @ r_world_body.T


def world_to_body(vectors_world: FloatArray, r_world_body: FloatArray) -> FloatArray:
    """Rotate world (ENU) vectors, shape (3,) or (n, 3), into the body (FLU) frame."""
    return np.asarray(vectors_world, dtype=np.float64) @ r_world_body
