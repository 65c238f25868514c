"""The real service and planner against the bundled MAVLink simulator over UDP, lockstep."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.config import parse_config
from companion.service import Service
from companion.service.link import UdpOutLink
from companion.service.notify import SystemdNotifier

sim_mavlink = pytest.importorskip("companion.sim.mavlink")
scenario_mod = pytest.importorskip("companion.sim.scenario")

pytestmark = [pytest.mark.sim, pytest.mark.timeout(60)]

SCENARIOS = Path(__file__).resolve().parents[1] / "config" / "scenarios"


async def fly(
    personality: str,
    until_s: float,
    control: dict[str, Any] | None = None,
    start_heading_deg: float | None = None,
    **sim: Any,
) -> tuple[Service, Any]:
    """The paper's route; the simulated vehicle boots facing the scenario's start heading
    (west) or `start_heading_deg` (ENU degrees)."""
    sc = scenario_mod.load_scenario(SCENARIOS / "paper.yaml")
    if start_heading_deg is not None:
        raw = sc.model_dump()
        raw["route"] = {**raw["route"], "start_heading_deg": start_heading_deg}
        sc = scenario_mod.Scenario.model_validate(raw)
    server = sim_mavlink.SimServer.from_scenario(
        sc,
        SCENARIOS,
        port=0,
        speedup=math.inf,
        lockstep={"enabled": True, "period_s": 0.05},
        personality=personality,
        **{"prearm_delay_s": 0.5, **sim},
    )
    await server.start()
    start = np.array(sc.start_position[:2])
    goal = np.array(sc.route.points[-1]) - start  # route points are relative to home
    cfg = parse_config(
        {
            "link": {"connection": f"udpout:127.0.0.1:{server.port}"},
            "control": {
                "time_source": "sim",
                "auto_start": {"enabled": True},
                **(control or {}),
            },
            "route": {
                "source": "config",
                "points": [goal.tolist()],
                "arrival_heading_deg": 180.0,
            },
            "planner": sc.planner.model_dump(),
            "sensors": [s.model_dump(exclude_none=True) for s in sc.sensors],
        }
    )
    svc = Service(cfg, UdpOutLink("127.0.0.1", server.port), notifier=SystemdNotifier({}))
    task = asyncio.create_task(svc.run())
    try:
        await server.run_until(until_s)
    finally:
        svc.stop()
        assert await asyncio.wait_for(task, 10) == 0
        await server.close()
    return svc, server


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
async def test_service_flies_towards_the_goal_in_lockstep(personality: str) -> None:
    svc, server = await fly(personality, 22.0)
    assert server.stats.lockstep_stalls == 0
    assert svc.status().owner == "engaged" and svc.counters["planner_starts"] == 1
    c = svc.counter_values()
    assert c["codec.bad_crc"] == 0 and c.get("service.planner_errors", 0) == 0
    truth = server.truth
    xs = np.array([t.position_enu[0] for t in truth])
    last = np.array(truth[-1].position_enu)
    # the vehicle boots facing west (the scenario's start heading) and goes west towards the
    # goal at about v_d = 1 m/s, H_d = 2 m above the ground
    assert last[0] < xs.max() - 3.0
    assert np.all(np.diff(xs[-200:]) < 0.0)
    assert 1.0 < last[2] < 6.0


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
async def test_vehicle_turns_to_face_the_route_before_flying_it(
    personality: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Taken over facing east with the goal west, the vehicle turns in place first: the
    route does not begin with a loop out along the old heading. The control
    (face_route_deg 180: start from the heading the vehicle has) swings east first."""
    caplog.set_level("INFO", logger="companion")
    _, server = await fly(personality, 30.0, start_heading_deg=0.0)
    east = [t.position_enu[0] for t in server.truth if t.mode in ("GUIDED", "OFFBOARD")]
    x0 = east[0]
    assert "to face the route" in caplog.text
    assert max(east) - x0 < 0.5
    assert east[-1] < x0 - 5.0
    assert abs(wrap(server.truth[-1].yaw_rad - math.pi)) < 0.5  # flying west

    _, server = await fly(
        personality, 30.0, control={"face_route_deg": 180.0}, start_heading_deg=0.0
    )
    east = [t.position_enu[0] for t in server.truth if t.mode in ("GUIDED", "OFFBOARD")]
    assert max(east) - east[0] > 2.0


def wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


async def test_pilot_mode_change_stops_the_service() -> None:
    svc, server = await fly(
        "ardupilot", 17.0, faults={"mode_changes": [{"at_s": 15.0, "mode": "LOITER"}]}
    )
    assert svc.status().owner.value == "released"
    assert svc.counters["released"] == 1
    assert server.truth[-1].mode == "LOITER"  # and it stays there: no mode change by us


@pytest.mark.parametrize(
    ("personality", "reason"),
    [
        ("ardupilot", "Mode change to GUIDED failed: requires position"),
        ("px4", "Preflight Fail: no heading reference"),
    ],
)
async def test_auto_start_retries_while_the_simulator_refuses_after_boot(
    personality: str, reason: str, caplog: pytest.LogCaptureFixture
) -> None:
    """The simulator refuses GUIDED and arming for prearm_delay_s after boot (as ArduCopter
    does for ~40 s, PX4 for a few): auto start retries, shows the reason, then flies."""
    caplog.set_level("INFO", logger="companion")
    svc, _ = await fly(personality, 24.0, prearm_delay_s=4.0)
    assert "refused" in caplog.text and reason in caplog.text
    assert svc.status().owner == "engaged" and svc.counters["auto_start_failed"] == 0
