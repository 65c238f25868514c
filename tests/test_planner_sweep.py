"""The heading's swing across the sensor layout's gaps (`Planner._swept_yaw`,
`sight.sweep_amplitude_rad`, `PlannerParams.yaw_sweep_period_m`)."""

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.harness import metrics as metrics_mod
from companion.harness.closed_loop import run
from companion.planner import PlannerParams, VehicleState
from companion.planner.planner import SWEEP_YAW_RATE_MAX_RAD_S
from companion.planner.sensors import SensorTable
from companion.planner.sight import SWEEP_AMPLITUDE_MAX_RAD, sweep_amplitude_rad
from companion.sim.scenario import load_scenario
from companion.sim.world import World
from companion.tuning import SensorConfig, sensor_table
from tests.test_planner_sectors import planner_over_flat_ground
from tests.test_sight import table

ROOT = Path(__file__).parent.parent


def test_the_swing_is_half_the_widest_gap_ahead() -> None:
    """paper-11: beams at 0, 45 and 90 degrees either side (the 45-degree ones 25 degrees
    up count: a pole or a wall standing on the ground rises into them); horizontal-7: every
    30 degrees; ring-8: 45-degree sectors that touch, no gap."""
    assert sweep_amplitude_rad(table("paper-11.yaml")) == pytest.approx(math.radians(22.5))
    assert sweep_amplitude_rad(table("horizontal-7.yaml")) == pytest.approx(math.radians(15.0))
    assert sweep_amplitude_rad(table("ring-8.yaml")) == 0.0


def test_a_single_beam_swings_no_more_than_the_cap() -> None:
    specs = [s for s in yaml.safe_load((ROOT / "config/sensors/paper-11.yaml").read_text())]
    lone = [s for s in specs if s["role"] == "surface" or s["name"] == "front"]
    layout = sensor_table([SensorConfig.model_validate(s) for s in lone])
    assert sweep_amplitude_rad(layout) == SWEEP_AMPLITUDE_MAX_RAD


def _fly(sensors: SensorTable, params: PlannerParams, cycles: int) -> list:  # type: ignore[type-arg]
    """Flat ground, a 40 m route along +x, the vehicle where the setpoint puts it."""
    planner, ranges = planner_over_flat_ground(sensors, 40.0, params)
    state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    out = []
    for _ in range(cycles):
        res = planner.step(state, ranges, 0.05)
        out.append(res)
        sp = res.setpoint
        state = VehicleState(sp.position_enu, 0.0, sp.pitch_rad, sp.yaw_rad)
    return out


def test_the_heading_swings_once_each_way_per_period_of_travel() -> None:
    """On a straight route along +x the yaw is the swing itself: it reaches the amplitude
    either way, changes sign every half period of X_d's travel, and the path and X_d's
    speed are those of the heading held on the path."""
    params = PlannerParams(yaw_sweep_period_m=4.0)
    results = _fly(table("paper-11.yaml"), params, 1200)
    x = np.array([r.setpoint.position_enu[0] for r in results])
    yaw = np.array([r.setpoint.yaw_rad for r in results])
    moving = (x > 1.0) & (x < 38.0)
    amp = math.radians(22.5)
    assert yaw[moving].max() == pytest.approx(amp, abs=math.radians(0.5))
    assert yaw[moving].min() == pytest.approx(-amp, abs=math.radians(0.5))
    # Sign changes 2 m of travel apart (half a period).
    xs = x[moving]
    flips = xs[1:][np.diff(np.sign(yaw[moving])) != 0]
    assert len(flips) >= 10
    np.testing.assert_allclose(np.diff(flips), 2.0, atol=0.06)
    held = _fly(table("paper-11.yaml"), PlannerParams(yaw_sweep_period_m=0.0), 1200)
    for a, b in zip(results, held, strict=True):
        np.testing.assert_allclose(a.setpoint.position_enu[:2], b.setpoint.position_enu[:2])
        assert a.setpoint.position_enu[2] == pytest.approx(b.setpoint.position_enu[2], abs=1e-3)
        assert b.setpoint.yaw_rad == 0.0
    first = results[0].diagnostics.events[0]
    assert first.startswith("sensor layout leaves a 45 deg gap ahead: the heading swings 22 deg")


def test_at_rest_the_heading_is_the_paths_again() -> None:
    results = _fly(table("paper-11.yaml"), PlannerParams(), 1800)
    assert results[-1].diagnostics.finished
    assert results[-1].setpoint.yaw_rad == pytest.approx(0.0, abs=1e-9)


def test_no_swing_without_a_gap_or_when_off() -> None:
    ring = _fly(table("ring-8.yaml"), PlannerParams(), 400)
    assert all(r.setpoint.yaw_rad == 0.0 for r in ring)
    assert not any("swings" in e for r in ring for e in r.diagnostics.events)
    off = _fly(table("paper-11.yaml"), PlannerParams(yaw_sweep_period_m=0.0), 400)
    assert all(r.setpoint.yaw_rad == 0.0 for r in off)


def test_a_negative_period_is_refused() -> None:
    with pytest.raises(ValueError, match="yaw_sweep_period_m"):
        PlannerParams(yaw_sweep_period_m=-1.0)


@pytest.mark.slow
def test_a_pillar_in_the_gap_is_seen_in_time_only_with_the_swing() -> None:
    """`pillar-in-gap-paper`: a 0.6 m pillar 0.9 m beside the route, between the paper
    layout's beams. With the heading on the path it is seen inside D_min; swinging, from
    afar, and passed at D_min or more."""
    path = ROOT / "config/scenarios/pillar-in-gap-paper.yaml"
    scenario = load_scenario(path)
    world = World.from_config(scenario.world, path.parent)
    clearance = {}
    for period in (0.0, 4.0):
        planner = scenario.planner.model_copy(update={"yaw_sweep_period_m": period})
        flown = scenario.model_copy(update={"planner": planner})
        m = metrics_mod.for_run(flown, world, run(flown, world))
        assert m["reached_goal"]
        clearance[period] = m["min_clearance_m"]
    assert clearance[0.0] < 1.5
    assert clearance[4.0] >= scenario.planner.d_min_m


def test_a_fast_x_d_swings_no_faster_than_the_rate_cap() -> None:
    """v_d 3 m/s (2.44 m/s, the layout's limit): a swing per 4 m would turn at 1.5 rad/s;
    the phase advances slower instead, and the swing still reaches its amplitude."""
    results = _fly(table("paper-11.yaml"), PlannerParams(v_d_mps=3.0), 800)
    yaw = np.array([r.setpoint.yaw_rad for r in results])
    speed = np.array([r.diagnostics.speed_ref_mps for r in results])
    assert speed.max() > 2.4
    moving = speed[1:] > 0.1  # (at rest the heading turns back at the rate at rest)
    assert np.abs(np.diff(yaw))[moving].max() <= SWEEP_YAW_RATE_MAX_RAD_S * 0.05 + 1e-12
    assert np.abs(yaw).max() == pytest.approx(math.radians(22.5), abs=math.radians(0.5))
