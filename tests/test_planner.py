"""Planner.step: determinism, terrain following on flat ground, controls and bad input."""

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.planner import ArcMethod, Decision, Planner, PlannerParams, Route, VehicleState
from companion.planner.planner import ACCEL_FEEDFORWARD_MAX_MPS2
from companion.planner.sensors import Group
from companion.tuning import SensorConfig, sensor_table

SENSORS = sensor_table(
    [
        SensorConfig.model_validate(s)
        for s in yaml.safe_load(
            (Path(__file__).parent.parent / "config/sensors/paper-11.yaml").read_text()
        )
    ]
)


def flat_ranges(height: float) -> np.ndarray:
    """What the paper's sensors read at `height` over flat ground with nothing around."""
    r = SENSORS.max_range_m.copy()
    for i in SENSORS.surface_index.values():
        r[i] = height / math.cos(math.pi / 4)
    return r


def make(params: PlannerParams | None = None, z: float = 2.0) -> Planner:
    route = Route(np.array([[0.0, 0.0], [40.0, 0.0]]), 0.0, 0.0)
    return Planner(params or PlannerParams(), SENSORS, route, np.array([0.0, 0.0, z]))


def fly(planner: Planner, cycles: int, height: float = 2.0) -> list:  # type: ignore[type-arg]
    out = []
    state = VehicleState(np.array([0.0, 0.0, height]), 0.0, 0.0, 0.0)
    for _ in range(cycles):
        res = planner.step(state, flat_ranges(height), 0.05)
        out.append(res)
        sp = res.setpoint
        state = VehicleState(sp.position_enu, 0.0, sp.pitch_rad, sp.yaw_rad)
    return out


def test_same_input_same_output() -> None:
    a, b = fly(make(), 100), fly(make(), 100)
    for ra, rb in zip(a, b, strict=True):
        np.testing.assert_array_equal(ra.setpoint.position_enu, rb.setpoint.position_enu)
        assert ra.diagnostics.decision == rb.diagnostics.decision


def test_flat_ground_flies_level_at_v_d() -> None:
    results = fly(make(), 200)
    last = results[-1]
    assert last.diagnostics.decision is Decision.VERTICAL
    assert last.setpoint.pitch_rad == pytest.approx(0.0, abs=1e-12)
    assert last.setpoint.position_enu[2] == pytest.approx(2.0, abs=1e-9)
    assert last.diagnostics.speed_ref_mps == pytest.approx(1.0)
    np.testing.assert_allclose(last.setpoint.velocity_enu, [1.0, 0.0, 0.0], atol=1e-9)
    # Started from rest, ramped at accel_max, then 1 m/s: 10 s -> 10 m - v^2 / (2 a).
    assert last.setpoint.position_enu[0] == pytest.approx(10.0 - 1.0, abs=0.06)


def test_the_acceleration_fed_forward_is_the_change_of_x_d_velocity() -> None:
    """Ramping up at accel_max, cruising, braking to the goal: the setpoint's acceleration
    is the velocity's change over the cycle (m/s^2, ENU), within the feed-forward cap."""
    results = fly(make(), 1000)
    dt, a_max = 0.05, PlannerParams().accel_max_mps2
    prev = np.zeros(3)
    for r in results:
        sp = r.setpoint
        np.testing.assert_allclose(sp.acceleration_enu, (sp.velocity_enu - prev) / dt, atol=1e-9)
        assert np.linalg.norm(sp.acceleration_enu) <= ACCEL_FEEDFORWARD_MAX_MPS2 + 1e-12
        prev = sp.velocity_enu
    along = [r.setpoint.acceleration_enu[0] for r in results]
    assert along[0] == pytest.approx(a_max) and along[100] == pytest.approx(0.0, abs=1e-9)
    braking = [a for a in along if a < -0.05]  # to the goal, at about accel_max
    assert float(np.median(braking)) == pytest.approx(-a_max, rel=0.05)


def test_reaches_the_goal_and_stops() -> None:
    results = fly(make(), 1000)
    done = [r for r in results if r.diagnostics.finished]
    assert done, "never finished"
    np.testing.assert_allclose(done[0].setpoint.position_enu[:2], [40.0, 0.0], atol=0.05)
    assert done[0].diagnostics.speed_ref_mps == 0.0


def test_at_rest_x_d_moves_to_a_new_h_d_within_its_limits() -> None:
    """Stopped at the goal over flat ground (z = 0) with H_d raised to 3 m: X_d climbs to
    3 m and stops there, no faster than half the path's vertical speed at phi_max, speeding
    up and slowing down at accel_max, with the climb fed forward as velocity and reported as
    the reference speed; it does not move horizontally. (Eq. (5) alone moves X_d only along
    its path: at rest it held 2 m.)"""
    params = PlannerParams()
    planner = make(params)
    state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    for _ in range(1000):
        res = planner.step(state, flat_ranges(float(state.position_enu[2])), 0.05)
        state = VehicleState(res.setpoint.position_enu, 0.0, 0.0, res.setpoint.yaw_rad)
        if res.diagnostics.finished:
            break
    assert res.diagnostics.finished
    goal_xy = res.setpoint.position_enu[:2].copy()
    planner.set_desired_height(3.0)
    z = [float(state.position_enu[2])]
    vz = [0.0]
    for _ in range(200):
        res = planner.step(state, flat_ranges(float(state.position_enu[2])), 0.05)
        sp = res.setpoint
        np.testing.assert_allclose(sp.position_enu[:2], goal_xy, atol=1e-9)
        np.testing.assert_allclose(sp.velocity_enu[:2], 0.0, atol=1e-12)
        assert sp.velocity_enu[2] == pytest.approx((float(sp.position_enu[2]) - z[-1]) / 0.05)
        assert res.diagnostics.speed_ref_mps == pytest.approx(abs(float(sp.velocity_enu[2])))
        z.append(float(sp.position_enu[2]))
        vz.append(float(sp.velocity_enu[2]))
        state = VehicleState(sp.position_enu, 0.0, 0.0, sp.yaw_rad)
    top = 0.5 * params.v_d_mps * math.sin(params.phi_max_rad)
    assert max(vz) == pytest.approx(top) and min(vz) >= 0.0
    assert max(np.abs(np.diff(vz))) <= params.accel_max_mps2 * 0.05 + 1e-12
    assert max(z) < 3.001 and z[-1] == pytest.approx(3.0, abs=1e-3) and vz[-1] == 0.0


def test_paper_arc_method_agrees_with_exact() -> None:
    exact = fly(make(PlannerParams(arc_method=ArcMethod.EXACT)), 300)
    paper = fly(make(PlannerParams(arc_method=ArcMethod.PAPER, paper_delta=1e-5)), 300)
    gap = np.linalg.norm(exact[-1].setpoint.position_enu - paper[-1].setpoint.position_enu)
    assert gap < 0.05  # the search overshoots by up to |B'| delta per cycle


def test_higher_h_d_ramps_up_within_phi_max() -> None:
    planner = make()
    fly(planner, 40)
    planner.set_desired_height(4.0)
    results = fly(planner, 5)
    assert all(0 < r.setpoint.pitch_rad <= 0.6 for r in results)
    with pytest.raises(ValueError, match="H_d"):
        planner.set_desired_height(float("nan"))


def test_replace_route_keeps_position_and_heading() -> None:
    planner = make()
    last = fly(planner, 60)[-1]
    diag = last.diagnostics
    heading = planner.path.segments[diag.segment].heading(diag.parameter)  # (the yaw swings)
    planner.replace_route(np.array([[30.0, 20.0]]), math.pi / 2)
    assert planner.path.heading(0.0) == pytest.approx(heading, abs=1e-9)
    np.testing.assert_allclose(planner.path.point(0.0), last.setpoint.position_enu[:2], atol=1e-9)


@pytest.mark.parametrize(
    ("ranges", "dt", "match"),
    [
        (np.zeros(3), 0.05, "expected 11 ranges"),
        (flat_ranges(2.0), 0.0, "dt_s"),
        (flat_ranges(2.0), float("nan"), "dt_s"),
    ],
)
def test_bad_input_is_refused(ranges: np.ndarray, dt: float, match: str) -> None:
    planner = make()
    state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match=match):
        planner.step(state, ranges, dt)


def test_nan_ranges_mean_nothing_detected_and_hold_altitude() -> None:
    planner = make()
    state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    res = planner.step(state, np.full(11, np.nan), 0.05)
    assert not res.diagnostics.surface_valid
    assert res.setpoint.pitch_rad == 0.0
    with pytest.raises(ValueError, match="finite"):
        VehicleState(np.array([0.0, np.nan, 2.0]), 0.0, 0.0, 0.0)


def test_descends_on_the_forward_ground_point_when_the_backward_sensor_has_none() -> None:
    """A vehicle pitched nose-down looks past the ground behind it (or the service could not
    pair the reading with an attitude): X_d keeps descending to H_d above the ground the
    forward sensor measures, instead of holding its height for want of eq. (3)'s second
    point."""
    planner = make(z=4.0)
    back = SENSORS.surface_index[Group.SURFACE_BACK]
    state = VehicleState(np.array([0.0, 0.0, 4.0]), 0.0, 0.0, 0.0)
    pitches = []
    for _ in range(200):
        ranges = flat_ranges(float(state.position_enu[2]))
        ranges[back] = math.nan
        res = planner.step(state, ranges, 0.05)
        pitches.append(res.setpoint.pitch_rad)
        sp = res.setpoint  # a body that stays level, as the ranges above assume
        state = VehicleState(sp.position_enu, 0.0, 0.0, sp.yaw_rad)
    assert not res.diagnostics.surface_valid  # (the diagnostic still says so)
    assert min(pitches) == pytest.approx(-0.6)
    assert state.position_enu[2] == pytest.approx(2.0, abs=0.02)


def test_start_far_from_the_route_is_refused() -> None:
    route = Route(np.array([[0.0, 0.0], [40.0, 0.0]]))
    with pytest.raises(ValueError, match="prepend the vehicle position"):
        Planner(PlannerParams(), SENSORS, route, np.array([5.0, 5.0, 2.0]))
