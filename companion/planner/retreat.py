"""Dead-end retreat: where to back out to along the covered track, and the correction on
the other side from there.

When the planner is blocked at rest, it backs out along the track it has covered (known to
be free) to the nearest point from which a correction on the side not yet tried exists.
Pure functions over the covered track (x, y metres, local ENU); searched in work units
(`avoidance.detour_search`), so that a caller with a budget per cycle can resume it.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Generator, Sequence
from dataclasses import dataclass

import numpy as np

from companion.planner.avoidance import AvoidanceRequest, Detour, SearchFrame, detour_search
from companion.planner.bezier import CubicBezier
from companion.planner.params import PlannerParams
from companion.planner.path import Path
from companion.planner.route import Route
from companion.planner.types import FloatArray, Side

RETREAT_STEPS_M = (3.0, 6.0, 9.0, 12.0, 16.0, 20.0, 25.0, 30.0, 40.0)
"""How far back along the covered track a retreat may end, tried nearest first, metres."""
_KEEP_EVERY_M = 2.0
"""Spacing of the track points the way back passes through, metres."""
_SHARP_TURN_RAD = math.radians(60.0)
"""The way back stops and turns on the spot where the track turns more than this at one of
those points (`split_at_turns`)."""


@dataclass(frozen=True, slots=True)
class RetreatPlan:
    """A retreat: the path (back along the track to `back_length_m`, then the correction),
    how far back (`back_m`, one of RETREAT_STEPS_M), the correction found from there, and
    the side that was a dead end."""

    path: Path
    back_m: float
    back_length_m: float
    detour: Detour
    failed_side: Side
    turns_m: tuple[float, ...] = ()
    """Arc lengths (m, along `path`) of the sharp turns of the way back (`split_at_turns`):
    the vehicle stops and turns on the spot at each."""


def backwards_track(here_xy: FloatArray, track_xy: Sequence[tuple[float, float]]) -> FloatArray:
    """The covered track from here backwards, (n, 2) metres: here, then the recorded track
    points newest first."""
    return np.vstack([here_xy, np.array(track_xy)[::-1]])


def retreat_search(
    route: Route,
    request: AvoidanceRequest,
    params: PlannerParams,
    track: FloatArray,
    track_spacing_m: float,
    failed_side: Side,
    frame: SearchFrame | None = None,
) -> Generator[None, None, RetreatPlan | None]:
    """Search, in work units (`detour_search`'s), for the nearest point of the backwards
    track (`backwards_track`, points about track_spacing_m apart) from which a correction
    exists that avoids failed_side; None if there is none within RETREAT_STEPS_M. frame:
    the request's `SearchFrame` if the caller has one (made here otherwise), shared by
    every trial: they differ only in where they start."""
    if len(track) < 3 or len(request.conflict_xy) == 0:
        return None  # (with no conflict every trial's search returns None at once)
    seglen = np.hypot(*np.diff(track, axis=0).T)
    along = np.concatenate([[0.0], np.cumsum(seglen)])
    if along[-1] < RETREAT_STEPS_M[0]:
        return None
    if frame is None:
        frame = SearchFrame.of(route, request, params)
    for back_m in RETREAT_STEPS_M:
        if back_m > along[-1]:
            break
        j = int(np.searchsorted(along, back_m))
        target = track[j]
        trial = AvoidanceRequest(
            start_xy=target,
            start_dir=None,
            conflict_xy=request.conflict_xy,
            obstacles_xy=request.obstacles_xy,
            committed_side=Side.NONE,
            free_left_m=request.free_left_m,
            free_right_m=request.free_right_m,
            avoid_side=failed_side,
            obstacles_inflation=request.obstacles_inflation,
        )
        detour = yield from detour_search(route, trial, params, frame)
        if detour is None:
            continue
        # Back along the covered track (known free), through points every ~2 m.
        keep = track[: j + 1][:: max(1, int(_KEEP_EVERY_M / track_spacing_m))]
        if float(np.hypot(*(keep[-1] - target))) > 1e-6:
            keep = np.vstack([keep, target])
        if len(keep) < 2:
            continue
        segments: list[CubicBezier] = []
        turns: list[float] = []
        length = 0.0
        for piece in split_at_turns(keep):
            if segments:
                turns.append(length)
            back = Route(piece)
            segments += back.segments
            length += back.length
        return RetreatPlan(
            path=Path([*segments, *detour.path.segments]),
            back_m=back_m,
            back_length_m=length,
            detour=detour,
            failed_side=failed_side,
            turns_m=tuple(turns),
        )
    return None


def split_at_turns(points_xy: FloatArray) -> list[FloatArray]:
    """The polyline (n, 2) cut at each point where it turns by more than _SHARP_TURN_RAD,
    each piece (k >= 2, 2) sharing its end with the next one's start. The covered track
    turns so where the vehicle turned on the spot (it may double back over a few points);
    one spline through such points would loop round them (a base point's Catmull-Rom
    tangent is W_i+1 - W_i-1) and turn X_d about at speed."""
    d = np.diff(points_xy, axis=0)
    cos_turn = (d[:-1] * d[1:]).sum(axis=1) / np.maximum(
        np.hypot(*d[:-1].T) * np.hypot(*d[1:].T), 1e-12
    )
    sharp = np.flatnonzero(cos_turn < math.cos(_SHARP_TURN_RAD)) + 1
    bounds = [0, *sharp.tolist(), len(points_xy) - 1]
    return [points_xy[a : b + 1] for a, b in itertools.pairwise(bounds)]
