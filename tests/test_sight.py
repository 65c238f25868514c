"""sight.py: how far ahead a layout flags a wall, the speed that can stop within it, and
where ahead no obstacle sensor looks level."""

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.planner import Planner, PlannerParams, Route, VehicleState
from companion.planner.sensors import (
    Group,
    Role,
    SensorSpec,
    SensorTable,
    boresight_from_rpy_frd,
)
from companion.planner.sight import (
    describe_level_gaps,
    layout_speed_limit_mps,
    level_gaps_deg,
    wall_flag_distance_m,
)
from companion.tuning import SensorConfig, sensor_table

CONFIG = Path(__file__).parent.parent / "config/sensors"


def table(name: str):  # type: ignore[no-untyped-def]
    specs = yaml.safe_load((CONFIG / name).read_text())
    return sensor_table([SensorConfig.model_validate(s) for s in specs])


def test_level_sensors_flag_a_wall_only_near() -> None:
    """Level rays, surface rays 45 degrees down: the chord from the ground point H_d ahead
    to a wall hit d ahead is steeper than phi_max only for d < H_d + H_d / tan(phi_max)."""
    d = wall_flag_distance_m(table("horizontal-7.yaml"), 2.0, 0.6)
    assert d == pytest.approx(2.0 + 2.0 / math.tan(0.6), abs=0.06)


def test_upward_sensors_flag_a_wall_far() -> None:
    """The paper's 30-degree-up ray climbs almost as fast as phi_max: it flags a wall
    across the path as far as its range reaches."""
    d = wall_flag_distance_m(table("paper-11.yaml"), 2.0, 0.6)
    assert d == pytest.approx(12.0 * math.cos(math.radians(30.0)), abs=0.06)


def test_speed_limit_stops_within_the_room() -> None:
    v = layout_speed_limit_mps(4.9, 2.3, 0.5, 0.05)
    assert v * 0.05 + v * v / (2 * 0.5) == pytest.approx(4.9 - 2.3)
    assert layout_speed_limit_mps(2.0, 2.3, 0.5, 0.05) == 0.0


def test_speed_limit_includes_the_reaction_and_the_lead() -> None:
    """The stop as planned: a cycle at v, the reaction time at v, the rest point v t short,
    the vehicle's lead; all of it within the distance the layout can confirm."""
    v = layout_speed_limit_mps(4.9, 2.3, 0.5, 0.05, reaction_s=0.4)
    assert v * (0.05 + 0.4) + v * 0.4 + v * v / (2 * 0.5) == pytest.approx(4.9 - 2.3)
    assert v < layout_speed_limit_mps(4.9, 2.3, 0.5, 0.05)
    lead = layout_speed_limit_mps(4.9, 2.3, 0.5, 0.05, reaction_s=0.4, allowance_m=0.5)
    assert lead * 0.85 + lead * lead / (2 * 0.5) == pytest.approx(4.9 - 2.3 - 0.5)
    assert layout_speed_limit_mps(4.9, 2.3, 0.5, 0.05, reaction_s=0.4, allowance_m=3.0) == 0.0


def _over_flat_ground_at_3_mps() -> tuple[
    SensorTable, PlannerParams, Planner, np.ndarray, VehicleState
]:
    """A planner with the level layout (horizontal-7) and v_d = 3 m/s, above what it can
    stop for, over flat ground 2 m below: (sensors, params, planner, ranges, state)."""
    sensors = table("horizontal-7.yaml")
    params = PlannerParams(v_d_mps=3.0, accel_max_mps2=1.0)
    route = Route(np.array([[0.0, 0.0], [200.0, 0.0]]), 0.0, 0.0)
    planner = Planner(params, sensors, route, np.array([0.0, 0.0, 2.0]))
    ranges = sensors.max_range_m.copy()
    for i in sensors.surface_index.values():
        ranges[i] = 2.0 / math.cos(math.pi / 4)
    state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    return sensors, params, planner, ranges, state


def test_planner_announces_and_applies_the_layout_limit() -> None:
    """With v_d above what a level layout can stop for, X_d never exceeds the limit."""
    sensors, params, planner, ranges, state = _over_flat_ground_at_3_mps()
    events: list[str] = []
    speeds = []
    for _ in range(200):
        res = planner.step(state, ranges, 0.05)
        events += res.diagnostics.events
        speeds.append(res.diagnostics.speed_ref_mps)
        # The vehicle follows X_d (one left behind would hold it on the leash).
        state = VehicleState(np.array(res.setpoint.position_enu), 0.0, 0.0, 0.0)
    flag = wall_flag_distance_m(sensors, 2.0, 0.6)
    limit = layout_speed_limit_mps(flag, 2.3, 1.0, 0.05, params.reaction_time_s)
    assert limit < layout_speed_limit_mps(flag, 2.3, 1.0, 0.05) < 3.0
    assert max(speeds) == pytest.approx(limit, rel=1e-6)
    assert sum("speed limited" in e for e in events) == 1


def test_a_jittering_period_announces_the_layout_limit_once() -> None:
    """The service steps with the period it measured, different every cycle: the limit
    follows each cycle's period, and the pilot is told once, not every cycle."""
    sensors, params, planner, ranges, state = _over_flat_ground_at_3_mps()
    flag = wall_flag_distance_m(sensors, 2.0, 0.6)
    events: list[str] = []
    for k in range(200):
        dt = 0.05 + 0.004 * math.sin(1.7 * k)
        res = planner.step(state, ranges, dt)
        events += res.diagnostics.events
        limit = layout_speed_limit_mps(flag, 2.3, 1.0, dt, params.reaction_time_s)
        assert res.diagnostics.speed_ref_mps <= limit * (1 + 1e-9)
        state = VehicleState(np.array(res.setpoint.position_enu), 0.0, 0.0, 0.0)
    assert sum("speed limited" in e for e in events) == 1


def test_the_vehicle_ahead_of_x_d_lowers_the_layout_limit() -> None:
    """A vehicle measured ahead of its setpoint (an overshooting position controller) has
    that much less room: the layout's limit drops while it lasts."""
    sensors, _, planner, ranges, state = _over_flat_ground_at_3_mps()
    speeds = []
    for _ in range(200):
        res = planner.step(state, ranges, 0.05)
        speeds.append(res.diagnostics.speed_ref_mps)
        ahead = np.array(res.setpoint.position_enu) + np.array([0.6, 0.0, 0.0])
        state = VehicleState(ahead, 0.0, 0.0, 0.0)
    flag = wall_flag_distance_m(sensors, 2.0, 0.6)
    limit = layout_speed_limit_mps(flag, 2.3, 1.0, 0.05, 0.4, allowance_m=0.6)
    assert max(speeds) == pytest.approx(limit, rel=1e-6)
    assert limit < layout_speed_limit_mps(flag, 2.3, 1.0, 0.05, 0.4)


def test_the_paper_layout_looks_level_only_ahead_and_abeam() -> None:
    """Level beams at -90, 0 and 90 degrees; the three up-tilted beams do not count."""
    assert level_gaps_deg(table("paper-11.yaml")) == [(-90.0, 0.0), (0.0, 90.0)]


def test_level_beams_30_degrees_apart_leave_30_degree_gaps() -> None:
    gaps = level_gaps_deg(table("horizontal-7.yaml"))
    assert len(gaps) == 6
    assert all(b - a == pytest.approx(30.0) for a, b in gaps)
    assert sorted(gaps)[0] == pytest.approx((-90.0, -60.0))


def test_sectors_that_touch_cover_the_half_ahead() -> None:
    layout = table("ring-8.yaml")
    assert level_gaps_deg(layout) == []
    assert describe_level_gaps(layout) == "level obstacle sensors cover the half ahead"


def _layout(*sensors: tuple[float, float, float]) -> SensorTable:
    """Obstacle sensors (bearing deg right of the nose, elevation deg up, fov deg) and the
    forward and back surface sensors every table needs."""
    specs = [
        SensorSpec.from_frd(
            i,
            Role.OBSTACLE,
            Group.FORWARD,
            boresight_from_rpy_frd(0.0, math.radians(el), math.radians(b)),
            0.2,
            12.0,
            fov_rad=math.radians(fov),
        )
        for i, (b, el, fov) in enumerate(sensors)
    ]
    n = len(specs)
    for k, (group, yaw) in enumerate(((Group.SURFACE_FORWARD, 0.0), (Group.SURFACE_BACK, 180.0))):
        down = boresight_from_rpy_frd(0.0, math.radians(-45.0), math.radians(yaw))
        specs.append(SensorSpec.from_frd(n + k, Role.SURFACE, group, down, 0.2, 10.0))
    return SensorTable(specs)


def test_gaps_count_sectors_widths_and_leave_out_tilted_sensors() -> None:
    """A 100-degree sector on the nose, level beams 70 degrees out each side, and a beam 80
    degrees right but 20 degrees up (not level): gaps 50-70 and 70-90 on each side, all 20
    degrees wide, so from the left."""
    layout = _layout((0.0, 0.0, 100.0), (-70.0, 0.0, 0.0), (70.0, 0.0, 0.0), (80.0, 20.0, 0.0))
    gaps = level_gaps_deg(layout)
    assert gaps == [(-90.0, -70.0), (-70.0, -50.0), (50.0, 70.0), (70.0, 90.0)]
    line = describe_level_gaps(layout)
    assert line.startswith("4 bearing gap(s) ahead without a level obstacle sensor, the widest")
    assert "the widest 20 deg (90 deg left to 70 deg left)" in line
    # A solid between two rays 20 degrees apart meets one within w / (2 sin 10 deg).
    assert f"{1.0 / (2.0 * math.sin(math.radians(10.0))):.1f} m per metre" in line


def test_a_layout_with_no_level_sensor_has_one_gap_across_the_half_ahead() -> None:
    assert level_gaps_deg(_layout((0.0, 30.0, 0.0))) == [(-90.0, 90.0)]
