"""Obstacle memory: steep points seen by the obstacle sensors, kept in the world frame.

Points are binned on a horizontal grid (one point per `cell_m` square, the newest wins), so
a wall seen for a minute costs as much as a wall seen once. Points farther than `radius_m`
from the vehicle are forgotten, and the oldest go first when `max_points` is reached.
Deterministic: "age" is the planner's cycle count, never a clock.
"""

from __future__ import annotations

import math

import numpy as np

from companion.planner.types import FloatArray


class ObstacleMemory:
    def __init__(self, cell_m: float, radius_m: float, max_points: int) -> None:
        if cell_m <= 0 or radius_m <= 0 or max_points < 1:
            raise ValueError("cell_m and radius_m must be > 0 and max_points >= 1")
        self.cell_m = cell_m
        self.radius_m = radius_m
        self.max_points = max_points
        self._cells: dict[tuple[int, int], tuple[float, float, float, int]] = {}
        self._xy: FloatArray | None = None

    def __len__(self) -> int:
        return len(self._cells)

    def add(self, points_enu: FloatArray, cycle: int) -> int:
        """Store points (k, 3); returns how many cells were new."""
        new = 0
        inv = 1.0 / self.cell_m
        for x, y, z in np.asarray(points_enu, dtype=np.float64).reshape(-1, 3):
            if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
                continue
            key = (math.floor(x * inv), math.floor(y * inv))
            if key not in self._cells:
                new += 1
            else:
                del self._cells[key]  # re-insert so dict order stays oldest-first
            self._cells[key] = (float(x), float(y), float(z), cycle)
        while len(self._cells) > self.max_points:
            del self._cells[next(iter(self._cells))]
        if len(points_enu):
            self._xy = None
        return new

    def forget_far(self, position_xy: FloatArray) -> int:
        """Drop points farther than radius_m from position_xy; returns how many."""
        if not self._cells:
            return 0
        xy = self.points_xy()
        far = np.hypot(xy[:, 0] - position_xy[0], xy[:, 1] - position_xy[1]) > self.radius_m
        if not far.any():
            return 0
        keys = list(self._cells)
        for i in np.flatnonzero(far):
            del self._cells[keys[i]]
        self._xy = None
        return int(far.sum())

    def points_xy(self) -> FloatArray:
        """Remembered points, (k, 2) x, y metres, oldest first."""
        if self._xy is None:
            if self._cells:
                self._xy = np.array([(v[0], v[1]) for v in self._cells.values()])
            else:
                self._xy = np.empty((0, 2))
        return self._xy

    def near(self, position_xy: FloatArray, radius_m: float) -> FloatArray:
        """Remembered points within radius_m of position_xy, (k, 2)."""
        xy = self.points_xy()
        if len(xy) == 0:
            return xy
        d = np.hypot(xy[:, 0] - position_xy[0], xy[:, 1] - position_xy[1])
        out: FloatArray = xy[d <= radius_m]
        return out
