"""Last resort when blocked at rest: a way to the next base point over a grid of the memory.

The corrections (`avoidance`) hold one lateral offset along the route and the retreat
(`retreat`) backs out along the covered track; neither can go round the end of a wall to a
base point behind it, or out of a pocket the other way. When both fail at rest, this module
searches the obstacle memory rasterised on a grid (A*, 8-connected), pulls the cell path
taut into straight legs, and returns them with a stop at every corner: the vehicle stops,
turns on the spot and goes on, as it does after backing out. The legs end at the base point,
where the route's tail takes over (one more stop to turn onto it).

Unseen space counts as free: the way is a proposal from what is known, checked like every
correction (`avoidance.keeps_clear`: D_m, or the re-plan distance in a narrow place, from
every remembered point along the legs and the tail's look-ahead), and re-planned as new
points come in. Pure and deterministic; searched in work units like the other searches.
Frame: local ENU x, y metres.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Generator
from dataclasses import dataclass

import numpy as np

from companion.planner.avoidance import AvoidanceRequest, keeps_clear, min_distance
from companion.planner.bezier import CubicBezier
from companion.planner.params import PlannerParams
from companion.planner.path import Path, project
from companion.planner.route import Route
from companion.planner.types import BoolArray, FloatArray

CELL_M = 0.5
"""Grid cell size, metres."""
MARGINS_M = (15.0, 30.0)
"""The grid covers the start and the base point grown by the first of these, metres; by the
next when no way was found on it (a pocket whose walls reach farther than the first margin
from both ends: the way out goes round their far end)."""
EXPANSIONS_PER_UNIT = 50
"""A* cell expansions per work unit (about as costly as one candidate correction's check)."""
MAX_EXPANSIONS = 60_000
"""A search that expands more cells than this gives up (bounded work)."""
BASE_POINTS_TRIED = 2
"""How many base points ahead are tried as the goal, nearest first."""
SIGHT_BATCH = 32
"""Sight lines tested in one array when pulling the cell path taut."""
_NEIGHBOURS = ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1))
_SQRT2 = math.sqrt(2.0)
_HALF_DIAGONAL_M = CELL_M * math.sqrt(0.5)


@dataclass(frozen=True, slots=True)
class GridPlan:
    """A way over the grid: the path (straight legs, then the route's tail from the base
    point), the arc lengths along it at which to stop (every corner and the base point),
    which base point it goes to, where that is on the route, and the legs' length (m)."""

    path: Path
    stops: tuple[float, ...]
    base_index: int
    rejoin_s: float
    legs_length_m: float


def grid_search(
    route: Route, request: AvoidanceRequest, params: PlannerParams
) -> Generator[None, None, GridPlan | None]:
    """Search, in work units, for straight legs from request.start_xy to one of the next
    BASE_POINTS_TRIED base points that keep D_m (else the re-plan distance plus 5 cm) from
    every remembered point; None if there is none."""
    start = np.asarray(request.start_xy, dtype=np.float64)
    obstacles = request.obstacles_xy
    inflation = request.obstacles_inflation
    if inflation is None:
        inflation = np.zeros(len(obstacles))
    d_m = params.d_min_m + params.clearance_margin_m
    narrow_m = params.d_min_m + 0.5 * params.clearance_margin_m + 0.05
    start_clear = float(min_distance(start[None, :], obstacles, inflation)[0])
    s0 = float(project(route.polyline(), start[None, :])[0][0])
    ahead = np.flatnonzero(route.base_s > s0 + 0.5)[:BASE_POINTS_TRIED]
    keeps = (d_m, narrow_m) if d_m - narrow_m >= 0.1 else (d_m,)
    # Each keep with the half-diagonal margin (every point of a free cell keeps it), then the
    # last with cell centres only: a passage whose middle is clear by less than keep + half a
    # diagonal has no free cell at all (the legs are checked on their own samples anyway).
    levels = [(keep, _HALF_DIAGONAL_M) for keep in keeps] + [(keeps[-1], 0.0)]
    for margin_m, k in itertools.product(MARGINS_M, ahead.tolist()):
        goal = route.base_points[k]
        for keep_m, cell_margin_m in levels:
            grid = _Grid.around(
                start, goal, obstacles, inflation, keep_m, start_clear, cell_margin_m, margin_m
            )
            yield
            if grid.blocked_at(goal):
                continue
            cells = yield from _astar(grid, start, goal)
            if cells is None:
                continue
            corners = yield from _pull_taut(grid, cells, start, goal)
            plan = _plan(route, k, corners)
            legs = list(plan.path.segments[: len(corners) - 1])
            tail = list(plan.path.segments[len(corners) - 1 :])
            yield
            if keeps_clear(legs, tail, obstacles, inflation, keep_m, start_clear, params):
                return plan
    return None


@dataclass(frozen=True, slots=True)
class _Grid:
    """Blocked cells (ny, nx) of a grid with its lower-left corner at origin (x, y)."""

    origin: FloatArray
    blocked: BoolArray

    @classmethod
    def around(
        cls,
        start: FloatArray,
        goal: FloatArray,
        obstacles: FloatArray,
        inflation: FloatArray,
        keep_m: float,
        start_clear_m: float,
        cell_margin_m: float = _HALF_DIAGONAL_M,
        margin_m: float = MARGINS_M[0],
    ) -> _Grid:
        """The grid over start and goal grown by margin_m; a cell is blocked when its centre
        is within keep_m + the point's inflation + cell_margin_m of a point (`_discs`; half
        a cell diagonal: every point of a free cell keeps keep_m). Around a start whose own
        cell that blocks (closer than keep_m + cell_margin_m: between two solids, the cells
        on every side of it are blocked too), the cells it needs to get out are left free
        (the check of the legs holds it to avoidance.ESCAPE_SLOPE and to its own clearance
        less 5 cm)."""
        lo = np.minimum(start, goal) - margin_m
        hi = np.maximum(start, goal) + margin_m
        nx, ny = (np.ceil((hi - lo) / CELL_M).astype(int) + 1).tolist()
        blocked = np.zeros((ny, nx), dtype=bool)
        cell_keep_m = keep_m + cell_margin_m
        reach = cell_keep_m + inflation
        near = np.all((obstacles >= lo - reach[:, None]) & (obstacles <= hi + reach[:, None]), 1)
        pts, reach = obstacles[near], reach[near]
        if len(pts):
            blocked |= _discs(blocked.shape, lo, pts, reach)
        if start_clear_m < cell_keep_m:
            free_r = cell_keep_m - start_clear_m + 2.0 * CELL_M
            iy, ix = np.mgrid[0:ny, 0:nx]
            cx, cy = lo[0] + (ix + 0.5) * CELL_M, lo[1] + (iy + 0.5) * CELL_M
            blocked[np.hypot(cx - start[0], cy - start[1]) <= free_r] = False
        return cls(lo, blocked)

    def cell(self, xy: FloatArray) -> tuple[int, int]:
        """(ix, iy) of the cell holding xy (clamped to the grid)."""
        ny, nx = self.blocked.shape
        ix, iy = np.floor((np.asarray(xy) - self.origin) / CELL_M).astype(int).tolist()
        return min(max(ix, 0), nx - 1), min(max(iy, 0), ny - 1)

    def centre(self, ix: int, iy: int) -> FloatArray:
        return self.origin + (np.array([ix, iy]) + 0.5) * CELL_M

    def blocked_at(self, xy: FloatArray) -> bool:
        ix, iy = self.cell(xy)
        return bool(self.blocked[iy, ix])

    def clear_lines(self, a: FloatArray, ends: FloatArray) -> BoolArray:
        """`clear_line(a, b)` for every b of ends (k, 2) at once: the same samples (np.linspace's
        own steps), one array for all the lines."""
        ny, nx = self.blocked.shape
        span = ends - a[None, :]
        counts = np.maximum(2, np.ceil(np.hypot(span[:, 0], span[:, 1]) / (0.25 * CELL_M)) + 1)
        counts = counts.astype(int)
        line = np.repeat(np.arange(len(ends)), counts)
        first = np.concatenate([[0], np.cumsum(counts)[:-1]])
        k = np.arange(int(counts.sum())) - np.repeat(first, counts)
        t = k * np.repeat(1.0 / (counts - 1), counts)
        t[first + counts - 1] = 1.0  # as np.linspace sets its stop
        xy = a[None, :] + t[:, None] * span[line]
        idx = np.floor((xy - self.origin) / CELL_M).astype(int)
        out = (idx[:, 0] < 0) | (idx[:, 1] < 0) | (idx[:, 0] >= nx) | (idx[:, 1] >= ny)
        hit = out.copy()
        inside = ~out
        hit[inside] = self.blocked[idx[inside, 1], idx[inside, 0]]
        clear: BoolArray = ~np.logical_or.reduceat(hit, first)
        return clear

    def clear_line(self, a: FloatArray, b: FloatArray) -> bool:
        """True if no blocked cell lies under the segment a-b (sampled every quarter cell)."""
        n = max(2, math.ceil(float(np.hypot(*(b - a))) / (0.25 * CELL_M)) + 1)
        xy = a[None, :] + np.linspace(0.0, 1.0, n)[:, None] * (b - a)[None, :]
        ny, nx = self.blocked.shape
        idx = np.floor((xy - self.origin) / CELL_M).astype(int)
        if np.any(idx < 0) or np.any(idx[:, 0] >= nx) or np.any(idx[:, 1] >= ny):
            return False
        return not bool(self.blocked[idx[:, 1], idx[:, 0]].any())


def _discs(shape: tuple[int, int], lo: FloatArray, pts: FloatArray, reach: FloatArray) -> BoolArray:
    """Cells of a grid (shape (ny, nx), origin lo) whose centre lies within each point's
    reach (metres), row by row: in the row of centre height y a point covers the cells whose
    centre is within sqrt(reach^2 - (y - y_p)^2) of x_p, one interval, marked at its ends in
    a difference array and summed along the row."""
    ny, nx = shape
    rows = np.ceil(reach / CELL_M).astype(int)
    span = np.arange(-int(rows.max()), int(rows.max()) + 1)
    iy = np.floor((pts[:, 1] - lo[1]) / CELL_M).astype(int)[:, None] + span[None, :]  # (k, m)
    dy = lo[1] + (iy + 0.5) * CELL_M - pts[:, 1, None]
    half_sq = reach[:, None] ** 2 - dy**2
    ok = (half_sq >= 0.0) & (iy >= 0) & (iy < ny)
    half = np.sqrt(np.where(ok, half_sq, 0.0))
    x = (pts[:, 0, None] - lo[0]) / CELL_M - 0.5  # the point's x in cell-centre units
    ix0 = np.maximum(np.ceil(x - half / CELL_M).astype(int), 0)
    ix1 = np.minimum(np.floor(x + half / CELL_M).astype(int), nx - 1)
    ok &= ix0 <= ix1
    # The difference array as two counts of flat indices (np.add.at's sums, faster).
    row = iy[ok] * (nx + 1)
    size = ny * (nx + 1)
    ends = np.bincount(row + ix0[ok], minlength=size)
    ends -= np.bincount(row + ix1[ok] + 1, minlength=size)
    covered: BoolArray = np.cumsum(ends.reshape(ny, nx + 1)[:, :nx], axis=1) > 0
    return covered


def _astar(
    grid: _Grid, start: FloatArray, goal: FloatArray
) -> Generator[None, None, list[tuple[int, int]] | None]:
    """Cells from start's to goal's, 8-connected through free cells (the start's cell may
    be blocked); yields every EXPANSIONS_PER_UNIT expansions; None if there is no way or the
    search expands more than MAX_EXPANSIONS cells. Ties break on insertion order.

    Cells are flat indices into the grid framed by a border of blocked cells (a neighbour
    off the grid is a blocked one), with plain lists for the costs: the same search as
    with (ix, iy) tuples in dicts, at half the cost per expansion."""
    ny, nx = grid.blocked.shape
    w = nx + 2
    framed = np.ones((ny + 2, w), dtype=bool)
    framed[1:-1, 1:-1] = grid.blocked
    wall: list[bool] = framed.ravel().tolist()
    (sx, sy), (gx, gy) = grid.cell(start), grid.cell(goal)
    s, g = (sy + 1) * w + sx + 1, (gy + 1) * w + gx + 1
    size = len(wall)
    best = [math.inf] * size
    best[s] = 0.0
    parent = [-1] * size
    done = bytearray(size)
    frontier: list[tuple[float, int, int]] = [(0.0, 0, s)]
    count, expanded = 1, 0
    pop, push, hypot = heapq.heappop, heapq.heappush, math.hypot
    while frontier:
        _, _, here = pop(frontier)
        if done[here]:
            continue
        if here == g:
            path = [here]
            while parent[path[-1]] >= 0:
                path.append(parent[path[-1]])
            return [(c % w - 1, c // w - 1) for c in reversed(path)]
        done[here] = 1
        expanded += 1
        if expanded > MAX_EXPANSIONS:
            return None
        if expanded % EXPANSIONS_PER_UNIT == 0:
            yield
        hx, hy = here % w - 1, here // w - 1
        cost_here = best[here]
        for dx, dy in _NEIGHBOURS:
            nxt = here + dy * w + dx
            if wall[nxt]:
                continue
            if dx and dy:
                if wall[here + dx] or wall[here + dy * w]:
                    continue  # no corner cutting between two blocked cells
                cost = cost_here + _SQRT2
            else:
                cost = cost_here + 1.0
            if cost < best[nxt]:
                best[nxt] = cost
                parent[nxt] = here
                push(frontier, (cost + hypot(gx - hx - dx, gy - hy - dy), count, nxt))
                count += 1
    return None


def _pull_taut(
    grid: _Grid, cells: list[tuple[int, int]], start: FloatArray, goal: FloatArray
) -> Generator[None, None, list[FloatArray]]:
    """The cell path as few straight legs: from each corner, the farthest later cell centre
    (or the goal) in clear sight; yields every EXPANSIONS_PER_UNIT sight lines. Corners
    from start to goal."""
    points = [start, *(grid.centre(ix, iy) for ix, iy in cells[1:-1]), goal]
    xy = np.array(points)
    corners = [start]
    i, lines = 0, 0
    while i < len(points) - 1:
        # The farthest clear j, looked for from the end SIGHT_BATCH lines at a time; the
        # lines counted (and the units yielded) are those a one-by-one scan would test.
        j = len(points) - 1
        while j > i + 1:
            lo = max(i + 2, j - SIGHT_BATCH + 1)
            clear = np.flatnonzero(grid.clear_lines(xy[i], xy[lo : j + 1]))
            found = lo + int(clear[-1]) if len(clear) else None
            stop = found if found is not None else lo - 1
            for _ in range(j - max(stop, i + 1)):
                lines += 1
                if lines % EXPANSIONS_PER_UNIT == 0:
                    yield
            j = stop if found is None else found
            if found is not None:
                break
        corners.append(points[j])
        i = j
    return corners


def _plan(route: Route, k: int, corners: list[FloatArray]) -> GridPlan:
    """Straight legs through the corners, then the route's tail from base point k."""
    legs = []
    for a, b in itertools.pairwise(corners):
        d = b - a
        legs.append(CubicBezier(np.array([a, a + d / 3.0, a + 2.0 * d / 3.0, b])))
    tail = route.tail_from(float(route.base_s[k]))
    stops, along = [], 0.0
    for leg in legs:
        along += leg.length
        stops.append(along)
    return GridPlan(
        path=Path([*legs, *tail]),
        stops=tuple(stops),
        base_index=k,
        rejoin_s=float(route.base_s[k]),
        legs_length_m=along,
    )
