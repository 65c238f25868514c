"""Range sensors as the world shows them: a beam is one ray, a sector the nearest of a fan.

A proximity sector (ArduPilot's proximity library reports the nearest object within each
45-degree sector) is not a ray: a thin pillar between two sector boresights is still seen
by both sectors it lies in. A sensor with a field of view (`SensorSpec.fov_rad`) is cast as
SECTOR_RAYS rays across it (`companion.planner.sensors.sector_fan_flu`) and reads the
nearest hit. Directions body FLU, the world ENU, ranges metres.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from companion.planner.sensors import sector_fan_flu
from companion.planner.types import FloatArray

SECTOR_RAYS = 9
"""Rays across a sector (5.6 degrees apart over 45: a 1 m pillar is hit up to 10 m away)."""

Raycast = Callable[[FloatArray, FloatArray, FloatArray], FloatArray]
"""(origins (n, 3), directions (n, 3), max ranges (n,)) -> ranges (n,), inf: nothing."""


class SensorFan:
    """The rays of a set of sensors (boresights (n, 3) body FLU, fov (n,) radians): every
    sensor's fan, and where each sensor's rays start in it."""

    def __init__(self, boresights_flu: FloatArray, fov_rad: FloatArray) -> None:
        u = np.asarray(boresights_flu, dtype=np.float64).reshape(-1, 3)
        w = np.asarray(fov_rad, dtype=np.float64).reshape(-1)
        if u.shape[0] == w.shape[0] and not (w > 0.0).any():
            # beams only: one ray each, the boresight (what sector_fan_flu gives a beam)
            self.directions_flu: FloatArray = u.copy()
            self.starts = np.arange(u.shape[0], dtype=np.intp)
            self.owner = self.starts.copy()
            self.narrow = True
            return
        fans = [
            sector_fan_flu(u, float(w), SECTOR_RAYS if w > 0.0 else 1)
            for u, w in zip(np.asarray(boresights_flu).reshape(-1, 3), fov_rad, strict=True)
        ]
        counts = np.array([len(f) for f in fans], dtype=np.intp)
        self.directions_flu = np.vstack(fans) if fans else np.zeros((0, 3))
        self.starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.intp)
        self.owner = np.repeat(np.arange(len(fans)), counts)
        self.narrow = bool(np.all(counts == 1))

    def ranges(
        self,
        raycast: Raycast,
        position_enu: FloatArray,
        r_world_body: FloatArray,
        max_range_m: FloatArray,
    ) -> FloatArray:
        """Range of every sensor (n,), metres: the nearest hit of its fan; inf where none."""
        if len(self.owner) == 0:
            return np.zeros(0)
        dirs = self.directions_flu @ r_world_body.T
        origins = np.empty_like(dirs)  # (cheaper than np.broadcast_to for a few rays)
        origins[:] = position_enu
        rng = np.asarray(max_range_m)
        if self.narrow:  # one ray per sensor, in order: owner is 0, 1, 2, ...
            return np.asarray(raycast(origins, dirs, rng))
        hits = np.asarray(raycast(origins, dirs, rng[self.owner]))
        out: FloatArray = np.minimum.reduceat(hits, self.starts)
        return out
