"""The ground around the vehicle from the surface sensors' recent hits: a local quadric.

Eq. (3) takes the ground's slope from one chord, forward ground point to backward one, in
the heading's vertical plane. Two things it cannot see cost height (docs/paper.md, "Beyond
eqs (3)-(4)"):
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

import functools
import math
from dataclasses import dataclass

import numpy as np

from companion.planner.types import FloatArray

# Ridge weights per coefficient (c0..c5) relative to the number of points: slopes are
# barely held, curvatures somewhat more, the cross term most (the sensors' cross of points
# fixes it poorly).
_RIDGE = np.array([0.0, 1e-3, 1e-3, 0.1, 0.5, 0.1])
_RIDGE_DIAG = np.diag(_RIDGE)
_MIN_POINTS = 8
# The local origin of the stored rows moves when a fit is asked for farther than this, metres.
_REBASE_M = 8.0
# A fit is redone once this many points have come in since (else when its centre moves).
_REFIT_POINTS = 2
# Fits kept for reuse: the planner asks about two places a cycle (under X_d, and ahead).
_KEPT_FITS = 2


@dataclass(frozen=True, slots=True)
class GroundFit:
    """z = c0 + c1 x + c2 y + c3 x^2 + c4 x y + c5 y^2; x, y metres from (origin_x,
    origin_y), world ENU."""

    origin_x: float
    origin_y: float
    coef: tuple[float, float, float, float, float, float]
    points: int

    def height(self, x: float, y: float) -> float:
        """z at world (x, y), metres."""
        return float(self.heights(x, y))

    def heights(self, x: FloatArray | float, y: FloatArray | float) -> FloatArray | float:
        """z at world (x, y) (arrays or numbers), metres."""
        c0, c1, c2, c3, c4, c5 = self.coef
        dx, dy = x - self.origin_x, y - self.origin_y
        return c0 + c1 * dx + c2 * dy + c3 * dx * dx + c4 * dx * dy + c5 * dy * dy

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
    it is spacing_m (horizontally) from the last one it stored.

    Each point is kept with its row of the quadric's design matrix about a local origin (moved,
    and the rows recomputed, when a fit is asked for farther than _REBASE_M from it), and the
    last fits are reused while their centre has moved less than refit_m and fewer than
    _REFIT_POINTS points have come in: a fit is a 6 x 6 solve, the rest of a cycle is cheaper.
    """

    def __init__(self, capacity: int = 384, spacing_m: float = 0.2, refit_m: float = 0.1) -> None:
        self._xyz = np.zeros((capacity, 3))
        self._rows = np.zeros((capacity, 6))
        self._ox, self._oy = 0.0, 0.0
        self._count = 0
        self._next = 0
        self._spacing2 = spacing_m * spacing_m
        self._refit2 = refit_m * refit_m
        self._last: dict[int, tuple[float, float]] = {}
        self._fits: list[tuple[float, float, float, int, GroundFit | None]] = []
        self._added = 0

    def __len__(self) -> int:
        return self._count

    def add(self, key: int, x: float, y: float, z: float) -> None:
        """Store the point of sensor `key` unless it is within spacing of that sensor's last."""
        last = self._last.get(key)
        if last is not None and (x - last[0]) ** 2 + (y - last[1]) ** 2 < self._spacing2:
            return
        self._last[key] = (x, y)
        i = self._next
        self._xyz[i] = (x, y, z)
        u, v = x - self._ox, y - self._oy
        self._rows[i] = (1.0, u, v, u * u, u * v, v * v)
        self._next = (i + 1) % len(self._xyz)
        self._count = min(self._count + 1, len(self._xyz))
        self._added += 1

    def fit(self, x: float, y: float, radius_m: float) -> GroundFit | None:
        """The quadric through the stored points within radius_m of (x, y), or None when
        fewer than a handful are there (the last fit while little has changed)."""
        for last in self._fits:
            if (
                last[2] == radius_m
                and (x - last[0]) ** 2 + (y - last[1]) ** 2 < self._refit2
                and self._added - last[3] < _REFIT_POINTS
            ):
                return last[4]
        if (x - self._ox) ** 2 + (y - self._oy) ** 2 > _REBASE_M * _REBASE_M:
            self._rebase(x, y)
        fit = self._solve(x, y, radius_m)
        self._fits = [(x, y, radius_m, self._added, fit), *self._fits[: _KEPT_FITS - 1]]
        return fit

    def near(self, x: float, y: float, radius_m: float) -> tuple[FloatArray, FloatArray]:
        """The stored points within radius_m of world (x, y) horizontally, (k, 3) world ENU
        metres (a copy), and their squared horizontal distances from (x, y), (k,) m^2."""
        xyz = self._xyz[: self._count]
        dx = xyz[:, 0] - x
        dy = xyz[:, 1] - y
        r2 = dx * dx + dy * dy
        inside = r2 <= radius_m * radius_m
        return xyz.compress(inside, axis=0), r2[inside]

    def _rebase(self, x: float, y: float) -> None:
        """Move the local origin to (x, y) and recompute the stored rows."""
        self._ox, self._oy = x, y
        u = self._xyz[:, 0] - x
        v = self._xyz[:, 1] - y
        self._rows[:, 1], self._rows[:, 2] = u, v
        self._rows[:, 3], self._rows[:, 4], self._rows[:, 5] = u * u, u * v, v * v

    def _solve(self, x: float, y: float, radius_m: float) -> GroundFit | None:
        n_all = self._count
        rows = self._rows[:n_all]
        u = rows[:, 1] - (x - self._ox)
        v = rows[:, 2] - (y - self._oy)
        near = u * u + v * v <= radius_m * radius_m
        a = rows.compress(near, axis=0)
        n = len(a)
        if n < _MIN_POINTS:
            return None
        lhs = a.T @ a
        lhs += _RIDGE_DIAG * n  # (+ 0.0 off the diagonal: the same numbers)
        coef = _solve6(lhs, a.T @ self._xyz[:n_all, 2][near])
        c0, c1, c2, c3, c4, c5 = coef.tolist()
        return GroundFit(self._ox, self._oy, (c0, c1, c2, c3, c4, c5), n)


def _solve6(lhs: FloatArray, rhs: FloatArray) -> FloatArray:
    """lhs^-1 rhs for the fit's 6 x 6 normal equations. lhs is positive definite (the ridge,
    and n >= _MIN_POINTS rows of ones in c0), never singular. (numpy's private gufunc behind
    `np.linalg.solve` skips its checks and is faster, but a private API may change under a
    planner in flight.)"""
    return np.asarray(np.linalg.solve(lhs, rhs), dtype=np.float64)


def offsets_from_fit(
    fit: GroundFit,
    x: float,
    y: float,
    yaw_rad: float,
    h_d_m: float,
    lead_m: float,
    reach_m: float = math.inf,
) -> tuple[float, float]:
    """The two heights (metres) eq. (3)'s aim point lacks at world (x, y), the aim's place:
    H_d (sqrt(1 + g_a^2 + g_c^2) - sqrt(1 + g_a^2)) for the slope across the heading (g_a,
    g_c the fitted slope along and across), and -g'' L^2 / 2 for the lag over a curved
    profile (g'' along the heading, L the aim's distance ahead, lead_m, counted at most
    reach_m: the fit's curvature describes the ground within its radius, and carried over a
    longer lead its error grows with L^2 — on a descent the forward ground point can lie 5 m
    ahead, where 0.04 1/m of error is 0.5 m of height)."""
    lead_m = min(lead_m, reach_m)
    gx, gy = fit.gradient(x, y)
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    along = gx * c + gy * s
    across = -gx * s + gy * c
    tilt = math.sqrt(1.0 + along * along + across * across)
    side = h_d_m * (tilt - math.sqrt(1.0 + along * along))
    bend = -0.5 * fit.second_along(yaw_rad) * lead_m * lead_m
    return side, bend


def carry_to_heading(
    gx: float, gy: float, x: float, y: float, xd: float, yd: float, heading_rad: float
) -> tuple[float, float]:
    """A place (x, y) off the line from (xd, yd) along heading_rad (ENU, from +x), and the
    ground's slope there (gx, gy, dz/dx and dz/dy): how far along the line the place lies
    (metres) and the height the ground changes by from the place over to that point of the
    line (metres, the slope times the offset). World ENU."""
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    along = (x - xd) * c + (y - yd) * s
    return along, gx * (xd + along * c - x) + gy * (yd + along * s - y)


_MAX = np.maximum.reduce  # (ndarray.max's Python layer costs more than the reduction here)
_RING_FRACTIONS = np.repeat(np.array([0.0, 0.25, 0.5, 0.75, 0.95]), 16)
_RING_ANGLES = np.tile(np.linspace(0.0, 2.0 * math.pi, 16, endpoint=False), 5)
_RING_COS = np.cos(_RING_ANGLES)
_RING_SIN = np.sin(_RING_ANGLES)


@functools.lru_cache(maxsize=8)
def _rings(h_d_m: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The rings of `fit_floor_z` for one H_d: each sample's offset from the centre, east
    and north (80,) metres, and its sphere's rise sqrt(h_d_m^2 - r^2) (80,) metres (every
    ring lies within h_d_m). Read-only; the same numbers `floor_z` works out."""
    r = h_d_m * _RING_FRACTIONS
    east, north = r * _RING_COS, r * _RING_SIN
    rise = np.sqrt(np.maximum(h_d_m * h_d_m - r * r, 0.0))
    for a in (east, north, rise):
        a.setflags(write=False)
    return east, north, rise


def fit_floor_z(fit: GroundFit, x: float, y: float, h_d_m: float) -> float:
    """`floor_z` of the fitted surface about world (x, y): the lowest height there at least
    h_d_m from the fit sampled on 5 rings of 16 points out to 0.95 h_d_m, metres.

    The surface sensors sample the ground along four lines; the nearest ground may lie
    between them (a mesa's corner between the forward and the side line, 1 m away, with
    H 0.2 m short of H_d while every stored point said the height was enough). The fit
    spans the lines; it rounds a crease, so the points' own floor still holds at one.
    The rings' offsets and rises depend on h_d_m alone (`_rings`)."""
    east, north, rise = _rings(h_d_m)
    z = fit.heights(x + east, y + north)
    return float(_MAX(z + rise))


def floor_z(z: FloatArray, r2: FloatArray, h_d_m: float) -> float:
    """The lowest height at which a place is at least h_d_m from every point of heights z
    (k,) metres at squared horizontal distances r2 (k,) m^2 from it; -inf when none lies
    within h_d_m horizontally.

    H is the shortest distance to the surface: a point p within h_d_m horizontally needs
    z >= p_z + sqrt(h_d_m^2 - r^2) (the envelope of spheres of radius h_d_m about the
    points). A fit cannot follow a crease or an edge (a mesa's rim, a flank's foot); the
    points themselves can. Points on the surface: at this height the true H is at most
    h_d_m."""
    if len(z) == 0:
        return -math.inf
    room = h_d_m * h_d_m - r2
    need = z + np.sqrt(np.maximum(room, 0.0))
    need[room <= 0.0] = -math.inf
    return float(_MAX(need))
