"""Conversions between MAVLink's NED/FRD conventions and the planner's ENU/FLU frames.

MAVLink: local frame NED (x north, y east, z down), body FRD (x forward, y right, z down),
ATTITUDE yaw clockwise from north. Planner: local ENU, body FLU, yaw counter-clockwise from
east. Each function here is its own inverse or has one next to it; tests round-trip them.
"""

from __future__ import annotations

import math

import numpy as np

from companion.planner.types import FloatArray

# ENU <- NED swaps x/y and flips z; FLU <- FRD flips y and z. Both are involutions.
_SWAP_NED_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_FLIP_FRD_FLU = np.diag([1.0, -1.0, -1.0])


def wrap_pi(angle_rad: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def ned_to_enu(vector_ned: FloatArray) -> FloatArray:
    """(north, east, down) -> (east, north, up); shape (3,) or (n, 3)."""
    out: FloatArray = np.asarray(vector_ned, dtype=np.float64) @ _SWAP_NED_ENU.T
    return out


def enu_to_ned(vector_enu: FloatArray) -> FloatArray:
    """(east, north, up) -> (north, east, down); shape (3,) or (n, 3)."""
    out: FloatArray = np.asarray(vector_enu, dtype=np.float64) @ _SWAP_NED_ENU.T
    return out


def frd_to_flu(vector_frd: FloatArray) -> FloatArray:
    """Body (forward, right, down) -> (forward, left, up); shape (3,) or (n, 3)."""
    return np.asarray(vector_frd, dtype=np.float64) @ _FLIP_FRD_FLU.T


def flu_to_frd(vector_flu: FloatArray) -> FloatArray:
    """Body (forward, left, up) -> (forward, right, down); shape (3,) or (n, 3)."""
    return np.asarray(vector_flu, dtype=np.float64) @ _FLIP_FRD_FLU.T


def yaw_ned_to_enu(yaw_ned_rad: float) -> float:
    """MAVLink yaw (clockwise from north) -> planner yaw (counter-clockwise from east)."""
    return wrap_pi(math.pi / 2.0 - yaw_ned_rad)


def yaw_enu_to_ned(yaw_enu_rad: float) -> float:
    """Planner yaw (counter-clockwise from east) -> MAVLink yaw (clockwise from north)."""
    return wrap_pi(math.pi / 2.0 - yaw_enu_rad)


def attitude_ned_to_enu(
    roll_rad: float, pitch_rad: float, yaw_rad: float
) -> tuple[float, float, float]:
    """MAVLink ATTITUDE (FRD body in NED) -> (roll, pitch, yaw) of the FLU body in ENU.

    Roll (right wing down) and pitch (nose up) keep their sign; only yaw changes.
    """
    return roll_rad, pitch_rad, yaw_ned_to_enu(yaw_rad)


def attitude_enu_to_ned(
    roll_rad: float, pitch_rad: float, yaw_rad: float
) -> tuple[float, float, float]:
    """Inverse of `attitude_ned_to_enu`."""
    return roll_rad, pitch_rad, yaw_enu_to_ned(yaw_rad)


def quaternion_to_matrix(q_wxyz: FloatArray) -> FloatArray:
    """Rotation matrix of a quaternion (w, x, y, z), normalised first.

    Raises ValueError for a zero or non-finite quaternion.
    """
    q = np.asarray(q_wxyz, dtype=np.float64).reshape(4)
    norm = float(np.linalg.norm(q))
    if not math.isfinite(norm) or norm < 1e-9:
        raise ValueError(f"quaternion must be finite and non-zero, got {q.tolist()}")
    w, x, y, z = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quaternion(r: FloatArray) -> FloatArray:
    """Quaternion (w, x, y, z) with w >= 0 of a rotation matrix."""
    m = np.asarray(r, dtype=np.float64)
    tr = float(np.trace(m))
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    out = np.array(q)
    return out if out[0] >= 0.0 else -out
