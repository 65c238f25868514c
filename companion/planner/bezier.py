"""Cubic Bezier segments in the horizontal plane (eq. 5), with exact arc-length inversion.

A segment is four control points (W1, P1, P2, W2) as rows of a (4, 2) array, local ENU
x, y in metres. The parameter t (the paper's delta) runs over [0, 1]. Arc length uses
8-point Gauss-Legendre quadrature on a table of sub-intervals (16, halved adaptively where
the quadrature has not converged, as next to a cusp); its inverse uses Newton's method
safeguarded by bisection, so a given arc length maps back to t to ~1e-12 m.

Speed: the per-cycle calls (`point`, `velocity`, `unit_tangent`, `heading`, `speed`,
`parameter_at`) are scalar pure-float code; the work done once per segment (the table,
`uniform_samples`, `parameters_at`) is vectorised over all its nodes or samples at once.
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from companion.planner.types import FloatArray

_GL_NODES, _GL_WEIGHTS = np.polynomial.legendre.leggauss(8)
_GL = tuple((float(x), float(w)) for x, w in zip(_GL_NODES, _GL_WEIGHTS, strict=True))
_TABLE_INTERVALS = 16
_TABLE_MAX_DEPTH = 16


def _bernstein(t: FloatArray) -> FloatArray:
    """Cubic Bernstein basis, shape (len(t), 4)."""
    u = 1.0 - t
    return np.stack([u * u * u, 3.0 * t * u * u, 3.0 * t * t * u, t * t * t], axis=-1)


class UniformSamples(NamedTuple):
    """Samples of a segment uniform in arc length: arc lengths from its start (n,), points
    and unit tangents (n, 2), signed curvature (n,) in 1/m."""

    s: FloatArray
    points: FloatArray
    tangents: FloatArray
    curvature: FloatArray


@dataclass(frozen=True)
class CubicBezier:
    """B(t) = (1-t)^3 W1 + 3t(1-t)^2 P1 + 3t^2(1-t) P2 + t^3 W2, t in [0, 1] (eq. 5).

    control: (4, 2) control points, metres. The arc-length table is built once, on first
    use; `uniform_samples` are kept once computed.
    """

    control: FloatArray
    _table: tuple[tuple[float, ...], tuple[float, ...]] | None = field(
        init=False, repr=False, compare=False
    )
    _c: tuple[float, ...] = field(init=False, repr=False, compare=False)
    _d: tuple[float, ...] = field(init=False, repr=False, compare=False)
    _h: tuple[tuple[float, float], ...] = field(init=False, repr=False, compare=False)
    _uniform: dict[float, UniformSamples] = field(init=False, repr=False, compare=False)

    @property
    def control_floats(self) -> tuple[float, ...]:
        """The control points as plain floats x0, y0, x1, y1, x2, y2, x3, y3, metres."""
        return self._c

    @property
    def hodograph_floats(self) -> tuple[float, ...]:
        """The hodograph's control points 3 diff(control) as plain floats (dx0, dy0, dx1,
        dy1, dx2, dy2), metres: the numbers numpy's `3.0 * np.diff(control, axis=0)` gives."""
        return self._d

    def __post_init__(self) -> None:
        c = np.array(self.control, dtype=np.float64)
        if c.shape != (4, 2):
            raise ValueError(f"control points must be a finite (4, 2) array, got {c!r}")
        self._setup(c, c.ravel().tolist())

    @classmethod
    def from_floats(cls, flat: list[float]) -> CubicBezier:
        """The segment of control points x0, y0, x1, y1, x2, y2, x3, y3 (plain floats, metres):
        `CubicBezier(np.array(...).reshape(4, 2))` without the array's round trip (a segment
        is built per candidate correction)."""
        seg = object.__new__(cls)
        seg._setup(np.array(flat, dtype=np.float64).reshape(4, 2), flat)
        return seg

    def _setup(self, c: FloatArray, flat: list[float]) -> None:
        # Scalar copies of the control points and of the hodograph's control points
        # (x0, y0, x1, y1, ...) for the per-cycle scalar fast paths (pure-float maths; the
        # same operations, in the same order, as the array forms 3 diff(c) and the powers
        # below, so the same numbers). Plain floats: a segment is built per candidate
        # correction, and numpy's overhead on a (4, 2) array is most of that cost.
        if not all(map(math.isfinite, flat)):
            raise ValueError(f"control points must be a finite (4, 2) array, got {c!r}")
        c.setflags(write=False)
        object.__setattr__(self, "control", c)
        x0, y0, x1, y1, x2, y2, x3, y3 = flat
        d = (
            3.0 * (x1 - x0),
            3.0 * (y1 - y0),
            3.0 * (x2 - x1),
            3.0 * (y2 - y1),
            3.0 * (x3 - x2),
            3.0 * (y3 - y2),
        )
        object.__setattr__(self, "_c", tuple(flat))
        object.__setattr__(self, "_d", d)
        # The hodograph in powers of t: B'(t) = h0 + h1 t + h2 t^2, for vectorised speeds.
        object.__setattr__(
            self,
            "_h",
            (
                (d[0], d[1]),
                (2.0 * (d[2] - d[0]), 2.0 * (d[3] - d[1])),
                (d[0] - 2.0 * d[2] + d[4], d[1] - 2.0 * d[3] + d[5]),
            ),
        )
        object.__setattr__(self, "_uniform", {})
        object.__setattr__(self, "_table", None)

    def _arc_table(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(knots, lengths): the arc-length table, built on first use (a candidate detour
        segment that fails its curvature check never needs one)."""
        if self._table is not None:
            return self._table
        # The table: each interval's quadrature whole and in halves, all intervals in one
        # vectorised pass; the few that disagree (next to a cusp) are refined one by one.
        n = _TABLE_INTERVALS
        a = np.arange(n) / n
        b = np.arange(1, n + 1) / n
        m = 0.5 * (a + b)
        quad = self._gauss_legendre_many(np.concatenate([a, a, m]), np.concatenate([b, m, b]))
        # Plain floats from here (the same numbers as numpy's scalars, fewer calls).
        whole = quad[:n].tolist()
        halves = (quad[n : 2 * n] + quad[2 * n :]).tolist()
        a_list, b_list = a.tolist(), b.tolist()
        knots = [0.0]
        cum = [0.0]
        cusps = self._cusps()
        for k in range(n):
            inside = [r for r in cusps if a_list[k] < r < b_list[k]]
            if inside:
                # |B'| has a kink at a cusp: integrate up to it and from it, never across.
                edges = [a_list[k], *inside, b_list[k]]
                for lo, hi in itertools.pairwise(edges):
                    self._refine(lo, hi, 0, knots, cum)
            elif abs(whole[k] - halves[k]) > 1e-13 * (1.0 + whole[k]):
                self._refine(a_list[k], b_list[k], 0, knots, cum)
            else:
                knots.append(b_list[k])
                cum.append(cum[-1] + halves[k])
        table = (tuple(knots), tuple(cum))
        object.__setattr__(self, "_table", table)
        return table

    def _cusps(self) -> list[float]:
        """The t in (0, 1) where B'(t) = 0 (a cusp, or a straight curve doubling back),
        sorted: both components of the hodograph vanish there."""
        (x0, y0), (x1, y1), (x2, y2) = self._h
        scale = 1.0 + max(abs(x0), abs(y0), abs(x1), abs(y1), abs(x2), abs(y2))
        found: list[float] = []
        for c2, c1, c0 in ((x2, x1, x0), (y2, y1, y0)):
            for t in _real_roots_quadratic(c2, c1, c0):
                if not 0.0 < t < 1.0:
                    continue
                # `speeds` at one t in plain floats (the same operations, the same number).
                dx = (x2 * t + x1) * t + x0
                dy = (y2 * t + y1) * t + y0
                if math.sqrt(dx * dx + dy * dy) <= 1e-9 * scale:
                    found.append(t)
        return sorted(set(found))

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
        if isinstance(t, float):
            return np.array(self.point(t))
        tt = np.asarray(t, dtype=np.float64)
        return _bernstein(tt) @ self.control

    def point(self, t: float) -> tuple[float, float]:
        """B(t) at a scalar t as (x, y) floats (the pure-float fast path of `evaluate`)."""
        c = self._c
        u = 1.0 - t
        b0, b1, b2, b3 = u * u * u, 3.0 * t * u * u, 3.0 * t * t * u, t * t * t
        return (
            b0 * c[0] + b1 * c[2] + b2 * c[4] + b3 * c[6],
            b0 * c[1] + b1 * c[3] + b2 * c[5] + b3 * c[7],
        )

    def velocity(self, t: float) -> tuple[float, float]:
        """B'(t) at a scalar t as (dx/dt, dy/dt) floats, metres per unit t."""
        d = self._d
        u = 1.0 - t
        a, b, c = u * u, 2.0 * t * u, t * t
        return a * d[0] + b * d[2] + c * d[4], a * d[1] + b * d[3] + c * d[5]

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

    def unit_tangent(self, t: float) -> tuple[float, float]:
        """Unit tangent at t as (x, y) floats (the chord direction at a cusp)."""
        dx, dy = self.velocity(t)
        n = math.hypot(dx, dy)
        if n < 1e-12:
            c = self._c
            dx, dy = c[6] - c[0], c[7] - c[1]
            n = math.hypot(dx, dy) or 1.0
        return dx / n, dy / n

    def tangent(self, t: float) -> FloatArray:
        """Unit tangent at t, (2,) (falls back to the chord direction at a cusp)."""
        return np.array(self.unit_tangent(t))

    def heading(self, t: float) -> float:
        """Heading of the tangent, radians CCW from +x."""
        tx, ty = self.unit_tangent(t)
        return math.atan2(ty, tx)

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
        """Integral of |B'| over [a, b], 8-point Gauss-Legendre (`speed` inlined: this is
        the innermost loop of the arc-length table and of its inverse)."""
        d0, d1, d2, d3, d4, d5 = self._d
        half, mid = 0.5 * (b - a), 0.5 * (b + a)
        total = 0.0
        for x, w in _GL:
            t = mid + half * x
            u = 1.0 - t
            p, q, r = u * u, 2.0 * t * u, t * t
            total += w * math.hypot(p * d0 + q * d2 + r * d4, p * d1 + q * d3 + r * d5)
        return half * total

    def _gauss_legendre_many(self, a: FloatArray, b: FloatArray) -> FloatArray:
        """`_gauss_legendre` over the intervals [a_i, b_i] at once, (n,)."""
        half, mid = 0.5 * (b - a), 0.5 * (b + a)
        speed = self.speeds(mid[:, None] + half[:, None] * _GL_NODES)
        out: FloatArray = half * (speed @ _GL_WEIGHTS)
        return out

    def speeds(self, t: FloatArray) -> FloatArray:
        """|B'(t)| for an array of t (any shape), metres per unit t. The hodograph in
        powers of t, B'(t) = h0 + t (h1 + t h2), evaluated by Horner's rule."""
        (x0, y0), (x1, y1), (x2, y2) = self._h
        dx = (x2 * t + x1) * t + x0
        dy = (y2 * t + y1) * t + y0
        out: FloatArray = np.sqrt(dx * dx + dy * dy)
        return out

    @property
    def length(self) -> float:
        """Total arc length, metres."""
        return self._arc_table()[1][-1]

    def arc_length(self, t: float) -> float:
        """Arc length from t = 0 to t, metres."""
        t = min(max(t, 0.0), 1.0)
        knots, lengths = self._arc_table()
        k = min(bisect.bisect_right(knots, t) - 1, len(knots) - 2)
        return lengths[k] + self._gauss_legendre(knots[k], t)

    def parameter_at(self, s: float, tol_m: float = 1e-12) -> float:
        """The t in [0, 1] at which the arc length from 0 equals s (clamped to the segment).

        Newton's method on L(t) - s with L'(t) = |B'(t)|, kept inside the table interval
        that brackets s; a step that leaves the bracket is replaced by bisection.
        """
        knots, lengths = self._arc_table()
        if s <= 0.0:
            return 0.0
        if s >= lengths[-1]:
            return 1.0
        k = min(bisect.bisect_left(lengths, s) - 1, len(lengths) - 2)
        k = max(k, 0)
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

    def parameters_at(self, s: FloatArray, tol_m: float = 1e-12) -> FloatArray:
        """`parameter_at` for an array of arc lengths (n,): the same safeguarded Newton
        iteration, on all of them at once; each one stops changing when it has converged."""
        s = np.asarray(s, dtype=np.float64)
        knots, lengths = map(np.array, self._arc_table())
        k = np.clip(np.searchsorted(lengths, s) - 1, 0, len(lengths) - 2)
        base, start = lengths[k], knots[k]
        lo, hi = start, knots[k + 1]
        span = lengths[k + 1] - base
        frac = np.divide(s - base, span, out=np.full(len(s), 0.5), where=span > 0.0)
        t = lo + (hi - lo) * frac
        done = (s <= 0.0) | (s >= lengths[-1])  # answered below, outside (0, length)
        for _ in range(50):
            f = base + self._gauss_legendre_many(start, t) - s
            active = ~done & (np.abs(f) > tol_m)
            if not active.any():
                break
            done |= ~active
            over = f > 0.0
            hi = np.where(over, t, hi)
            lo = np.where(over, lo, t)
            # Newton; where |B'| vanishes the step is 0, which leaves the bracket: bisect.
            v = self.speeds(t)
            t_new = t - f / np.where(v > 1e-12, v, np.inf)
            t_new = np.where((lo < t_new) & (t_new < hi), t_new, 0.5 * (lo + hi))
            t = np.where(active, t_new, t)
            done |= active & (hi - lo < 1e-15)
        out: FloatArray = np.where(s <= 0.0, 0.0, np.where(s >= lengths[-1], 1.0, t))
        return out

    def uniform_samples(self, spacing_m: float) -> UniformSamples:
        """Samples uniform in arc length at about spacing_m, both ends included (cached)."""
        cached = self._uniform.get(spacing_m)
        if cached is None:
            n = max(2, math.ceil(self.length / spacing_m) + 1)
            lengths = np.linspace(0.0, self.length, n)
            ts = self.parameters_at(lengths)
            d = self.derivative(ts, 1)
            norm = np.hypot(d[:, 0], d[:, 1])
            norm[norm < 1e-12] = 1.0
            cached = UniformSamples(
                lengths, self.evaluate(ts), d / norm[:, None], self.curvature(ts)
            )
            for a in cached:
                a.setflags(write=False)
            self._uniform[spacing_m] = cached
        return cached

    def sample(self, n: int, bases: dict[int, FloatArray] | None = None) -> FloatArray:
        """n points at uniform t, including both ends, (n, 2). bases: a cache of the
        Bernstein basis at n uniform t, by n (the same for every segment), kept by a caller
        that samples many segments; the same numbers either way."""
        basis = None if bases is None else bases.get(n)
        if basis is None:
            basis = _bernstein(np.linspace(0.0, 1.0, n))
            if bases is not None:
                basis.setflags(write=False)
                bases[n] = basis
        out: FloatArray = basis @ self.control  # (`evaluate`'s product)
        return out


def _real_roots_quadratic(c2: float, c1: float, c0: float) -> list[float]:
    """Real roots of c2 t^2 + c1 t + c0 (closed form, plain floats): a pair whose imaginary
    part is below 1e-12 counts as one real root. None when c2 = c1 = 0."""
    if c2 == 0.0:
        return [] if c1 == 0.0 else [-c0 / c1]
    mid = -c1 / (2.0 * c2)
    disc = c1 * c1 - 4.0 * c2 * c0
    if disc < 0.0:
        return [mid] if math.sqrt(-disc) / (2.0 * abs(c2)) < 1e-12 else []
    # The larger-magnitude root first, the other from the product c0 / c2 (no cancellation).
    q = -0.5 * (c1 + math.copysign(math.sqrt(disc), c1))
    if q == 0.0:
        return [mid]
    return [q / c2, c0 / q]


def _pair(v: FloatArray | Sequence[float]) -> tuple[float, float]:
    """x, y of a 2-vector as plain floats."""
    x, y = v.tolist() if isinstance(v, np.ndarray) else v
    return float(x), float(y)


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
    # Plain floats, the array form's operations element by element (the same numbers).
    x0, y0 = _pair(start)
    x3, y3 = _pair(end)
    sx, sy = _pair(start_dir)
    ex, ey = _pair(end_dir)
    dx, dy = x3 - x0, y3 - y0
    chord = math.sqrt(dx * dx + dy * dy)
    h0 = chord / 3.0 if handle_m is None else float(handle_m)
    h1 = h0 if end_handle_m is None else float(end_handle_m)
    return CubicBezier.from_floats(
        [x0, y0, x0 + h0 * sx, y0 + h0 * sy, x3 - h1 * ex, y3 - h1 * ey, x3, y3]
    )
