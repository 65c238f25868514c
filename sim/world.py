"""The simulated world: a height field z = height(x, y) built from analytic features.

Frame: local ENU (x east, y north, z up), metres. Everything below the surface is solid.

    terrain(x, y) = ground_z + sum of additive features (gaussian_hill, plane, heightmap)
    surface(x, y) = max(terrain, top of every solid feature whose footprint holds (x, y))

Solid features (mesa, cylinder, box) stand on ground_z: their top is at ground_z + height.
Each feature has a name and an `obstacle` flag; obstacle features make up the solid that
`World.obstacle_distance` measures (the min-clearance metric), where a feature counts only
where it rises above the terrain under it.

Sensors are simulated by `World.raycast` (vectorised ray marching plus refinement). The
clearance metrics `surface_distance` / `obstacle_distance` measure solid features exactly
(closed form) and the smooth terrain by searching a float32 raster of it, built lazily on
first use, then refining on the analytic terrain.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, model_validator

from companion.planner.types import FloatArray

__all__ = [
    "OBSTACLE_MIN_RISE_M",
    "BoxConfig",
    "CylinderConfig",
    "FeatureConfig",
    "FeatureInfo",
    "GaussianHillConfig",
    "HeightmapConfig",
    "MesaConfig",
    "PlaneConfig",
    "World",
    "WorldConfig",
]

OBSTACLE_MIN_RISE_M = 0.01
"""An obstacle feature is solid only where it rises more than this above the terrain (m)."""
_FOOTPRINT_EPS_M = 0.01  # a gaussian hill's footprint: where it adds more than this
CORE_FRACTION = 0.05  # a gaussian hill's core: where it adds more than this share of its height
_CULL_EPS_M = 1e-12  # beyond this contribution a feature is skipped during evaluation
_TINY = 1e-200  # stands in for a zero direction component in slab tests

XY = tuple[float, float]
BBox = tuple[float, float, float, float]  # xmin, xmax, ymin, ymax
HeightFn = Callable[[FloatArray, FloatArray], FloatArray]

_CFG = ConfigDict(extra="forbid", allow_inf_nan=False)


# --------------------------------------------------------------------------- configuration


class GaussianHillConfig(BaseModel):
    """Additive hill h * exp(-r^2 / 2 sigma^2); sigma_xy_m + yaw_deg make it elliptic."""

    model_config = _CFG
    type: Literal["gaussian_hill"] = "gaussian_hill"
    name: str = Field("gaussian_hill", min_length=1)
    obstacle: bool = False
    center: XY
    height_m: float
    sigma_m: PositiveFloat | None = None
    sigma_xy_m: tuple[PositiveFloat, PositiveFloat] | None = None
    yaw_deg: float = 0.0
    """Rotation of the sigma_xy axes, degrees CCW from +x."""

    @model_validator(mode="after")
    def _one_sigma(self) -> GaussianHillConfig:
        if (self.sigma_m is None) == (self.sigma_xy_m is None):
            raise ValueError("gaussian_hill needs exactly one of sigma_m or sigma_xy_m")
        return self


class MesaConfig(BaseModel):
    """Steep hill: flat top disc of radius_m at ground_z + height_m, sides at side_slope_deg."""

    model_config = _CFG
    type: Literal["mesa"] = "mesa"
    name: str = Field("mesa", min_length=1)
    obstacle: bool = True
    center: XY
    radius_m: PositiveFloat
    height_m: PositiveFloat
    side_slope_deg: float = Field(80.0, gt=0.0, le=90.0)


class CylinderConfig(BaseModel):
    """Vertical cylinder standing on ground_z."""

    model_config = _CFG
    type: Literal["cylinder"] = "cylinder"
    name: str = Field("cylinder", min_length=1)
    obstacle: bool = True
    center: XY
    radius_m: PositiveFloat
    height_m: PositiveFloat


class BoxConfig(BaseModel):
    """Box standing on ground_z: size_m = (length along its x, width along its y, height)."""

    model_config = _CFG
    type: Literal["box"] = "box"
    name: str = Field("box", min_length=1)
    obstacle: bool = True
    center: XY
    size_m: tuple[PositiveFloat, PositiveFloat, PositiveFloat]
    yaw_deg: float = 0.0
    """Rotation of the box about z, degrees CCW from +x."""


class PlaneConfig(BaseModel):
    """Additive inclined plane, 0 at `point`, rising at slope_deg towards direction_deg."""

    model_config = _CFG
    type: Literal["plane"] = "plane"
    name: str = Field("plane", min_length=1)
    obstacle: bool = False
    slope_deg: float = Field(ge=0.0, lt=90.0)
    direction_deg: float = 0.0
    """Direction of steepest ascent, degrees CCW from +x."""
    point: XY = (0.0, 0.0)


class HeightmapConfig(BaseModel):
    """Additive grid of heights from a .npy file (rows = y, cols = x), bilinear, 0 outside."""

    model_config = _CFG
    type: Literal["heightmap"] = "heightmap"
    name: str = Field("heightmap", min_length=1)
    obstacle: bool = False
    file: str = Field(min_length=1)
    """Path to the .npy file; relative paths are relative to the loader's base_dir."""
    resolution_m: PositiveFloat
    origin: XY = (0.0, 0.0)
    """World (x, y) of element [0, 0]."""


FeatureConfig = Annotated[
    GaussianHillConfig | MesaConfig | CylinderConfig | BoxConfig | PlaneConfig | HeightmapConfig,
    Field(discriminator="type"),
]


class WorldConfig(BaseModel):
    model_config = _CFG
    ground_z_m: float = 0.0
    features: list[FeatureConfig] = Field(default_factory=list)


# --------------------------------------------------------------------------- features


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


class _Feature(ABC):
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


class _GaussianHill(_Feature):
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


class _Mesa(_Feature):
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
        # The column is convex: z < top, r <= r_out and (mesa) r <= R + (top - z) / tan.
        px, py, oz = o[:, 0] - self.cx, o[:, 1] - self.cy, o[:, 2]
        dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
        top = self.ground + self.h
        a = np.maximum(dx * dx + dy * dy, 1e-300)
        b = px * dx + py * dy
        pp = px * px + py * py
        disc = b * b - a * (pp - self.r_out * self.r_out)
        sq = np.sqrt(np.maximum(disc, 0.0))
        t_in = np.maximum((-b - sq) / a, 0.0)
        t_out = np.where(disc >= 0.0, (sq - b) / a, -np.inf)
        t_top = (top - oz) / dz  # z < top: before t_top going up, after it going down
        t_in = np.where(dz < 0.0, np.maximum(t_in, t_top), t_in)
        t_out = np.where(dz > 0.0, np.minimum(t_out, t_top), t_out)
        if self.tan is not None:
            # Cone r = G(t) = g0 + g1 t (G > 0 wherever z < top): q(t) = G^2 - r^2 >= 0.
            g0 = self.r + (top - oz) / self.tan
            g1 = -dz / self.tan
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
            c_in = np.where(qa < 0.0, lo, np.where(dz > 0.0, -np.inf, hi))
            c_out = np.where(
                qa < 0.0, np.where(qd >= 0.0, hi, -np.inf), np.where(dz > 0.0, lo, np.inf)
            )
            t_in = np.fmax(t_in, c_in)
            t_out = np.fmin(t_out, c_out)
        return t_in, t_out

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


class _Box(_Feature):
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
        # Slabs in the box's frame, and z < top.
        ox, oy = o[:, 0] - self.cx, o[:, 1] - self.cy
        dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
        c, s = self.c, self.s
        u0, du = ox * c + oy * s, dx * c + dy * s
        v0, dv = oy * c - ox * s, dy * c - dx * s
        du = np.where(du == 0.0, _TINY, du)
        dv = np.where(dv == 0.0, _TINY, dv)
        u1, u2 = (-self.hl - u0) / du, (self.hl - u0) / du
        v1, v2 = (-self.hw - v0) / dv, (self.hw - v0) / dv
        t_top = (self.top - o[:, 2]) / dz  # z < top: before t_top going up, after going down
        t_in = np.maximum(np.minimum(u1, u2), np.minimum(v1, v2))
        t_in = np.maximum(t_in, np.where(dz < 0.0, t_top, 0.0))
        t_out = np.minimum(np.maximum(u1, u2), np.maximum(v1, v2))
        t_out = np.minimum(t_out, np.where(dz > 0.0, t_top, np.inf))
        return np.maximum(t_in, 0.0), t_out

    def column_distance(self, px: float, py: float, pz: float) -> float:
        dx, dy = px - self.cx, py - self.cy
        u = dx * self.c + dy * self.s
        v = dy * self.c - dx * self.s
        dh = math.hypot(max(abs(u) - self.hl, 0.0), max(abs(v) - self.hw, 0.0))
        return math.hypot(dh, max(pz - self.top, 0.0))

    def info(self) -> FeatureInfo:
        return FeatureInfo(self.name, self.type, self.obstacle, self.corners.copy(), None)


class _Plane(_Feature):
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


class _Heightmap(_Feature):
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


def _make_feature(cfg: FeatureConfig, ground_z: float, base_dir: Path | None) -> _Feature:
    if isinstance(cfg, GaussianHillConfig):
        return _GaussianHill(cfg)
    if isinstance(cfg, MesaConfig | CylinderConfig):
        return _Mesa(cfg, ground_z)
    if isinstance(cfg, BoxConfig):
        return _Box(cfg, ground_z)
    if isinstance(cfg, PlaneConfig):
        return _Plane(cfg)
    return _Heightmap(cfg, base_dir)


def _intersects(a: BBox | None, b: BBox) -> bool:
    return a is None or (a[0] <= b[1] and b[0] <= a[1] and a[2] <= b[3] and b[2] <= a[3])


def _union(boxes: list[BBox]) -> BBox:
    return (
        min(b[0] for b in boxes),
        max(b[1] for b in boxes),
        min(b[2] for b in boxes),
        max(b[3] for b in boxes),
    )


# --------------------------------------------------------------------------- raster search


class _Raster:
    """float32 samples of a height function on a regular grid, for nearest-solid searches.

    Grid point (ix, iy) is at (x0 + ix*cell, y0 + iy*cell); -inf marks "no solid". Samples
    are stored in B x B blocks with each block's maximum, for a two-level branch-and-bound
    search: a block can hold the nearest point only if its lower bound beats the best
    upper bound (the distance to the block's highest sample, or one given).
    """

    B = 8

    def __init__(self, bbox: BBox, cell: float, fn: HeightFn) -> None:
        B = self.B
        # Grid points on multiples of the cell, covering bbox.
        self.x0 = math.floor(bbox[0] / cell) * cell
        self.y0 = math.floor(bbox[2] / cell) * cell
        bbox = (
            self.x0,
            math.ceil(bbox[1] / cell) * cell,
            self.y0,
            math.ceil(bbox[3] / cell) * cell,
        )
        self.cell = cell
        self.nx = round((bbox[1] - bbox[0]) / cell) + 1
        self.ny = round((bbox[3] - bbox[2]) / cell) + 1
        self.x1 = self.x0 + (self.nx - 1) * cell
        self.y1 = self.y0 + (self.ny - 1) * cell
        self.nbx, self.nby = -(-self.nx // B), -(-self.ny // B)
        z = np.full((self.nby * B, self.nbx * B), -np.inf, dtype=np.float32)
        xs = self.x0 + np.arange(self.nx, dtype=np.float64) * cell
        rows = max(1, 1_000_000 // self.nx)
        for r0 in range(0, self.ny, rows):
            r1 = min(self.ny, r0 + rows)
            ys = self.y0 + np.arange(r0, r1, dtype=np.float64) * cell
            z[r0:r1, : self.nx] = fn(xs[None, :], ys[:, None])
        # Block-major copy: zb[by, bx] is the B x B block (rows y, cols x).
        self.zb = np.ascontiguousarray(z.reshape(self.nby, B, self.nbx, B).transpose(0, 2, 1, 3))
        flat = self.zb.reshape(self.nby, self.nbx, B * B)
        arg = np.argmax(flat, axis=2)
        self.bmax = np.take_along_axis(flat, arg[..., None], axis=2)[..., 0].astype(np.float64)
        span = B * cell
        self.brx0 = self.x0 + np.arange(self.nbx, dtype=np.float64)[None, :] * span
        self.bry0 = self.y0 + np.arange(self.nby, dtype=np.float64)[:, None] * span
        self.brx0, self.bry0 = np.broadcast_arrays(self.brx0, self.bry0)
        self.ax = self.brx0 + (arg % B) * cell
        self.ay = self.bry0 + (arg // B) * cell
        self.offs = np.arange(B, dtype=np.float64) * cell
        ne = np.nonzero(np.isfinite(self.bmax))
        self._ne_cols = tuple(
            a[ne] for a in (self.brx0, self.bry0, self.bmax, self.ax, self.ay, self.zb)
        )

    def nearest_sample(self, px: float, py: float, pz: float) -> tuple[float, float, float]:
        """(distance, qx, qy) to the solid under the grid point nearest p_xy (inside)."""
        ix = min(max(round((px - self.x0) / self.cell), 0), self.nx - 1)
        iy = min(max(round((py - self.y0) / self.cell), 0), self.ny - 1)
        B = self.B
        z = float(self.zb[iy // B, ix // B, iy % B, ix % B])
        qx, qy = self.x0 + ix * self.cell, self.y0 + iy * self.cell
        return math.hypot(qx - px, qy - py, max(pz - z, 0.0)), qx, qy

    def contains(self, px: float, py: float, r: float) -> bool:
        return px - r >= self.x0 and px + r <= self.x1 and py - r >= self.y0 and py + r <= self.y1

    def search_window(self, px: float, py: float, pz: float, r: float) -> _Hit:
        """`_search` over the blocks within r (m) of p_xy, horizontally."""
        span = self.B * self.cell
        bx0 = max(0, int((px - r - self.x0) // span))
        bx1 = min(self.nbx, int((px + r - self.x0) // span) + 1)
        by0 = max(0, int((py - r - self.y0) // span))
        by1 = min(self.nby, int((py + r - self.y0) // span) + 1)
        if bx0 >= bx1 or by0 >= by1:
            return _NO_HIT
        w = (slice(by0, by1), slice(bx0, bx1))
        cols = (self.brx0[w], self.bry0[w], self.bmax[w], self.ax[w], self.ay[w], self.zb[w])
        return self._search(px, py, pz, r, cols)

    def search_all(self, px: float, py: float, pz: float, ub: float) -> _Hit:
        """`_search` over every block that holds solid."""
        return self._search(px, py, pz, ub, self._ne_cols)

    def _search(
        self,
        px: float,
        py: float,
        pz: float,
        ub: float,
        cols: tuple[NDArray[np.floating[Any]], ...],
    ) -> _Hit:
        """Nearest sample q by sqrt(|q - p_xy|^2 + max(0, pz - z(q))^2) (m), among the
        blocks that can beat ub. cols: per block (any array shape S) origin x, origin y,
        max, argmax x, argmax y and the samples (S + (B, B)).
        """
        rx0, ry0, bmax, ax, ay, zb = cols
        if rx0.size == 0:
            return _NO_HIT
        ext = (self.B - 1) * self.cell
        dx = np.maximum(rx0 - px, 0.0) + np.maximum(px - ext - rx0, 0.0)
        dy = np.maximum(ry0 - py, 0.0) + np.maximum(py - ext - ry0, 0.0)
        dz2 = np.maximum(pz - bmax, 0.0) ** 2
        lb2 = dx * dx + dy * dy + dz2
        ub2 = min(ub * ub, float(np.min((ax - px) ** 2 + (ay - py) ** 2 + dz2)))
        if not math.isfinite(ub2):
            return _NO_HIT
        keep = lb2 <= ub2 * (1.0 + 1e-9) + 1e-12
        xs = rx0[keep][:, None, None] + self.offs[None, None, :] - px
        ys = ry0[keep][:, None, None] + self.offs[None, :, None] - py
        d2 = xs * xs + ys * ys + np.maximum(pz - zb[keep].astype(np.float64), 0.0) ** 2
        if d2.size == 0:
            return _NO_HIT
        k = int(np.argmin(d2))
        best = float(d2.flat[k])
        if not math.isfinite(best):
            return _NO_HIT
        kb, ky, kx = np.unravel_index(k, d2.shape)
        return _Hit(math.sqrt(best), float(xs[kb, 0, kx]) + px, float(ys[kb, ky, 0]) + py)


class _Hit(NamedTuple):
    """Result of a raster search: distance (m) and the sample's (x, y)."""

    dist: float
    x: float
    y: float


_NO_HIT = _Hit(math.inf, 0.0, 0.0)


def _grid(n: int) -> tuple[FloatArray, FloatArray]:
    g = np.linspace(-1.0, 1.0, n)
    return np.tile(g, n), np.repeat(g, n)


_GRID_FIRST = _grid(11)
_GRID_NEXT = _grid(9)


def _local_min(
    p: tuple[float, float, float],
    qx: float,
    qy: float,
    best: float,
    span: float,
    fn: HeightFn,
    target: float = 0.005,
    max_moves: int = 16,
) -> float:
    """Refine min sqrt(|q - p_xy|^2 + max(0, pz - fn(q))^2) (m) around (qx, qy).

    Evaluates fn on square grids of half-width `span` (m) centred on the best point so
    far: while the best point lands near the grid's edge the grid follows it (up to
    max_moves times), otherwise it shrinks, until its step is below `target` (m). The
    first grid also holds p_xy itself; if p is at or below fn there, returns 0.
    """
    px, py, pz = p
    gx, gy = _GRID_FIRST
    first = True
    moves = 0
    while True:
        X = qx + span * gx
        Y = qy + span * gy
        if first:
            X, Y = np.append(X, px), np.append(Y, py)
        d2 = (X - px) ** 2 + (Y - py) ** 2 + np.maximum(pz - fn(X, Y), 0.0) ** 2
        if first and d2[-1] == 0.0:
            return 0.0
        first = False
        k = int(np.argmin(d2))
        on_edge = False
        if d2[k] < best * best:
            best = math.sqrt(float(d2[k]))
            qx, qy = float(X[k]), float(Y[k])
            # Near the grid's edge: the minimum may lie beyond it (a slanted wall or edge
            # seen through the grid's staircase), so follow it.
            on_edge = k < gx.size and max(abs(gx[k]), abs(gy[k])) >= 0.7
        if on_edge and moves < max_moves:
            moves += 1
            continue
        step = 2.0 * span / (round(math.sqrt(gx.size)) - 1)
        if step <= target:
            return best
        span = step
        gx, gy = _GRID_NEXT


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


# --------------------------------------------------------------------------- world


class World:
    """Height-field world (ENU metres) with ray casting and distance queries.

    extent: (xmin, xmax, ymin, ymax) of the terrain raster used by surface_distance (outside
    it the search is analytic and slower); default the bounding box of the bounded
    features padded by margin_m. raster_cell_m: raster spacing, enlarged if the raster
    would exceed max_raster_cells. ray_step_m: the reference ray march's default step;
    scan_step_m: the default sampling step of the terrain in `raycast`. Metres.
    """

    def __init__(
        self,
        config: WorldConfig | None = None,
        base_dir: Path | str | None = None,
        *,
        extent: BBox | None = None,
        margin_m: float = 10.0,
        raster_cell_m: float = 0.1,
        max_raster_cells: int = 8_000_000,
        ray_step_m: float = 0.1,
        scan_step_m: float = 0.25,
    ) -> None:
        cfg = config if config is not None else WorldConfig()
        if not (raster_cell_m > 0 and ray_step_m > 0 and scan_step_m > 0 and margin_m >= 0):
            raise ValueError("raster_cell_m, ray_step_m and scan_step_m must be > 0, margin_m >= 0")
        self.ground_z = float(cfg.ground_z_m)
        bd = Path(base_dir) if base_dir is not None else None
        feats = [_make_feature(f, self.ground_z, bd) for f in cfg.features]
        used: set[str] = set()
        for f in feats:  # make names unique: hill, hill_2, ...
            base, k = f.name, 1
            while f.name in used:
                k += 1
                f.name = f"{base}_{k}"
            used.add(f.name)
        self._features = feats
        self._additive = [f for f in feats if not f.solid]
        self._solid = [f for f in feats if f.solid]
        self._obstacles = [f for f in feats if f.obstacle]
        bounded = [f.footprint_bbox for f in feats if f.footprint_bbox is not None]
        if extent is not None:
            if not (extent[0] < extent[1] and extent[2] < extent[3]):
                raise ValueError(f"extent must be (xmin, xmax, ymin, ymax), got {extent}")
            self._extent: BBox = (
                float(extent[0]),
                float(extent[1]),
                float(extent[2]),
                float(extent[3]),
            )
        else:
            b = _union(bounded) if bounded else (0.0, 0.0, 0.0, 0.0)
            self._extent = (b[0] - margin_m, b[1] + margin_m, b[2] - margin_m, b[3] + margin_m)
            if self._extent[0] >= self._extent[1] or self._extent[2] >= self._extent[3]:
                self._extent = (-1.0, 1.0, -1.0, 1.0)
        x0, x1, y0, y1 = self._extent
        area = (x1 - x0) * (y1 - y0)
        self.raster_cell_m = max(raster_cell_m, math.sqrt(area / max_raster_cells))
        self.ray_step_m = ray_step_m
        self.scan_step_m = scan_step_m
        self._terrain_raster: _Raster | None = None
        self._obstacle_cache: tuple[list[_Feature], _Raster | None] | None = None

    @classmethod
    def from_config(
        cls, cfg: WorldConfig, base_dir: Path | str | None = None, **kwargs: Any
    ) -> World:
        """Build a world; relative heightmap paths are resolved against base_dir.

        kwargs: the keyword options of `World` (extent, raster_cell_m, ray_step_m, ...).
        """
        return cls(cfg, base_dir, **kwargs)

    @classmethod
    def from_dict(cls, data: dict[str, object], base_dir: Path | str | None = None) -> World:
        """Validate a plain mapping (e.g. from YAML) as a WorldConfig and build the world."""
        return cls(WorldConfig.model_validate(data), base_dir)

    # ------------------------------------------------------------------ accessors

    @property
    def features(self) -> tuple[FeatureInfo, ...]:
        return tuple(f.info() for f in self._features)

    @property
    def obstacle_features(self) -> tuple[FeatureInfo, ...]:
        return tuple(f.info() for f in self._obstacles)

    def extent(self) -> BBox:
        """(xmin, xmax, ymin, ymax) of the world's region of interest, metres."""
        return self._extent

    # ------------------------------------------------------------------ heights

    @staticmethod
    def _xy(x: ArrayLike, y: ArrayLike) -> tuple[FloatArray, FloatArray]:
        bx, by = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        return bx, by

    @staticmethod
    def _box(x: FloatArray, y: FloatArray) -> BBox | None:
        if x.size == 0:
            return None
        return (float(x.min()), float(x.max()), float(y.min()), float(y.max()))

    @staticmethod
    def _cull(feats: list[_Feature], box: BBox | None) -> list[_Feature]:
        """The features that can affect points inside box (all of them if box is None)."""
        if box is None:
            return feats
        return [f for f in feats if _intersects(f.cull_bbox, box)]

    def _terrain(self, x: FloatArray, y: FloatArray, box: BBox | None = None) -> FloatArray:
        z = np.full(np.broadcast_shapes(x.shape, y.shape), self.ground_z)
        for f in self._cull(self._additive, box):
            z += f.evaluate(x, y)
        return z

    def _surface(self, x: FloatArray, y: FloatArray) -> FloatArray:
        box = self._box(x, y)
        z = self._terrain(x, y, box)
        for f in self._cull(self._solid, box):
            np.maximum(z, f.evaluate(x, y), out=z)
        return z

    def _level(self, f: _Feature, x: FloatArray, y: FloatArray, terrain: FloatArray) -> FloatArray:
        """Top of feature f's own solid where it rises above the terrain, else -inf."""
        v = f.evaluate(x, y)
        if f.solid:
            return np.where(v > terrain + OBSTACLE_MIN_RISE_M, v, -np.inf)
        return np.where(v > OBSTACLE_MIN_RISE_M, terrain, -np.inf)

    def _obstacle_level(self, x: FloatArray, y: FloatArray) -> FloatArray:
        z = np.full(np.broadcast_shapes(x.shape, y.shape), -np.inf)
        box = self._box(x, y)
        obs = self._cull(self._obstacles, box)
        if obs:
            t = self._terrain(x, y, box)
            for f in obs:
                np.maximum(z, self._level(f, x, y, t), out=z)
        return z

    def height(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """Surface height z (m) at (x, y) (ENU m, any broadcastable shapes)."""
        return self._surface(*self._xy(x, y))

    def terrain_height(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """Height (m) of the terrain alone: ground + additive features, no solid features."""
        bx, by = self._xy(x, y)
        return self._terrain(bx, by, self._box(bx, by))

    def obstacle_height(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """Top (m) of the obstacle solid (all obstacle features) at (x, y); -inf where none."""
        return self._obstacle_level(*self._xy(x, y))

    def feature_height(self, name: str, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """Top (m) of one feature's own solid where it rises above the terrain, else -inf."""
        for f in self._features:
            if f.name == name:
                bx, by = self._xy(x, y)
                return self._level(f, bx, by, self._terrain(bx, by))
        raise KeyError(f"no feature named {name!r}")

    def is_inside(self, p: ArrayLike) -> bool:
        """True if point p (3,) ENU m is strictly below the surface."""
        q = np.asarray(p, np.float64).reshape(3)
        return bool(q[2] < float(self.height(q[0], q[1])))

    # ------------------------------------------------------------------ ray casting

    @staticmethod
    def _ray_args(
        origins: ArrayLike, directions: ArrayLike, max_range_m: ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Validated (n, 3) origins, unit directions and (n,) ranges."""
        o = np.asarray(origins, np.float64).reshape(-1, 3)
        d = np.asarray(directions, np.float64).reshape(-1, 3)
        n = o.shape[0]
        if d.shape[0] != n:
            raise ValueError(f"origins and directions differ in length: {n} vs {d.shape[0]}")
        norm = np.sqrt(np.einsum("ij,ij->i", d, d))
        if n and not (float(norm.min()) > 1e-12 and math.isfinite(float(norm.sum()))):
            raise ValueError("ray directions must be finite and non-zero")
        d = d / norm[:, None]
        rng = np.broadcast_to(np.asarray(max_range_m, np.float64), (n,))
        if n and not (float(rng.min()) >= 0.0 and math.isfinite(float(rng.sum()))):
            raise ValueError("max_range_m must be finite and >= 0")
        return o, d, rng

    def raycast(
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
        tol_m. Where a height map is in reach the plain march `_raycast_march` (every
        ray_step_m) is used instead: it is faster there. It is also the tests' reference.
        """
        o, d, rng = self._ray_args(origins, directions, max_range_m)
        n = o.shape[0]
        step = self.scan_step_m if step_m is None else float(step_m)
        if not step > 0:
            raise ValueError(f"step_m must be > 0, got {step}")
        if n == 0:
            return np.full(0, np.inf)
        d = np.where(d == 0.0, _TINY, d)  # no zero components: slab tests divide by them
        r_max = float(rng.max())
        lo3, hi3 = o.min(axis=0), o.max(axis=0)
        box = (
            float(lo3[0]) - r_max,
            float(hi3[0]) + r_max,
            float(lo3[1]) - r_max,
            float(hi3[1]) + r_max,
        )
        end = rng.copy()  # the terrain matters up to the first solid's entry
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            for f in self._solid:
                if _intersects(f.cull_bbox, box):
                    t_in, t_out = f.ray_interval(o, d)
                    t_in = np.where(t_in < t_out, t_in, np.inf)
                    np.minimum(end, t_in, out=end)
        solid_hit = end < rng if self._solid else np.zeros(n, bool)
        # Terrain along ray i: f(t) = g0 + g1 t - N(x(t), y(t)): g the height above the
        # affine part (ground and planes), N the sum of the other additive features.
        g0 = o[:, 2] - self.ground_z
        g1 = d[:, 2].copy()
        nonlinear: list[_Feature] = []
        for f in self._additive:
            if f.affine:
                assert isinstance(f, _Plane)
                g0 = g0 - ((o[:, 0] - f.px) * f.gx + (o[:, 1] - f.py) * f.gy)
                g1 = g1 - (d[:, 0] * f.gx + d[:, 1] * f.gy)
            elif _intersects(f.cull_bbox, box):
                nonlinear.append(f)
        if any(f.curvature is None for f in nonlinear):
            # Height maps: their Lipschitz bound is loose (the steepest cell anywhere) and
            # there is no curvature bound, so the plain march is faster.
            return self._raycast_march(o, d, rng, tol_m=tol_m)
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
        feats: list[_Feature],
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
        m = max(2, math.ceil(float(end.max()) / step))
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
        # sample inside (j; k < j where there is one).
        ks: list[int] = np.argmax(bad, axis=1).tolist()
        js: list[int] = np.argmax(ins, axis=1).tolist()
        hits: list[bool] = np.any(ins, axis=1).tolist()
        bads: list[bool] = np.any(bad, axis=1).tolist()
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
            kc, jc = np.asarray(ks)[c], np.asarray(js)[c]
            res[c] = self._refine_terrain(
                o[c], d[c], g0[c], g1[c], feats, T[c, kc], T[c, jc], F[c, kc], F[c, jc], tol
            )
        if slow:
            u = np.array(slow)
            ku = np.asarray(ks)[u]
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
        feats: list[_Feature],
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
                t = self._raycast_march(o[idx] + a[:, None] * d[idx], d[idx], end[idx] - a)
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

    @staticmethod
    def _sum_at(feats: list[_Feature], o: FloatArray, d: FloatArray, T: FloatArray) -> FloatArray:
        """Sum of the features' contributions at o + T d, (n, m) for T (n, m)."""
        X = o[:, 0:1] + d[:, 0:1] * T
        Y = o[:, 1:2] + d[:, 1:2] * T
        N = feats[0].evaluate(X, Y)
        for f in feats[1:]:
            N = N + f.evaluate(X, Y)
        return N

    def _refine_terrain(
        self,
        o: FloatArray,
        d: FloatArray,
        g0: FloatArray,
        g1: FloatArray,
        feats: list[_Feature],
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
        kf = np.full(lo.size, np.inf)
        if math.isfinite(curv):
            kf = curv * (d[:, 0] ** 2 + d[:, 1] ** 2) * 0.125
        u = _unit_steps(m)[1:-1]
        delta = tol / 2.2
        while True:
            w = hi - lo
            drop = flo - fhi
            ts = lo + w * (flo / drop)
            if float(np.max(kf * w * w * w / drop - 0.5 * tol)) <= 0.0 or float(w.max()) <= tol:
                return ts
            T = np.concatenate(
                [lo[:, None] + w[:, None] * u, (ts - delta)[:, None], (ts + delta)[:, None]],
                axis=1,
            )
            T = np.clip(T, lo[:, None], hi[:, None])
            F = g0[:, None] + g1[:, None] * T - self._sum_at(feats, o, d, T)
            ins = F < 0.0
            r = np.arange(lo.size)
            kh = np.argmin(np.where(ins, T, np.inf), axis=1)
            found = ins[r, kh]
            hi = np.where(found, T[r, kh], hi)
            fhi = np.where(found, F[r, kh], fhi)
            cand = np.where(~ins & (hi[:, None] > T), T, -np.inf)
            kl = np.argmax(cand, axis=1)
            better = cand[r, kl] > lo
            lo = np.where(better, T[r, kl], lo)
            flo = np.where(better, F[r, kl], flo)

    def _raycast_march(
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
        o, d, rng = self._ray_args(origins, directions, max_range_m)
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
        return np.asarray(z < self._surface(x, y))

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

    def _terrain_c(self, x: FloatArray, y: FloatArray) -> FloatArray:
        return self._terrain(x, y, self._box(x, y))

    def _additive_obstacle_level(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """Terrain height where an additive obstacle feature rises above it, else -inf."""
        z = np.full(np.broadcast_shapes(x.shape, y.shape), -np.inf)
        box = self._box(x, y)
        feats = self._cull([f for f in self._obstacles if not f.solid], box)
        if feats:
            t = self._terrain(x, y, box)
            for f in feats:
                np.maximum(z, self._level(f, x, y, t), out=z)
        return z

    @property
    def _terrain_ras(self) -> _Raster:
        if self._terrain_raster is None:
            self._terrain_raster = _Raster(self._extent, self.raster_cell_m, self._terrain_c)
        return self._terrain_raster

    @property
    def _obstacle_parts(self) -> tuple[list[_Feature], _Raster | None]:
        """Solid obstacle features that rise above the terrain somewhere, and a raster of
        the additive obstacle features' solid (None if there are none)."""
        if self._obstacle_cache is None:
            cell = self.raster_cell_m
            exposed = []
            for f in self._obstacles:
                if f.solid and f.footprint_bbox is not None:
                    x0, x1, y0, y1 = f.footprint_bbox
                    xs = np.linspace(x0, x1, max(2, math.ceil((x1 - x0) / cell) + 1))
                    ys = np.linspace(y0, y1, max(2, math.ceil((y1 - y0) / cell) + 1))
                    X, Y = xs[None, :], ys[:, None]
                    if np.any(np.isfinite(self._level(f, X, Y, self._terrain_c(X, Y)))):
                        exposed.append(f)
            boxes = [f.footprint_bbox or self._extent for f in self._obstacles if not f.solid]
            ras = None
            if boxes:
                b = _union(boxes)
                b = (b[0] - cell, b[1] + cell, b[2] - cell, b[3] + cell)
                ras = _Raster(b, cell, self._additive_obstacle_level)
            self._obstacle_cache = (exposed, ras)
        return self._obstacle_cache

    @staticmethod
    def _solid_distance(feats: list[_Feature], px: float, py: float, pz: float) -> float:
        """Exact distance (m) from p to the union of the solid features' columns."""
        best = math.inf
        for f in feats:
            if f.bbox_distance(px, py) < best:
                best = min(best, f.column_distance(px, py, pz))
        return best

    def surface_distance(self, p: ArrayLike) -> float:
        """Shortest 3-D distance (m) from point p (3,) ENU to the solid; 0 if inside.

        min over (x, y) of sqrt(|(x, y) - p_xy|^2 + max(0, p_z - height(x, y))^2). Solid
        features (mesa, cylinder, box) are measured exactly; the terrain by a raster
        search within its vertical clearance (which bounds the answer), refined on the
        analytic terrain around the best sample, to a few millimetres.
        """
        px, py, pz = (float(v) for v in np.asarray(p, np.float64).reshape(3))
        d = self._solid_distance(self._solid, px, py, pz)
        if d == 0.0:
            return 0.0
        return min(d, self._terrain_distance((px, py, pz), d))

    def _terrain_distance(self, p: tuple[float, float, float], ub: float) -> float:
        """Distance (m) from p to the terrain's solid if below ub, else some value >= ub."""
        d = self._terrain_distance_newton(p)
        if d is not None:
            return d
        return self._terrain_distance_raster(p, ub)

    def _terrain_distance_newton(self, p: tuple[float, float, float]) -> float | None:
        """Exact distance (m) from p to smooth terrain by Newton's method, or None where
        the minimum is not certainly unique.

        With c = p_z - terrain(p_xy) > 0, the nearest point lies within c of p_xy. There
        the squared distance phi(q) = |q - p_xy|^2 + (p_z - T(q))^2 (no clamp needed while
        p_z - T > 0, i.e. L < 1) has Hessian >= 2 (1 - (c + L c) K) I, L and K bounding
        the terrain's slope and curvature: if positive, phi is strictly convex on that
        disc and its one stationary point there is the nearest point.
        """
        px, py, pz = p
        feats = []
        lip = curv = 0.0
        for f in self._additive:
            if f.curvature is None:
                return None
            feats.append(f)
            lip += f.lipschitz
            curv += f.curvature
        t0 = self.ground_z
        for f in feats:
            t0 += f.jet(px, py)[0]
        c = pz - t0
        if c <= 0.0:
            return 0.0
        if lip >= 0.9 or (c + lip * c) * curv >= 0.9:
            return None
        qx, qy = px, py
        for _ in range(50):
            t, gx, gy, hxx, hxy, hyy = self.ground_z, 0.0, 0.0, 0.0, 0.0, 0.0
            for f in feats:
                j = f.jet(qx, qy)
                t, gx, gy = t + j[0], gx + j[1], gy + j[2]
                hxx, hxy, hyy = hxx + j[3], hxy + j[4], hyy + j[5]
            h = pz - t
            # Half gradient and half Hessian of phi.
            ax = qx - px - h * gx
            ay = qy - py - h * gy
            mxx = 1.0 + gx * gx - h * hxx
            mxy = gx * gy - h * hxy
            myy = 1.0 + gy * gy - h * hyy
            det = mxx * myy - mxy * mxy
            sx = (myy * ax - mxy * ay) / det
            sy = (mxx * ay - mxy * ax) / det
            qx, qy = qx - sx, qy - sy
            if abs(sx) + abs(sy) < 1e-10:
                break
        else:
            return None
        t = self.ground_z
        for f in feats:
            t += f.jet(qx, qy)[0]
        dx, dy, dz = qx - px, qy - py, pz - t
        if dx * dx + dy * dy > c * c * (1.0 + 1e-9) or dz <= 0.0:
            return None
        return math.sqrt(dx * dx + dy * dy + dz * dz)

    def _terrain_distance_raster(self, p: tuple[float, float, float], ub: float) -> float:
        """`_terrain_distance` by a raster search refined on the analytic terrain."""
        px, py, pz = p
        ras = self._terrain_ras
        cell = ras.cell
        if ras.contains(px, py, 0.0):
            d, qx, qy = ras.nearest_sample(px, py, pz)  # a true terrain point
            r = min(d, ub)
            if ras.contains(px, py, r):
                hit = ras.search_window(px, py, pz, r)
                if hit.dist < d:
                    d, qx, qy = hit
                if d > ub + 2.0 * cell:  # refining cannot gain that much on smooth terrain
                    return d
                return _local_min(p, qx, qy, d, cell, self._terrain_c)
        # Outside the raster: analytic search on local grids within the clearance.
        c = pz - float(self._terrain_c(np.array(px), np.array(py)))
        if c <= 0.0:
            return 0.0
        span = min(c, ub)
        return _local_min(p, px, py, c, span, self._terrain_c, target=0.2 * cell)

    def obstacle_distance(self, p: ArrayLike) -> float:
        """Shortest 3-D distance (m) from p (3,) ENU to the obstacle features' solid.

        The ordinary ground is ignored; 0 inside an obstacle, inf if there is none. A
        solid feature counts (its whole column) if it rises above the terrain anywhere; an
        additive one where it rises more than OBSTACLE_MIN_RISE_M (raster + refinement).
        """
        px, py, pz = (float(v) for v in np.asarray(p, np.float64).reshape(3))
        exposed, ras = self._obstacle_parts
        d = self._solid_distance(exposed, px, py, pz)
        if ras is None or d == 0.0:
            return d
        hit = ras.search_all(px, py, pz, d)
        if not hit.dist < d + 2.0 * ras.cell:
            inside = pz < float(self._additive_obstacle_level(np.array(px), np.array(py)))
            return 0.0 if inside else d
        best = _local_min(
            (px, py, pz), hit.x, hit.y, hit.dist, ras.cell, self._additive_obstacle_level
        )
        return min(d, best)
