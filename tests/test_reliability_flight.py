"""Faults in flight: the real service and planner against companion/sim/ over UDP, lockstep.

One flight per fault here (seeds 1..17, one each), with what the service must do
asserted from its flight log and counters, and on the TRUE trajectory (every physics tick)
that the vehicle never came closer than D_min to the pillar and never touched the surface.
The 20-seed sweep of every fault, on ArduPilot and PX4, is in test_reliability_long.py
(`pytest -m long`); its table is in docs/reliability.md.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tests.reliability_flight import (
    D_MIN_M,
    FAULTS,
    FlightOutcome,
    fly_fault,
)

pytestmark = [pytest.mark.sim, pytest.mark.timeout(120)]

CASES = [(f, i + 1) for i, f in enumerate(FAULTS)]
"""One flight per fault, each with its own seed (1..17): the fault strikes at a different
time of the flight in each (tests.reliability_flight.fault_time)."""


def check_behaviour(o: FlightOutcome) -> None:
    """What the service must have done for fault `o.fault` (ArduPilot personality)."""
    c, t0 = o.counters, o.t0
    engaged = [x for x in o.cycles if x.own == "engaged"]
    assert engaged, "never took over"
    name = o.fault
    # Where the planner is fed wrong data it believes (stuck readings, double spikes that
    # survive the median) it may stop short or detour: safe, but not always finished in
    # time (see the sweep in docs/reliability.md). Elsewhere the service must get there.
    wrong_data = ("stuck_range", "stuck_surface", "spikes", "spikes_close")
    # gps_reset: for the 0.5 s before the position goes stale the planner sees the vehicle
    # still while its sensors move; next to the pillar it may call itself blocked and back
    # out (safe, slower): finishing in time is in the sweep, not asserted here.
    if name not in ("reboot", "mode_change", "gps_reset", *wrong_data):
        assert o.reached_goal, f"final distance {o.final_distance_m:.2f} m"
    if name in ("none", "noise", "sensor_dropouts", *wrong_data):
        assert {x.sp_kind for x in engaged} == {"planner"}  # continue: never held or stopped
    if name == "sensor_dropout_window":  # sensor 8 silent for 2 s: hold, then resume
        held = [x.t for x in o.cycles if x.sp_kind == "hold"]
        assert held and t0 + 0.4 <= held[0] <= t0 + 0.7 and held[-1] <= t0 + 3.2
        assert o.kinds_between(t0 + 0.7, t0 + 2.0) == {"hold"}
    if name == "gps_glitch":  # rejected as a glitch: stop while in doubt, then resume
        assert c["input.rejected_position_jump"] >= 10
        assert c.get("input.position_jump_accepted", 0) == 0
        stop = [x.t for x in engaged if x.verdict == "stop"]
        assert stop and t0 <= stop[0] <= t0 + 0.1 and stop[-1] <= t0 + 1.6
    if name == "gps_reset":  # rejected, stale (stop), accepted after 1 s, plan kept
        assert c["input.position_jump_accepted"] == 1
        # The jump itself keeps the plan (its frame moves). On resuming, a planner whose X_d
        # ended more than restart_distance_m from the vehicle restarts there (`host.step`):
        # with the heading swinging across the gaps the pillar is avoided earlier, and in
        # seed 10 X_d is 3.5 m off on resuming (not traced further).
        assert c["service.planner_starts"] <= 2
        stop = [x.t for x in engaged if x.verdict == "stop"]
        assert stop and t0 <= stop[0] <= t0 + 0.1 and stop[-1] <= t0 + 2.2  # + resume_after
        # the planner's frame moved with the jump: the plan, and the goal, stay in the world
    if name == "dup_reorder":
        assert c.get("input.duplicate", 0) + c.get("input.out_of_order", 0) > 0
    if name == "link_cut_3s":  # stop commanding (nothing new: the brake), then resume
        assert o.kinds_between(t0 + 0.6, t0 + 3.0) == {"brake"}
        assert {x.verdict for x in o.cycles_between(t0 + 0.6, t0 + 3.0)} == {"stop"}
        assert "planner" in o.kinds_between(t0 + 3.0, t0 + 6.0)
    if name in ("reboot", "mode_change"):  # released for good: the pilot's (or failsafe's)
        after = o.cycles_between(t0 + 1.5, math.inf)
        assert after and all(x.own == "released" and x.sp_kind is None for x in after)
        assert c["service.released"] == 1
        mode_after = o.modes[int(np.searchsorted(o.truth_t, t0 + 2.0))]
        assert mode_after == ("LOITER" if name == "mode_change" else "STABILIZE")
        if name == "reboot":
            assert c["input.time_boot_backwards"] >= 1
    if name == "companion_restart":  # a new instance attaches and flies on
        assert o.restarts == 1
        assert o.kinds_between(t0 + 0.1, t0 + 3.0) == set()  # nobody there
        assert "planner" in o.kinds_between(t0 + 3.0, t0 + 8.0)


@pytest.mark.parametrize(("fault", "seed"), CASES, ids=[f"{f}-{s}" for f, s in CASES])
def test_fault_in_flight(fault: str, seed: int, tmp_path: Path) -> None:
    o = fly_fault(fault, seed, tmp_path)
    assert o.min_clearance_m >= D_MIN_M, o.summary()
    assert o.min_height_m > 0.0, o.summary()
    assert o.lockstep_stalls <= (1 if fault == "companion_restart" else 0)
    check_behaviour(o)


def test_scheduled_faults_never_fall_between_ticks() -> None:
    """A fault at 13.7 s (tick times are k * 0.01 in floating point) happens, once."""
    import asyncio

    from companion.sim.mavlink import SimServer
    from tests.reliability_flight import scenario

    async def run() -> list[str]:
        sc = scenario({"faults": {"mode_changes": [{"at_s": 0.07, "mode": "LOITER"}]}})
        server = SimServer.from_scenario(sc, ".", port=0, speedup=math.inf)
        await server.start()
        try:
            await server.run_until(0.2)
        finally:
            await server.close()
        return [s.mode for s in server.truth]

    modes = asyncio.run(run())
    assert "LOITER" in modes and modes.index("LOITER") == 8


def test_sim_position_jump_and_link_fault_windows() -> None:
    """The simulator's new faults: a position offset in a window (or for good), and link
    faults that apply only within their windows."""
    from companion.sim.mavlink.config import FaultsConfig, LinkFaultConfig
    from companion.sim.mavlink.faults import FaultSchedule, LinkFaults, fault_rngs

    sched = FaultSchedule(
        FaultsConfig.model_validate(
            {
                "position_jumps": [
                    {"at_s": 1.0, "offset_m": [1, 2, 3], "duration_s": 0.5},
                    {"at_s": 2.0, "offset_m": [10, 0, 0]},
                ]
            }
        )
    )
    assert list(sched.position_offset(0.99)) == [0, 0, 0]
    assert list(sched.position_offset(1.2)) == [1, 2, 3]
    assert list(sched.position_offset(1.5)) == [0, 0, 0]
    assert list(sched.position_offset(100.0)) == [10, 0, 0]
    link: LinkFaults[int] = LinkFaults(
        LinkFaultConfig(loss_probability=1.0, windows=[(1.0, 2.0)]), fault_rngs(1)[1]
    )
    assert link.filter(1, 0.5) == [1] and link.filter(2, 1.5) == [] and link.filter(3, 2.0) == [3]
