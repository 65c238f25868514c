"""X_d waits for a vehicle that does not follow (`PlannerParams.leash_m`): it slows from half
the leash, stops at the leash, says so, goes on when the vehicle closes up, and a route is
not called done with the vehicle elsewhere."""

import math

import numpy as np
import pytest

from companion.planner import PlannerParams, VehicleState, speed
from companion.tuning import PlannerConfig
from tests.test_planner import flat_ranges, make

DT = 0.05


def hold_vehicle(leash_m: float, stuck_x: float, cycles: int) -> tuple[list, float]:  # type: ignore[type-arg]
    """Fly the 40 m straight route with a vehicle that follows X_d until x = stuck_x and
    stays there (landed, held back): the results and where the vehicle stays (x)."""
    planner = make(PlannerParams(leash_m=leash_m))
    state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    out = []
    for _ in range(cycles):
        res = planner.step(state, flat_ranges(2.0), DT)
        out.append(res)
        sp = res.setpoint.position_enu
        x = min(float(sp[0]), stuck_x)
        state = VehicleState(np.array([x, float(sp[1]), float(sp[2])]), 0.0, 0.0, 0.0)
    return out, float(state.position_enu[0])


def test_leash_limit_is_full_speed_to_half_then_a_stop_at_the_leash() -> None:
    assert speed.leash_limit(0.0, 2.0, 1.0, 0.5) == 1.0
    assert speed.leash_limit(1.0, 2.0, 0.7, 0.5) == 0.7  # the same float up to half the leash
    assert speed.leash_limit(1.5, 2.0, 1.0, 0.5) == pytest.approx(math.sqrt(0.5))
    assert speed.leash_limit(1.5, 2.0, 0.2, 0.5) == 0.2
    assert speed.leash_limit(1.995, 2.0, 1.0, 0.5) == 0.0  # at rest just short of it
    assert speed.leash_limit(9.0, 2.0, 1.0, 0.5) == 0.0


def test_x_d_waits_at_the_leash_for_a_stuck_vehicle_and_says_so() -> None:
    results, x_vehicle = hold_vehicle(2.0, stuck_x=10.0, cycles=1200)  # 60 s: 40 m at 1 m/s
    far = max(float(r.setpoint.position_enu[0]) for r in results) - x_vehicle
    # X_d brakes at accel_max from where the lag reaches half the leash: a little past it.
    assert far <= 2.0 + 0.1
    assert far > 1.5  # it did go on while the vehicle followed, and somewhat beyond
    assert results[-1].diagnostics.speed_ref_mps == 0.0
    assert not any(r.diagnostics.finished for r in results)
    events = [e for r in results for e in r.diagnostics.events]
    waits = [e for e in events if "waiting for it to follow" in e]
    assert len(waits) == 1, events
    assert "leash 2 m" in waits[0]


def test_without_the_leash_x_d_runs_away_and_the_route_is_called_done() -> None:
    # The behaviour the leash replaces, measured with a leash longer than the route.
    results, x_vehicle = hold_vehicle(1000.0, stuck_x=10.0, cycles=1200)
    assert any(r.diagnostics.finished for r in results)
    assert float(results[-1].setpoint.position_enu[0]) - x_vehicle > 25.0


def test_x_d_goes_on_when_the_vehicle_closes_up() -> None:
    planner = make(PlannerParams(leash_m=2.0))
    state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    events: list[str] = []
    x_stuck = 5.0
    for k in range(1600):
        res = planner.step(state, flat_ranges(2.0), DT)
        events += res.diagnostics.events
        sp = res.setpoint.position_enu
        # Held back for the first 30 s, then free to follow again.
        x = float(sp[0]) if k > 600 else min(float(sp[0]), x_stuck)
        state = VehicleState(np.array([x, float(sp[1]), float(sp[2])]), 0.0, 0.0, 0.0)
        if res.diagnostics.finished:
            break
    assert res.diagnostics.finished
    np.testing.assert_allclose(res.setpoint.position_enu[:2], [40.0, 0.0], atol=0.05)
    assert [e for e in events if "leash" in e or "following again" in e] == [
        "vehicle 2.0 m from the setpoint (leash 2 m): waiting for it to follow",
        "vehicle following again",
    ]


def test_a_vehicle_within_half_the_leash_flies_as_without_it() -> None:
    # Trailing by a constant 0.8 m (a position controller's lag at 1 m/s): the same X_d.
    def flight(leash_m: float) -> list[float]:
        planner = make(PlannerParams(leash_m=leash_m))
        state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
        xs = []
        for _ in range(400):
            sp = planner.step(state, flat_ranges(2.0), DT).setpoint.position_enu
            xs.append(float(sp[0]))
            state = VehicleState(np.array([max(float(sp[0]) - 0.8, 0.0), 0.0, 2.0]), 0.0, 0.0, 0.0)
        return xs

    assert flight(2.0) == flight(1000.0)


@pytest.mark.parametrize("value", [0.0, -1.0, math.inf, math.nan])
def test_a_bad_leash_is_refused(value: float) -> None:
    with pytest.raises(ValueError, match="leash_m"):
        PlannerParams(leash_m=value)
    with pytest.raises(ValueError, match="leash_m"):
        PlannerConfig(leash_m=value)
