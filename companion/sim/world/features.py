"""Feature geometry: each configured feature as a height function with the bounds the ray
cast and the distance queries rely on (slope, curvature, third derivative), closed-form ray
intervals and column distances of the solid ones, and a plan-view description for plots.

Additive features (gaussian_hill, plane, heightmap) return their contribution to the terrain;
solid ones (mesa, cylinder, box) their absolute top inside the footprint and -inf outside.
World ENU, metres.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from companion.planner.types import FloatArray
from companion.sim.world.schema import (
    BoxConfig,
    CylinderConfig,
    FeatureConfig,
    GaussianHillConfig,
    HeightmapConfig,
    MesaConfig,
    PlaneConfig,
)

OBSTACLE_MIN_RISE_M = 0.01
"""An obstacle feature is solid only where it rises more than this above the terrain (m)."""
_FOOTPRINT_EPS_M = 0.01  # a gaussian hill's footprint: where it adds more than this
CORE_FRACTION = 0.05  # a gaussian hill's core: where it adds more than this share of its height
_CULL_EPS_M = 1e-12  # beyond this contribution a feature is skipped during evaluation
TINY = 1e-200  # stands in for a zero direction component in slab tests

BBox = tuple[float, float, float, float]  # xmin, xmax, ymin, ymax
HeightFn = Callable[[FloatArray, FloatArray], FloatArray]


@dataclass(frozen=True)
class FeatureInfo:
    """Plan-view description of a feature, for plots. Metres, world ENU.

    polygon: (n, 2) outline of the footprint (None for an unbounded plane); circle:
    (x, y, radius) for round footprints, else None. core: for relief that fades out (a
    Gaussian hill), the outline where it rises more than CORE_FRACTION of its height: what
    "over the hill" means for the metrics (the footprint reaches out to 1 cm of relief).
    """

    name: str
    type: str
    obstacle: bool
    polygon: FloatArray | None
    circle: tuple[float, float, float] | None
    core: FloatArray | None = None


def _circle_polygon(cx: float, cy: float, r: float, n: int = 64) -> FloatArray:
    a = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    return np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a)])


def _ellipse_bbox(cx: float, cy: float, a: float, b: float, yaw: float) -> BBox:
    c, s = math.cos(yaw), math.sin(yaw)
    hx = math.hypot(a * c, b * s)
    hy = math.hypot(a * s, b * c)
    return (cx - hx, cx + hx, cy - hy, cy + hy)


class Feature(ABC):
    """Runtime feature. Additive ones return their contribution; solid ones their absolute
    top height inside the footprint and -inf outside."""

    solid: bool
    footprint_bbox: BBox | None  # where it matters (plots, raster extent); None = unbounded
    cull_bbox: BBox | None  # outside it the feature has no effect at all
    affine = False  # additive and affine in (x, y): the plane
    lipschitz = 0.0  # additive: a bound of |grad| of the contribution (m/m)
    curvature: float | None = 0.0  # additive: a bound of |Hessian| (1/m); None = not smooth
    jerk: float | None = 0.0  # additive: a bound of its third derivative along a line (1/m^2)

    def __init__(self, name: str, type_: str, obstacle: bool) -> None:
        self.name = name
        self.type = type_
        self.obstacle = obstacle

    @abstractmethod
    def evaluate(self, x: FloatArray, y: FloatArray) -> FloatArray: ...

    @abstractmethod
    def info(self) -> FeatureInfo: ...

    def jet(self, x: float, y: float) -> tuple[float, float, float, float, float, float]:
        """Smooth additive features: (value, d/dx, d/dy, d2/dx2, d2/dxdy, d2/dy2) at (x, y)."""
        raise NotImplementedError(f"{self.type} has no analytic derivatives")

    def ray_interval(self, o: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Solid features: (t_in, t_out), (n,) each, of the rays o + t d (o, d: (n, 3), no
        zero components in d) inside the feature's solid (a convex column); empty where
        t_in >= t_out."""
        raise NotImplementedError(f"{self.type} is not a solid feature")

    def column_distance(self, px: float, py: float, pz: float) -> float:
        """Solid features: exact 3-D distance (m) from p to the feature's solid, which is
        everything below its top inside its footprint. 0 inside."""
        raise NotImplementedError(f"{self.type} is not a solid feature")

    def bbox_distance(self, px: float, py: float) -> float:
        """Horizontal distance (m) from p_xy to the cull box: a lower bound of any distance
        to the feature."""
        if self.cull_bbox is None:
            return 0.0
        x0, x1, y0, y1 = self.cull_bbox
        return math.hypot(max(x0 - px, 0.0, px - x1), max(y0 - py, 0.0, py - y1))


class _GaussianHill(Feature):
    solid = False

    def __init__(self, cfg: GaussianHillConfig) -> None:
        super().__init__(cfg.name, cfg.type, cfg.obstacle)
        self.cx, self.cy = cfg.center
        self.h = cfg.height_m
        sx, sy = cfg.sigma_xy_m if cfg.sigma_xy_m is not None else (cfg.sigma_m, cfg.sigma_m)
        assert sx is not None and sy is not None
        self.sx, self.sy = float(sx), float(sy)
        self.yaw = math.radians(cfg.yaw_deg)
        self.c, self.s = math.cos(self.yaw), math.sin(self.yaw)
        self.k_fp = self._k(_FOOTPRINT_EPS_M)
        self.footprint_bbox = self._bbox(self.k_fp)
        self.cull_bbox = self._bbox(self._k(_CULL_EPS_M))
        smin = min(self.sx, self.sy)
        self.lipschitz = abs(self.h) * math.exp(-0.5) / smin
        self.curvature = abs(self.h) / (smin * smin)
        # Along a line the hill is a 1-D gaussian of sigma >= smin: |(3s - s^3) e^(-s^2/2)|
        # peaks at 1.379.
        self.jerk = 1.38 * abs(self.h) / smin**3

    def _k(self, eps: float) -> float:
        """Number of sigmas at which the contribution falls to eps."""
        return math.sqrt(2.0 * math.log(abs(self.h) / eps)) if abs(self.h) > eps else 0.0

    def _bbox(self, k: float) -> BBox:
        return _ellipse_bbox(self.cx, self.cy, k * self.sx, k * self.sy, self.yaw)

    def evaluate(self, x: FloatArray, y: FloatArray) -> FloatArray:
        dx, dy = x - self.cx, y - self.cy
        if self.sx == self.sy:
            return self.h * np.exp((dx * dx + dy * dy) * (-0.5 / self.sx**2))
        u = (dx * self.c + dy * self.s) / self.sx
        v = (dy * self.c - dx * self.s) / self.sy
        return self.h * np.exp(-0.5 * (u * u + v * v))

    def jet(self, x: float, y: float) -> tuple[float, float, float, float, float, float]:
        dx, dy = x - self.cx, y - self.cy
        c, s = self.c, self.s
        ax, ay = 1.0 / (self.sx * self.sx), 1.0 / (self.sy * self.sy)
        u = dx * c + dy * s
        v = dy * c - dx * s
        e = self.h * math.exp(-0.5 * (u * u * ax + v * v * ay))
        gu, gv = -u * ax * e, -v * ay * e  # gradient in the hill's frame
        huu = (u * u * ax - 1.0) * ax * e
        hvv = (v * v * ay - 1.0) * ay * e
        huv = u * v * ax * ay * e
        gx, gy = gu * c - gv * s, gu * s + gv * c
        hxx = c * c * huu - 2.0 * c * s * huv + s * s * hvv
        hyy = s * s * huu + 2.0 * c * s * huv + c * c * hvv
        hxy = c * s * (huu - hvv) + (c * c - s * s) * huv
        return e, gx, gy, hxx, hxy, hyy

    def info(self) -> FeatureInfo:
        a = np.linspace(0.0, 2.0 * math.pi, 64, endpoint=False)
        u, v = self.k_fp * self.sx * np.cos(a), self.k_fp * self.sy * np.sin(a)
        poly = np.column_stack(
            [self.cx + u * self.c - v * self.s, self.cy + u * self.s + v * self.c]
        )
        circle = None
        if self.sx == self.sy:
            circle = (self.cx, self.cy, self.k_fp * self.sx)
        k_core = math.sqrt(2.0 * math.log(1.0 / CORE_FRACTION))
        core = np.column_stack(
            [
                self.cx + (u * self.c - v * self.s) * k_core / max(self.k_fp, 1e-9),
                self.cy + (u * self.s + v * self.c) * k_core / max(self.k_fp, 1e-9),
            ]
        )
        return FeatureInfo(self.name, self.type, self.obstacle, poly, circle, core)


class _Mesa(Feature):
    solid = True

    def __init__(self, cfg: MesaConfig | CylinderConfig, ground_z: float) -> None:
        super().__init__(cfg.name, cfg.type, cfg.obstacle)
        self.cx, self.cy = cfg.center
        self.r = cfg.radius_m
        self.h = cfg.height_m
        self.ground = ground_z
        slope = cfg.side_slope_deg if isinstance(cfg, MesaConfig) else 90.0
        self.tan: float | None = None if slope >= 90.0 else math.tan(math.radians(slope))
        self.r_out = self.r if self.tan is None else self.r + self.h / self.tan
        self.footprint_bbox = (
            self.cx - self.r_out,
            self.cx + self.r_out,
            self.cy - self.r_out,
            self.cy + self.r_out,
        )
        self.cull_bbox = self.footprint_bbox

    def evaluate(self, x: FloatArray, y: FloatArray) -> FloatArray:
        r = np.hypot(x - self.cx, y - self.cy)
        top = self.ground + self.h
        if self.tan is None:
            return np.where(r <= self.r, top, -np.inf)
        z = np.maximum(top - np.maximum(r - self.r, 0.0) * self.tan, self.ground)
        return np.where(r <= self.r_out, z, -np.inf)

    def ray_interval(self, o: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
        t_in, t_out = mesa_intervals(o, d, *MesaParams.of([self]))
        return t_in[:, 0], t_out[:, 0]

    def column_distance(self, px: float, py: float, pz: float) -> float:
        # A solid of revolution: work in the (r, z) half-plane. Its section is the region
        # under top (r <= R), the side line down to (r_out, ground), and r <= r_out.
        r = math.hypot(px - self.cx, py - self.cy)
        top = self.ground + self.h
        if self.tan is None:
            return math.hypot(max(r - self.r, 0.0), max(pz - top, 0.0))
        if r <= self.r_out and pz <= top - max(r - self.r, 0.0) * self.tan:
            return 0.0
        d_top = math.hypot(max(r - self.r, 0.0), pz - top)
        # Side segment from (R, top) to (r_out, ground).
        sr, sz = self.r_out - self.r, -self.h
        t = min(max(((r - self.r) * sr + (pz - top) * sz) / (sr * sr + sz * sz), 0.0), 1.0)
        d_side = math.hypot(r - self.r - t * sr, pz - top - t * sz)
        d_foot = math.hypot(r - self.r_out, max(pz - self.ground, 0.0))
        return min(d_top, d_side, d_foot)

    def info(self) -> FeatureInfo:
        poly = _circle_polygon(self.cx, self.cy, self.r_out)
        return FeatureInfo(
            self.name, self.type, self.obstacle, poly, (self.cx, self.cy, self.r_out)
        )


class _Box(Feature):
    solid = True

    def __init__(self, cfg: BoxConfig, ground_z: float) -> None:
        super().__init__(cfg.name, cfg.type, cfg.obstacle)
        self.cx, self.cy = cfg.center
        self.hl, self.hw = cfg.size_m[0] / 2.0, cfg.size_m[1] / 2.0
        self.top = ground_z + cfg.size_m[2]
        yaw = math.radians(cfg.yaw_deg)
        self.c, self.s = math.cos(yaw), math.sin(yaw)
        corners = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)
        corners *= [self.hl, self.hw]
        rot = np.array([[self.c, -self.s], [self.s, self.c]])
        self.corners = corners @ rot.T + [self.cx, self.cy]
        self.footprint_bbox = (
            float(self.corners[:, 0].min()),
            float(self.corners[:, 0].max()),
            float(self.corners[:, 1].min()),
            float(self.corners[:, 1].max()),
        )
        self.cull_bbox = self.footprint_bbox

    def evaluate(self, x: FloatArray, y: FloatArray) -> FloatArray:
        dx, dy = x - self.cx, y - self.cy
        u = dx * self.c + dy * self.s
        v = dy * self.c - dx * self.s
        inside = (np.abs(u) <= self.hl) & (np.abs(v) <= self.hw)
        return np.where(inside, self.top, -np.inf)

    def ray_interval(self, o: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
        t_in, t_out = box_intervals(o, d, *BoxParams.of([self]))
        return t_in[:, 0], t_out[:, 0]

    def column_distance(self, px: float, py: float, pz: float) -> float:
        dx, dy = px - self.cx, py - self.cy
        u = dx * self.c + dy * self.s
        v = dy * self.c - dx * self.s
        dh = math.hypot(max(abs(u) - self.hl, 0.0), max(abs(v) - self.hw, 0.0))
        return math.hypot(dh, max(pz - self.top, 0.0))

    def info(self) -> FeatureInfo:
        return FeatureInfo(self.name, self.type, self.obstacle, self.corners.copy(), None)


class Plane(Feature):
    solid = False
    footprint_bbox = None
    cull_bbox = None

    def __init__(self, cfg: PlaneConfig) -> None:
        super().__init__(cfg.name, cfg.type, cfg.obstacle)
        t = math.tan(math.radians(cfg.slope_deg))
        d = math.radians(cfg.direction_deg)
        self.gx, self.gy = t * math.cos(d), t * math.sin(d)
        self.px, self.py = cfg.point
        self.lipschitz = math.hypot(self.gx, self.gy)

    affine = True

    def jet(self, x: float, y: float) -> tuple[float, float, float, float, float, float]:
        return (x - self.px) * self.gx + (y - self.py) * self.gy, self.gx, self.gy, 0.0, 0.0, 0.0

    def evaluate(self, x: FloatArray, y: FloatArray) -> FloatArray:
        return (x - self.px) * self.gx + (y - self.py) * self.gy

    def info(self) -> FeatureInfo:
        return FeatureInfo(self.name, self.type, self.obstacle, None, None)


class _Heightmap(Feature):
    solid = False

    def __init__(self, cfg: HeightmapConfig, base_dir: Path | None) -> None:
        super().__init__(cfg.name, cfg.type, cfg.obstacle)
        path = Path(cfg.file)
        if not path.is_absolute() and base_dir is not None:
            path = Path(base_dir) / path
        try:
            data = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise ValueError(f"heightmap '{cfg.name}': cannot load file {path}: {exc}") from exc
        if data.ndim != 2 or data.shape[0] < 2 or data.shape[1] < 2:
            raise ValueError(
                f"heightmap '{cfg.name}': file must hold a 2-D array of at least 2x2, "
                f"got shape {data.shape}"
            )
        if not np.issubdtype(data.dtype, np.number) or not np.all(np.isfinite(data)):
            raise ValueError(f"heightmap '{cfg.name}': heights must be finite numbers")
        self.z = np.ascontiguousarray(data, dtype=np.float64)
        self.res = cfg.resolution_m
        self.ox, self.oy = cfg.origin
        self.nr, self.nc = self.z.shape
        self.rect: BBox = (
            self.ox,
            self.ox + (self.nc - 1) * self.res,
            self.oy,
            self.oy + (self.nr - 1) * self.res,
        )
        self.footprint_bbox = self.cull_bbox = self.rect
        # Bilinear cells: |grad| <= hypot(max |dz/dx| on the cell's x edges, same for y).
        zx = np.abs(np.diff(self.z, axis=1)) / self.res
        zy = np.abs(np.diff(self.z, axis=0)) / self.res
        gx = np.maximum(zx[:-1], zx[1:])
        gy = np.maximum(zy[:, :-1], zy[:, 1:])
        self.lipschitz = float(np.sqrt(np.max(gx * gx + gy * gy)))
        self.curvature = None
        self.jerk = None

    def evaluate(self, x: FloatArray, y: FloatArray) -> FloatArray:
        fx = (x - self.ox) / self.res
        fy = (y - self.oy) / self.res
        inside = (fx >= 0.0) & (fx <= self.nc - 1) & (fy >= 0.0) & (fy <= self.nr - 1)
        fx = np.clip(np.nan_to_num(fx), 0.0, self.nc - 1)
        fy = np.clip(np.nan_to_num(fy), 0.0, self.nr - 1)
        i = np.minimum(fx.astype(np.intp), self.nc - 2)
        j = np.minimum(fy.astype(np.intp), self.nr - 2)
        tx, ty = fx - i, fy - j
        z = self.z
        lo = z[j, i] * (1.0 - tx) + z[j, i + 1] * tx
        hi = z[j + 1, i] * (1.0 - tx) + z[j + 1, i + 1] * tx
        return np.where(inside, lo * (1.0 - ty) + hi * ty, 0.0)

    def info(self) -> FeatureInfo:
        x0, x1, y0, y1 = self.rect
        poly = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=np.float64)
        return FeatureInfo(self.name, self.type, self.obstacle, poly, None)


class AdditiveSum:
    """The sum of additive features at points, every gaussian hill of a kind (round or
    elliptic) in one set of array operations: bit for bit the sum feature by feature in
    their order, ((base + f0) + f1) + ..., each term as `Feature.evaluate` gives it.

    Points as one stacked (2, ...) array of x and y (world ENU, metres)."""

    MAX_BATCH = 1 << 12
    """points x hills of a batch; beyond it, feature by feature (the batch pays where the
    arrays are small, numpy's cost per call ahead of its cost per element)."""

    def __init__(self, feats: Sequence[Feature]) -> None:
        self.feats = list(feats)
        rnd: list[_GaussianHill] = []
        ell: list[_GaussianHill] = []
        self._order: list[tuple[int, int]] = []  # (kind: 0 round, 1 elliptic, 2 other, index)
        for i, f in enumerate(self.feats):
            if isinstance(f, _GaussianHill) and f.sx == f.sy:
                self._order.append((0, len(rnd)))
                rnd.append(f)
            elif isinstance(f, _GaussianHill):
                self._order.append((1, len(ell)))
                ell.append(f)
            else:
                self._order.append((2, i))
        self._only_rnd = len(rnd) == len(self.feats)
        # per hill, as `_GaussianHill.evaluate` computes them: centre; round: -0.5 / sigma^2
        # and h; elliptic: cos, sin, sigma_x, sigma_y, h
        self._rnd = np.array([[f.cx, f.cy, -0.5 / f.sx**2, f.h] for f in rnd]).reshape(-1, 4)
        self._ell = np.array([[f.cx, f.cy, f.c, f.s, f.sx, f.sy, f.h] for f in ell]).reshape(-1, 7)
        self._shaped: dict[int, tuple[FloatArray, ...]] = {}

    def _params(self, nd: int) -> tuple[FloatArray, ...]:
        """The parameters shaped to broadcast against (k, 2, ...) and (k, ...), nd: the
        points' dimensions."""
        p = self._shaped.get(nd)
        if p is None:
            one = (1,) * nd
            r, e = self._rnd, self._ell
            p = self._shaped[nd] = (
                r[:, :2].reshape(-1, 2, *one),
                *(r[:, j].reshape(-1, *one) for j in (2, 3)),
                e[:, :2].reshape(-1, 2, *one),
                *(e[:, j].reshape(-1, *one) for j in range(2, 7)),
            )
        return p

    def __call__(self, xy: FloatArray, base: float | None = None) -> FloatArray:
        """The sum at points xy (2, ...), shape xy.shape[1:], with base added first if given
        (zeros if there are neither features nor base)."""
        k = len(self.feats)
        if k == 0:
            return np.full(xy.shape[1:], 0.0 if base is None else base)
        # 0-d: arrays out. One point: numpy sums a (k, 1) stack pairwise along axis 0 (a
        # contiguous reduction), not front to back as the hills one by one.
        if k == 1 or xy.ndim == 1 or xy[0].size == 1 or xy[0].size * k > self.MAX_BATCH:
            return self._one_by_one(xy, base)
        p = self._params(xy.ndim - 1)
        rnd = self._round(xy, p) if self._rnd.shape[0] else xy
        if self._only_rnd:
            if base is not None:
                rnd[0] += base  # base + f0, as f0 + base
            out: FloatArray = np.add.reduce(rnd, axis=0)  # in order along axis 0
            return out
        ell = self._elliptic(xy, p) if self._ell.shape[0] else xy
        terms = [
            rnd[j] if kind == 0 else ell[j] if kind == 1 else self.feats[j].evaluate(xy[0], xy[1])
            for kind, j in self._order
        ]
        z = terms[0] if base is None else terms[0] + base
        for t in terms[1:]:
            z = z + t
        return z

    def _one_by_one(self, xy: FloatArray, base: float | None) -> FloatArray:
        x, y = xy[0], xy[1]
        if base is None:
            z = self.feats[0].evaluate(x, y)
            for f in self.feats[1:]:
                z = z + f.evaluate(x, y)
            return np.asarray(z)  # (0-d: not a numpy scalar)
        z = np.full(xy.shape[1:], base)
        for f in self.feats:
            z += f.evaluate(x, y)
        return z

    @staticmethod
    def _round(xy: FloatArray, p: tuple[FloatArray, ...]) -> FloatArray:
        """(k, ...) h exp((dx^2 + dy^2) (-0.5 / sigma^2)) of the round hills."""
        dd = xy - p[0]
        dd *= dd
        q = dd[:, 0] + dd[:, 1]
        q *= p[1]
        np.exp(q, out=q)
        q *= p[2]
        return q

    @staticmethod
    def _elliptic(xy: FloatArray, p: tuple[FloatArray, ...]) -> FloatArray:
        """(k, ...) h exp(-0.5 (u^2 + v^2)) of the elliptic hills: u = (dx c + dy s) / sx,
        v = (dy c - dx s) / sy."""
        dd = xy - p[3]
        dx, dy = dd[:, 0], dd[:, 1]
        c, s, sx, sy, h = p[4:]
        u = dx * c
        u += dy * s
        u /= sx
        v = dy * c
        v -= dx * s
        v /= sy
        u *= u
        v *= v
        u += v
        u *= -0.5
        np.exp(u, out=u)
        u *= h
        return u


# Ray intervals of the solid columns, for n rays against k features of a kind at once: the
# parameters as (k,) arrays, the results (n, k). Every element is computed by the same
# operations as for one feature alone, so a batch gives bit-identical ranges.


class MesaParams(NamedTuple):
    """Mesas and cylinders as (k,) arrays: centre, top radius, foot radius (m), absolute top
    (m) and side slope tan (NaN for a vertical side: a cylinder)."""

    cx: FloatArray
    cy: FloatArray
    r: FloatArray
    r_out: FloatArray
    top: FloatArray
    tan: FloatArray

    @classmethod
    def of(cls, feats: Sequence[_Mesa]) -> MesaParams:
        return cls(
            np.array([f.cx for f in feats], dtype=np.float64),
            np.array([f.cy for f in feats], dtype=np.float64),
            np.array([f.r for f in feats], dtype=np.float64),
            np.array([f.r_out for f in feats], dtype=np.float64),
            np.array([f.ground + f.h for f in feats], dtype=np.float64),
            np.array([math.nan if f.tan is None else f.tan for f in feats], dtype=np.float64),
        )


def mesa_intervals(
    o: FloatArray,
    d: FloatArray,
    cx: FloatArray,
    cy: FloatArray,
    r: FloatArray,
    r_out: FloatArray,
    top: FloatArray,
    tan: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """(t_in, t_out), (n, k) each, of rays o + t d (o, d: (n, 3), no zero components in d)
    inside k mesa/cylinder columns; empty where t_in >= t_out. Call under
    np.errstate(divide/invalid/over="ignore")."""
    # The column is convex: z < top, r <= r_out and (mesa) r <= R + (top - z) / tan.
    px, py, oz = o[:, 0:1] - cx, o[:, 1:2] - cy, o[:, 2:3]
    dx, dy, dz = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    up, down = dz > 0.0, dz < 0.0
    a = np.maximum(dx * dx + dy * dy, 1e-300)
    b = px * dx + py * dy
    pp = px * px + py * py
    disc = b * b - a * (pp - r_out * r_out)
    sq = np.sqrt(np.maximum(disc, 0.0))
    t_in = np.maximum((-b - sq) / a, 0.0)
    t_out = np.where(disc >= 0.0, (sq - b) / a, -np.inf)
    above = top - oz
    t_top = above / dz  # z < top: before t_top going up, after it going down
    t_in = np.where(down, np.maximum(t_in, t_top), t_in)
    t_out = np.where(up, np.minimum(t_out, t_top), t_out)
    cone = ~np.isnan(tan)
    cones = int(np.count_nonzero(cone))
    if cones:
        # Cone r = G(t) = g0 + g1 t (G > 0 wherever z < top): q(t) = G^2 - r^2 >= 0.
        g0 = r + above / tan
        g1 = -dz / tan
        qa = g1 * g1 - a
        qb = g0 * g1 - b
        qc = g0 * g0 - pp
        qd = qb * qb - qa * qc
        sq = np.sqrt(np.maximum(qd, 0.0))
        qq = -(qb + np.copysign(sq, qb))
        r1, r2 = qc / qq, qq / qa
        lo, hi = np.fmin(r1, r2), np.fmax(r1, r2)
        # qa < 0: inside between the roots (if any); qa >= 0: two half-lines, the
        # lower nappe's is the first one going up and the second one going down.
        inner = qa < 0.0
        c_in = np.where(inner, lo, np.where(up, -np.inf, hi))
        c_out = np.where(inner, np.where(qd >= 0.0, hi, -np.inf), np.where(up, lo, np.inf))
        if cones == cone.size:
            return np.fmax(t_in, c_in), np.fmin(t_out, c_out)
        # a cylinder's column (no cone) keeps its interval as it is
        t_in = np.where(cone, np.fmax(t_in, c_in), t_in)
        t_out = np.where(cone, np.fmin(t_out, c_out), t_out)
    return t_in, t_out


class BoxParams(NamedTuple):
    """Boxes as (k,) arrays: centre (m), cos and sin of yaw, half length and half width
    (m) and absolute top (m)."""

    cx: FloatArray
    cy: FloatArray
    c: FloatArray
    s: FloatArray
    hl: FloatArray
    hw: FloatArray
    top: FloatArray

    @classmethod
    def of(cls, feats: Sequence[_Box]) -> BoxParams:
        def col(name: str) -> FloatArray:
            return np.array([getattr(f, name) for f in feats], dtype=np.float64)

        return cls(*(col(n) for n in ("cx", "cy", "c", "s", "hl", "hw", "top")))


def box_intervals(
    o: FloatArray,
    d: FloatArray,
    cx: FloatArray,
    cy: FloatArray,
    c: FloatArray,
    s: FloatArray,
    hl: FloatArray,
    hw: FloatArray,
    top: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """(t_in, t_out), (n, k) each, of rays o + t d inside k boxes (slabs in each box's frame,
    and z < top); empty where t_in >= t_out. Same conventions as `mesa_intervals`."""
    ox, oy = o[:, 0:1] - cx, o[:, 1:2] - cy
    dx, dy, dz = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    u0, du = ox * c + oy * s, dx * c + dy * s
    v0, dv = oy * c - ox * s, dy * c - dx * s
    du = np.where(du == 0.0, TINY, du)
    dv = np.where(dv == 0.0, TINY, dv)
    u1, u2 = (-hl - u0) / du, (hl - u0) / du
    v1, v2 = (-hw - v0) / dv, (hw - v0) / dv
    t_top = (top - o[:, 2:3]) / dz  # z < top: before t_top going up, after going down
    t_in = np.maximum(np.minimum(u1, u2), np.minimum(v1, v2))
    t_in = np.maximum(t_in, np.where(dz < 0.0, t_top, 0.0))
    t_out = np.minimum(np.maximum(u1, u2), np.maximum(v1, v2))
    t_out = np.minimum(t_out, np.where(dz > 0.0, t_top, np.inf))
    return np.maximum(t_in, 0.0), t_out


class SolidColumns:
    """All solid features of a world, batched by kind, with their cull boxes as arrays."""

    def __init__(self, solids: Sequence[Feature]) -> None:
        self.mesas = [f for f in solids if isinstance(f, _Mesa)]
        self.boxes = [f for f in solids if isinstance(f, _Box)]
        if len(self.mesas) + len(self.boxes) != len(solids):
            raise TypeError("a solid feature is neither a mesa/cylinder nor a box")
        self._mesa = MesaParams.of(self.mesas)
        self._box = BoxParams.of(self.boxes)
        self._mesa_bb = self._bboxes(self.mesas)
        self._box_bb = self._bboxes(self.boxes)

    @staticmethod
    def _bboxes(feats: Sequence[Feature]) -> FloatArray:
        """(k, 4) cull boxes as (xmin, -xmax, ymin, -ymax): a box b meets them where every
        column is <= (b_xmax, -b_xmin, b_ymax, -b_ymin) (one comparison for all)."""
        bb = np.array([f.cull_bbox for f in feats], dtype=np.float64).reshape(-1, 4)
        signed: FloatArray = bb * np.array([1.0, -1.0, 1.0, -1.0])
        return signed

    @staticmethod
    def _in_reach(bb: FloatArray, box: BBox) -> NDArray[np.bool_]:
        return np.asarray((bb <= np.array([box[1], -box[0], box[3], -box[2]])).all(1))

    def first_entry(self, o: FloatArray, d: FloatArray, end: FloatArray, box: BBox) -> FloatArray:
        """min(end, the first entry t of each ray into any solid column whose cull box meets
        box), (n,). o, d: (n, 3), no zero components in d."""
        out = end
        for bb, params, fn in (
            (self._mesa_bb, self._mesa, mesa_intervals),
            (self._box_bb, self._box, box_intervals),
        ):
            if not bb.shape[0]:
                continue
            keep = self._in_reach(bb, box)
            kept = int(np.count_nonzero(keep))
            if not kept:
                continue
            sel = params if kept == keep.size else type(params)(*(p[keep] for p in params))
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                t_in, t_out = fn(o, d, *sel)
            t_in = np.where(t_in < t_out, t_in, np.inf)
            out = np.minimum(out, t_in.min(axis=1))
        return out


def make_feature(cfg: FeatureConfig, ground_z: float, base_dir: Path | None) -> Feature:
    if isinstance(cfg, GaussianHillConfig):
        return _GaussianHill(cfg)
    if isinstance(cfg, MesaConfig | CylinderConfig):
        return _Mesa(cfg, ground_z)
    if isinstance(cfg, BoxConfig):
        return _Box(cfg, ground_z)
    if isinstance(cfg, PlaneConfig):
        return Plane(cfg)
    return _Heightmap(cfg, base_dir)


def intersects(a: BBox | None, b: BBox) -> bool:
    return a is None or (a[0] <= b[1] and b[0] <= a[1] and a[2] <= b[3] and b[2] <= a[3])


def union(boxes: list[BBox]) -> BBox:
    return (
        min(b[0] for b in boxes),
        max(b[1] for b in boxes),
        min(b[2] for b in boxes),
        max(b[3] for b in boxes),
    )
