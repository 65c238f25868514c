"""Seeded random worlds: terrain, obstacles and a route, checked to be flyable.

`generate(seed)` draws a world and a route from one integer seed and returns them as the
`world:` and `route:` sections of a scenario (`WorldConfig`, `RouteConfig`), so a generated
world is an ordinary scenario: `scenario(seed, sensors, vehicle)` wraps it and
`scenario_yaml` writes it out as a file that `companion simulate` flies and that can be kept
in config/scenarios/ as a regression scenario. Same seed and same `WorldGenConfig`: the same
world, on any machine (numpy's PCG64 stream, values rounded to millimetres).

What is drawn (frame: local ENU, metres; see docs/scenarios.md):
- a route of 2-5 base points, 60-200 m long, turning at most 75 degrees per base point;
- terrain: gaussian hills and elongated ridges near the route, some overlapping (creases),
  each no steeper than `hill_slope_deg`; the sum is checked against `max_terrain_slope_deg`;
- obstacles placed along the route: mesas (flanks 30-85 degrees), cylinders, boxes, walls
  across the route with a gap, narrow passages, cliffs beside the route and U-shaped dead
  ends open towards the vehicle. Every solid is an obstacle (D_min applies to it), whatever
  its flank; the hills are terrain. No obstacle is placed within reach of a base point, and
  obstacles of different motifs keep at least 2 D_min + `passage_extra_m` apart, so every
  gap in a world is either such a passage or one of a motif's own.

What is checked, not assumed (a draw that fails is thrown away and the next one is drawn
from the same seed's stream):
- the start (first base point at H_d above the surface) and every base point are at least
  D_min + `clear_margin_m` from every obstacle, in 3-D at H_d above the surface and
  horizontally from every footprint;
- a passable corridor: on an occupancy grid of the obstacle footprints inflated by
  D_min + `corridor_margin_m` (plus half a cell's diagonal), a breadth-first search from
  the start reaches every base point (so start -> W1 -> ... -> goal is connected);
- the terrain (the hills; obstacle footprints left out) is no steeper than
  `max_terrain_slope_deg` on the grid.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field

from companion.sim.scenario import Expectation, Scenario
from companion.sim.vehicle import VehicleModelConfig
from companion.sim.world import (
    BoxConfig,
    CylinderConfig,
    FeatureConfig,
    GaussianHillConfig,
    MesaConfig,
    World,
    WorldConfig,
)
from companion.tuning import PlannerConfig, RouteConfig, SensorConfig

__all__ = [
    "MOTIFS",
    "GeneratedWorld",
    "WorldGenConfig",
    "WorldGenError",
    "corridor_reachable",
    "generate",
    "occupancy_grid",
    "scenario",
    "scenario_yaml",
    "to_scenario",
]

_SALT = 0x7E11A1  # keeps these streams apart from other uses of the same small seeds
_MM = 3  # decimals kept (millimetres): the written file holds exactly the checked world

MOTIFS = (
    "mesa",
    "cylinder",
    "box",
    "wall_with_gap",
    "passage",
    "cliff",
    "dead_end",
)
"""Obstacle shapes the generator places along the route."""

Range = tuple[float, float]
_HILL_TRIES = 50  # terrain draws per attempt before the route is drawn again
_PLACE_TRIES = 20  # positions tried for one obstacle before it is left out
_SEPARATION_CELL_M = 1.0  # grid of the check that obstacles of different motifs keep apart


class WorldGenError(RuntimeError):
    """No world passed the checks within max_attempts draws."""


class WorldGenConfig(BaseModel):
    """What the generator draws and what it guarantees. Metres, degrees, m/s, seconds."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    d_min_m: Annotated[float, Field(gt=0)] = 2.0
    h_d_m: Annotated[float, Field(gt=0)] = 2.0
    v_d_mps: Annotated[float, Field(gt=0)] = 1.0
    route_length_m: Range = (60.0, 200.0)
    base_points: tuple[int, int] = (2, 5)
    """Inclusive range of the number of base points (start and goal included)."""
    min_leg_m: Annotated[float, Field(gt=0)] = 15.0
    max_turn_deg: Annotated[float, Field(ge=0, le=120)] = 75.0
    hills_per_100m: Range = (2.0, 5.0)
    hill_slope_deg: Annotated[float, Field(gt=0, lt=60)] = 20.0
    """Steepest slope of one hill or ridge."""
    max_terrain_slope_deg: Annotated[float, Field(gt=0, lt=80)] = 30.0
    """Steepest slope of the sum of the hills (checked)."""
    obstacles_per_100m: Range = (2.0, 4.0)
    motifs: tuple[str, ...] = MOTIFS
    mesa_slope_deg: Range = (30.0, 85.0)
    clear_margin_m: Annotated[float, Field(ge=0)] = 2.0
    """Start and base points are at least d_min_m + this from every obstacle."""
    corridor_margin_m: Annotated[float, Field(ge=0)] = 0.5
    """The corridor search inflates obstacles by d_min_m + this."""
    passage_extra_m: Annotated[float, Field(ge=0)] = 2.0
    """Narrow passages and gaps are at least 2 d_min_m + this wide."""
    grid_cell_m: Annotated[float, Field(gt=0.05, le=2.0)] = 0.5
    grid_pad_m: Annotated[float, Field(ge=5)] = 30.0
    duration_factor: Annotated[float, Field(gt=1)] = 3.0
    """duration_s = duration_factor * route length / v_d + duration_extra_s."""
    duration_extra_s: Annotated[float, Field(ge=0)] = 120.0
    max_attempts: Annotated[int, Field(ge=1)] = 200


@dataclass(frozen=True)
class GeneratedWorld:
    """A generated world and route, with what was drawn and how many draws it took."""

    seed: int
    world: WorldConfig
    route: RouteConfig
    duration_s: float
    motifs: tuple[str, ...]
    attempts: int
    route_length_m: float

    def describe(self) -> str:
        counts: dict[str, int] = {}
        for m in self.motifs:
            counts[m] = counts.get(m, 0) + 1
        shapes = ", ".join(f"{k} x{v}" if v > 1 else k for k, v in counts.items()) or "none"
        n = len(self.route.points)
        return (
            f"seeded random world {self.seed}: {n} base points, {self.route_length_m:.0f} m; "
            f"obstacles: {shapes}"
        )


# --------------------------------------------------------------------------- drawing


def _r(v: float) -> float:
    return round(float(v), _MM)


def _xy(p: Sequence[float] | np.ndarray) -> tuple[float, float]:
    return (_r(p[0]), _r(p[1]))


class _Route:
    """A polyline with arc length, tangent and normal lookup (ENU metres)."""

    def __init__(self, points: np.ndarray) -> None:
        self.points = points
        seg = np.diff(points, axis=0)
        self.lengths = np.hypot(seg[:, 0], seg[:, 1])
        self.cum = np.concatenate([[0.0], np.cumsum(self.lengths)])
        self.length = float(self.cum[-1])
        self.tangents = seg / self.lengths[:, None]

    def frame(self, s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Point, unit tangent and unit left normal at arc length s."""
        i = int(np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.lengths) - 1))
        t = self.tangents[i]
        p = self.points[i] + t * (s - self.cum[i])
        return p, t, np.array([-t[1], t[0]])

    def distance(self, q: np.ndarray) -> np.ndarray:
        """Horizontal distance (m) of points q (n, 2) to the polyline."""
        best = np.full(len(q), np.inf)
        for a, t, ln in zip(self.points[:-1], self.tangents, self.lengths, strict=True):
            u = np.clip((q - a) @ t, 0.0, ln)
            best = np.minimum(best, np.hypot(*(q - (a + u[:, None] * t)).T))
        return best


def _draw_route(rng: np.random.Generator, cfg: WorldGenConfig) -> np.ndarray:
    lo, hi = cfg.base_points
    n = int(rng.integers(lo, hi + 1))
    length = float(rng.uniform(*cfg.route_length_m))
    legs = n - 1
    spare = max(length - cfg.min_leg_m * legs, 0.0)
    leg_m = cfg.min_leg_m + spare * rng.dirichlet(np.full(legs, 2.0))
    heading0 = float(rng.uniform(-math.pi, math.pi))
    heading = heading0
    pts = [np.zeros(2)]
    max_turn = math.radians(cfg.max_turn_deg)
    for k in range(legs):
        if k > 0:
            turn = float(rng.uniform(-max_turn, max_turn))
            # keep the route from folding back on itself
            heading = float(np.clip(heading + turn, heading0 - 2.1, heading0 + 2.1))
        pts.append(pts[-1] + leg_m[k] * np.array([math.cos(heading), math.sin(heading)]))
    return np.array([_xy(p) for p in pts])


def _draw_hills(
    rng: np.random.Generator, cfg: WorldGenConfig, route: _Route
) -> list[FeatureConfig]:
    n = max(1, round(route.length / 100.0 * rng.uniform(*cfg.hills_per_100m)))
    tan_max = math.tan(math.radians(cfg.hill_slope_deg))
    out: list[FeatureConfig] = []
    k = 0
    while len(out) < n:
        k += 1
        p, _t, nrm = route.frame(float(rng.uniform(-10.0, route.length + 10.0)))
        c = p + nrm * float(rng.normal(0.0, 12.0))
        h = float(rng.uniform(1.0, 6.0))
        if rng.random() < 0.15:
            h = -float(rng.uniform(1.0, 3.0))  # a hollow
        # steepest slope of a gaussian: |h| e^-1/2 / sigma
        s_min = abs(h) * math.exp(-0.5) / tan_max
        ridge = rng.random() < 0.35
        if ridge:
            sxy = (_r(rng.uniform(2.5, 5.0) * s_min), _r(rng.uniform(1.0, 1.6) * s_min))
            yaw = _r(rng.uniform(0.0, 180.0))
            out.append(
                GaussianHillConfig(
                    name=f"ridge {k}", center=_xy(c), height_m=_r(h), sigma_xy_m=sxy, yaw_deg=yaw
                )
            )
        else:
            sigma = _r(rng.uniform(1.0, 2.0) * s_min)
            out.append(
                GaussianHillConfig(name=f"hill {k}", center=_xy(c), height_m=_r(h), sigma_m=sigma)
            )
        if rng.random() < 0.4 and len(out) < n + 2:
            # an overlapping neighbour: the two make a crease between them
            h2 = float(rng.uniform(1.0, 5.0))
            s2 = _r(rng.uniform(1.0, 1.8) * h2 * math.exp(-0.5) / tan_max)
            ang = float(rng.uniform(0.0, 2.0 * math.pi))
            c2 = c + (1.2 * max(s_min, s2)) * np.array([math.cos(ang), math.sin(ang)])
            out.append(
                GaussianHillConfig(name=f"hill {k}b", center=_xy(c2), height_m=_r(h2), sigma_m=s2)
            )
    return out


class _Placer:
    """Draws obstacle motifs in the route's local frame (u along, v to the left)."""

    def __init__(
        self,
        rng: np.random.Generator,
        cfg: WorldGenConfig,
        route: _Route,
        terrain: World,
    ) -> None:
        self.rng = rng
        self.cfg = cfg
        self.route = route
        self.terrain = terrain
        self.features: list[FeatureConfig] = []
        self.k = 0

    def _z_top(self, centre: np.ndarray, radius: float, rise: float) -> float:
        """Height above ground_z that stands `rise` m above the terrain under the footprint."""
        a = np.linspace(0.0, 2.0 * math.pi, 12, endpoint=False)
        xs = np.concatenate([[centre[0]], centre[0] + radius * np.cos(a)])
        ys = np.concatenate([[centre[1]], centre[1] + radius * np.sin(a)])
        return float(np.max(self.terrain.terrain_height(xs, ys))) + rise

    def _box(
        self, name: str, c: np.ndarray, along: np.ndarray, size: tuple[float, float], rise: float
    ) -> None:
        yaw = math.degrees(math.atan2(along[1], along[0]))
        h = self._z_top(c, 0.5 * math.hypot(*size), rise)
        self.features.append(
            BoxConfig(
                name=name,
                center=_xy(c),
                size_m=(_r(size[0]), _r(size[1]), _r(max(h, 1.0))),
                yaw_deg=_r(yaw),
            )
        )

    def place(self, motif: str, s: float) -> None:
        self.k += 1
        rng, cfg, k = self.rng, self.cfg, self.k
        p, t, n = self.route.frame(s)
        gap_min = 2.0 * cfg.d_min_m + cfg.passage_extra_m
        if motif == "mesa":
            r = float(rng.uniform(2.0, 10.0))
            slope = float(rng.uniform(*cfg.mesa_slope_deg))
            rise = float(rng.uniform(3.0, 12.0))
            r_out = r + rise / math.tan(math.radians(slope))
            c = p + n * float(rng.uniform(-r_out, r_out))
            h = self._z_top(c, r_out, rise)
            self.features.append(
                MesaConfig(
                    name=f"mesa {k}",
                    center=_xy(c),
                    radius_m=_r(r),
                    height_m=_r(max(h, 1.0)),
                    side_slope_deg=_r(slope),
                )
            )
        elif motif == "cylinder":
            r = float(rng.uniform(0.5, 3.0))
            c = p + n * float(rng.uniform(-6.0, 6.0))
            h = self._z_top(c, r, float(rng.uniform(4.0, 15.0)))
            self.features.append(
                CylinderConfig(name=f"cylinder {k}", center=_xy(c), radius_m=_r(r), height_m=_r(h))
            )
        elif motif == "box":
            size = (float(rng.uniform(2.0, 12.0)), float(rng.uniform(1.0, 8.0)))
            ang = float(rng.uniform(0.0, math.pi))
            along = np.array([math.cos(ang), math.sin(ang)])
            c = p + n * float(rng.uniform(-6.0, 6.0))
            self._box(f"box {k}", c, along, size, float(rng.uniform(3.0, 12.0)))
        elif motif == "wall_with_gap":
            gap = gap_min + float(rng.uniform(0.0, 4.0))
            v_gap = float(rng.uniform(-10.0, 10.0))
            thick = float(rng.uniform(0.8, 2.0))
            rise = float(rng.uniform(4.0, 10.0))
            for side, sign in (("left", 1.0), ("right", -1.0)):
                ln = float(rng.uniform(8.0, 25.0))
                v = v_gap + sign * (gap / 2.0 + ln / 2.0)
                self._box(f"wall {k} {side}", p + n * v, n, (ln, thick), rise)
        elif motif == "passage":
            width = gap_min + float(rng.uniform(0.0, 3.0))
            slack = (width - gap_min) / 2.0
            v0 = float(rng.uniform(-slack, slack))
            ln = float(rng.uniform(10.0, 25.0))
            rise = float(rng.uniform(4.0, 12.0))
            for side, sign in (("left", 1.0), ("right", -1.0)):
                thick = float(rng.uniform(2.0, 8.0))
                v = v0 + sign * (width / 2.0 + thick / 2.0)
                self._box(f"passage {k} {side}", p + n * v, t, (ln, thick), rise)
        elif motif == "cliff":
            sign = 1.0 if rng.random() < 0.5 else -1.0
            off = cfg.d_min_m + float(rng.uniform(1.0, 5.0))  # route to the cliff's foot
            rise = float(rng.uniform(6.0, 20.0))
            if rng.random() < 0.5:
                thick = float(rng.uniform(3.0, 10.0))
                ln = float(rng.uniform(15.0, 40.0))
                self._box(f"cliff {k}", p + n * sign * (off + thick / 2.0), t, (ln, thick), rise)
            else:
                slope = float(rng.uniform(60.0, 85.0))
                r = float(rng.uniform(10.0, 25.0))
                r_out = r + rise / math.tan(math.radians(slope))
                c = p + n * sign * (off + r_out)
                h = self._z_top(c, r_out, rise)
                self.features.append(
                    MesaConfig(
                        name=f"cliff {k}",
                        center=_xy(c),
                        radius_m=_r(r),
                        height_m=_r(h),
                        side_slope_deg=_r(slope),
                    )
                )
        elif motif == "dead_end":
            inner = gap_min + float(rng.uniform(0.0, 8.0))
            depth = float(rng.uniform(8.0, 20.0))
            thick = float(rng.uniform(0.8, 1.5))
            rise = float(rng.uniform(4.0, 8.0))
            v0 = float(rng.uniform(-inner / 4.0, inner / 4.0))
            back = p + t * (depth + thick / 2.0) + n * v0
            self._box(f"dead end {k} back", back, n, (inner + 2.0 * thick, thick), rise)
            for side, sign in (("left", 1.0), ("right", -1.0)):
                c = p + t * (depth / 2.0) + n * (v0 + sign * (inner / 2.0 + thick / 2.0))
                self._box(f"dead end {k} {side}", c, t, (depth, thick), rise)
        else:
            raise ValueError(f"unknown motif {motif!r}; known: {', '.join(MOTIFS)}")


# --------------------------------------------------------------------------- checks


@dataclass(frozen=True)
class _Grid:
    """Occupancy of obstacle footprints on a regular grid: occ[iy, ix] at
    (x0 + ix * cell, y0 + iy * cell)."""

    x0: float
    y0: float
    cell: float
    occ: np.ndarray
    bbox: tuple[float, float, float, float]

    def index(self, x: float, y: float) -> tuple[int, int]:
        return round((y - self.y0) / self.cell), round((x - self.x0) / self.cell)


def occupancy_grid(world: World, bbox: tuple[float, float, float, float], cell_m: float) -> _Grid:
    """Where an obstacle feature stands (its footprint), sampled at cell centres."""
    x0, x1, y0, y1 = bbox
    xs = x0 + np.arange(math.ceil((x1 - x0) / cell_m) + 1) * cell_m
    ys = y0 + np.arange(math.ceil((y1 - y0) / cell_m) + 1) * cell_m
    occ = np.isfinite(world.obstacle_height(xs[None, :], ys[:, None]))
    return _Grid(float(xs[0]), float(ys[0]), cell_m, occ, bbox)


def _dilate(occ: np.ndarray, radius_cells: float) -> np.ndarray:
    """occ grown by a disc of radius_cells (cells within that distance of an occupied one)."""
    r = math.floor(radius_cells)
    out = occ.copy()
    ny, nx = occ.shape
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if abs(dy) >= ny or abs(dx) >= nx:
                continue  # shifted off the grid
            if (dx or dy) and dx * dx + dy * dy <= radius_cells * radius_cells:
                src = occ[max(0, -dy) : ny - max(0, dy), max(0, -dx) : nx - max(0, dx)]
                out[max(0, dy) : ny - max(0, -dy), max(0, dx) : nx - max(0, -dx)] |= src
    return out


def corridor_reachable(
    free: np.ndarray, start: tuple[int, int], targets: Sequence[tuple[int, int]]
) -> bool:
    """Breadth-first search over 8-connected free cells from start; True if every target
    (row, col) is reached. Cells outside the grid are blocked."""
    ny, nx = free.shape
    cells = [start, *targets]
    if any(not (0 <= r < ny and 0 <= c < nx) or not free[r, c] for r, c in cells):
        return False
    pad = np.zeros((ny + 2, nx + 2), dtype=bool)
    pad[1:-1, 1:-1] = free
    w = nx + 2
    flat = pad.ravel()
    seen = np.zeros_like(flat)
    steps = np.array([-w - 1, -w, -w + 1, -1, 1, w - 1, w, w + 1])
    frontier = np.array([(start[0] + 1) * w + start[1] + 1])
    seen[frontier] = True
    want = np.array([(r + 1) * w + c + 1 for r, c in targets])
    while len(frontier):
        if seen[want].all():
            return True
        nb = (frontier[:, None] + steps[None, :]).ravel()
        nb = nb[flat[nb] & ~seen[nb]]
        nb = np.unique(nb)
        seen[nb] = True
        frontier = nb
    return bool(seen[want].all())


def _route_grid(
    world: World, points: np.ndarray, cfg: WorldGenConfig, cell_m: float | None = None
) -> _Grid:
    """Obstacle occupancy on the grid around the route (base points padded by grid_pad_m);
    cell_m: the grid's cell, default grid_cell_m."""
    pad = cfg.grid_pad_m
    bbox = (
        float(points[:, 0].min()) - pad,
        float(points[:, 0].max()) + pad,
        float(points[:, 1].min()) - pad,
        float(points[:, 1].max()) + pad,
    )
    return occupancy_grid(world, bbox, cell_m or cfg.grid_cell_m)


def _terrain_slope_ok(world: World, grid: _Grid, cfg: WorldGenConfig) -> bool:
    """Steepest slope of the surface away from obstacle footprints (finite differences on
    the grid) within max_terrain_slope_deg."""
    max_deg = cfg.max_terrain_slope_deg
    ny, nx = grid.occ.shape
    xs = grid.x0 + np.arange(nx) * grid.cell
    ys = grid.y0 + np.arange(ny) * grid.cell
    z = world.height(xs[None, :], ys[:, None])
    gy, gx = np.gradient(z, grid.cell)
    slope = np.hypot(gx, gy)
    near_obstacle = _dilate(grid.occ, 2.0)
    free = ~near_obstacle
    return bool(np.all(slope[free] <= math.tan(math.radians(max_deg)) + 1e-9))


def _check(world: World, points: np.ndarray, cfg: WorldGenConfig) -> str | None:
    """None if the world keeps the guarantees, else what failed."""
    need = cfg.d_min_m + cfg.clear_margin_m
    for i, (x, y) in enumerate(points):
        z = float(world.height(x, y)) + cfg.h_d_m
        if world.obstacle_distance((x, y, z)) < need:
            return f"base point {i} within {need} m of an obstacle"
    grid = _route_grid(world, points, cfg)
    half_diag = grid.cell * math.sqrt(0.5)
    clear = ~_dilate(grid.occ, (need + half_diag) / grid.cell)
    idx = [grid.index(x, y) for x, y in points]
    if not all(clear[r, c] for r, c in idx):
        return "base point within reach of an obstacle footprint"
    free = ~_dilate(grid.occ, (cfg.d_min_m + cfg.corridor_margin_m + half_diag) / grid.cell)
    if not corridor_reachable(free, idx[0], idx[1:]):
        return "no corridor from the start through the base points to the goal"
    if not _terrain_slope_ok(world, grid, cfg):
        return "terrain steeper than max_terrain_slope_deg"
    return None


# --------------------------------------------------------------------------- public API


def generate(seed: int, cfg: WorldGenConfig | None = None) -> GeneratedWorld:
    """The world and route of one seed (>= 0). WorldGenError if max_attempts draws fail."""
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    cfg = cfg or WorldGenConfig()
    unknown = set(cfg.motifs) - set(MOTIFS)
    if unknown:
        raise ValueError(f"unknown motifs {sorted(unknown)}; known: {', '.join(MOTIFS)}")
    rng = np.random.default_rng(np.random.SeedSequence([_SALT, seed]))
    need = cfg.d_min_m + cfg.clear_margin_m
    separation = 2.0 * cfg.d_min_m + cfg.passage_extra_m
    last = ""
    for attempt in range(1, cfg.max_attempts + 1):
        points = _draw_route(rng, cfg)
        route = _Route(points)
        for _ in range(_HILL_TRIES):
            hills = _draw_hills(rng, cfg, route)
            terrain = World(WorldConfig(features=hills))
            if _terrain_slope_ok(terrain, _route_grid(terrain, points, cfg), cfg):
                break
        else:
            last = "terrain steeper than max_terrain_slope_deg"
            continue
        base_z = terrain.height(points[:, 0], points[:, 1]) + cfg.h_d_m
        base_xyz = np.column_stack([points, base_z])
        placer = _Placer(rng, cfg, route, terrain)
        m = max(1, round(route.length / 100.0 * rng.uniform(*cfg.obstacles_per_100m)))
        motifs: list[str] = []
        margin = min(20.0, route.length / 4.0)
        coarse = _route_grid(terrain, points, cfg, cell_m=_SEPARATION_CELL_M)
        # cells closer than the separation to an obstacle already placed (conservative)
        taken = np.zeros_like(coarse.occ)
        sep_cells = (separation + 2.0 * _SEPARATION_CELL_M) / _SEPARATION_CELL_M
        for _ in range(m):
            motif = str(rng.choice(list(cfg.motifs)))
            for _ in range(_PLACE_TRIES):
                kept = len(placer.features)
                placer.place(motif, float(rng.uniform(margin, route.length - margin)))
                new = World(WorldConfig(features=placer.features[kept:]))
                occ = occupancy_grid(new, coarse.bbox, _SEPARATION_CELL_M).occ
                if not (occ & taken).any() and all(
                    new.obstacle_distance(q) >= need for q in base_xyz
                ):
                    motifs.append(motif)
                    taken |= _dilate(occ, sep_cells)
                    break
                del placer.features[kept:]
        if not motifs:
            last = "no obstacle could be placed clear of the base points"
            continue
        wc = WorldConfig(features=[*hills, *placer.features])
        problem = _check(World(wc), points, cfg)
        if problem is None:
            return GeneratedWorld(
                seed=seed,
                world=wc,
                route=RouteConfig(points=[_xy(p) for p in points]),
                duration_s=_r(
                    round(cfg.duration_factor * route.length / cfg.v_d_mps + cfg.duration_extra_s)
                ),
                motifs=tuple(motifs),
                attempts=attempt,
                route_length_m=route.length,
            )
        last = problem
    raise WorldGenError(
        f"seed {seed}: no world passed the checks in {cfg.max_attempts} draws ({last})"
    )


def scenario(
    seed: int,
    sensors: Sequence[SensorConfig],
    vehicle: VehicleModelConfig | None = None,
    cfg: WorldGenConfig | None = None,
    planner: PlannerConfig | None = None,
    name: str | None = None,
) -> Scenario:
    """The seed's world as a scenario (see `to_scenario`)."""
    cfg = cfg or WorldGenConfig()
    return to_scenario(generate(seed, cfg), sensors, vehicle, cfg, planner, name)


def to_scenario(
    gen: GeneratedWorld,
    sensors: Sequence[SensorConfig],
    vehicle: VehicleModelConfig | None = None,
    cfg: WorldGenConfig | None = None,
    planner: PlannerConfig | None = None,
    name: str | None = None,
) -> Scenario:
    """A generated world as a scenario expecting the safety targets: the goal reached, no
    collision, clearance >= D_min. Planner values: `planner`, else D_min, H_d and v_d of
    cfg with the other defaults."""
    cfg = cfg or WorldGenConfig()
    planner = planner or PlannerConfig(h_d_m=cfg.h_d_m, d_min_m=cfg.d_min_m, v_d_mps=cfg.v_d_mps)
    return Scenario(
        name=name or f"random-{gen.seed}",
        description=gen.describe(),
        duration_s=gen.duration_s,
        world=gen.world,
        route=gen.route,
        vehicle=vehicle or VehicleModelConfig(),
        sensors=list(sensors),
        planner=planner,
        expect=Expectation(reached_goal=True, min_clearance_m=planner.d_min_m, collisions=0),
    )


def _dump(model: BaseModel) -> dict[str, Any]:
    data: dict[str, Any] = model.model_dump(mode="json", exclude_defaults=True)
    return data


def scenario_yaml(sc: Scenario, sensors_ref: str | None = None, header: str = "") -> str:
    """The scenario as YAML text that `load_scenario` reads back into an equal Scenario.

    sensors_ref: write `sensors: REF` (a file path relative to where the file will live)
    instead of the list. header: comment lines put on top.
    """
    doc: dict[str, Any] = {"name": sc.name}
    if sc.description:
        doc["description"] = sc.description
    doc["duration_s"] = sc.duration_s
    if sc.dt_s != Scenario.model_fields["dt_s"].default:
        doc["dt_s"] = sc.dt_s
    if sc.start_position is not None:
        doc["start_position"] = list(sc.start_position)
    world: dict[str, Any] = {}
    if sc.world.ground_z_m != 0.0:
        world["ground_z_m"] = sc.world.ground_z_m
    world["features"] = [
        {"type": f.type, "name": f.name, **{k: v for k, v in _dump(f).items() if k != "name"}}
        for f in sc.world.features
    ]
    doc["world"] = world
    doc["route"] = _dump(sc.route)
    doc["vehicle"] = {"model": sc.vehicle.model, **_dump(sc.vehicle)}
    doc["sensors"] = sensors_ref if sensors_ref is not None else [_dump(s) for s in sc.sensors]
    doc["planner"] = sc.planner.model_dump(mode="json", exclude_defaults=True)
    doc["expect"] = _dump(sc.expect)
    if sc.mavlink is not None:
        doc["mavlink"] = sc.mavlink
    body = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=100)
    lines = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines())
    return lines + body
