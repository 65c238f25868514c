"""The stop before an obstacle allows for late readings and a trailing position controller
(`PlannerParams.reaction_time_s`, the vehicle measured ahead of X_d)."""

import itertools
import math

import numpy as np
import pytest

from companion.planner import Decision, Planner, PlannerParams, Route, VehicleState, speed
from companion.tuning import PlannerConfig
from tests.test_planner import SENSORS, flat_ranges

D_MIN = 2.0
TRIGGER = D_MIN + 0.5 * 0.6  # the defaults' re-plan distance, metres


def approach(
    reaction_s: float, allow_ahead: bool, latency_s: float = 0.5, rest_margin: bool = True
) -> float:
    """1-D approach at 1 m/s to a wall 20 m ahead, X_d scheduled as `Planner` does (clearance
    limit, then ramp). The ranges arrive latency_s late and are placed from the position
    now (the wall seems farther by the distance flown meanwhile); the vehicle tracks X_d
    with a second-order position controller (velocity feed-forward), which trails and then
    overshoots a decelerating setpoint. rest_margin: X_d comes to rest v_d t short of the
    trigger (`speed.rest_margin_m`), as `Planner` has it. Returns the vehicle's least true
    clearance, metres."""
    dt, accel, wall = 0.05, 0.5, 20.0
    x_d = v = x = v_x = 0.0
    past = [0.0] * (round(latency_s / dt) + 1)  # vehicle positions, oldest first
    seen = math.inf  # nearest wall point in the memory
    least = math.inf
    wn, zeta = 1.5, 0.6
    for _ in range(int(60.0 / dt)):
        late_range = wall - past[0]
        if late_range < 8.0:
            seen = min(seen, x + late_range)
        look_s = np.arange(x_d, x_d + 25.0, 0.1)
        clearance = np.abs(seen - look_s) if math.isfinite(seen) else np.full(len(look_s), 99.0)
        ahead = max(x - x_d, 0.0) if allow_ahead else 0.0
        margin = speed.rest_margin_m(1.0, reaction_s) if rest_margin else 0.0
        limit = speed.clearance_limit(
            look_s, clearance, x_d, accel, TRIGGER, True, reaction_s, ahead, margin
        )
        v = speed.ramp(v, min(1.0, limit), accel, dt)
        x_d += v * dt
        v_x += (wn * wn * (x_d - x) + 2.0 * zeta * wn * (v - v_x)) * dt
        x += v_x * dt
        past = [*past[1:], x]
        least = min(least, wall - x)
    return least


def test_latency_and_lag_put_the_ideal_stop_inside_d_min() -> None:
    assert approach(0.0, allow_ahead=False) < D_MIN - 0.2


def test_the_reaction_allowance_keeps_d_min() -> None:
    default = PlannerParams().reaction_time_s
    assert 0.3 <= default <= 0.5
    assert approach(default, allow_ahead=True) >= D_MIN + 0.3  # with a margin
    assert approach(default, allow_ahead=True, latency_s=0.7) >= D_MIN  # and later readings
    # the rest point's margin is what leaves room: without it the stop ends at the edge
    assert approach(default, allow_ahead=True, rest_margin=False) < D_MIN + 0.1
    # the reaction allowance and the vehicle-ahead term are both needed in this loop
    assert approach(default, allow_ahead=False, rest_margin=False) < D_MIN
    assert approach(0.0, allow_ahead=True) < D_MIN


def test_rest_margin_is_the_reaction_distance_at_cruise_speed() -> None:
    assert speed.rest_margin_m(1.5, 0.4) == pytest.approx(0.6)
    assert speed.rest_margin_m(1.5, 0.0) == 0.0  # the paper's ideal stop
    look_s = np.arange(0.0, 20.0, 0.1)
    clearance = np.abs(10.0 - look_s)
    plain = speed.clearance_limit(look_s, clearance, 0.0, 0.5, TRIGGER, True, 0.4)
    short = speed.clearance_limit(look_s, clearance, 0.0, 0.5, TRIGGER, True, 0.4, 0.0, 0.4)
    d = 10.0 - TRIGGER - 0.05
    assert plain * 0.4 + plain**2 / 1.0 == pytest.approx(d, abs=0.1)
    assert short * 0.4 + short**2 / 1.0 == pytest.approx(d - 0.4, abs=0.1)


def test_reacting_speed_stops_within_the_distance() -> None:
    for d in (0.05, 0.5, 3.0):
        for t in (0.0, 0.3, 1.0):
            v = speed.reacting_speed(d, 0.5, t)
            assert v * t + v * v / (2 * 0.5) == pytest.approx(d)
    assert speed.reacting_speed(0.5, 0.5, 0.4) < speed.braking_speed(0.5, 0.5)
    assert speed.reacting_speed(0.005, 0.5, 0.4) == 0.0  # no endless creep


def test_band_limit_stops_the_vehicle_at_its_floor() -> None:
    a, t, floor, replan = 0.5, 0.4, 2.0, 2.3
    assert speed.band_limit(2.3, floor, replan, a, t) == math.inf  # outside the band
    caps = [speed.band_limit(c, floor, replan, a, t) for c in (2.25, 2.1, 2.0, 1.95, 1.9)]
    assert all(x > y for x, y in itertools.pairwise(caps))  # slower, nearer
    assert caps[-1] == 0.0  # BAND_CREEP_M below the floor: at rest
    for c, v in zip((2.25, 2.1, 2.0), caps, strict=False):
        # kept up for t, then braking at a: stopped within (c - floor + creep) metres
        assert v * t + v * v / (2.0 * a) == pytest.approx(c - floor + speed.BAND_CREEP_M)


@pytest.mark.parametrize("bad", [-0.1, math.nan, math.inf, 6.0])
def test_bad_reaction_time_is_refused(bad: float) -> None:
    with pytest.raises(ValueError, match="reaction_time_s"):
        PlannerParams(reaction_time_s=bad)
    with pytest.raises(ValueError, match="reaction_time_s"):
        PlannerConfig(reaction_time_s=bad)


def _blocked_planner(reaction_s: float) -> Planner:
    route = Route(np.array([[0.0, 0.0], [60.0, 0.0]]), 0.0, 0.0)
    planner = Planner(
        PlannerParams(reaction_time_s=reaction_s), SENSORS, route, np.array([0.0, 0.0, 2.0])
    )
    angle = np.arange(0.0, 2.0 * math.pi, 0.02)  # a ring of 12 m radius round the start
    ring = np.column_stack([12.0 * np.cos(angle), 12.0 * np.sin(angle), np.full_like(angle, 2.0)])
    planner._memory.add(ring, 0)  # no way out: the planner stops before it
    return planner


def _speeds(planner: Planner, ahead_m: float, cycles: int) -> list[float]:
    out = []
    state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    for _ in range(cycles):
        res = planner.step(state, flat_ranges(2.0), 0.05)
        out.append(res.diagnostics.speed_ref_mps)
        p = np.array(res.setpoint.position_enu)
        p[0] += ahead_m
        state = VehicleState(p, 0.0, 0.0, 0.0)
    return out


def test_the_planner_stops_earlier_for_the_reaction_and_the_vehicle_ahead(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The ring lives only in the memory; the rays, which read "nothing", would carve it.
    monkeypatch.setattr(Planner, "_carve", lambda self, *args: None)
    stops = {}
    for reaction_s, ahead_m in ((0.0, 0.0), (0.4, 0.0), (0.4, 0.3)):
        planner = _blocked_planner(reaction_s)
        speeds = _speeds(planner, ahead_m, 600)
        assert speeds[-1] == 0.0
        stops[(reaction_s, ahead_m)] = planner._xd_prev[0]
        assert (
            planner._blocked
            or planner.step(
                VehicleState(planner._xd_prev, 0.0, 0.0, 0.0), flat_ranges(2.0), 0.05
            ).diagnostics.decision
            is Decision.BLOCKED
        )
    # with the reaction time X_d rests v_d t (0.4 m) short of the paper's stop ...
    assert stops[(0.4, 0.0)] == pytest.approx(stops[(0.0, 0.0)] - 0.4, abs=0.02)
    assert 12.0 - stops[(0.0, 0.0)] > D_MIN
    # ... and with the vehicle measured 0.3 m ahead X_d holds back by as much again
    assert stops[(0.4, 0.3)] == pytest.approx(stops[(0.4, 0.0)] - 0.3, abs=0.02)


def test_blocked_is_said_once_per_stop(monkeypatch: pytest.MonkeyPatch) -> None:
    """A conflict that vanishes for a cycle at rest (a point carved, then seen again) does
    not repeat the "blocked" event."""
    monkeypatch.setattr(Planner, "_carve", lambda self, *args: None)
    planner = _blocked_planner(0.4)
    said = []
    state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    for k in range(600):
        if k in (500, 540):  # the memory empties for one cycle, then has the ring again
            ring = planner._memory
            planner._memory = type(ring)(1.0, 40.0, 4096)
        res = planner.step(state, flat_ranges(2.0), 0.05)
        if k in (500, 540):
            assert res.diagnostics.decision is not Decision.BLOCKED
            planner._memory = ring
        said += [e for e in res.diagnostics.events if e.startswith("blocked")]
        state = VehicleState(np.array(res.setpoint.position_enu), 0.0, 0.0, 0.0)
    assert planner._blocked
    assert len(said) == 1
