"""companion.sim.worldgen: seeded worlds are reproducible, keep their guarantees, load as YAML."""

from __future__ import annotations

import math
from collections import deque
from functools import cache
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.planner.sensors import Group, Role
from companion.sim.scenario import load_scenario
from companion.sim.vehicle import VehicleModelConfig
from companion.sim.world import BoxConfig, MesaConfig, World, WorldConfig
from companion.sim.worldgen import (
    MOTIFS,
    WorldGenConfig,
    WorldGenError,
    corridor_reachable,
    generate,
    occupancy_grid,
    scenario,
    scenario_yaml,
)
from companion.tuning import SensorConfig

SENSORS = Path(__file__).parent.parent / "config" / "sensors"
SEEDS = range(50)


def _layout(name: str) -> list[SensorConfig]:
    data = yaml.safe_load((SENSORS / f"{name}.yaml").read_text(encoding="utf-8"))
    return [SensorConfig.model_validate(d) for d in data]


@cache
def _generated(seed: int):  # type: ignore[no-untyped-def]
    return generate(seed)


def test_same_seed_same_world() -> None:
    a, b = generate(7), generate(7)
    assert a.world == b.world and a.route == b.route and a.duration_s == b.duration_s
    sensors = _layout("paper-11")
    assert scenario_yaml(scenario(7, sensors)) == scenario_yaml(scenario(7, sensors))


def test_seeds_differ() -> None:
    worlds = [_generated(s).world for s in range(5)]
    assert all(worlds[i] != worlds[j] for i in range(5) for j in range(i + 1, 5))


def test_negative_seed_refused() -> None:
    with pytest.raises(ValueError, match="seed"):
        generate(-1)


def test_unknown_motif_refused() -> None:
    with pytest.raises(ValueError, match="unknown motifs"):
        generate(0, WorldGenConfig(motifs=("mesa", "volcano")))


def test_impossible_guarantee_raises() -> None:
    # Base points 200 m clear of every obstacle placed along a 60-200 m route: no draw passes.
    cfg = WorldGenConfig(clear_margin_m=200.0, max_attempts=3, obstacles_per_100m=(4.0, 4.0))
    with pytest.raises(WorldGenError, match="seed 3"):
        generate(3, cfg)


def _bfs(free: np.ndarray, start: tuple[int, int]) -> np.ndarray:
    """Plain breadth-first search, 8-connected: the cells reached from start."""
    ny, nx = free.shape
    seen = np.zeros_like(free)
    seen[start] = True
    queue = deque([start])
    while queue:
        r, c = queue.popleft()
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                rr, cc = r + dr, c + dc
                if 0 <= rr < ny and 0 <= cc < nx and free[rr, cc] and not seen[rr, cc]:
                    seen[rr, cc] = True
                    queue.append((rr, cc))
    return seen


def _inflate(occ: np.ndarray, radius_cells: float) -> np.ndarray:
    """Cells within radius of an occupied cell, by brute force over the occupied cells."""
    rows, cols = np.nonzero(occ)
    yy, xx = np.mgrid[0 : occ.shape[0], 0 : occ.shape[1]]
    out = occ.copy()
    for r, c in zip(rows, cols, strict=True):
        near = (yy - r) ** 2 + (xx - c) ** 2 <= radius_cells**2
        out |= near
    return out


@pytest.mark.parametrize("seed", SEEDS)
def test_guarantees_hold(seed: int) -> None:
    cfg = WorldGenConfig()
    g = _generated(seed)
    world = World(g.world)
    pts = np.array(g.route.points)
    # Route shape as promised.
    assert cfg.base_points[0] <= len(pts) <= cfg.base_points[1]
    legs = np.hypot(*np.diff(pts, axis=0).T)
    assert cfg.route_length_m[0] - 0.01 <= legs.sum() <= cfg.route_length_m[1] + 0.01
    assert g.duration_s > legs.sum() / cfg.v_d_mps
    # Start and base points: D_min + 2 m from every obstacle, 3-D at H_d and horizontally.
    need = cfg.d_min_m + cfg.clear_margin_m
    for x, y in pts:
        z = float(world.height(x, y)) + cfg.h_d_m
        assert world.obstacle_distance((x, y, z)) >= need
        a = np.linspace(0.0, 2.0 * math.pi, 72, endpoint=False)
        for rad in (0.0, need / 2.0, need - 0.01):
            ring = world.obstacle_height(x + rad * np.cos(a), y + rad * np.sin(a))
            assert not np.isfinite(ring).any(), f"footprint within {rad} m of base point"
    # Mesa flanks in range; every solid is an obstacle.
    for f in g.world.features:
        if isinstance(f, MesaConfig):
            assert 30.0 <= f.side_slope_deg <= 85.0
        if f.type in ("mesa", "cylinder", "box"):
            assert f.obstacle
    # A corridor: an independent search on a coarser grid (1 m cells, inflation rounded up).
    cell = 1.0
    bbox = (pts[:, 0].min() - 30, pts[:, 0].max() + 30, pts[:, 1].min() - 30, pts[:, 1].max() + 30)
    grid = occupancy_grid(world, bbox, cell)
    radius = (cfg.d_min_m + cell * math.sqrt(0.5)) / cell
    free = ~_inflate(grid.occ, radius)
    idx = [grid.index(x, y) for x, y in pts]
    reached = _bfs(free, idx[0])
    assert all(reached[r, c] for r, c in idx), "no corridor through the base points"


def test_every_motif_appears() -> None:
    seen = {m for s in SEEDS for m in _generated(s).motifs}
    assert seen == set(MOTIFS)


def test_narrow_gaps_are_wide_enough() -> None:
    """Walls with a gap and passages: the two boxes of the motif keep 2 D_min + 2 m apart."""
    cfg = WorldGenConfig(motifs=("wall_with_gap", "passage"))
    checked = 0
    for seed in range(10):
        boxes = [f for f in generate(seed, cfg).world.features if isinstance(f, BoxConfig)]
        pairs: dict[str, list[BoxConfig]] = {}
        for b in boxes:
            pairs.setdefault(b.name.rsplit(" ", 1)[0], []).append(b)
        for left, right in (p for p in pairs.values() if len(p) == 2):
            w = World(WorldConfig(features=[left]))
            corners = World(WorldConfig(features=[right])).features[0].polygon
            assert corners is not None
            # Distance from the right box's outline (densely sampled) to the left box.
            fine = np.concatenate(
                [np.linspace(corners[i], corners[(i + 1) % 4], 50) for i in range(4)]
            )
            d = min(w.obstacle_distance((x, y, 0.0)) for x, y in fine)
            assert d >= 2 * cfg.d_min_m + cfg.passage_extra_m - 1e-6
            checked += 1
    assert checked >= 5


def test_corridor_search() -> None:
    free = np.ones((20, 30), dtype=bool)
    free[:, 15] = False  # a wall across
    assert not corridor_reachable(free, (10, 2), [(10, 28)])
    assert corridor_reachable(free, (10, 2), [(5, 10)])
    free[12, 15] = True  # a one-cell gap
    assert corridor_reachable(free, (10, 2), [(10, 28), (0, 0)])
    assert not corridor_reachable(free, (10, 15), [(10, 28)])  # start inside the wall


@pytest.mark.parametrize("layout", ["paper-11", "horizontal-7", "ring-8"])
@pytest.mark.parametrize("vehicle", ["ideal", "multicopter"])
def test_yaml_round_trip(tmp_path: Path, layout: str, vehicle: str) -> None:
    sc = scenario(11, _layout(layout), VehicleModelConfig(model=vehicle))  # type: ignore[arg-type]
    inline = tmp_path / "inline.yaml"
    inline.write_text(scenario_yaml(sc, header="seed 11"), encoding="utf-8")
    assert inline.read_text(encoding="utf-8").startswith("# seed 11\n")
    assert load_scenario(inline) == sc
    sub = tmp_path / "scenarios"
    sub.mkdir()
    (tmp_path / "sensors").mkdir()
    (tmp_path / "sensors" / "s.yaml").write_text(
        (SENSORS / f"{layout}.yaml").read_text(encoding="utf-8"), encoding="utf-8"
    )
    ref = sub / "ref.yaml"
    ref.write_text(scenario_yaml(sc, sensors_ref="../sensors/s.yaml"), encoding="utf-8")
    assert load_scenario(ref) == sc
    assert sc.expect.reached_goal and sc.expect.min_clearance_m == sc.planner.d_min_m


def test_layouts() -> None:
    """The sensor layouts load, and their groups are the ones their files describe."""
    for name, n_obstacle in (("paper-11", 7), ("horizontal-7", 7), ("ring-8", 8)):
        table = [s.to_spec() for s in _layout(name)]
        obstacle = [s for s in table if s.role is Role.OBSTACLE]
        surface = {s.group for s in table if s.role is Role.SURFACE}
        assert len(obstacle) == n_obstacle
        assert surface == {
            Group.SURFACE_FORWARD,
            Group.SURFACE_BACK,
            Group.SURFACE_LEFT,
            Group.SURFACE_RIGHT,
        }
        for s in obstacle:
            u = s.boresight_flu  # x forward, y left
            if name != "paper-11":
                assert abs(u[2]) < 1e-9  # horizontal
            if s.group is Group.FORWARD:
                assert u[0] > 0.8
            elif s.group is Group.LEFT:
                assert u[1] > 0.5 or u[0] < -0.99  # the ring's rear sector is in L
            else:
                assert u[1] < -0.5
