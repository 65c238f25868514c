"""Dead-end retreat: where to back out to along the covered track, and the correction on
the other side from there.

When the planner is blocked at rest, it backs out along the track it has covered (known to
be free) to the nearest point from which a correction on the side not yet tried exists.
Pure functions over the covered track (x, y metres, local ENU); searched in work units
(`avoidance.detour_search`), so that a caller with a budget per cycle can resume it.
"""

from __future__ import annotations

from collections.abc import Generator, Sequence
from dataclasses import dataclass

import numpy as np

from companion.planner.avoidance import AvoidanceRequest, Detour, detour_search
from companion.planner.params import PlannerParams
from companion.planner.path import Path
from companion.planner.route import Route
from companion.planner.types import FloatArray, Side

RETREAT_STEPS_M = (3.0, 6.0, 9.0, 12.0, 16.0, 20.0, 25.0, 30.0, 40.0)
"""How far back along the covered track a retreat may end, tried nearest first, metres."""
_KEEP_EVERY_M = 2.0
"""Spacing of the track points the way back passes through, metres."""


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
) -> Generator[None, None, RetreatPlan | None]:
    """Search, in work units (`detour_search`'s), for the nearest point of the backwards
    track (`backwards_track`, points about track_spacing_m apart) from which a correction
    exists that avoids failed_side; None if there is none within RETREAT_STEPS_M."""
    if len(track) < 3:
        return None
    seglen = np.hypot(*np.diff(track, axis=0).T)
    along = np.concatenate([[0.0], np.cumsum(seglen)])
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
        detour = yield from detour_search(route, trial, params)
        if detour is None:
            continue
        # Back along the covered track (known free), through points every ~2 m.
        keep = track[: j + 1][:: max(1, int(_KEEP_EVERY_M / track_spacing_m))]
        if float(np.hypot(*(keep[-1] - target))) > 1e-6:
            keep = np.vstack([keep, target])
        if len(keep) < 2:
            continue
        back = Route(keep)
        return RetreatPlan(
            path=Path([*back.segments, *detour.path.segments]),
            back_m=back_m,
            back_length_m=back.length,
            detour=detour,
            failed_side=failed_side,
        )
    return None
