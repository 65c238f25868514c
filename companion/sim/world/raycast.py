"""Ray casting against the height field: range sensors of the simulator.

`RayCaster.cast` intersects every ray of a call with every solid feature in closed form and
scans the smooth terrain in one vectorised pass (Lipschitz clearing, parabola or secant
refinement); `RayCaster.march` is the plain reference march (sample every step, then
subdivide), slower, and the tests' oracle. Rays: origins and directions as rows, shape
(n, 3), world ENU metres; ranges in metres, inf where nothing is hit.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.planner.types import FloatArray
from companion.sim.world.features import TINY, Feature, Plane, SolidColumns, intersects
from companion.sim.world.heights import HeightField

# reductions as ufunc methods: the same results, without ndarray methods' Python layer
_MIN = np.minimum.reduce
_MAX = np.maximum.reduce
_SUM = np.add.reduce


def ray_args(
    origins: ArrayLike, directions: ArrayLike, max_range_m: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Validated (n, 3) origins, unit directions and (n,) ranges."""
    o = np.asarray(origins, np.float64).reshape(-1, 3)
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    n = o.shape[0]
    if d.shape[0] != n:
        raise ValueError(f"origins and directions differ in length: {n} vs {d.shape[0]}")
    norm = np.sqrt(np.einsum("ij,ij->i", d, d))
    if n and not (float(_MIN(norm)) > 1e-12 and math.isfinite(float(_SUM(norm)))):
        raise ValueError("ray directions must be finite and non-zero")
    d = d / norm[:, None]
    rng = np.asarray(max_range_m, np.float64)
    if rng.shape != (n,):  # (np.broadcast_to costs more than a ray cast's arithmetic)
        rng = np.broadcast_to(rng, (n,))
    if n and not (float(_MIN(rng)) >= 0.0 and math.isfinite(float(_SUM(rng)))):
        raise ValueError("max_range_m must be finite and >= 0")
    return o, d, rng


_UNIT_STEPS: dict[int, FloatArray] = {}


def _unit_steps(m: int) -> FloatArray:
    """(m + 1,) evenly spaced from 0 to 1 (cached)."""
    u = _UNIT_STEPS.get(m)
    if u is None:
        u = _UNIT_STEPS[m] = np.arange(m + 1) / m
    return u


def _parabola_root(
    f: list[float], k: int, m: int, end: float, dh2: float, jerk: float, tol: float
) -> float | None:
    """The crossing in the scan's bracket [t_k, t_k+1] (t_i = end i / m) from the parabola
    through three samples f = f(t_i0 .. t_i0+2), i0 = max(k - 1, 0), if its error is known
    to be below tol / 2, else None. The parabola is within e = 0.0642 J |dh|^3 w^3 of the
    terrain function (J: bound of the third derivative along a line, w: spacing), so every
    crossing lies within e / S of its root, S being its least slope on the bracket."""
    i0 = max(k - 1, 0)
    if len(f) < 3:
        return None
    f0, f1, f2 = f
    w = end / m
    qa = 0.5 * (f2 - 2.0 * f1 + f0)  # p(s) = qa s^2 + (f1 - f0 - qa) s + f0, s = (t - t_i0) / w
    sa = float(k - i0)  # the bracket is [sa, sa + 1]
    pb = 2.0 * qa * sa + (f1 - f0 - qa)  # p'(sa)
    pa = f1 if sa > 0.0 else f0  # p(sa) >= 0
    slope = -max(pb, 2.0 * qa + pb)  # least descent over the bracket, per unit of s
    if not slope > 0.0:
        return None
    if 0.0642 * jerk * dh2**1.5 * w**4 / slope > 0.5 * tol:
        return None
    u = 2.0 * pa / (math.sqrt(max(pb * pb - 4.0 * qa * pa, 0.0)) - pb)
    return w * (i0 + sa + min(max(u, 0.0), 1.0))


class RayCaster:
    """Ray casts against one height field. ray_step_m: the reference march's default step;
    scan_step_m: the default sampling step of the terrain in `cast`. Metres."""

    def __init__(self, field: HeightField, ray_step_m: float, scan_step_m: float) -> None:
        self.field = field
        self.ray_step_m = ray_step_m
        self.scan_step_m = scan_step_m
        self._solids = SolidColumns(field.solid)

    def cast(
        self,
        origins: ArrayLike,
        directions: ArrayLike,
        max_range_m: ArrayLike,
        step_m: float | None = None,
        tol_m: float = 1e-4,
    ) -> FloatArray:
        """Range (m) along each ray to the surface; inf if nothing within max_range_m.

        origins, directions: (n, 3) ENU (directions are normalised); max_range_m: (n,) or
        scalar. A ray starting below the surface returns 0.

        The solid features (cylinder, box, mesa: convex columns) are intersected in closed
        form. The terrain (ground, planes: affine along a ray, also closed form; hills) is
        sampled every step_m at most (default scan_step_m) in one vectorised evaluation; an
        interval between two samples above the terrain is cleared by a Lipschitz bound of
        the terrain (its steepest slope), else subdivided, so nothing deeper than tol_m is
        skipped however thin. The first crossing comes from a parabola through three
        samples where a bound of its error allows, else from secant-guided subdivision to
        tol_m. Where a height map is in reach the plain march `march` (every
        ray_step_m) is used instead: it is faster there. It is also the tests' reference.
        """
        o, d, rng = ray_args(origins, directions, max_range_m)
        n = o.shape[0]
        step = self.scan_step_m if step_m is None else float(step_m)
        if not step > 0:
            raise ValueError(f"step_m must be > 0, got {step}")
        if n == 0:
            return np.full(0, np.inf)
        if not d.all():  # no zero components: slab tests divide by them
            d = np.where(d == 0.0, TINY, d)
        r_max = float(_MAX(rng))
        lo3, hi3 = _MIN(o, axis=0), _MAX(o, axis=0)
        box = (
            float(lo3[0]) - r_max,
            float(hi3[0]) + r_max,
            float(lo3[1]) - r_max,
            float(hi3[1]) + r_max,
        )
        # the terrain matters up to the first solid's entry: all rays against all solids
        end = self._solids.first_entry(o, d, rng, box)
        solid_hit = end < rng if self.field.solid else np.zeros(n, bool)
        # Terrain along ray i: f(t) = g0 + g1 t - N(x(t), y(t)): g the height above the
        # affine part (ground and planes), N the sum of the other additive features.
        g0 = o[:, 2] - self.field.ground_z
        g1 = d[:, 2].copy()
        nonlinear: list[Feature] = []
        for f in self.field.additive:
            if f.affine:
                assert isinstance(f, Plane)
                g0 = g0 - ((o[:, 0] - f.px) * f.gx + (o[:, 1] - f.py) * f.gy)
                g1 = g1 - (d[:, 0] * f.gx + d[:, 1] * f.gy)
            elif intersects(f.cull_bbox, box):
                nonlinear.append(f)
        if any(f.curvature is None for f in nonlinear):
            # Height maps: their Lipschitz bound is loose (the steepest cell anywhere) and
            # there is no curvature bound, so the plain march is faster.
            return self.march(o, d, rng, tol_m=tol_m)
        if not nonlinear:
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(g0 < 0.0, 0.0, np.where(g1 < 0.0, -g0 / g1, np.inf))
            t_ter = np.where(t <= end, t, np.inf)
        else:
            t_ter = self._scan_terrain(o, d, end, g0, g1, nonlinear, step, tol_m)
        out = np.where(solid_hit, end, np.inf)
        return np.minimum(out, t_ter)

    def _scan_terrain(
        self,
        o: FloatArray,
        d: FloatArray,
        end: FloatArray,
        g0: FloatArray,
        g1: FloatArray,
        feats: list[Feature],
        step: float,
        tol: float,
    ) -> FloatArray:
        """First t in [0, end] where g0 + g1 t < N(o + t d) (N: sum of feats), else inf.

        One vectorised pass samples every ray at m + 1 points; an interval between samples
        above the terrain is cleared when even the highest N its slope bound allows stays
        under the ray. The first sample inside the terrain and the last one before it
        bracket the crossing if no interval before that bracket is left uncleared; a ray
        that grazes the terrain earlier is searched again more finely (`_scan_slow`).
        """
        n = o.shape[0]
        lip = sum(f.lipschitz for f in feats)
        m = max(2, math.ceil(float(_MAX(end)) / step))
        T = end[:, None] * _unit_steps(m)
        N = self._sum_at(feats, o, d, T)
        G = g0[:, None] + g1[:, None] * T
        F = G - N
        ins = F < 0.0
        # Interval j is cleared if min G on it > max N: (N_j + N_j+1 + L |dh| w) / 2.
        dh2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]
        wl = (end * (0.5 / m) * lip) * np.sqrt(dh2)
        bad = np.minimum(G[:, :-1], G[:, 1:]) - 0.5 * (N[:, :-1] + N[:, 1:]) <= wl[:, None] - tol
        bad |= ins[:, 1:]  # implied, but for rounding and a height map's edge (a step)
        # Per ray in Python from here: the first interval not cleared (k) and the first
        # sample inside (j; k < j where there is one). Only the few rays that graze or hit
        # the terrain get past the first test; the same classification and parabola as
        # array operations measured slower, for 11 rays a cast and for 76 (8 sector fans).
        # (Array methods: np.argmax(x) and the like add a Python layer per call.)
        ka, ja = bad.argmax(axis=1), ins.argmax(axis=1)
        r = np.arange(n)
        ks: list[int] = ka.tolist()
        js: list[int] = ja.tolist()
        hits: list[bool] = ins[r, ja].tolist()  # the first True, if any
        bads: list[bool] = bad[r, ka].tolist()
        out = [math.inf] * n
        jerk: float | None = 0.0
        for f in feats:
            jerk = None if f.jerk is None or jerk is None else jerk + f.jerk
        refine: list[int] = []
        slow: list[int] = []
        for i in range(n):
            if not bads[i]:
                continue
            k, j = ks[i], js[i]
            if hits[i] and j == 0:
                out[i] = 0.0
            elif not hits[i] or j - k > 2:
                slow.append(i)
            elif jerk is None or j != k + 1:
                refine.append(i)
            else:
                t = _parabola_root(
                    F[i, max(k - 1, 0) : max(k - 1, 0) + 3].tolist(),
                    k,
                    m,
                    float(end[i]),
                    float(dh2[i]),
                    jerk,
                    tol,
                )
                if t is None:
                    refine.append(i)
                else:
                    out[i] = t
        res = np.array(out)
        if refine:
            c = np.array(refine)
            kc, jc = ka[c], ja[c]
            res[c] = self._refine_terrain(
                o[c], d[c], g0[c], g1[c], feats, T[c, kc], T[c, jc], F[c, kc], F[c, jc], tol
            )
        if slow:
            u = np.array(slow)
            ku = ka[u]
            res[u] = self._scan_slow(o[u], d[u], T[u, ku], end[u], g0[u], g1[u], feats, step, tol)
        return res

    def _scan_slow(
        self,
        o: FloatArray,
        d: FloatArray,
        a: FloatArray,
        end: FloatArray,
        g0: FloatArray,
        g1: FloatArray,
        feats: list[Feature],
        step: float,
        tol: float,
        m_sub: int = 8,
    ) -> FloatArray:
        """`_scan_terrain` from a (above the terrain) on, splitting the intervals the slope
        bound cannot clear until they are cleared, hold a crossing or are below tol."""
        n = o.shape[0]
        out = np.full(n, np.inf)
        dh2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]
        lh = sum(f.lipschitz for f in feats) * np.sqrt(dh2)
        curv = sum(f.curvature if f.curvature is not None else math.inf for f in feats)
        kf = curv * dh2 * 0.125 if math.isfinite(curv) else np.full(n, np.inf)
        fine = step / m_sub
        idx = np.arange(n)
        b = end.copy()
        m = max(m_sub, math.ceil(float((b - a).max()) / fine))
        rounds = 0
        while idx.size:
            rounds += 1
            if rounds > 200:  # a ray running along the terrain: march the rest of it
                t = self.march(o[idx] + a[:, None] * d[idx], d[idx], end[idx] - a)
                out[idx] = a + t
                break
            w = b - a
            T = a[:, None] + w[:, None] * _unit_steps(m)
            N = self._sum_at(feats, o[idx], d[idx], T)
            G = g0[idx, None] + g1[idx, None] * T
            F = G - N
            # Not cleared if the terrain may rise more than tol above the ray: by the slope
            # bound, and (smooth terrain) by the curvature bound, f >= chord - K w^2 / 8.
            wl = (0.5 * w / m * lh[idx])[:, None]
            bad = np.minimum(G[:, :-1], G[:, 1:]) - 0.5 * (N[:, :-1] + N[:, 1:]) <= wl - tol
            sag = (kf[idx] * (w / m) ** 2)[:, None]
            bad &= np.minimum(F[:, :-1], F[:, 1:]) <= sag - tol
            bad |= F[:, 1:] < 0.0
            k = np.argmax(bad, axis=1)
            r = np.arange(idx.size)
            anyb = bad[r, k]
            cross = anyb & (F[r, k + 1] < 0.0)
            if cross.any():
                c = np.nonzero(cross)[0]
                kc = k[c]
                i = idx[c]
                out[i] = self._refine_terrain(
                    o[i],
                    d[i],
                    g0[i],
                    g1[i],
                    feats,
                    T[c, kc],
                    T[c, kc + 1],
                    F[c, kc],
                    F[c, kc + 1],
                    tol,
                )
            unsure = anyb & ~cross
            split = unsure & (w / m > tol)
            # Next windows: the unsure interval, split; else on from the window's end.
            na = np.where(split, T[r, k], np.where(unsure, T[r, k + 1], b))
            nb = np.where(split, T[r, k + 1], end[idx])
            cont = ~cross & (na < nb)
            idx, a, b, split = idx[cont], na[cont], nb[cont], split[cont]
            if idx.size:
                whole = np.where(split, 0.0, b - a)
                m = max(m_sub, math.ceil(float(whole.max()) / fine))
        return out

    def _sum_at(
        self, feats: list[Feature], o: FloatArray, d: FloatArray, T: FloatArray
    ) -> FloatArray:
        """Sum of the features' contributions at o + T d, (n, m) for T (n, m): every hill
        of a kind at once (`AdditiveSum`), bit for bit the sum feature by feature."""
        # x and y in one pass: (2, n, m), element for element as o_x + d_x T and o_y + d_y T
        xy = o[:, :2].T[:, :, None] + d[:, :2].T[:, :, None] * T
        return self.field.sum_of(feats)(xy)

    def _refine_terrain(
        self,
        o: FloatArray,
        d: FloatArray,
        g0: FloatArray,
        g1: FloatArray,
        feats: list[Feature],
        lo: FloatArray,
        hi: FloatArray,
        flo: FloatArray,
        fhi: FloatArray,
        tol: float,
        m: int = 16,
    ) -> FloatArray:
        """The crossing in brackets [lo, hi] (f(lo) >= 0 > f(hi)) to within tol/2.

        Answers the secant root of the bracket once its error is known to be small enough:
        on smooth terrain every crossing in [lo, hi] lies within K |dh|^2 w^2 / (8 S) of it
        (K: curvature bound, w: width, S: the secant's slope); else once w <= tol. Each
        round samples m - 1 evenly spaced points and two either side of the secant root.
        """
        curv = 0.0
        for f in feats:
            if f.curvature is None:
                curv = math.inf
                break
            curv += f.curvature
        if math.isfinite(curv):
            kf = curv * (d[:, 0] ** 2 + d[:, 1] ** 2) * 0.125
        else:
            kf = np.full(lo.size, np.inf)
        u = _unit_steps(m)[1:-1]
        r = np.arange(lo.size)
        delta = tol / 2.2
        while True:
            w = hi - lo
            drop = flo - fhi
            ts = lo + w * (flo / drop)
            if float((kf * w * w * w / drop - 0.5 * tol).max()) <= 0.0 or float(w.max()) <= tol:
                return ts
            T = np.empty((lo.size, m + 1))
            np.multiply(w[:, None], u, out=T[:, : m - 1])
            T[:, : m - 1] += lo[:, None]
            T[:, m - 1] = ts - delta
            T[:, m] = ts + delta
            # clamped into the bracket (as np.clip, without its Python layer)
            np.minimum(np.maximum(T, lo[:, None], out=T), hi[:, None], out=T)
            F = g0[:, None] + g1[:, None] * T - self._sum_at(feats, o, d, T)
            ins = F < 0.0
            kh = np.where(ins, T, np.inf).argmin(axis=1)
            found = ins[r, kh]
            hi = np.where(found, T[r, kh], hi)
            fhi = np.where(found, F[r, kh], fhi)
            cand = np.where(~ins & (hi[:, None] > T), T, -np.inf)
            kl = cand.argmax(axis=1)
            better = cand[r, kl] > lo
            lo = np.where(better, T[r, kl], lo)
            flo = np.where(better, F[r, kl], flo)

    def march(
        self,
        origins: ArrayLike,
        directions: ArrayLike,
        max_range_m: ArrayLike,
        step_m: float | None = None,
        tol_m: float = 1e-4,
    ) -> FloatArray:
        """Reference ray casting by plain marching: each ray is sampled every step_m
        (default ray_step_m; a feature thinner than that can be missed at a grazing angle)
        in one vectorised height evaluation, then the interval holding the first crossing
        is subdivided to tol_m."""
        o, d, rng = ray_args(origins, directions, max_range_m)
        n = o.shape[0]
        step = self.ray_step_m if step_m is None else float(step_m)
        if not step > 0:
            raise ValueError(f"step_m must be > 0, got {step}")
        out = np.full(n, np.inf)
        if n == 0:
            return out
        nmax = math.ceil(float(rng.max()) / step)
        chunk = max(16, 100_000 // n)  # samples per ray per height evaluation
        act = np.arange(n)
        lo: list[FloatArray] = []
        hi: list[FloatArray] = []
        hit_idx: list[NDArray[np.intp]] = []
        j0 = 0
        while act.size and j0 <= nmax:
            j = np.arange(j0, min(nmax, j0 + chunk - 1) + 1)
            r = rng[act]
            t = np.minimum(j[None, :] * step, r[:, None])
            ins = self._inside_along(o[act], d[act], t)
            first = np.argmax(ins, axis=1)
            hit = ins[np.arange(act.size), first]
            f = first[hit]
            tk = t[hit, f]
            if j0 == 0:  # rays starting below the surface
                out[act[hit & (first == 0)]] = 0.0
                keep = f > 0
                act_hit, f, tk = act[hit][keep], f[keep], tk[keep]
                tprev = t[hit][keep][np.arange(f.size), f - 1]
            else:
                act_hit = act[hit]
                before = np.minimum((j0 - 1) * step, rng[act_hit])
                tprev = np.where(f > 0, t[hit, np.maximum(f - 1, 0)], before)
            hit_idx.append(act_hit)
            lo.append(tprev)
            hi.append(tk)
            act = act[~hit]
            j0 += j.size
        if hit_idx:
            idx = np.concatenate(hit_idx)
            if idx.size:
                out[idx] = self._refine_hits(
                    o[idx], d[idx], np.concatenate(lo), np.concatenate(hi), tol_m
                )
        return out

    def _inside_along(self, o: FloatArray, d: FloatArray, t: FloatArray) -> NDArray[np.bool_]:
        """Boolean (n, m): is o + t d below the surface, for ray n at parameter t[n, m]."""
        x = o[:, 0:1] + d[:, 0:1] * t
        y = o[:, 1:2] + d[:, 1:2] * t
        z = o[:, 2:3] + d[:, 2:3] * t
        return np.asarray(z < self.field.surface(x, y))

    def _refine_hits(
        self, o: FloatArray, d: FloatArray, lo: FloatArray, hi: FloatArray, tol: float, m: int = 32
    ) -> FloatArray:
        """Shrink brackets [lo, hi] (lo outside, hi inside) m-fold per round to tol (m)."""
        while float(np.max(hi - lo)) > tol:
            w = (hi - lo) / m
            t = lo[:, None] + w[:, None] * np.arange(1, m)[None, :]
            ins = np.concatenate([self._inside_along(o, d, t), np.ones((lo.size, 1), bool)], 1)
            k = np.argmax(ins, axis=1)
            lo, hi = lo + w * k, lo + w * (k + 1)
        return 0.5 * (lo + hi)

    # ------------------------------------------------------------------ distances
