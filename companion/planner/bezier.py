"""Cubic Bezier segments in the horizontal plane (eq. 5), with exact arc-length inversion.

A segment is four control points (W1, P1, P2, W2) as rows of a (4, 2) array, local ENU
x, y in metres. The parameter t (the paper's delta) runs over [0, 1]. Arc length uses
8-point Gauss-Legendre quadrature on a table of sub-intervals (16, halved adaptively where
the quadrature has not converged, as next to a cusp); its inverse uses Newton's method
safeguarded by bisection, so a given arc length maps back to t to ~1e-12 m.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

import numpy as np

from companion.planner.types import FloatArray

_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(8)
_GL_X = tuple(float(x) for x in _GL_NODES)
_GL_W = tuple(float(w) for w in _GL_WEIGHTS)
_TABLE_INTERVALS = 16
_TABLE_MAX_DEPTH = 16


def _bernstein(t: FloatArray) -> FloatArray:
    """Cubic Bernstein basis, shape (len(t), 4)."""
    u = 1.0 - t
    return np.stack([u * u * u, 3.0 * t * u * u, 3.0 * t * t * u, t * t * t], axis=-1)


@dataclass(frozen=True)
class CubicBezier:
    """B(t) = (1-t)^3 W1 + 3t(1-t)^2 P1 + 3t^2(1-t) P2 + t^3 W2, t in [0, 1] (eq. 5).

    control: (4, 2) control points, metres. The arc-length table is built once on creation.
    """

    control: FloatArray
    _knots: tuple[float, ...] = field(init=False, repr=False, compare=False)
    _lengths: tuple[float, ...] = field(init=False, repr=False, compare=False)
    _d: tuple[float, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        c = np.array(self.control, dtype=np.float64)
        if c.shape != (4, 2) or not np.all(np.isfinite(c)):
            raise ValueError(f"control points must be a finite (4, 2) array, got {c!r}")
        c.setflags(write=False)
        object.__setattr__(self, "control", c)
        # Scalar copies of the hodograph's control points for the hot path (pure-float maths).
        d = 3.0 * np.diff(c, axis=0)
        object.__setattr__(self, "_d", tuple(map(float, d.ravel())))
        knots = [0.0]
        cum = [0.0]
        for k in range(_TABLE_INTERVALS):
            self._refine(k / _TABLE_INTERVALS, (k + 1) / _TABLE_INTERVALS, 0, knots, cum)
        object.__setattr__(self, "_knots", tuple(knots))
        object.__setattr__(self, "_lengths", tuple(cum))

    def _refine(self, a: float, b: float, depth: int, knots: list[float], cum: list[float]) -> None:
        """Append table intervals covering [a, b], halving where the quadrature has not
        converged (near a cusp, where |B'| has a kink)."""
        whole = self._gauss_legendre(a, b)
        m = 0.5 * (a + b)
        halves = self._gauss_legendre(a, m) + self._gauss_legendre(m, b)
        if abs(whole - halves) > 1e-13 * (1.0 + whole) and depth < _TABLE_MAX_DEPTH:
            self._refine(a, m, depth + 1, knots, cum)
            self._refine(m, b, depth + 1, knots, cum)
            return
        knots.append(b)
        cum.append(cum[-1] + halves)

    # --- evaluation -------------------------------------------------------------------
    def evaluate(self, t: float | FloatArray) -> FloatArray:
        """Point(s) B(t); t scalar -> (2,), t array (n,) -> (n, 2)."""
        tt = np.asarray(t, dtype=np.float64)
        return _bernstein(tt) @ self.control

    def derivative(self, t: float | FloatArray, order: int = 1) -> FloatArray:
        """d^k B / dt^k for k = 1, 2, 3; same shapes as `evaluate`."""
        tt = np.asarray(t, dtype=np.float64)
        c = self.control
        if order == 1:
            d = 3.0 * np.diff(c, axis=0)
            u = 1.0 - tt
            basis = np.stack([u * u, 2.0 * tt * u, tt * tt], axis=-1)
            return basis @ d
        if order == 2:
            d2 = 6.0 * np.diff(c, n=2, axis=0)
            basis = np.stack([1.0 - tt, tt], axis=-1)
            return basis @ d2
        if order == 3:
            d3 = 6.0 * np.diff(c, n=3, axis=0)[0]
            return np.broadcast_to(d3, (*tt.shape, 2)).copy()
        raise ValueError(f"derivative order must be 1, 2 or 3, got {order}")

    def speed(self, t: float) -> float:
        """|B'(t)| in metres per unit t (scalar, pure-float fast path)."""
        d = self._d
        u = 1.0 - t
        a, b, c = u * u, 2.0 * t * u, t * t
        dx = a * d[0] + b * d[2] + c * d[4]
        dy = a * d[1] + b * d[3] + c * d[5]
        return math.hypot(dx, dy)

    def curvature(self, t: float | FloatArray) -> FloatArray:
        """Signed curvature (1/m), positive turning left (counter-clockwise)."""
        d1 = self.derivative(t, 1)
        d2 = self.derivative(t, 2)
        cross = d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0]
        speed = np.hypot(d1[..., 0], d1[..., 1])
        with np.errstate(divide="ignore", invalid="ignore"):
            k = cross / speed**3
        return np.where(speed > 1e-12, k, 0.0)

    def tangent(self, t: float) -> FloatArray:
        """Unit tangent at t (falls back to the chord direction at a cusp)."""
        d = self.derivative(t, 1)
        n = float(np.hypot(d[0], d[1]))
        if n < 1e-12:
            d = self.control[3] - self.control[0]
            n = float(np.hypot(d[0], d[1])) or 1.0
        return np.asarray(d / n, dtype=np.float64)

    def heading(self, t: float) -> float:
        """Heading of the tangent, radians CCW from +x."""
        d = self.tangent(t)
        return math.atan2(float(d[1]), float(d[0]))

    # --- de Casteljau -------------------------------------------------------------------
    def split(self, t: float) -> tuple[CubicBezier, CubicBezier]:
        """De Casteljau subdivision at t: two segments that together trace this one."""
        if not 0.0 <= t <= 1.0:
            raise ValueError(f"split parameter must be in [0, 1], got {t}")
        p0, p1, p2, p3 = self.control
        a = p0 + (p1 - p0) * t
        b = p1 + (p2 - p1) * t
        c = p2 + (p3 - p2) * t
        d = a + (b - a) * t
        e = b + (c - b) * t
        f = d + (e - d) * t
        return CubicBezier(np.array([p0, a, d, f])), CubicBezier(np.array([f, e, c, p3]))

    # --- arc length ---------------------------------------------------------------------
    def _gauss_legendre(self, a: float, b: float) -> float:
        """Integral of |B'| over [a, b], 8-point Gauss-Legendre."""
        half, mid = 0.5 * (b - a), 0.5 * (b + a)
        total = 0.0
        for x, w in zip(_GL_X, _GL_W, strict=True):
            total += w * self.speed(mid + half * x)
        return half * total

    @property
    def length(self) -> float:
        """Total arc length, metres."""
        return self._lengths[-1]

    def arc_length(self, t: float) -> float:
        """Arc length from t = 0 to t, metres."""
        t = min(max(t, 0.0), 1.0)
        k = min(bisect.bisect_right(self._knots, t) - 1, len(self._knots) - 2)
        return self._lengths[k] + self._gauss_legendre(self._knots[k], t)

    def parameter_at(self, s: float, tol_m: float = 1e-12) -> float:
        """The t in [0, 1] at which the arc length from 0 equals s (clamped to the segment).

        Newton's method on L(t) - s with L'(t) = |B'(t)|, kept inside the table interval
        that brackets s; a step that leaves the bracket is replaced by bisection.
        """
        lengths = self._lengths
        if s <= 0.0:
            return 0.0
        if s >= lengths[-1]:
            return 1.0
        k = min(bisect.bisect_left(lengths, s) - 1, len(lengths) - 2)
        k = max(k, 0)
        knots = self._knots
        lo, hi = knots[k], knots[k + 1]
        span = lengths[k + 1] - lengths[k]
        t = lo + (hi - lo) * ((s - lengths[k]) / span if span > 0.0 else 0.5)
        for _ in range(50):
            f = lengths[k] + self._gauss_legendre(knots[k], t) - s
            if abs(f) <= tol_m:
                return t
            if f > 0.0:
                hi = t
            else:
                lo = t
            v = self.speed(t)
            t_new = t - f / v if v > 1e-12 else 0.5 * (lo + hi)
            if not lo < t_new < hi:
                t_new = 0.5 * (lo + hi)
            if hi - lo < 1e-15:
                return t_new
            t = t_new
        return t

    def sample(self, n: int) -> FloatArray:
        """n points at uniform t, including both ends, (n, 2)."""
        return self.evaluate(np.linspace(0.0, 1.0, n))


def segment_through(
    start: FloatArray,
    start_dir: FloatArray,
    end: FloatArray,
    end_dir: FloatArray,
    handle_m: float | None = None,
    end_handle_m: float | None = None,
) -> CubicBezier:
    """Segment from `start` leaving along unit `start_dir` to `end` arriving along `end_dir`.

    Handles default to a third of the chord, which gives a curve without loops for
    moderate turns; pass equal handles at a joint for a parametric C1 join.
    """
    p0 = np.asarray(start, dtype=np.float64)
    p3 = np.asarray(end, dtype=np.float64)
    chord = float(np.linalg.norm(p3 - p0))
    h0 = chord / 3.0 if handle_m is None else handle_m
    h1 = h0 if end_handle_m is None else end_handle_m
    return CubicBezier(
        np.array([p0, p0 + h0 * np.asarray(start_dir), p3 - h1 * np.asarray(end_dir), p3])
    )
