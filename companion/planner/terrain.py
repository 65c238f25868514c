"""Terrain following, eqs (3)-(5): the aim point X_z, the desired pitch phi_d, and the
motion of the reference point X_d along the horizontal path at 3-D speed v.

World frame local ENU, metres; angles radians.
"""

from __future__ import annotations

import math

import numpy as np

from companion.planner.path import Path
from companion.planner.types import FloatArray


def aim_point(x_h1: FloatArray, x_h2: FloatArray, yaw_rad: float, h_d_m: float) -> FloatArray:
    """Eq. (3): X_z = R_psi (X_h1 - X_h2)/|X_h1 - X_h2| H_d + X_h1 (world ENU, metres).

    X_h1/X_h2: ground points of the forward and backward surface sensors. R_psi turns the
    fore-aft ground direction up by pi/2; the result is normalised after rotating because
    roll or side-slip take (X_h1 - X_h2) out of the heading's vertical plane (docs/paper.md).
    """
    x1, y1, z1 = np.asarray(x_h1, dtype=np.float64).tolist()
    x2, y2, z2 = np.asarray(x_h2, dtype=np.float64).tolist()
    return np.array(aim_point_xyz(x1, y1, z1, x2, y2, z2, yaw_rad, h_d_m))


def aim_point_xyz(
    x1: float, y1: float, z1: float, x2: float, y2: float, z2: float, yaw_rad: float, h_d_m: float
) -> tuple[float, float, float]:
    """`aim_point` in plain floats (the per-cycle path): X_h1 = (x1, y1, z1), X_h2 = (x2,
    y2, z2) in, X_z out, world ENU metres. R_psi is `rotations.r_psi` written out. Raises
    ValueError when the two points coincide or their direction is perpendicular to the
    heading."""
    gx, gy, gz = x1 - x2, y1 - y2, z1 - z2
    g_norm = math.sqrt(gx * gx + gy * gy + gz * gz)
    if g_norm < 1e-9:
        raise ValueError("forward and backward ground points coincide")
    gx, gy, gz = gx / g_norm, gy / g_norm, gz / g_norm
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    ux = s * s * gx - c * s * gy - c * gz
    uy = -c * s * gx + c * c * gy - s * gz
    uz = c * gx + s * gy
    up_norm = math.sqrt(ux * ux + uy * uy + uz * uz)
    if up_norm < 1e-9:
        raise ValueError("ground direction is perpendicular to the heading")
    return x1 + h_d_m * ux / up_norm, y1 + h_d_m * uy / up_norm, z1 + h_d_m * uz / up_norm


def desired_pitch(x_z: FloatArray, x_d_prev: FloatArray, phi_max_rad: float) -> float:
    """Eq. (4): phi_d = arctan((z_z - z_d(k-1)) / |[x_z, y_z] - [x_d(k-1), y_d(k-1)]|),
    clamped to [-phi_max, +phi_max] (requirement 5). Radians."""
    xz, yz, zz = np.asarray(x_z, dtype=np.float64).tolist()
    xd, yd, zd = np.asarray(x_d_prev, dtype=np.float64).tolist()
    return desired_pitch_xyz(xz, yz, zz, xd, yd, zd, phi_max_rad)


def desired_pitch_xyz(
    xz: float, yz: float, zz: float, xd: float, yd: float, zd: float, phi_max_rad: float
) -> float:
    """`desired_pitch` in plain floats (the per-cycle path): X_z = (xz, yz, zz), X_d(k-1) =
    (xd, yd, zd), world ENU metres. Radians."""
    dz = zz - zd
    dh = math.hypot(xz - xd, yz - yd)
    phi = math.atan2(dz, dh)
    return min(max(phi, -phi_max_rad), phi_max_rad)


def advance_exact(
    path: Path, s: float, z: float, step_m: float, phi_d_rad: float
) -> tuple[float, float]:
    """Eq. (5) with the exact arc-length inverse: move X_d by a 3-D distance step_m.

    The horizontal arc advances by step_m cos(phi_d) and z by tan(phi_d) times that, so the
    3-D speed of X_d is exactly step_m / dtau. Returns the new (s, z_d); s is clamped to the
    path's end. Locating the new s on its segment is the caller's `path.locate(s)`.
    """
    ds = step_m * math.cos(phi_d_rad)
    s_new = min(s + ds, path.length)
    ds = s_new - s
    return s_new, z + math.tan(phi_d_rad) * ds


def advance_paper(
    path: Path, segment: int, t: float, z: float, step_m: float, phi_d_rad: float, delta: float
) -> tuple[int, float, float, int]:
    """Eq. (5) with the paper's fixed-increment search (reference implementation).

    Steps the parameter by `delta` until the accumulated 3-D chord length reaches step_m
    (Steps 1-3 of section 3); overshoots by up to |B'| delta. Crosses into the next segment
    when the current one ends. Returns (segment, t, z_d, iterations).
    """
    tan_phi = math.tan(phi_d_rad)
    seg = path.segments[segment]
    prev = seg.point(t)
    travelled = 0.0
    horizontal = 0.0
    iterations = 0
    while travelled < step_m:
        iterations += 1
        t += delta
        if t >= 1.0:
            if segment + 1 < len(path.segments):
                segment += 1
                seg = path.segments[segment]
                t -= 1.0
            else:
                t = 1.0
        point = seg.point(t)
        sx = math.hypot(point[0] - prev[0], point[1] - prev[1])
        sz = tan_phi * sx
        travelled += math.hypot(sx, sz)
        horizontal += sx
        prev = point
        if t >= 1.0 and segment == len(path.segments) - 1:
            break
    return segment, t, z + tan_phi * horizontal, iterations
