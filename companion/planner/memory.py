"""Obstacle memory: steep points seen by the obstacle sensors, kept in the world frame.

Points are binned on a horizontal grid (one point per `cell_m` square, the newest wins), so
a wall seen for a minute costs as much as a wall seen once. Points farther than `radius_m`
from the vehicle are forgotten, and the oldest go first when `max_points` is reached.
Deterministic: "age" is the planner's cycle count, never a clock.

Each point carries an inflation (metres, >= 0): how much farther than D_min + margin the
path must stay from it horizontally, because the solid it lies on slopes towards the vehicle
below it (see `Planner._steep_points`). A re-observed cell takes the newest position. Its
slope only rises over its life: each measured slope (a short chord's) is a lower bound on the
surface's, so the steepest measured so far is the best one, and a reading whose slope is
shallower takes the inflation that came with the steepest. A reading without a measured
slope (no short chord) is taken as it is (its inflation, usually 0), as before; the steepest
slope stays for the next measured one.

A point may also carry a reach (metres, >= 0, on top of that inflation): how far a flank
below it is guessed to come nearer at flight height when no short chord measured its slope
(`Planner._steep_points`), with the height it comes down to. The guess is bounded by
evidence gathered over time:
- a cell takes a reach only once it or a cell next to it had one in an earlier cycle too
  (`_confirmed`); till then the reach waits;
- it reaches down at most at the steepest slope measured (short chords) within
  `slope_share_m` of it, or of its chords to the other remembered points there (points
  seen in other cycles at other heights: `_share_slopes`);
- what rays see free (`bound_reach`): a ray that passes at or below that height
  horizontally d from the point shows the solid there does not reach d (a heightfield is
  free above any free point), so the reach kept is at most the least such d seen. The
  bound stays with the cell while it lives; a re-observed point that moved within its cell
  takes the bound plus the distance moved (the free place seen is at most that much
  farther).
None of it lowers the inflation without the reach.

Storage: the points live in rows ("slots") of one preallocated array; a dict maps each grid
cell to its slot and keeps the cells oldest first. Adding or replacing a point writes one
row, and the (k, 2) array of points is gathered from the slots in one step when asked for.
`version` changes whenever the stored points do, so callers can cache what they derive;
`generation` only when a cell is added or dropped (not when a known cell is seen again).
A bounded change log (each touched slot with its x, y and inflation before the change)
lets such a cache catch up from an earlier version with `changes_since` instead of
deriving everything again.
"""

from __future__ import annotations

import bisect
import math
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from companion.planner.types import BoolArray, FloatArray

_INITIAL_SLOTS = 64
_REACH_STEP_M = 0.05
"""`bound_reach` lowers a stored inflation only by at least this much (or to no reach at
all), so that rays sweeping past a point do not change the memory every cycle, and neither
it nor `_share_slopes` looks at a reach of at most this much, metres."""
_LOG_ENTRIES = 512
"""The change log keeps at most about this many entries (one per slot touched by a change),
at least half as many; a caller further behind is told to derive afresh (`changes_since`
-> None)."""


class MemoryChanges(NamedTuple):
    """How the stored points changed between two versions, as (x, y, inflation) metres
    (world ENU): `removed` were stored at the earlier version and are no longer stored as
    they were (dropped, moved, or their inflation lowered); `added` are stored now and were
    not stored as they are at the earlier version (new, moved, or their inflation changed).
    The stored points now are those of the earlier version less `removed`, plus `added`,
    except that a point whose position stayed and whose inflation rose is in `added` only:
    its distance less its inflation can only fall."""

    removed: list[tuple[float, float, float]]
    added: list[tuple[float, float, float]]


class ObstacleMemory:
    def __init__(
        self,
        cell_m: float,
        radius_m: float,
        max_points: int,
        slope_share_m: float = 0.0,
        min_chord_m: float = 0.5,
    ) -> None:
        if cell_m <= 0 or radius_m <= 0 or max_points < 1 or not slope_share_m >= 0.0:
            raise ValueError(
                "cell_m and radius_m must be > 0, max_points >= 1 and slope_share_m >= 0"
            )
        self.cell_m = cell_m
        self.slope_share_m = slope_share_m
        self.min_chord_m = min_chord_m
        self.radius_m = radius_m
        self.max_points = max_points
        self.version = 0
        self.generation = 0
        self._cells: dict[tuple[int, int], int] = {}  # grid cell -> slot, oldest first
        self._xyz = np.full((_INITIAL_SLOTS, 3), np.inf)  # inf: a free slot
        self._cycle = np.zeros(_INITIAL_SLOTS, dtype=np.int64)
        self._inflation = np.zeros(_INITIAL_SLOTS)
        self._slope = np.full(_INITIAL_SLOTS, np.nan)  # the steepest slope measured, rad
        self._slope_inflation = np.zeros(_INITIAL_SLOTS)  # the inflation that came with it
        # The reach (`bound_reach`): the inflation without it, the reach as measured, the
        # height it comes down to (world z) and the bound seen free (inf: none), metres.
        self._base = np.zeros(_INITIAL_SLOTS)
        self._reach = np.zeros(_INITIAL_SLOTS)
        self._reach_z = np.zeros(_INITIAL_SLOTS)
        self._bound = np.full(_INITIAL_SLOTS, np.inf)
        # The cycle of the cell's first reading with a reach (-1: none), and a reach that
        # waits for a second cycle's (`_confirmed`), metres.
        self._reach_since = np.full(_INITIAL_SLOTS, -1, dtype=np.int64)
        self._reach_waiting = np.zeros(_INITIAL_SLOTS)
        # The steepest slope that capped the cell's reach (`_share_slopes`), rad (0: none).
        self._reach_slope = np.zeros(_INITIAL_SLOTS)
        self._free: list[int] = list(range(_INITIAL_SLOTS - 1, -1, -1))
        self._xy: FloatArray | None = None
        self._infl: FloatArray | None = None
        self._slots: npt.NDArray[np.intp] | None = None  # the cells' slots, oldest first
        # `forget_far`'s last measure: (x, y, slack), radius_m less the farthest stored
        # point's distance from (x, y); None when unknown. Until the position has moved
        # `slack` from (x, y) no stored point can be farther than radius_m (triangle
        # inequality), so most cycles need no distance at all. Adding a point lowers it.
        self._far_check: tuple[float, float, float] | None = None
        # The change log, one entry per slot touched: the version the change started from,
        # the slot, and its x, y and inflation before (NaN: it held no point). Versions
        # from `_log_floor` on are complete in it.
        self._log_version: list[int] = []
        self._log_slot: list[int] = []
        self._log_x: list[float] = []
        self._log_y: list[float] = []
        self._log_inflation: list[float] = []
        self._log_floor = 0

    def __len__(self) -> int:
        return len(self._cells)

    def _slot(self) -> int:
        """A free row of the point array, growing it when full."""
        if not self._free:
            old = len(self._xyz)
            self._xyz = np.concatenate([self._xyz, np.full((old, 3), np.inf)])
            self._cycle = np.concatenate([self._cycle, np.zeros(old, dtype=np.int64)])
            self._inflation = np.concatenate([self._inflation, np.zeros(old)])
            self._slope = np.concatenate([self._slope, np.full(old, np.nan)])
            self._slope_inflation = np.concatenate([self._slope_inflation, np.zeros(old)])
            self._base = np.concatenate([self._base, np.zeros(old)])
            self._reach = np.concatenate([self._reach, np.zeros(old)])
            self._reach_z = np.concatenate([self._reach_z, np.zeros(old)])
            self._bound = np.concatenate([self._bound, np.full(old, np.inf)])
            self._reach_since = np.concatenate(
                [self._reach_since, np.full(old, -1, dtype=np.int64)]
            )
            self._reach_waiting = np.concatenate([self._reach_waiting, np.zeros(old)])
            self._reach_slope = np.concatenate([self._reach_slope, np.zeros(old)])
            self._free = list(range(2 * old - 1, old - 1, -1))
        return self._free.pop()

    def add(
        self,
        points_enu: FloatArray,
        cycle: int,
        inflation_m: FloatArray | None = None,
        slope_rad: FloatArray | None = None,
        reach_m: FloatArray | None = None,
        reach_z_m: FloatArray | None = None,
    ) -> int:
        """Store points (k, 3) with their inflation (k,) metres (default 0) and the slope
        (k,) radians it comes from (default NaN: none measured); returns how many cells
        were new. A measured slope shallower than the steepest the cell has had brings
        that one's inflation instead of its own. reach_m (k,) metres (default 0) is added
        to the inflation as far as the cell's bound allows (`bound_reach`); reach_z_m (k,)
        the height (world z, metres) it comes down to."""
        new = 0
        inv = 1.0 / self.cell_m
        cells = self._cells
        pts = np.asarray(points_enu, dtype=np.float64).reshape(-1, 3)
        k = len(pts)
        inflation = (
            [0.0] * k
            if inflation_m is None
            else np.asarray(inflation_m, dtype=np.float64).reshape(-1).tolist()
        )
        slopes = (
            [math.nan] * k
            if slope_rad is None
            else np.asarray(slope_rad, dtype=np.float64).reshape(-1).tolist()
        )
        reaches = [0.0] * k if reach_m is None else np.asarray(reach_m, dtype=np.float64).tolist()
        reach_zs = (
            [0.0] * k if reach_z_m is None else np.asarray(reach_z_m, dtype=np.float64).tolist()
        )
        version = self.version
        xyz = self._xyz
        bound = self._bound
        confirmed: list[tuple[int, int]] = []  # cells whose reach was taken
        for (x, y, z), e, theta, reach, reach_z in zip(
            pts.tolist(), inflation, slopes, reaches, reach_zs, strict=True
        ):
            if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
                continue
            e = e if math.isfinite(e) and e > 0.0 else 0.0
            key = (math.floor(x * inv), math.floor(y * inv))
            slot = cells.pop(key, None)  # re-inserted below, so dict order stays oldest-first
            if slot is None:
                new += 1
                slot = self._slot()
                xyz, bound = self._xyz, self._bound  # (a new slot may have grown the arrays)
                self._slope[slot] = math.nan
                bound[slot] = math.inf
                self._reach_since[slot] = -1
                self._reach_slope[slot] = 0.0
                self._log(version, slot, math.nan, math.nan, math.nan)
            else:
                x0, y0 = xyz.item(slot, 0), xyz.item(slot, 1)
                self._log(version, slot, x0, y0, self._inflation.item(slot))
                if bound.item(slot) < math.inf:
                    bound[slot] += math.hypot(x - x0, y - y0)
            cells[key] = slot
            xyz[slot] = (x, y, z)
            self._cycle[slot] = cycle
            if math.isfinite(theta):
                kept = float(self._slope[slot])
                if not theta < kept:  # (also when none was kept: NaN)
                    self._slope[slot] = theta
                    self._slope_inflation[slot] = e
                e = float(self._slope_inflation[slot])
            self._reach_waiting[slot] = 0.0
            if math.isfinite(reach) and reach > 0.0:
                if self._reach_since.item(slot) < 0:
                    self._reach_since[slot] = cycle
                if self._confirmed(key, cycle):
                    confirmed.append(key)
                else:  # (one reading, a stray one maybe, widens nothing yet)
                    self._reach_waiting[slot] = reach
                    reach = 0.0
            else:
                reach = 0.0
            self._base[slot] = e
            self._reach_z[slot] = reach_z
            self._reach[slot] = reach
            self._inflation[slot] = e + min(reach, bound.item(slot))
            check = self._far_check
            if check is not None:
                cx, cy, slack = check
                self._far_check = (cx, cy, min(slack, self.radius_m - math.hypot(x - cx, y - cy)))
        for key in confirmed:
            self._take_waiting_near(key, version)
        self._share_slopes(pts[:, :2], version)
        while len(cells) > self.max_points:
            self._drop_slots([cells.pop(next(iter(cells)))])
            new += 1
        if new:
            self.generation += 1
        if len(points_enu):
            self._changed()
        return new

    def _neighbours(self, key: tuple[int, int]) -> list[int]:
        """The slots of cell `key` and the (up to 8) cells around it."""
        cells = self._cells
        kx, ky = key
        return [
            slot
            for dx in (-1, 0, 1)
            for dy in (-1, 0, 1)
            if (slot := cells.get((kx + dx, ky + dy))) is not None
        ]

    def _confirmed(self, key: tuple[int, int], cycle: int) -> bool:
        """Whether cell `key` or one around it had a reading with a reach before `cycle`:
        a reach is taken from the second cycle that sees one there."""
        since = self._reach_since
        return any(0 <= since.item(slot) < cycle for slot in self._neighbours(key))

    def _take_waiting_near(self, key: tuple[int, int], version: int) -> None:
        """A reach was taken in cell `key`: the cells around it take the reach they were
        waiting with (their change logged from `version`)."""
        waiting = self._reach_waiting
        for slot in self._neighbours(key):
            r = waiting.item(slot)
            if r <= 0.0:
                continue
            waiting[slot] = 0.0
            self._reach[slot] = r
            e = self._base.item(slot) + min(r, self._bound.item(slot))
            if e > self._inflation.item(slot):
                self._set_inflation(slot, e, version)

    def _share_slopes(self, added_xy: FloatArray, version: int) -> None:
        """Cap each point's reach at its rise over the tangent of the steepest of: the slopes
        measured (short chords') within slope_share_m of it horizontally, and its chords to
        the other remembered points within slope_share_m (at least min_chord_m long
        horizontally or vertically; points seen in other cycles: a beam tilted up meets a
        wall at other heights as the vehicle moves), and the slope that capped a point
        within min_chord_m of it (so along a row of points that a beam tilted up leaves on
        a face as the vehicle passes it, ahead of where a level beam measures the face).
        Each is a lower bound on the surface's slope near it, as the long chord's is, so
        that a solid measured steep (a wall, a pillar) is not taken to reach down at a long
        chord's shallower slope. Only points within slope_share_m of one just added
        (added_xy, (n, 2) metres) can be capped further. Lowered inflations are logged
        from `version`."""
        reach = self._reach
        if len(added_xy) == 0 or not (reach > _REACH_STEP_M).any():
            return
        self._slots = None  # (the cells changed: `add` has not yet said so)
        slots = self._cell_slots()
        xyz = self._xyz
        share = self.slope_share_m
        aims = slots[reach[slots] > _REACH_STEP_M]
        gap = xyz[aims, None, :2] - np.asarray(added_xy)[None, :, :]
        aims = aims[((gap * gap).sum(axis=2) <= share * share).any(axis=1)]
        if len(aims) == 0:
            return
        lo, hi = xyz[aims, :2].min(axis=0) - share, xyz[aims, :2].max(axis=0) + share
        slots = slots[np.all((xyz[slots, :2] >= lo) & (xyz[slots, :2] <= hi), axis=1)]
        d = xyz[aims, None, :] - xyz[None, slots, :]  # (k, m, 3)
        h = np.sqrt(d[:, :, 0] ** 2 + d[:, :, 1] ** 2)
        dz = np.abs(d[:, :, 2])
        near = h <= share
        measured = np.where(near, np.nan_to_num(self._slope[slots])[None, :], 0.0)
        # The slope that capped a point next to it (a row of points one beam met along a
        # face, the face measured steep at one end of the row).
        beside = np.where(h <= self.min_chord_m, self._reach_slope[slots][None, :], 0.0)
        chord = (h >= self.min_chord_m) | (dz >= self.min_chord_m)
        chords = np.where(near & chord, np.arctan2(dz, h), 0.0)
        steepest = np.maximum(np.maximum(measured, chords), beside).max(axis=1)
        has = steepest > 0.0
        if not has.any():
            return
        aims, steepest = aims[has], steepest[has]
        self._reach_slope[aims] = np.maximum(self._reach_slope[aims], steepest)
        rise = np.maximum(xyz[aims, 2] - self._reach_z[aims], 0.0)
        capped = np.minimum(reach[aims], rise / np.tan(steepest))
        lower = capped < reach[aims]
        for slot, r in zip(aims[lower].tolist(), capped[lower].tolist(), strict=True):
            reach[slot] = r
            e = self._base.item(slot) + min(r, self._bound.item(slot))
            if e < self._inflation.item(slot):
                self._set_inflation(slot, e, version)

    def _set_inflation(self, slot: int, inflation_m: float, version: int) -> None:
        """Give a stored point (its slot) a new inflation, metres, its change logged from
        `version`."""
        xyz = self._xyz
        self._log(version, slot, xyz.item(slot, 0), xyz.item(slot, 1), self._inflation.item(slot))
        self._inflation[slot] = inflation_m

    def _log(self, version: int, slot: int, x: float, y: float, inflation_m: float) -> None:
        """A change log entry: `slot` changes from version `version`, from (x, y) with
        inflation_m (NaN: it held no point)."""
        self._log_version.append(version)
        self._log_slot.append(slot)
        self._log_x.append(x)
        self._log_y.append(y)
        self._log_inflation.append(inflation_m)

    def _drop_slots(self, slots: list[int]) -> None:
        """Free the slots (their cells already removed), logging what they held."""
        if not slots:
            return
        n = len(slots)
        idx = np.asarray(slots, dtype=np.intp)
        self._log_version.extend([self.version] * n)
        self._log_slot.extend(slots)
        self._log_x.extend(self._xyz[idx, 0].tolist())
        self._log_y.extend(self._xyz[idx, 1].tolist())
        self._log_inflation.extend(self._inflation[idx].tolist())
        self._xyz[idx] = np.inf
        self._reach[idx] = 0.0
        self._free.extend(slots)

    def _changed(self) -> None:
        self._xy = None
        self._infl = None
        self._slots = None
        self.version += 1
        if len(self._log_slot) > _LOG_ENTRIES:
            # Down to about half at once (not a few entries every change); whole versions
            # only: those after the newest version an entry is cut from.
            floor = self._log_version[len(self._log_slot) - _LOG_ENTRIES // 2 - 1] + 1
            cut = bisect.bisect_left(self._log_version, floor)
            for log in (
                self._log_version,
                self._log_slot,
                self._log_x,
                self._log_y,
                self._log_inflation,
            ):
                del log[:cut]
            self._log_floor = floor

    def changes_since(self, version: int) -> MemoryChanges | None:
        """How the stored points changed since `version` (an earlier value of `version`),
        or None if the log no longer reaches back that far (derive afresh then)."""
        if version < self._log_floor or version > self.version:
            return None
        start = bisect.bisect_left(self._log_version, version)
        before: dict[int, int] = {}  # slot -> its first entry since `version`
        for i, slot in enumerate(self._log_slot[start:], start):
            before.setdefault(slot, i)
        removed: list[tuple[float, float, float]] = []
        added: list[tuple[float, float, float]] = []
        xyz, infl = self._xyz, self._inflation
        log_x, log_y, log_inflation = self._log_x, self._log_y, self._log_inflation
        for slot, i in before.items():
            was = log_inflation[i]
            x = xyz.item(slot, 0)  # (inf in a free slot)
            now = (x, xyz.item(slot, 1), infl.item(slot)) if x != math.inf else None
            if was != was:  # (NaN: no point before)
                if now is not None:
                    added.append(now)
            elif now is None:
                removed.append((log_x[i], log_y[i], was))
            elif now[0] == log_x[i] and now[1] == log_y[i]:
                if now[2] < was:
                    removed.append((log_x[i], log_y[i], was))
                if now[2] != was:
                    added.append(now)
            else:
                removed.append((log_x[i], log_y[i], was))
                added.append(now)
        return MemoryChanges(removed, added)

    def _cell_slots(self) -> npt.NDArray[np.intp]:
        """The slot of every cell, oldest first (kept until the points change)."""
        if self._slots is None:
            cells = self._cells
            self._slots = np.fromiter(cells.values(), dtype=np.intp, count=len(cells))
        return self._slots

    def forget_far(self, position_xy: FloatArray) -> int:
        """Drop points farther than radius_m from position_xy; returns how many."""
        if not self._cells:
            return 0
        x, y = float(position_xy[0]), float(position_xy[1])
        check = self._far_check
        # (1e-6 m: far above the rounding of distances of a few hundred metres.)
        if check is not None and math.hypot(x - check[0], y - check[1]) < check[2] - 1e-6:
            return 0
        xy = self.points_xy()
        d = np.hypot(xy[:, 0] - position_xy[0], xy[:, 1] - position_xy[1])
        far = d > self.radius_m
        if not np.count_nonzero(far):
            self._far_check = (x, y, self.radius_m - float(d.max()))
            return 0
        kept = d[~far]
        self._far_check = (x, y, self.radius_m - float(kept.max())) if len(kept) else None
        keys = list(self._cells)
        self._drop_slots([self._cells.pop(keys[i]) for i in far.nonzero()[0].tolist()])
        self._changed()
        self.generation += 1
        return int(far.sum())

    def has_reach(self) -> bool:
        """Whether any remembered point has a reach that `bound_reach` could still lower
        (it has work to do)."""
        return bool(np.count_nonzero(self._reach_live()))

    def _reach_live(self) -> BoolArray:
        """Per slot: a reach kept above _REACH_STEP_M, which only `bound_reach` can lower by
        a step (free slots: no)."""
        live: BoolArray = np.minimum(self._reach, self._bound) > _REACH_STEP_M
        return live

    def bound_reach(
        self,
        origin_enu: FloatArray,
        directions_enu: FloatArray,
        free_m: FloatArray,
        tolerance_m: float,
    ) -> int:
        """Bound the points' reach by free space: ray i starts at origin_enu (3,) along the
        unit direction directions_enu[i] (world ENU) and saw nothing for its first free_m[i]
        metres. The part of it at most tolerance_m above a point's reach height passes
        horizontally d from the point somewhere: the solid below the point does not reach
        d at that height, and the point's bound becomes at most d. Its inflation becomes
        the inflation without the reach, plus the reach up to the bound (lowered in steps
        of at least _REACH_STEP_M). Returns how many inflations were lowered."""
        slots = self._reach_live().nonzero()[0]
        if len(free_m) == 0 or len(slots) == 0:
            return 0
        o = np.asarray(origin_enu, dtype=np.float64).reshape(3)
        length = np.asarray(free_m, dtype=np.float64).reshape(1, -1)
        # A ray's stretch lies within its length of the origin horizontally: a point farther
        # than that plus its bound (and a margin far above rounding) cannot be tightened.
        rel = self._xyz[slots, :2] - o[:2]  # (k, 2)
        far = self._bound[slots] + (max(length[0].tolist()) + 1e-6)
        if np.count_nonzero(rel[:, 0] * rel[:, 0] + rel[:, 1] * rel[:, 1] <= far * far) == 0:
            return 0
        dirs = np.asarray(directions_enu, dtype=np.float64).reshape(-1, 3)
        # Each ray's stretch [lo, hi] (metres along it) at most the ceiling high, per point.
        ceiling = (self._reach_z[slots] + tolerance_m - o[2])[:, None]  # (k, 1)
        dz = dirs[:, 2][None, :]  # (1, n)
        with np.errstate(divide="ignore", invalid="ignore"):
            cross = ceiling / dz
        rising, falling = dz > 1e-9, dz < -1e-9
        level_ok = ceiling >= 0.0
        hi = np.where(rising, np.minimum(length, cross), np.where(falling | level_ok, length, -1.0))
        lo = np.where(falling, np.maximum(0.0, cross), 0.0)
        seen = (lo <= hi) & (hi >= 0.0)
        # Horizontal distance from each point to each stretch.
        dxy = dirs[:, :2]  # (n, 2)
        dxy_sq = (dxy * dxy).sum(axis=1)[None, :]  # (1, n)
        along = np.clip((rel @ dxy.T) / np.maximum(dxy_sq, 1e-12), lo, np.maximum(lo, hi))
        ex = rel[:, 0:1] - along * dxy[None, :, 0]
        ey = rel[:, 1:2] - along * dxy[None, :, 1]
        d = np.where(seen, np.sqrt(ex * ex + ey * ey), np.inf).min(axis=1)
        tighter = d < self._bound[slots]
        if not np.count_nonzero(tighter):
            return 0
        slots, d = slots[tighter], d[tighter]
        self._bound[slots] = d
        now = self._inflation[slots]
        new = self._base[slots] + np.minimum(self._reach[slots], d)
        lower = (now - new >= _REACH_STEP_M) | (
            (new - self._base[slots] < _REACH_STEP_M) & (now > new)
        )
        if not np.count_nonzero(lower):
            return 0
        version = self.version
        for slot, e in zip(slots[lower].tolist(), new[lower].tolist(), strict=True):
            self._set_inflation(slot, e, version)
        self._changed()
        return int(lower.sum())

    def carve_sectors(
        self,
        origin_enu: FloatArray,
        up_enu: FloatArray,
        boresights_enu: FloatArray,
        half_width_rad: FloatArray,
        free_m: FloatArray,
        tolerance_m: float,
        support_m: float = 0.0,
    ) -> int:
        """Free-space carving by sector readings: sector i (boresight boresights_enu[i], world
        ENU unit vector, spread +-half_width_rad[i] about up_enu, the body's up axis) saw
        nothing nearer than free_m[i] anywhere across it. A point on or above the sector's
        fan surface (at most tolerance_m below it: a point is an obstacle at every height,
        and a solid standing on the ground that reaches above the fan crosses it), inside
        its width and nearer than free_m[i] (along the fan), is dropped; support_m as in
        `carve`. Returns how many points were dropped."""
        if not self._cells or len(free_m) == 0:
            return 0
        slots = self._cell_slots()
        rel = self._xyz.take(slots, axis=0) - np.asarray(origin_enu, dtype=np.float64)
        # Only points within the longest reading can be carved: the rest is skipped cheaply
        # (this runs every cycle in motion).
        reach = float(np.max(free_m)) + tolerance_m
        near = ((rel * rel).sum(axis=1) < reach * reach).nonzero()[0]
        if len(near) == 0:
            return 0
        rel = rel[near]
        up = np.asarray(up_enu, dtype=np.float64).reshape(3)
        b = np.asarray(boresights_enu, dtype=np.float64).reshape(-1, 3)
        rise = rel @ up  # (k,)
        flat = rel - rise[:, None] * up  # (k, 3) across the up axis
        flat_len = np.sqrt((flat * flat).sum(axis=1))
        b_rise = b @ up  # (n,)
        b_flat = b - b_rise[:, None] * up
        b_flat_len = np.maximum(np.sqrt((b_flat * b_flat).sum(axis=1)), 1e-9)
        # the fan surface: rise = flat_len * b_rise / b_flat_len; the bearing within it
        above = rise[:, None] - flat_len[:, None] * (b_rise / b_flat_len)[None, :]
        cos_bearing = (flat @ b_flat.T) / np.maximum(flat_len[:, None] * b_flat_len[None, :], 1e-9)
        along = flat_len[:, None] / b_flat_len[None, :]
        widen = np.arcsin(np.minimum(tolerance_m / np.maximum(flat_len, 1e-9), 1.0))
        within = cos_bearing >= np.cos(
            np.minimum(np.asarray(half_width_rad)[None, :] + widen[:, None], np.pi)
        )
        free = np.asarray(free_m, dtype=np.float64).reshape(1, -1)
        inside = within & (along < free) & (above > -tolerance_m) & (flat_len[:, None] > 0.0)
        through = np.zeros(len(slots), dtype=bool)
        through[near] = inside.any(axis=1)
        return self._drop_through(slots, through, support_m)

    def carve(
        self,
        origin_enu: FloatArray,
        directions_enu: FloatArray,
        free_m: FloatArray,
        tolerance_m: float,
        support_m: float = 0.0,
    ) -> int:
        """Free-space carving: drop remembered points that rays pass through. Ray i starts at
        origin_enu (3,) along the unit direction directions_enu[i] (world ENU) and saw nothing
        for its first free_m[i] metres; a point within tolerance_m of the ray (3-D distance)
        and short of free_m[i] lies where the ray saw nothing. Callers pass free_m short of the
        measured range by a margin so that a surface point the ray ends on, or one it merely
        grazes next to where it ends, stays. support_m: a point with a remembered neighbour
        within support_m (3-D) that no ray clears lies on a surface seen more than once (a
        ray tangent to a pillar passes right beside the rim points it missed): kept.
        Returns how many points were dropped."""
        if not self._cells or len(free_m) == 0:
            return 0
        slots = self._cell_slots()
        rel = self._xyz.take(slots, axis=0) - np.asarray(origin_enu, dtype=np.float64)
        dirs = np.asarray(directions_enu, dtype=np.float64).reshape(-1, 3)
        along = rel @ dirs.T  # (k, n): distance along each ray
        off_sq = (rel * rel).sum(axis=1)[:, None] - along * along
        free = np.asarray(free_m, dtype=np.float64).reshape(1, -1)
        inside = (along > 0.0) & (along < free) & (off_sq < tolerance_m * tolerance_m)
        return self._drop_through(slots, inside.any(axis=1), support_m)

    def _drop_through(
        self, slots: npt.NDArray[np.intp], through: BoolArray, support_m: float
    ) -> int:
        """Drop the points (memory slots) that a carve found inside free space, but those with
        a neighbour within support_m that stays. Returns how many were dropped."""
        gone = through.nonzero()[0]
        if len(gone) and support_m > 0.0 and not through.all():
            pts = self._xyz[slots]
            others = pts[~through]
            # Only a point inside the dropped ones' bounding box grown by support_m can be
            # within support_m of one of them: the same answer, from fewer distances.
            lo = pts[gone].min(axis=0) - support_m
            hi = pts[gone].max(axis=0) + support_m
            others = others[np.all((others >= lo) & (others <= hi), axis=1)]
            if len(others):
                d_sq = ((pts[gone][:, None, :] - others[None, :, :]) ** 2).sum(axis=2)
                gone = gone[d_sq.min(axis=1) > support_m * support_m]
        if len(gone) == 0:
            return 0
        keys = list(self._cells)
        self._drop_slots([self._cells.pop(keys[i]) for i in gone.tolist()])
        self._changed()
        self.generation += 1
        return len(gone)

    def slot_points(self) -> tuple[FloatArray, FloatArray]:
        """Every slot's x, y (m, 2) metres and inflation (m,), in no useful order: the stored
        points, and +inf for the free slots (whose distance from anything is inf), without
        gathering them. Read-only views, valid until the next change."""
        return self._xyz[:, :2], self._inflation

    def points_xy(self) -> FloatArray:
        """Remembered points, (k, 2) x, y metres, oldest first."""
        if self._xy is None:
            slots = self._cell_slots()
            self._xy = self._xyz[slots, :2]
        return self._xy

    def inflation_m(self) -> FloatArray:
        """Inflation of each remembered point, (k,) metres, aligned with `points_xy`."""
        if self._infl is None:
            slots = self._cell_slots()
            self._infl = self._inflation[slots]
        return self._infl

    def near(self, position_xy: FloatArray, radius_m: float) -> FloatArray:
        """Remembered points within radius_m of position_xy, (k, 2)."""
        return self.near_with_inflation(position_xy, radius_m)[0]

    def near_with_inflation(
        self, position_xy: FloatArray, radius_m: float
    ) -> tuple[FloatArray, FloatArray]:
        """Remembered points within radius_m of position_xy, (k, 2), and their inflation."""
        xy = self.points_xy()
        if len(xy) == 0:
            return xy, np.zeros(0)
        d = np.hypot(xy[:, 0] - position_xy[0], xy[:, 1] - position_xy[1])
        keep = d <= radius_m
        out: FloatArray = xy[keep]
        infl: FloatArray = self.inflation_m()[keep]
        return out, infl
