"""The simulated world: a height field z = height(x, y) built from analytic features.

Frame: local ENU (x east, y north, z up), metres. Everything below the surface is solid.

    terrain(x, y) = ground_z + sum of additive features (gaussian_hill, plane, heightmap)
    surface(x, y) = max(terrain, top of every solid feature whose footprint holds (x, y))

Solid features (mesa, cylinder, box) stand on ground_z: their top is at ground_z + height.
Each feature has a name and an `obstacle` flag; obstacle features make up the solid that
`World.obstacle_distance` measures (the min-clearance metric), where a feature counts only
where it rises above the terrain under it.

Modules: `schema` (the YAML feature schema), `features` (feature geometry), `heights` (the
height field), `raycast` (range sensors: `RayCaster.cast`, and the reference march
`RayCaster.march`), `raster` and `distance` (the clearance metrics). `World` is a thin
facade over them.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from companion.planner.types import FloatArray
from companion.sim.world.distance import Distances
from companion.sim.world.features import (
    OBSTACLE_MIN_RISE_M,
    BBox,
    FeatureInfo,
    make_feature,
    union,
)
from companion.sim.world.heights import HeightField
from companion.sim.world.raycast import RayCaster
from companion.sim.world.schema import (
    BoxConfig,
    CylinderConfig,
    FeatureConfig,
    GaussianHillConfig,
    HeightmapConfig,
    MesaConfig,
    PlaneConfig,
    WorldConfig,
)

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


class World:
    """Height-field world (ENU metres) with ray casting and distance queries.

    extent: (xmin, xmax, ymin, ymax) of the terrain raster used by surface_distance (outside
    it the search is analytic and slower); default the bounding box of the bounded
    features padded by margin_m. raster_cell_m: raster spacing, enlarged if the raster
    would exceed max_raster_cells. ray_step_m: the reference ray march's default step;
    scan_step_m: the default sampling step of the terrain in `raycast`. Metres.

    `field`, `rays` and `distances` are the parts the facade delegates to.
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
        feats = [make_feature(f, self.ground_z, bd) for f in cfg.features]
        used: set[str] = set()
        for f in feats:  # make names unique: hill, hill_2, ...
            base, k = f.name, 1
            while f.name in used:
                k += 1
                f.name = f"{base}_{k}"
            used.add(f.name)
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
            b = union(bounded) if bounded else (0.0, 0.0, 0.0, 0.0)
            self._extent = (b[0] - margin_m, b[1] + margin_m, b[2] - margin_m, b[3] + margin_m)
            if self._extent[0] >= self._extent[1] or self._extent[2] >= self._extent[3]:
                self._extent = (-1.0, 1.0, -1.0, 1.0)
        x0, x1, y0, y1 = self._extent
        area = (x1 - x0) * (y1 - y0)
        self.raster_cell_m = max(raster_cell_m, math.sqrt(area / max_raster_cells))
        self.ray_step_m = ray_step_m
        self.scan_step_m = scan_step_m
        self.field = HeightField(self.ground_z, feats)
        self.rays = RayCaster(self.field, ray_step_m, scan_step_m)
        self.distances = Distances(self.field, self._extent, self.raster_cell_m)

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
        return tuple(f.info() for f in self.field.features)

    @property
    def obstacle_features(self) -> tuple[FeatureInfo, ...]:
        return tuple(f.info() for f in self.field.obstacles)

    def extent(self) -> BBox:
        """(xmin, xmax, ymin, ymax) of the world's region of interest, metres."""
        return self._extent

    # ------------------------------------------------------------------ heights

    def height(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """Surface height z (m) at (x, y) (ENU m, any broadcastable shapes)."""
        return self.field.surface(*self.field.xy(x, y))

    def terrain_height(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """Height (m) of the terrain alone: ground + additive features, no solid features."""
        bx, by = self.field.xy(x, y)
        return self.field.terrain(bx, by, self.field.box_of(bx, by))

    def obstacle_height(self, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """Top (m) of the obstacle solid (all obstacle features) at (x, y); -inf where none."""
        return self.field.obstacle_level(*self.field.xy(x, y))

    def feature_height(self, name: str, x: ArrayLike, y: ArrayLike) -> FloatArray:
        """Top (m) of one feature's own solid where it rises above the terrain, else -inf."""
        for f in self.field.features:
            if f.name == name:
                bx, by = self.field.xy(x, y)
                return self.field.level(f, bx, by, self.field.terrain(bx, by))
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
        scalar. A ray starting below the surface returns 0. See `RayCaster.cast`.
        """
        return self.rays.cast(origins, directions, max_range_m, step_m, tol_m)

    def raycast_march(
        self,
        origins: ArrayLike,
        directions: ArrayLike,
        max_range_m: ArrayLike,
        step_m: float | None = None,
        tol_m: float = 1e-4,
    ) -> FloatArray:
        """The reference ray cast (plain march every step_m, default ray_step_m, then
        subdivision to tol_m): slower than `raycast`, the tests' oracle. Same arguments."""
        return self.rays.march(origins, directions, max_range_m, step_m, tol_m)

    # ------------------------------------------------------------------ distances

    def surface_distance(self, p: ArrayLike) -> float:
        """Shortest 3-D distance (m) from point p (3,) ENU to the solid; 0 if inside."""
        return self.distances.surface_distance(p)

    def obstacle_distance(self, p: ArrayLike) -> float:
        """Shortest 3-D distance (m) from p (3,) ENU to the obstacle features' solid; 0
        inside an obstacle, inf if there is none."""
        return self.distances.obstacle_distance(p)
