"""The height field: ground plus features, as the surface, the terrain and the obstacle solid.

    terrain(x, y) = ground_z + sum of additive features (gaussian_hill, plane, heightmap)
    surface(x, y) = max(terrain, top of every solid feature whose footprint holds (x, y))

World ENU, metres; x, y any broadcastable arrays.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from companion.planner.types import FloatArray
from companion.sim.world.features import (
    OBSTACLE_MIN_RISE_M,
    AdditiveSum,
    BBox,
    Feature,
    intersects,
)


class HeightField:
    """Features split by kind: additive (terrain), solid (columns) and obstacle (either)."""

    def __init__(self, ground_z: float, features: list[Feature]) -> None:
        self.ground_z = ground_z
        self.features = features
        self.additive = [f for f in features if not f.solid]
        self.solid = [f for f in features if f.solid]
        self.obstacles = [f for f in features if f.obstacle]
        self._sums: dict[tuple[int, ...], AdditiveSum] = {}

    def sum_of(self, feats: list[Feature]) -> AdditiveSum:
        """The batched sum of these additive features (made once per set)."""
        key = tuple(map(id, feats))
        s = self._sums.get(key)
        if s is None:
            s = self._sums[key] = AdditiveSum(feats)
        return s

    @staticmethod
    def xy(x: ArrayLike, y: ArrayLike) -> tuple[FloatArray, FloatArray]:
        ax, ay = np.asarray(x, np.float64), np.asarray(y, np.float64)
        if ax.shape == ay.shape:  # (the common case; np.broadcast_arrays costs more)
            return ax, ay
        bx, by = np.broadcast_arrays(ax, ay)
        return bx, by

    @staticmethod
    def box_of(x: FloatArray, y: FloatArray) -> BBox | None:
        if x.size == 0:
            return None
        if x.size == 1 and y.size == 1:  # one point (the ground under the vehicle)
            px, py = float(x.reshape(-1)[0]), float(y.reshape(-1)[0])
            return (px, px, py, py)
        return (float(x.min()), float(x.max()), float(y.min()), float(y.max()))

    @staticmethod
    def cull(feats: list[Feature], box: BBox | None) -> list[Feature]:
        """The features that can affect points inside box (all of them if box is None)."""
        if box is None:
            return feats
        return [f for f in feats if intersects(f.cull_bbox, box)]

    def terrain(self, x: FloatArray, y: FloatArray, box: BBox | None = None) -> FloatArray:
        feats = self.cull(self.additive, box)
        if len(feats) > 1 and x.shape == y.shape and x.size * len(feats) <= AdditiveSum.MAX_BATCH:
            return self.sum_of(feats)(np.stack((x, y)), self.ground_z)
        z = np.full(np.broadcast_shapes(x.shape, y.shape), self.ground_z)
        for f in feats:
            z += f.evaluate(x, y)
        return z

    def surface(self, x: FloatArray, y: FloatArray) -> FloatArray:
        box = self.box_of(x, y)
        z = self.terrain(x, y, box)
        for f in self.cull(self.solid, box):
            np.maximum(z, f.evaluate(x, y), out=z)
        return z

    def level(self, f: Feature, x: FloatArray, y: FloatArray, terrain: FloatArray) -> FloatArray:
        """Top of feature f's own solid where it rises above the terrain, else -inf."""
        v = f.evaluate(x, y)
        if f.solid:
            return np.where(v > terrain + OBSTACLE_MIN_RISE_M, v, -np.inf)
        return np.where(v > OBSTACLE_MIN_RISE_M, terrain, -np.inf)

    def obstacle_level(self, x: FloatArray, y: FloatArray) -> FloatArray:
        z = np.full(np.broadcast_shapes(x.shape, y.shape), -np.inf)
        box = self.box_of(x, y)
        obs = self.cull(self.obstacles, box)
        if obs:
            t = self.terrain(x, y, box)
            for f in obs:
                np.maximum(z, self.level(f, x, y, t), out=z)
        return z

    def terrain_culled(self, x: FloatArray, y: FloatArray) -> FloatArray:
        return self.terrain(x, y, self.box_of(x, y))

    def additive_obstacle_level(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """Terrain height where an additive obstacle feature rises above it, else -inf."""
        z = np.full(np.broadcast_shapes(x.shape, y.shape), -np.inf)
        box = self.box_of(x, y)
        feats = self.cull([f for f in self.obstacles if not f.solid], box)
        if feats:
            t = self.terrain(x, y, box)
            for f in feats:
                np.maximum(z, self.level(f, x, y, t), out=z)
        return z
