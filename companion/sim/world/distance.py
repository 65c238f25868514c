"""Distance queries: the clearance metrics, from a point to the whole solid or to the obstacle
features' solid. Solid features are measured exactly (closed form); the smooth terrain by
Newton's method where the nearest point is certainly unique, else by a raster search refined
on the analytic terrain. World ENU, metres.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from companion.sim.world.features import BBox, Feature, union
from companion.sim.world.heights import HeightField
from companion.sim.world.raster import Raster, local_min


class Distances:
    """Distance queries on one height field. extent: (xmin, xmax, ymin, ymax) of the terrain
    raster; raster_cell_m: its spacing. The rasters are built lazily, on first use."""

    def __init__(self, field: HeightField, extent: BBox, raster_cell_m: float) -> None:
        self.field = field
        self.extent = extent
        self.raster_cell_m = raster_cell_m
        self._terrain_raster: Raster | None = None
        self._obstacle_cache: tuple[list[Feature], Raster | None] | None = None

    @property
    def _terrain_ras(self) -> Raster:
        if self._terrain_raster is None:
            self._terrain_raster = Raster(
                self.extent, self.raster_cell_m, self.field.terrain_culled, self.field.terrain
            )
        return self._terrain_raster

    @property
    def _obstacle_parts(self) -> tuple[list[Feature], Raster | None]:
        """Solid obstacle features that rise above the terrain somewhere, and a raster of
        the additive obstacle features' solid (None if there are none)."""
        if self._obstacle_cache is None:
            cell = self.raster_cell_m
            exposed = []
            for f in self.field.obstacles:
                if f.solid and f.footprint_bbox is not None:
                    x0, x1, y0, y1 = f.footprint_bbox
                    xs = np.linspace(x0, x1, max(2, math.ceil((x1 - x0) / cell) + 1))
                    ys = np.linspace(y0, y1, max(2, math.ceil((y1 - y0) / cell) + 1))
                    X, Y = xs[None, :], ys[:, None]
                    if np.any(
                        np.isfinite(self.field.level(f, X, Y, self.field.terrain_culled(X, Y)))
                    ):
                        exposed.append(f)
            boxes = [f.footprint_bbox or self.extent for f in self.field.obstacles if not f.solid]
            ras = None
            if boxes:
                b = union(boxes)
                b = (b[0] - cell, b[1] + cell, b[2] - cell, b[3] + cell)
                ras = Raster(b, cell, self.field.additive_obstacle_level)
            self._obstacle_cache = (exposed, ras)
        return self._obstacle_cache

    @staticmethod
    def _solid_distance(feats: list[Feature], px: float, py: float, pz: float) -> float:
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
        px, py, pz = np.asarray(p, np.float64).reshape(3).tolist()
        d = self._solid_distance(self.field.solid, px, py, pz)
        if d == 0.0:
            return 0.0
        return min(d, self._terrain_distance((px, py, pz), d))

    def _terrain_distance(self, p: tuple[float, float, float], ub: float) -> float:
        """Distance (m) from p to the terrain's solid if below ub, else some value >= ub."""
        d = self.terrain_distance_newton(p)
        if d is not None:
            return d
        return self.terrain_distance_raster(p, ub)

    def terrain_distance_newton(self, p: tuple[float, float, float]) -> float | None:
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
        for f in self.field.additive:
            if f.curvature is None:
                return None
            feats.append(f)
            lip += f.lipschitz
            curv += f.curvature
        t0 = self.field.ground_z
        for f in feats:
            t0 += f.jet(px, py)[0]
        c = pz - t0
        if c <= 0.0:
            return 0.0
        if lip >= 0.9 or (c + lip * c) * curv >= 0.9:
            return None
        qx, qy = px, py
        for _ in range(50):
            t, gx, gy, hxx, hxy, hyy = self.field.ground_z, 0.0, 0.0, 0.0, 0.0, 0.0
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
        t = self.field.ground_z
        for f in feats:
            t += f.jet(qx, qy)[0]
        dx, dy, dz = qx - px, qy - py, pz - t
        if dx * dx + dy * dy > c * c * (1.0 + 1e-9) or dz <= 0.0:
            return None
        return math.sqrt(dx * dx + dy * dy + dz * dz)

    def terrain_distance_raster(self, p: tuple[float, float, float], ub: float) -> float:
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
                return local_min(
                    p, qx, qy, d, cell, self.field.terrain_culled, boxed=self.field.terrain
                )
        # Outside the raster: analytic search on local grids within the clearance.
        c = pz - float(self.field.terrain_culled(np.array(px), np.array(py)))
        if c <= 0.0:
            return 0.0
        span = min(c, ub)
        return local_min(
            p,
            px,
            py,
            c,
            span,
            self.field.terrain_culled,
            target=0.2 * cell,
            boxed=self.field.terrain,
        )

    def obstacle_distance(self, p: ArrayLike) -> float:
        """Shortest 3-D distance (m) from p (3,) ENU to the obstacle features' solid.

        The ordinary ground is ignored; 0 inside an obstacle, inf if there is none. A
        solid feature counts (its whole column) if it rises above the terrain anywhere; an
        additive one where it rises more than OBSTACLE_MIN_RISE_M (raster + refinement).
        """
        px, py, pz = np.asarray(p, np.float64).reshape(3).tolist()
        exposed, ras = self._obstacle_parts
        d = self._solid_distance(exposed, px, py, pz)
        if ras is None or d == 0.0:
            return d
        hit = ras.search_all(px, py, pz, d)
        if not hit.dist < d + 2.0 * ras.cell:
            inside = pz < float(self.field.additive_obstacle_level(np.array(px), np.array(py)))
            return 0.0 if inside else d
        best = local_min(
            (px, py, pz), hit.x, hit.y, hit.dist, ras.cell, self.field.additive_obstacle_level
        )
        return min(d, best)
