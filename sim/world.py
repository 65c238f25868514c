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
_CULL_EPS_M = 1e-12  # beyond this contribution a feature is skipped during evaluation

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
    (x, y, radius) for round footprints, else None.
    """

    name: str
    type: str
    obstacle: bool
    polygon: FloatArray | None
    circle: tuple[float, float, float] | None


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

    def __init__(self, name: str, type_: str, obstacle: bool) -> None:
        self.name = name
        self.type = type_
        self.obstacle = obstacle

    @abstractmethod
    def evaluate(self, x: FloatArray, y: FloatArray) -> FloatArray: ...

    @abstractmethod
    def info(self) -> FeatureInfo: ...

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

    def info(self) -> FeatureInfo:
        a = np.linspace(0.0, 2.0 * math.pi, 64, endpoint=False)
        u, v = self.k_fp * self.sx * np.cos(a), self.k_fp * self.sy * np.sin(a)
        poly = np.column_stack(
            [self.cx + u * self.c - v * self.s, self.cy + u * self.s + v * self.c]
        )
        circle = None
        if self.sx == self.sy:
            circle = (self.cx, self.cy, self.k_fp * self.sx)
        return FeatureInfo(self.name, self.type, self.obstacle, poly, circle)


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
        except (OSError, ValueError) as exc:
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


# --------------------------------------------------------------------------- world


class World:
    """Height-field world (ENU metres) with ray casting and distance queries.

    extent: (xmin, xmax, ymin, ymax) of the terrain raster used by surface_distance (outside
    it the search is analytic and slower); default the bounding box of the bounded
    features padded by margin_m. raster_cell_m: raster spacing, enlarged if the raster
    would exceed max_raster_cells. ray_step_m: default ray-march step. Metres.
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
    ) -> None:
        cfg = config if config is not None else WorldConfig()
        if not (raster_cell_m > 0 and ray_step_m > 0 and margin_m >= 0):
            raise ValueError("raster_cell_m and ray_step_m must be > 0, margin_m >= 0")
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
        scalar. A ray starting below the surface returns 0. Each ray is sampled every step_m
        (default ray_step_m; a feature thinner than that can be missed at a grazing angle)
        in one vectorised height evaluation, then the interval holding the first crossing
        is subdivided to tol_m. Works for discontinuous surfaces (vertical walls).
        """
        o = np.asarray(origins, np.float64).reshape(-1, 3)
        d = np.asarray(directions, np.float64).reshape(-1, 3)
        n = o.shape[0]
        if d.shape[0] != n:
            raise ValueError(f"origins and directions differ in length: {n} vs {d.shape[0]}")
        norm = np.linalg.norm(d, axis=1)
        if not np.all(norm > 1e-12) or not np.all(np.isfinite(norm)):
            raise ValueError("ray directions must be finite and non-zero")
        d = d / norm[:, None]
        rng = np.broadcast_to(np.asarray(max_range_m, np.float64), (n,))
        if not np.all(np.isfinite(rng)) or np.any(rng < 0):
            raise ValueError("max_range_m must be finite and >= 0")
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
