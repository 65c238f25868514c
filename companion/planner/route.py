"""The route: base points W_1..W_n joined by cubic Bezier segments with a continuous tangent.

Control-point placement. The tangent direction at each base point is
- W_1: the start heading (or the direction to W_2 if none is given);
- W_n: the arrival heading (or the direction from W_{n-1});
- interior W_i: the Catmull-Rom direction, W_{i+1} - W_{i-1}, normalised.
Each segment W_i -> W_{i+1} gets handles along those directions. At an interior point both
neighbouring segments use the same handle length, a third of the shorter of the two chords,
so the joint is parametric C1 (equal first derivatives), not only tangent-continuous, and
short legs next to long ones do not loop. End handles are a third of their chord.
Frame: local ENU x, y metres; headings radians CCW from +x.
"""

from __future__ import annotations

import math

import numpy as np

from companion.planner.bezier import CubicBezier
from companion.planner.path import Path
from companion.planner.types import FloatArray


def _unit(v: FloatArray) -> FloatArray:
    n = float(np.hypot(v[0], v[1]))
    if n < 1e-12:
        raise ValueError("consecutive base points must differ")
    return np.asarray(v / n, dtype=np.float64)


def heading_vector(heading_rad: float) -> FloatArray:
    return np.array([math.cos(heading_rad), math.sin(heading_rad)])


class Route(Path):
    """Path through the base points W (n, 2) with given start and arrival headings."""

    def __init__(
        self,
        points_xy: FloatArray,
        start_heading_rad: float | None = None,
        arrival_heading_rad: float | None = None,
    ) -> None:
        w = np.array(points_xy, dtype=np.float64)
        if w.ndim != 2 or w.shape[1] != 2 or len(w) < 2:
            raise ValueError(f"base points must be an (n >= 2, 2) array, got shape {w.shape}")
        if not np.all(np.isfinite(w)):
            raise ValueError("base points must be finite")
        for h in (start_heading_rad, arrival_heading_rad):
            if h is not None and not math.isfinite(h):
                raise ValueError("headings must be finite")
        n = len(w)
        chords = [float(np.linalg.norm(w[i + 1] - w[i])) for i in range(n - 1)]
        if min(chords) < 1e-6:
            raise ValueError("consecutive base points must differ")
        dirs = [np.zeros(2)] * n
        dirs[0] = (
            heading_vector(start_heading_rad)
            if start_heading_rad is not None
            else _unit(w[1] - w[0])
        )
        dirs[-1] = (
            heading_vector(arrival_heading_rad)
            if arrival_heading_rad is not None
            else _unit(w[-1] - w[-2])
        )
        for i in range(1, n - 1):
            dirs[i] = _unit(w[i + 1] - w[i - 1])
        handles = (
            [chords[0] / 3.0]
            + [min(chords[i - 1], chords[i]) / 3.0 for i in range(1, n - 1)]
            + [chords[-1] / 3.0]
        )
        segments = []
        for i in range(n - 1):
            h0 = handles[i]
            h1 = handles[i + 1]
            segments.append(
                CubicBezier(
                    np.array([w[i], w[i] + h0 * dirs[i], w[i + 1] - h1 * dirs[i + 1], w[i + 1]])
                )
            )
        super().__init__(segments)
        w.setflags(write=False)
        self.base_points = w
        self.base_s = np.array([self.segment_start(i) for i in range(n - 1)] + [self.length])
        self.base_s_list: list[float] = self.base_s.tolist()
        """base_s as plain floats, ascending (for bisect)."""
        self.start_heading_rad = math.atan2(float(dirs[0][1]), float(dirs[0][0]))
        self.arrival_heading_rad = math.atan2(float(dirs[-1][1]), float(dirs[-1][0]))
        self.arrival_heading_given = arrival_heading_rad is not None
        """True when the arrival heading was asked for: the goal is then reached along it."""
