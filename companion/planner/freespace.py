"""Where proximity sectors have seen free space: evidence that trims a sector reading's arc.

A sector reading r (a proximity sensor's: the nearest object anywhere across its width) says
two things: something lies on the arc at r, and nothing lies across the fan nearer than r.
The planner enters a steep reading as the whole arc (`Planner._sector_arcs`): the object
is somewhere on it. From one place and heading the arc cannot be narrowed, but the readings
taken from other places and headings can: in a static world the object is not where an
earlier fan saw nothing. `FreeFans` keeps the fans of the last poses (each sector's free
stretch: its reading less a margin, or its max range when it saw nothing) and says which
points of a new arc lie inside one of them. Carving (`ObstacleMemory.carve_sectors`) is the
same evidence the other way round: a new fan drops remembered points it sees through.

The test is the fan of `ObstacleMemory.carve_sectors` narrowed instead of widened by the
tolerance: a point counts as seen free only when it is inside a fan by the tolerance
across its width and along its reach, so a point near a fan's edge, where an object just
outside the fan may be, is never left out. Height: a point on or above a fan's surface (at
most the tolerance below it) is tested, as the planner keeps D_min from a remembered point
at every height, as from a solid standing on the ground, which would cross the fan; a point
lower than that may be on a solid lower than the fan.

World frame local ENU, metres and radians.
"""

from __future__ import annotations

import math

import numpy as np

from companion.planner.types import BoolArray, FloatArray


class FreeFans:
    """The free fans of the sector readings of the last `poses` distinct poses (a pose is
    kept once the vehicle has moved `move_m` or turned `turn_rad` since the last kept one)."""

    def __init__(
        self,
        sectors: int,
        poses: int = 48,
        move_m: float = 0.25,
        turn_rad: float = math.radians(5.0),
        tolerance_m: float = 0.25,
    ) -> None:
        if sectors < 1 or poses < 1:
            raise ValueError("sectors and poses must be >= 1")
        rows = sectors * poses
        self._sectors = sectors
        # Per fan: its up axis, boresight (across the up axis) and the direction left of
        # it, each as a unit vector and its dot product with the fan's origin, so that a
        # point's coordinates in every fan come from three matrix products.
        self._up = np.zeros((rows, 3))
        self._up_o = np.zeros(rows)
        self._along = np.zeros((rows, 3))
        self._along_o = np.zeros(rows)
        self._across = np.zeros((rows, 3))
        self._across_o = np.zeros(rows)
        self._slope = np.zeros(rows)  # the boresight's rise per unit across the up axis
        self._sin_half = np.zeros(rows)  # of the half width
        self._cos_half = np.zeros(rows)
        self._reach = np.zeros(rows)  # free stretch across the up axis, metres
        self._used = np.zeros(rows, dtype=bool)
        self._next = 0
        self._last: tuple[float, float, float, float] | None = None
        self._move2 = move_m * move_m
        self._turn = turn_rad
        self._tol = tolerance_m

    def __len__(self) -> int:
        return int(self._used.sum())

    def add(
        self,
        origin_enu: FloatArray,
        up_enu: FloatArray,
        boresights_enu: FloatArray,
        half_width_rad: FloatArray,
        free_m: FloatArray,
        heading_rad: float,
    ) -> bool:
        """Keep this pose's fans (one row per sector, at most `sectors`: boresights (n, 3)
        world ENU unit vectors spread +-half_width_rad (n,) about up_enu, free for free_m
        (n,) metres along them) unless the pose is within move_m and turn_rad of the last
        kept one. heading_rad: the body's heading (ENU, from +x). True if kept."""
        x, y, z = np.asarray(origin_enu, dtype=np.float64).reshape(3).tolist()
        last = self._last
        if last is not None:
            moved2 = (x - last[0]) ** 2 + (y - last[1]) ** 2 + (z - last[2]) ** 2
            turned = abs(math.remainder(heading_rad - last[3], math.tau))
            if moved2 < self._move2 and turned < self._turn:
                return False
        self._last = (x, y, z, heading_rad)
        b = np.asarray(boresights_enu, dtype=np.float64).reshape(-1, 3)
        n = len(b)
        if n > self._sectors:
            raise ValueError(f"at most {self._sectors} sectors a pose, got {n}")
        up = np.asarray(up_enu, dtype=np.float64).reshape(3)
        rise = b @ up
        flat = b - rise[:, None] * up
        flat_len = np.maximum(np.sqrt((flat * flat).sum(axis=1)), 1e-9)
        along = flat / flat_len[:, None]  # the boresight across the up axis, unit
        across = np.cross(up, along)  # and the direction 90 degrees to its left
        half = np.asarray(half_width_rad, dtype=np.float64).reshape(-1)
        rows = slice(self._next, self._next + self._sectors)
        self._used[rows] = False
        k = slice(self._next, self._next + n)
        o = np.array([x, y, z])
        self._up[k] = up
        self._up_o[k] = up @ o
        self._along[k] = along
        self._along_o[k] = along @ o
        self._across[k] = across
        self._across_o[k] = across @ o
        self._slope[k] = rise / flat_len
        self._sin_half[k] = np.sin(half)
        self._cos_half[k] = np.cos(half)
        # Across the up axis, the free stretch reaches free_m along the boresight.
        self._reach[k] = np.asarray(free_m, dtype=np.float64).reshape(-1) * flat_len
        self._used[k] = True
        self._next = (self._next + self._sectors) % len(self._used)
        return True

    def seen_free(self, points_enu: FloatArray) -> BoolArray:
        """Which points (k, 3) lie inside a kept fan: on or above its surface (at most the
        tolerance below), inside its width and its free stretch by the tolerance: (k,)
        bool."""
        p = np.asarray(points_enu, dtype=np.float64).reshape(-1, 3)
        out = np.zeros(len(p), dtype=bool)
        rows = self._used.nonzero()[0]
        if len(p) == 0 or len(rows) == 0:
            return out
        tol = self._tol
        up, along, across = self._up[rows], self._along[rows], self._across[rows]
        rise = p @ up.T - self._up_o[rows]  # (k, m): height above each fan's origin
        a = p @ along.T - self._along_o[rows]  # ahead along its boresight
        c = p @ across.T - self._across_o[rows]  # to its left
        flat = np.sqrt(a * a + c * c)
        # Inside the wedge by tol from both edges: flat * sin(half - |bearing|) >= tol.
        inside = (
            (a * self._sin_half[rows] - np.abs(c) * self._cos_half[rows] >= tol)
            & (flat < self._reach[rows] - tol)
            & (rise - flat * self._slope[rows] > -tol)
        )
        out[:] = inside.any(axis=1)
        return out
