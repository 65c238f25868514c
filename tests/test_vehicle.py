"""Tests for sim.vehicle: the ideal tracker and the multicopter model."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from companion.planner.types import Setpoint, VehicleState
from companion.sim.vehicle import (
    IdealTracker,
    Multicopter,
    VehicleModelConfig,
    make_vehicle,
)

START = VehicleState(np.zeros(3), 0.0, 0.0, 0.0)


def sp(
    x: float, y: float, z: float, yaw: float = 0.0, v: tuple[float, ...] = (0, 0, 0)
) -> Setpoint:
    return Setpoint(np.array([x, y, z]), np.array(v, dtype=float), yaw, 0.0)


def test_ideal_tracker_reproduces_setpoint() -> None:
    v = IdealTracker(START)
    s = Setpoint(np.array([3.0, -2.0, 5.5]), np.array([1.0, 0.0, 0.2]), 0.7, -0.3)
    state = v.step(s, 0.1)
    np.testing.assert_array_equal(state.position_enu, s.position_enu)
    # Pitch along the trajectory's tangent (the velocity), as the paper assumes.
    assert (state.roll_rad, state.yaw_rad) == (0.0, 0.7)
    assert state.pitch_rad == pytest.approx(math.atan2(0.2, 1.0))
    assert v.state is state
    # Hovering or climbing straight up: the setpoint's own pitch.
    still = Setpoint(s.position_enu, np.array([0.0, 0.0, 1.0]), 0.7, -0.3)
    assert v.step(still, 0.1).pitch_rad == -0.3
    with pytest.raises(ValueError, match="dt_s"):
        v.step(s, -0.1)


def test_ideal_tracker_pitch_does_not_jump_as_motion_starts() -> None:
    """A MAVLink target carries no pitch (0) and a shaped velocity starting at a slant has a
    steep tangent: the pitch grows with the speed instead of jumping to it."""
    v = IdealTracker(START)
    pitches = []
    for k in range(1, 21):
        h = 0.025 * k  # horizontal speed ramp, m/s; descending at tan 0.6
        s = Setpoint(np.zeros(3), np.array([-h, 0.0, -0.6 * h]), 0.0, 0.0)
        pitches.append(v.step(s, 0.05).pitch_rad)
    steps = np.abs(np.diff([0.0, *pitches]))
    assert steps.max() < 0.11  # rad per 0.05 s tick: about 2 rad/s
    assert pitches[0] == 0.0 and pitches[-1] == pytest.approx(math.atan(-0.6))


def test_multicopter_converges_to_fixed_setpoint() -> None:
    m = Multicopter(START)
    target = sp(4.0, -3.0, 2.0, yaw=1.0)
    for _ in range(300):  # 15 s
        state = m.step(target, 0.05)
    np.testing.assert_allclose(state.position_enu, [4.0, -3.0, 2.0], atol=1e-2)
    np.testing.assert_allclose(m.velocity_enu, 0.0, atol=1e-2)
    assert state.yaw_rad == pytest.approx(1.0)
    assert abs(state.roll_rad) < 1e-3 and abs(state.pitch_rad) < 1e-3


def test_multicopter_tracks_a_moving_reference() -> None:
    m = Multicopter(START)
    dt, lag = 0.05, []
    for k in range(1, 401):
        t = k * dt
        state = m.step(sp(t, 0.0, 0.0, v=(1.0, 0.0, 0.0)), dt)
        lag.append(t - state.position_enu[0])
    assert max(lag) < 0.3
    assert abs(lag[-1]) < 0.05


def _climb_error(
    a_mps2: float, feedforward: bool, dt: float = 0.02, seconds: float = 10.0
) -> float:
    """How far (m) a multicopter ends below a reference climbing along z = a t^2 / 2."""
    m = Multicopter(START)
    accel = np.array([0.0, 0.0, a_mps2 if feedforward else 0.0])
    steps = round(seconds / dt)
    for k in range(1, steps + 1):
        t = k * dt
        z, vz = 0.5 * a_mps2 * t * t, a_mps2 * t
        m.step(Setpoint(np.array([0.0, 0.0, z]), np.array([0.0, 0.0, vz]), 0.0, 0.0, accel), dt)
    return 0.5 * a_mps2 * (steps * dt) ** 2 - float(m.state.position_enu[2])


def test_multicopter_follows_a_climbing_reference_without_lag_with_acceleration_feedforward() -> (
    None
):
    """Without the acceleration fed forward, the position gain must pull the reference's
    acceleration: the error settles a / kp larger. (Both carry the same small lead: each
    step flies towards the setpoint of the step's end.)"""
    a = 0.2  # up to 2 m/s in 10 s, within max_climb
    with_ff, without = _climb_error(a, True), _climb_error(a, False)
    assert abs(with_ff) < 0.05
    assert without - with_ff == pytest.approx(a / VehicleModelConfig().kp_per_s2, rel=0.02)


def test_multicopter_refuses_a_non_finite_acceleration() -> None:
    m = Multicopter(START)
    bad = Setpoint(np.zeros(3), np.zeros(3), 0.0, 0.0, np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(ValueError, match="acceleration"):
        m.step(bad, 0.05)


def test_multicopter_respects_limits() -> None:
    cfg = VehicleModelConfig(
        model="multicopter", max_speed_mps=2.0, max_climb_mps=1.0, max_accel_mps2=2.5
    )
    m = Multicopter(START, cfg)
    far = sp(100.0, 100.0, 100.0)
    prev_v = m.velocity_enu
    for _ in range(200):
        m.step(far, 0.1)
        v = m.velocity_enu
        assert math.hypot(v[0], v[1]) <= 2.0 + 1e-9
        assert abs(v[2]) <= 1.0 + 1e-9
        assert np.linalg.norm(v - prev_v) / 0.1 <= 2.5 + 1e-9
        assert np.linalg.norm(m.acceleration_enu) <= 2.5 + 1e-9
        prev_v = v
    assert math.hypot(*m.velocity_enu[:2]) == pytest.approx(2.0)
    assert m.velocity_enu[2] == pytest.approx(1.0)


@pytest.mark.parametrize("yaw", [0.0, math.pi / 2, -2.5])
def test_multicopter_pitches_nose_down_to_accelerate_forward(yaw: float) -> None:
    m = Multicopter(VehicleState(np.zeros(3), 0.0, 0.0, yaw))
    ahead = sp(5.0 * math.cos(yaw), 5.0 * math.sin(yaw), 0.0, yaw=yaw)
    state = m.step(ahead, 0.05)
    assert state.pitch_rad < -0.1  # nose down
    assert abs(state.roll_rad) < 1e-9
    # Accelerating to the right (right wing down, roll positive).
    m = Multicopter(VehicleState(np.zeros(3), 0.0, 0.0, yaw))
    right = sp(5.0 * math.sin(yaw), -5.0 * math.cos(yaw), 0.0, yaw=yaw)
    state = m.step(right, 0.05)
    assert state.roll_rad > 0.1
    assert abs(state.pitch_rad) < 1e-9
    # Braking: nose up.
    fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    m = Multicopter(VehicleState(np.zeros(3), 0.0, 0.0, yaw), initial_velocity_enu=2.0 * fwd)
    assert m.step(Setpoint(np.zeros(3), np.zeros(3), yaw, 0.0), 0.05).pitch_rad > 0.1


def test_multicopter_yaw_rate_limited_and_wraps() -> None:
    cfg = VehicleModelConfig(model="multicopter", max_yaw_rate_rad_s=1.0)
    m = Multicopter(VehicleState(np.zeros(3), 0.0, 0.0, 3.0), cfg)
    target = sp(0.0, 0.0, 0.0, yaw=-3.0)  # 0.28 rad away across +-pi
    yaws = [m.step(target, 0.1).yaw_rad for _ in range(5)]
    assert yaws[0] == pytest.approx(3.1)  # the short way, at 1 rad/s
    assert yaws[-1] == pytest.approx(-3.0)
    m = Multicopter(START, cfg)
    prev = 0.0
    for _ in range(20):
        y = m.step(sp(0.0, 0.0, 0.0, yaw=2.0), 0.05).yaw_rad
        assert abs(y - prev) <= 0.05 + 1e-12
        prev = y
    assert prev == pytest.approx(1.0)


def test_multicopter_substeps_long_steps() -> None:
    a, b = Multicopter(START), Multicopter(START)
    target = sp(3.0, 1.0, -1.0, yaw=0.5, v=(0.5, 0.0, 0.0))
    for _ in range(10):
        sa = a.step(target, 0.1)
        for _ in range(5):
            sb = b.step(target, 0.02)
    np.testing.assert_allclose(sa.position_enu, sb.position_enu, atol=1e-12)
    assert sa.yaw_rad == pytest.approx(sb.yaw_rad)
    assert a.step(target, 0.0) is a.state


def test_make_vehicle_and_config() -> None:
    assert isinstance(make_vehicle(None, START), IdealTracker)
    assert isinstance(make_vehicle(VehicleModelConfig(), START), IdealTracker)
    m = make_vehicle(VehicleModelConfig.model_validate({"model": "multicopter"}), START)
    assert isinstance(m, Multicopter)
    assert m.state is START
    with pytest.raises(ValidationError, match="kp_per_s2"):
        VehicleModelConfig.model_validate({"kp_per_s2": -1.0})
    with pytest.raises(ValidationError, match="model"):
        VehicleModelConfig.model_validate({"model": "submarine"})
    with pytest.raises(ValidationError, match="max_sped"):
        VehicleModelConfig.model_validate({"max_sped": 3})


@settings(max_examples=40, deadline=None, derandomize=True)
@given(
    target=st.tuples(*(st.floats(-50, 50),) * 3),
    vff=st.tuples(*(st.floats(-8, 8),) * 3),
    yaw=st.floats(-10, 10),
    dt=st.floats(0.005, 0.5),
)
def test_multicopter_limits_hold_for_any_setpoint(
    target: tuple[float, float, float],
    vff: tuple[float, float, float],
    yaw: float,
    dt: float,
) -> None:
    cfg = VehicleModelConfig(model="multicopter")
    m = Multicopter(START, cfg)
    prev_yaw = 0.0
    for _ in range(20):
        s = m.step(Setpoint(np.array(target), np.array(vff), yaw, 0.0), dt)
        v = m.velocity_enu
        assert math.hypot(v[0], v[1]) <= cfg.max_speed_mps + 1e-9
        assert abs(v[2]) <= cfg.max_climb_mps + 1e-9
        assert np.linalg.norm(m.acceleration_enu) <= cfg.max_accel_mps2 + 1e-9
        dyaw = abs((s.yaw_rad - prev_yaw + math.pi) % (2 * math.pi) - math.pi)
        assert dyaw <= cfg.max_yaw_rate_rad_s * dt + 1e-9
        assert -math.pi <= s.yaw_rad < math.pi
        # The tilt matches the horizontal acceleration (at most atan(a_max / g)).
        assert math.hypot(math.tan(s.roll_rad), math.tan(s.pitch_rad)) <= 3.0 / 9.80665 + 1e-9
        prev_yaw = s.yaw_rad
