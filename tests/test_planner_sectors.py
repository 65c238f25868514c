"""Proximity sectors: a reading covers 45 degrees. The simulator reads the nearest object in
the sector (a fan of rays), the planner remembers the reading as an arc across it."""

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.planner import Planner, PlannerParams, Route, VehicleState
from companion.planner.rotations import r_g
from companion.planner.sensors import Group, Role, SensorSpec, sector_fan_flu
from companion.sim.sensing import SECTOR_RAYS, SensorFan
from companion.tuning import SensorConfig, sensor_table

CONFIG = Path(__file__).parent.parent / "config/sensors"


def ring8():  # type: ignore[no-untyped-def]
    specs = yaml.safe_load((CONFIG / "ring-8.yaml").read_text())
    return sensor_table([SensorConfig.model_validate(s) for s in specs])


def planner_over_flat_ground(  # type: ignore[no-untyped-def]
    table, route_end_x: float = 60.0, params: PlannerParams | None = None
):
    """A planner (default params) with the sensor table at (0, 0, 2) heading east along a
    straight route, and the ranges of flat ground 2 m below with nothing in the obstacle
    sensors' reach: (planner, ranges)."""
    route = Route(np.array([[0.0, 0.0], [route_end_x, 0.0]]), 0.0, 0.0)
    planner = Planner(params or PlannerParams(), table, route, np.array([0.0, 0.0, 2.0]))
    ranges = table.max_range_m.copy()
    for i in table.surface_index.values():
        ranges[i] = 2.0 / math.cos(math.pi / 4)
    return planner, ranges


def test_fan_spans_the_sector_about_the_up_axis() -> None:
    u = np.array([math.cos(0.3), math.sin(0.3), 0.0])
    fan = sector_fan_flu(u, math.radians(45.0), 9)
    yaw = np.arctan2(fan[:, 1], fan[:, 0])
    np.testing.assert_allclose(yaw, 0.3 + np.linspace(-1, 1, 9) * math.radians(22.5), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(fan, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(sector_fan_flu(u, 0.0, 9), u[None, :])


def test_ring_layout_declares_its_sectors() -> None:
    table = ring8()
    obstacle = table.fov_rad[table.obstacle_index]
    np.testing.assert_allclose(obstacle, math.radians(45.0))
    assert np.all(table.fov_rad[list(table.surface_index.values())] == 0.0)


def test_bad_fov_is_refused() -> None:
    with pytest.raises(ValueError, match="fov"):
        SensorSpec.from_frd(0, Role.OBSTACLE, Group.FORWARD, [1, 0, 0], 0.2, 10, fov_rad=4.0)
    with pytest.raises(ValueError, match="fov_deg"):
        SensorConfig.model_validate(
            {"id": 0, "role": "obstacle", "group": "F", "orientation": 0, "fov_deg": 200}
        )


def _pillar_raycast(center_xy: tuple[float, float], radius_m: float):  # type: ignore[no-untyped-def]
    """Range along each ray to a vertical cylinder (inf if missed), metres."""
    c = np.array(center_xy)

    def cast(origins: np.ndarray, dirs: np.ndarray, max_range: np.ndarray) -> np.ndarray:
        o, d = origins[:, :2], dirs[:, :2]
        oc = o - c
        a = (d * d).sum(axis=1)
        b = 2.0 * (oc * d).sum(axis=1)
        k = (oc * oc).sum(axis=1) - radius_m**2
        disc = b * b - 4 * a * k
        t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a), np.inf)
        t = np.where((t > 0) & (t < max_range), t, np.inf)
        return t  # the directions are unit vectors

    return cast


def test_a_thin_pillar_between_two_boresights_is_read_by_the_sectors() -> None:
    """A 0.5 m pillar 6 m away at 22.5 degrees, between the front and the 45-degree sector:
    a beam along each boresight misses it, the sectors on both sides read it."""
    table = ring8()
    ang = math.radians(-22.5)  # to the right (FLU yaw negative)
    cast = _pillar_raycast((6.0 * math.cos(ang), 6.0 * math.sin(ang)), 0.25)
    rot = r_g(0.0, 0.0, 0.0)
    beams = SensorFan(table.boresights_flu, np.zeros(len(table)))
    sectors = SensorFan(table.boresights_flu, table.fov_rad)
    pos = np.zeros(3)
    narrow = beams.ranges(cast, pos, rot, table.max_range_m)
    wide = sectors.ranges(cast, pos, rot, table.max_range_m)
    front, right45 = table.index_of_id[0], table.index_of_id[1]
    assert np.isinf(narrow[front]) and np.isinf(narrow[right45])
    assert wide[front] == pytest.approx(5.75, abs=0.05)
    assert wide[right45] == pytest.approx(5.75, abs=0.05)
    assert len(sectors.directions_flu) == 8 * SECTOR_RAYS + 4


def test_a_sector_reading_enters_the_memory_as_an_arc() -> None:
    """A wall ahead read by the front sector only: the memory holds the arc across the
    sector at that range (the object may be anywhere on it), not one point ahead."""
    table = ring8()
    planner, ranges = planner_over_flat_ground(table)
    front = table.index_of_id[0]
    ranges[front] = 4.0
    state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    planner.step(state, ranges, 0.05)
    pts = planner.memory_points_xy
    assert len(pts) >= 5
    bearing = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
    np.testing.assert_allclose(np.hypot(pts[:, 0], pts[:, 1]), 4.0, atol=0.2)
    assert bearing.min() < -20.0 and bearing.max() > 20.0


def _moving_planner(table, point_xyz: tuple[float, float, float]):  # type: ignore[no-untyped-def]
    planner, ranges = planner_over_flat_ground(table, 200.0)
    state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    for _ in range(40):  # up to speed
        res = planner.step(state, ranges, 0.05)
        state = VehicleState(np.array(res.setpoint.position_enu), 0.0, 0.0, 0.0)
    assert res.diagnostics.speed_ref_mps > 0.5
    x = float(res.setpoint.position_enu[0])
    planner._memory.add(np.array([[x + point_xyz[0], point_xyz[1], point_xyz[2]]]), 0)
    return planner, state, ranges


def test_a_sector_carves_in_motion_a_beam_does_not() -> None:
    """Moving, a sector that reads 8 m drops a remembered point 4 m ahead 10 degrees off its
    boresight (it would have read it); a beam along the boresight passes 0.7 m beside it and
    keeps it (a beam carves only at rest)."""
    point = (4.0, -4.0 * math.tan(math.radians(10.0)), 2.0)
    table = ring8()
    planner, state, ranges = _moving_planner(table, point)
    ranges[table.index_of_id[0]] = 8.0
    assert len(planner._memory) == 1
    planner.step(state, ranges, 0.05)
    assert len(planner._memory) == 0
    beams = sensor_table(
        [
            SensorConfig.model_validate({k: v for k, v in s.items() if k != "fov_deg"})
            for s in yaml.safe_load((CONFIG / "ring-8.yaml").read_text())
        ]
    )
    planner, state, ranges = _moving_planner(beams, point)
    ranges[beams.index_of_id[0]] = 8.0
    planner.step(state, ranges, 0.05)
    assert len(planner._memory) == 1
