"""Free-space carving: remembered points that later rays see through are dropped."""

import math

import numpy as np
import pytest

from companion.planner import Decision, Planner, PlannerParams, Route, VehicleState
from companion.planner.memory import ObstacleMemory
from companion.planner.types import PathMode
from tests.test_planner import SENSORS, flat_ranges


def memory_with(points: list[tuple[float, float, float]]) -> ObstacleMemory:
    mem = ObstacleMemory(0.25, 40.0, 4096)
    mem.add(np.array(points), 0)
    return mem


def test_a_ray_that_sees_beyond_a_point_drops_it() -> None:
    mem = memory_with([(5.0, 0.05, 2.0), (5.0, 3.0, 2.0)])
    gone = mem.carve(np.array([0.0, 0.0, 2.0]), np.array([[1.0, 0.0, 0.0]]), np.array([9.5]), 0.25)
    assert gone == 1
    assert np.allclose(mem.points_xy(), [[5.0, 3.0]])  # off the ray: kept


def test_points_at_the_end_beside_or_behind_the_ray_stay() -> None:
    origin = np.array([0.0, 0.0, 2.0])
    ray = np.array([[1.0, 0.0, 0.0]])
    # the ray ends on a wall at 6 m (carved up to 5.5 m): the wall's points stay, and so do
    # points 0.3 m beside the ray (grazed) and behind the sensor
    mem = memory_with([(6.0, 0.0, 2.0), (5.6, 0.1, 2.0), (3.0, 0.3, 2.0), (-2.0, 0.0, 2.0)])
    assert mem.carve(origin, ray, np.array([5.5]), 0.25) == 0
    assert len(mem) == 4
    # in 3-D: a point 1 m above the ray stays
    mem = memory_with([(3.0, 0.0, 3.0)])
    assert mem.carve(origin, ray, np.array([9.5]), 0.25) == 0


def test_carving_is_deterministic() -> None:
    rng = np.random.default_rng(3)
    pts = [tuple(p) for p in rng.uniform([-5, -5, 0], [5, 5, 4], (200, 3))]
    dirs = rng.normal(size=(11, 3))
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    a, b = memory_with(pts), memory_with(pts)
    na = a.carve(np.zeros(3), dirs, np.full(11, 8.0), 0.5)
    nb = b.carve(np.zeros(3), dirs, np.full(11, 8.0), 0.5)
    assert na == nb > 0
    assert np.array_equal(a.points_xy(), b.points_xy())


def _fly_with_one_spurious_echo(carve: bool, monkeypatch: pytest.MonkeyPatch) -> tuple:  # type: ignore[type-arg]
    if not carve:
        monkeypatch.setattr(Planner, "_carve", lambda self, *args: None)
    route = Route(np.array([[0.0, 0.0], [40.0, 0.0]]), 0.0, 0.0)
    planner = Planner(PlannerParams(), SENSORS, route, np.array([0.0, 0.0, 2.0]))
    here = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    out = []
    for k in range(200):
        ranges = flat_ranges(2.0)
        if k == 20:  # one cycle of echoes 2.5 m away on every obstacle sensor: phantoms
            ranges[SENSORS.obstacle_index] = 2.5
        res = planner.step(here, ranges, 0.05)
        out.append(res)
        here = VehicleState(res.setpoint.position_enu, 0.0, 0.0, res.setpoint.yaw_rad)
    return out, planner


@pytest.mark.parametrize("carve", [True, False])
def test_phantoms_that_later_rays_see_through_end_the_blocked_state(
    carve: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    out, planner = _fly_with_one_spurious_echo(carve, monkeypatch)
    assert out[20].diagnostics.decision is Decision.BLOCKED  # the phantoms block at first
    last = out[-1].diagnostics
    if carve:  # the next cycle's rays see nothing where they are: cleared, flying on
        assert last.decision is not Decision.BLOCKED
        assert last.speed_ref_mps == pytest.approx(1.0)
        assert out[-1].setpoint.position_enu[0] > 5.0
    else:  # without carving the phantoms stay: no flying on through them
        phantoms = planner.memory_points_xy
        assert len(phantoms) > 0
        # Stopped for good, or (the last resort) straight legs round them that keep D_min.
        assert last.decision is Decision.BLOCKED or last.mode is PathMode.AROUND
        for res in out[20:]:
            xy = res.setpoint.position_enu[:2]
            assert float(np.min(np.hypot(*(phantoms - xy).T))) >= PlannerParams().d_min_m


def test_a_wall_the_rays_end_on_is_kept() -> None:
    route = Route(np.array([[0.0, 0.0], [40.0, 0.0]]), 0.0, 0.0)
    planner = Planner(PlannerParams(), SENSORS, route, np.array([0.0, 0.0, 2.0]))
    ys = np.arange(-30.0, 30.01, 0.25)
    planner._memory.add(np.column_stack([np.full_like(ys, 3.0), ys, np.full_like(ys, 2.0)]), 0)
    before = len(planner.memory_points_xy)
    ranges = flat_ranges(2.0)
    for i in SENSORS.obstacle_index:  # every obstacle ray ends on the wall plane x = 3
        u = SENSORS.boresights_flu[i]
        if u[0] > 1e-6:
            ranges[i] = 3.0 / u[0] if 3.0 / u[0] < SENSORS.max_range_m[i] else math.nan
    planner.step(VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0), ranges, 0.05)
    assert len(planner.memory_points_xy) >= before


def test_a_sector_carves_across_its_width_only() -> None:
    """A 45-degree sector (boresight +x, level) that read 6 m: nothing is nearer anywhere
    across it. Points inside its width nearer than 5.5 m go, also one 1 m above its plane
    (the planner keeps D_min from a point at every height, as from a solid rising from the
    ground, and that solid would cross the sector's plane); those outside its width, beyond
    its range, or 1 m below its plane (a solid lower than the sector) stay."""
    inside = [(4.0, 4.0 * math.tan(math.radians(20.0)), 2.0), (3.0, 0.0, 2.0), (2.0, 0.5, 3.0)]
    outside = [(4.0, 4.0 * math.tan(math.radians(30.0)), 2.0), (7.0, 0.0, 2.0), (2.5, -0.5, 1.0)]
    mem = memory_with(inside + outside)
    gone = mem.carve_sectors(
        np.array([0.0, 0.0, 2.0]),
        np.array([0.0, 0.0, 1.0]),
        np.array([[1.0, 0.0, 0.0]]),
        np.array([math.radians(22.5)]),
        np.array([5.5]),
        0.25,
    )
    assert gone == 3
    kept = {tuple(np.round(p, 3)) for p in mem.points_xy()}
    assert kept == {tuple(np.round(p[:2], 3)) for p in outside}
    # the same points, a beam along the boresight: only the one on it goes
    mem = memory_with(inside + outside)
    ray = np.array([[1.0, 0.0, 0.0]])
    assert mem.carve(np.array([0.0, 0.0, 2.0]), ray, np.array([5.5]), 0.25) == 1
