"""A horizontal path: a chain of cubic Bezier segments addressed by arc length.

Positions on the path are arc lengths s in metres from its start; `locate` turns s into
(segment index, parameter t) with the exact arc-length inverse. Frame: local ENU x, y.
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.planner.bezier import CubicBezier
from companion.planner.types import FloatArray

_TAIL_CACHE_SIZE = 256
"""Route tails `Path.tail_from` keeps (the oldest is dropped first)."""


@dataclass(frozen=True, slots=True)
class Polyline:
    """Dense samples of a path: arc length s (n,), points (n, 2), unit tangents and left
    normals (n, 2), signed curvature (n,) in 1/m."""

    s: FloatArray
    points: FloatArray
    tangents: FloatArray
    normals: FloatArray
    curvature: FloatArray
    s_list: list[float]
    """s as plain floats (for bisect)."""


class Path:
    """Segments joined end to end; s = 0 at the first segment's start."""

    def __init__(self, segments: Sequence[CubicBezier]) -> None:
        if not segments:
            raise ValueError("a path needs at least one segment")
        for a, b in itertools.pairwise(segments):
            gap = float(np.linalg.norm(a.control[3] - b.control[0]))
            if gap > 1e-6:
                raise ValueError(f"segments must join end to start (gap {gap:.3g} m)")
        self.segments: tuple[CubicBezier, ...] = tuple(segments)
        starts = [0.0]
        for seg in self.segments:
            starts.append(starts[-1] + seg.length)
        self._starts = starts
        self._polyline: Polyline | None = None
        self._tails: dict[float, list[CubicBezier]] = {}
        # The last `locate`: X_d at rest asks for the same s cycle after cycle.
        self._located: tuple[float, int, float] = (math.nan, 0, 0.0)

    @property
    def length(self) -> float:
        """Total arc length, metres."""
        return self._starts[-1]

    def segment_start(self, index: int) -> float:
        """Arc length at the start of segment `index`."""
        return self._starts[index]

    def locate(self, s: float) -> tuple[int, float]:
        """(segment index, t) of arc length s, clamped to the path."""
        if s <= 0.0:
            return 0, 0.0
        if s >= self.length:
            return len(self.segments) - 1, 1.0
        last_s, last_k, last_t = self._located
        if s == last_s:
            return last_k, last_t
        k = min(bisect.bisect_right(self._starts, s) - 1, len(self.segments) - 1)
        t = self.segments[k].parameter_at(s - self._starts[k])
        self._located = (s, k, t)
        return k, t

    def arc_length_at(self, index: int, t: float) -> float:
        """Arc length of (segment index, t)."""
        return self._starts[index] + self.segments[index].arc_length(t)

    def point(self, s: float) -> FloatArray:
        k, t = self.locate(s)
        return self.segments[k].evaluate(t)

    def tangent(self, s: float) -> FloatArray:
        k, t = self.locate(s)
        return self.segments[k].tangent(t)

    def heading(self, s: float) -> float:
        """Tangent heading at s, radians CCW from +x."""
        d = self.tangent(s)
        return math.atan2(float(d[1]), float(d[0]))

    @property
    def end(self) -> FloatArray:
        return np.asarray(self.segments[-1].control[3], dtype=np.float64)

    def polyline(self, spacing_m: float = 0.25) -> Polyline:
        """Dense samples at roughly `spacing_m` (cached for the default spacing)."""
        if spacing_m == 0.25 and self._polyline is not None:
            return self._polyline
        ss, pts, tans, curv = [], [], [], []
        for k, seg in enumerate(self.segments):
            # Uniform in arc length (the exact inverse of the table); a segment keeps its
            # samples, so a corrected path re-uses those of the route segments it joins.
            lengths, points, tangents, curvature = seg.uniform_samples(spacing_m)
            first = 1 if k > 0 else 0
            ss.append(self._starts[k] + lengths[first:])
            pts.append(points[first:])
            tans.append(tangents[first:])
            curv.append(curvature[first:])
        tangents = np.concatenate(tans)
        s_all = np.concatenate(ss)
        poly = Polyline(
            s=s_all,
            points=np.concatenate(pts),
            tangents=tangents,
            normals=np.stack([-tangents[:, 1], tangents[:, 0]], axis=1),
            curvature=np.concatenate(curv),
            s_list=s_all.tolist(),
        )
        if spacing_m == 0.25:
            self._polyline = poly
        return poly

    def tail_from(self, s: float) -> list[CubicBezier]:
        """The segments after arc length s (`split_at`'s second part), kept per s: the
        re-plan search asks for the same few rejoin points cycle after cycle, and the cut
        segment's arc-length table is then built once. The list is shared: do not modify."""
        tail = self._tails.get(s)
        if tail is None:
            if len(self._tails) >= _TAIL_CACHE_SIZE:
                self._tails.pop(next(iter(self._tails)))
            tail = self._tails[s] = self.split_at(s)[1]
        return tail

    def split_at(self, s: float) -> tuple[list[CubicBezier], list[CubicBezier]]:
        """Segments before and after arc length s (de Casteljau at the cut)."""
        k, t = self.locate(s)
        before = list(self.segments[:k])
        after = list(self.segments[k + 1 :])
        seg = self.segments[k]
        if t <= 1e-12:
            after.insert(0, seg)
        elif t >= 1.0 - 1e-12:
            before.append(seg)
        else:
            left, right = seg.split(t)
            before.append(left)
            after.insert(0, right)
        return before, after


def project(poly: Polyline, points_xy: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Frenet coordinates of points against a dense polyline: arc length s and signed
    lateral offset l (positive to the left), metres. points_xy: (k, 2)."""
    q = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    if len(q) == 0:
        return np.empty(0), np.empty(0)
    j = _nearest_samples(poly.points, q)
    rel = q - poly.points[j]
    along = np.einsum("ij,ij->i", rel, poly.tangents[j])
    lateral = np.einsum("ij,ij->i", rel, poly.normals[j])
    s = np.clip(poly.s[j] + along, poly.s[0], poly.s[-1])
    return s, lateral


_GROUP = 128
"""Points whose nearest samples are searched together (`_nearest_samples`)..."""
_ONE_BOX_MAX = 16384
"""... once one box round all the points leaves more than this many point-sample pairs."""


def _nearest_samples(samples_xy: FloatArray, points_xy: FloatArray) -> NDArray[np.intp]:
    """The index of the sample nearest each point (the lowest of equally near ones), (k,).

    Every 8th sample bounds each point's distance to the polyline from above, so the nearest
    samples lie in the points' bounding box grown by the largest of those bounds
    (`_candidates`). Many points spread along a long path (the memory's, for a correction)
    make that box span the path: then they are taken in groups of _GROUP, in the order of
    their nearest every-8th sample, each with its own box (637 points against 257 candidate
    samples: 4-6 ms in one search's set-up, 1.2 ms in groups). Every sample as near to a
    point as its nearest lies within its group's box too, so each point gets the same index,
    from the same distances, as from all the samples at once."""
    coarse = samples_xy[::8]
    dx = points_xy[:, 0, None] - coarse[None, :, 0]
    dy = points_xy[:, 1, None] - coarse[None, :, 1]
    d2 = dx * dx + dy * dy
    bound2 = d2.min(axis=1)
    near = _candidates(samples_xy, points_xy, bound2)
    if len(points_xy) <= _GROUP or len(near) * len(points_xy) <= _ONE_BOX_MAX:
        return _nearest_among(samples_xy, points_xy, near)
    order = np.argsort(d2.argmin(axis=1), kind="stable")
    out = np.empty(len(points_xy), dtype=np.intp)
    for start in range(0, len(order), _GROUP):
        rows = order[start : start + _GROUP]
        group = points_xy.take(rows, axis=0)
        out[rows] = _nearest_among(
            samples_xy, group, _candidates(samples_xy, group, bound2.take(rows))
        )
    return out


def _nearest_among(
    samples_xy: FloatArray, points_xy: FloatArray, near: NDArray[np.intp]
) -> NDArray[np.intp]:
    """The nearest of the candidate samples `near` (ascending) to each point, (k,)."""
    dx = points_xy[:, 0, None] - samples_xy[None, near, 0]
    dy = points_xy[:, 1, None] - samples_xy[None, near, 1]
    nearest: NDArray[np.intp] = near[np.argmin(dx * dx + dy * dy, axis=1)]
    return nearest


def _candidates(
    samples_xy: FloatArray, points_xy: FloatArray, bound2: FloatArray
) -> NDArray[np.intp]:
    """Indices (ascending) of the samples that can be the nearest to one of the points:
    those in the points' bounding box grown by the largest of bound2 (k,), each point's
    squared distance to a sample (m^2); on a long path that leaves out most samples before
    the (k, n) distances are formed."""
    reach = math.sqrt(float(bound2.max())) * (1.0 + 1e-9) + 1e-9
    lo = points_xy.min(axis=0) - reach
    hi = points_xy.max(axis=0) + reach
    return np.flatnonzero(np.all((samples_xy >= lo) & (samples_xy <= hi), axis=1))
