"""The ground around the vehicle from the surface sensors' recent hits: a local quadric.

Eq. (3) takes the ground's slope from one chord, forward ground point to backward one, in
the heading's vertical plane. Two things it cannot see cost height (docs/terrain.md):
- a slope across the heading: H is the shortest distance to the surface, so on a side slope
  of angle b the vehicle must fly H_d / cos(b) above the ground, not H_d;
- curvature: eq. (4) steers towards a point about L = |X_z - X_d| ahead, a first-order lag
  of length L, which on relief of second derivative g'' along the path settles g'' L^2 / 2
  off H_d (too low over a crest, too high in a hollow).
`GroundPoints` keeps the last surface hits (every surface sensor, steep ones left out: they
are obstacles) a little apart along the track; `GroundPoints.fit` fits
z = c0 + c1 x + c2 y + c3 x^2 + c4 x y + c5 y^2 about a point (ridge-regularised, so a
direction no sensor has seen keeps zero slope and curvature). `GroundFit` gives its slope
and its second derivative along a heading.

World frame local ENU, metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# Ridge weights per coefficient (c0..c5) relative to the number of points: slopes are
# barely held, curvatures somewhat more, the cross term most (the sensors' cross of points
# fixes it poorly).
_RIDGE = np.array([0.0, 1e-3, 1e-3, 0.1, 0.5, 0.1])
_MIN_POINTS = 8


@dataclass(frozen=True, slots=True)
class GroundFit:
    """z = c0 + c1 x + c2 y + c3 x^2 + c4 x y + c5 y^2, x/y metres from origin_xy (ENU)."""

    origin_x: float
    origin_y: float
    coef: tuple[float, float, float, float, float, float]
    points: int

    def gradient(self, x: float, y: float) -> tuple[float, float]:
        """dz/dx, dz/dy at world (x, y) (dimensionless)."""
        _, c1, c2, c3, c4, c5 = self.coef
        dx, dy = x - self.origin_x, y - self.origin_y
        return c1 + 2.0 * c3 * dx + c4 * dy, c2 + c4 * dx + 2.0 * c5 * dy

    def second_along(self, yaw_rad: float) -> float:
        """d^2 z / ds^2 along the horizontal direction yaw_rad (ENU, from +x), 1/m."""
        _, _, _, c3, c4, c5 = self.coef
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        return 2.0 * (c3 * c * c + c4 * c * s + c5 * s * s)


class GroundPoints:
    """The last `capacity` ground points (world ENU, metres), each sensor's stored only once
    it is spacing_m (horizontally) from the last one it stored."""

    def __init__(self, capacity: int = 96, spacing_m: float = 0.2) -> None:
        self._xyz = np.zeros((capacity, 3))
        self._count = 0
        self._next = 0
        self._spacing2 = spacing_m * spacing_m
        self._last: dict[int, tuple[float, float]] = {}

    def __len__(self) -> int:
        return self._count

    def add(self, key: int, x: float, y: float, z: float) -> None:
        """Store the point of sensor `key` unless it is within spacing of that sensor's last."""
        last = self._last.get(key)
        if last is not None and (x - last[0]) ** 2 + (y - last[1]) ** 2 < self._spacing2:
            return
        self._last[key] = (x, y)
        self._xyz[self._next] = (x, y, z)
        self._next = (self._next + 1) % len(self._xyz)
        self._count = min(self._count + 1, len(self._xyz))

    def fit(self, x: float, y: float, radius_m: float) -> GroundFit | None:
        """The quadric through the stored points within radius_m of (x, y), or None when
        fewer than a handful are there."""
        pts = self._xyz[: self._count]
        dx = pts[:, 0] - x
        dy = pts[:, 1] - y
        near = dx * dx + dy * dy <= radius_m * radius_m
        n = int(np.count_nonzero(near))
        if n < _MIN_POINTS:
            return None
        dx, dy, z = dx[near], dy[near], pts[near, 2]
        a = np.stack([np.ones(n), dx, dy, dx * dx, dx * dy, dy * dy], axis=1)
        lhs = a.T @ a + np.diag(_RIDGE * n)
        rhs = a.T @ z
        coef = np.linalg.solve(lhs, rhs)
        c0, c1, c2, c3, c4, c5 = (float(v) for v in coef)
        return GroundFit(x, y, (c0, c1, c2, c3, c4, c5), n)


def offsets_from_fit(
    fit: GroundFit, x: float, y: float, yaw_rad: float, h_d_m: float, lead_m: float
) -> tuple[float, float]:
    """The two heights (metres) eq. (3)'s aim point lacks at world (x, y), the aim's place:
    H_d (sqrt(1 + g_a^2 + g_c^2) - sqrt(1 + g_a^2)) for the slope across the heading (g_a,
    g_c the fitted slope along and across), and -g'' lead^2 / 2 for the lag over a curved
    profile (g'' along the heading, lead the aim's distance ahead)."""
    gx, gy = fit.gradient(x, y)
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    along = gx * c + gy * s
    across = -gx * s + gy * c
    tilt = math.sqrt(1.0 + along * along + across * across)
    side = h_d_m * (tilt - math.sqrt(1.0 + along * along))
    bend = -0.5 * fit.second_along(yaw_rad) * lead_m * lead_m
    return side, bend
