"""The service end to end through an in-memory link against a fake autopilot."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math
from collections.abc import AsyncIterator
from typing import Any

import numpy as np
import pytest

from companion.config import ServiceConfig
from companion.service import Service, memory_pair
from companion.service.identity import Health
from companion.service.notify import SystemdNotifier
from companion.service.setpoints import TYPE_MASK
from tests.service_fakes import HOME, FakeAutopilot, PlannerBox, enu_of, make_config

pytestmark = pytest.mark.timeout(20)

GUIDED = 4
LOITER = 5


@contextlib.asynccontextmanager
async def running(
    cfg: ServiceConfig | None = None, **ap_kwargs: Any
) -> AsyncIterator[tuple[Service, FakeAutopilot, PlannerBox]]:
    a, b = memory_pair()
    box = PlannerBox()
    svc = Service(cfg or make_config(), a, planner_factory=box, notifier=SystemdNotifier({}))
    ap = FakeAutopilot(b, **ap_kwargs)
    task = asyncio.create_task(svc.run())
    await ap.start()
    try:
        yield svc, ap, box
    finally:
        svc.stop()
        rc = await asyncio.wait_for(task, 5)
        await ap.stop()
        assert rc == 0


async def until(pred: Any, timeout: float = 5.0) -> None:
    deadline = asyncio.get_running_loop().time() + timeout
    while not pred():
        if asyncio.get_running_loop().time() > deadline:
            raise TimeoutError("condition not met")
        await asyncio.sleep(0.01)


async def test_detects_ardupilot_configures_and_waits_in_standby() -> None:
    async with running() as (svc, ap, _):
        await until(lambda: svc.status().configured)
        assert svc.status().autopilot is not None and svc.status().autopilot.value == "ardupilot"
        assert int(svc.status().setpoint_frame or 0) == 6
        intervals = {
            int(c.param1): c.param2 for c in ap.commands if int(c.command) == 511
        }  # SET_MESSAGE_INTERVAL
        assert intervals == {30: 50_000.0, 33: 50_000.0, 132: 50_000.0, 242: 2_000_000.0}
        assert any(int(c.command) == 512 and int(c.param1) == 242 for c in ap.commands)
        await until(lambda: svc.status().health is Health.STANDBY)
        await ap.wait_for(lambda: any(r.msg.system_status == 3 for r in ap.of_type("HEARTBEAT")))
        hb = ap.of_type("HEARTBEAT")[-1].msg
        assert (hb.type, hb.autopilot) == (18, 8)
        assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 191
        assert not ap.setpoints()  # LOITER: not ours


async def test_detects_px4_and_uses_global_frame() -> None:
    async with running(kind="px4") as (svc, _, _):
        await until(lambda: svc.status().configured)
        assert svc.status().autopilot is not None and svc.status().autopilot.value == "px4"
        assert int(svc.status().setpoint_frame or 0) == 5


async def test_ignores_other_systems_until_and_after_lock() -> None:
    async with running(sysid=7) as (svc, ap, _):
        await until(lambda: svc.status().configured)
        # a second "autopilot" with another system id on the same link is ignored
        intruder = FakeAutopilot(ap.link, sysid=9)
        intruder.custom_mode = GUIDED
        for _ in range(5):
            intruder.heartbeat()
            intruder.telemetry()
        await asyncio.sleep(0.1)
        assert svc.status().target_system == 7
        assert svc.counter_values()["conn.other_system"] >= 10
        assert svc.codec.system_id == 7  # our id follows the autopilot's
        assert not ap.setpoints()


async def test_guided_engages_and_setpoints_are_position_velocity_acceleration_yaw() -> None:
    async with running() as (svc, ap, box):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 10)
        assert svc.status().health is Health.ACTIVE
        planner = box.made[0]
        route = planner.route
        assert route is not None
        sp = ap.setpoints()[-1].msg
        assert sp.coordinate_frame == 6
        assert sp.type_mask == TYPE_MASK == 0b1000_0000_0000  # only the yaw rate ignored
        assert sp.type_mask & 512 == 0  # no force bit
        assert (sp.target_system, sp.target_component) == (1, 1)
        assert sp.vx == pytest.approx(0.0, abs=1e-6)  # east 1 m/s = NED (0, 1, 0)
        assert sp.vy == pytest.approx(1.0)
        assert sp.yaw == pytest.approx(math.pi / 2)  # ENU 0 (east) = NED 90 deg
        east, north = enu_of(sp)
        assert 0.0 < east < 5.0 and abs(north) < 0.1
        assert sp.alt == pytest.approx(5.0, abs=0.05)  # relative to home
        state, ranges, dt = planner.inputs[-1]
        assert dt == pytest.approx(0.05, abs=0.03)
        np.testing.assert_allclose(ranges, [0.0, 7.0, 7.0])
        assert state.yaw_rad == pytest.approx(math.pi / 2)  # NED yaw 0 = north = ENU 90 deg
        texts = [r.msg.text for r in ap.of_type("STATUSTEXT")]
        assert "flying route" in texts and "first step" in texts


async def test_mode_change_stops_setpoints_within_one_cycle_and_never_switches_back() -> None:
    async with running(cfg=make_config(control={"reengage": False})) as (svc, ap, _):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 5)
        ap.set_mode(LOITER)
        n = len(ap.setpoints())
        await asyncio.sleep(0.5)
        assert len(ap.setpoints()) <= n + 1  # at most one already on its way
        assert svc.status().owner.value == "released"
        assert not any(int(c.command) == 176 for c in ap.commands)  # no mode change by us
        ap.set_mode(GUIDED)  # re-engage disabled: stays silent
        await asyncio.sleep(0.3)
        assert len(ap.setpoints()) <= n + 1
        assert any("LOITER" in r.msg.text for r in ap.of_type("STATUSTEXT"))


async def test_pilot_reengage_restarts_planner_from_current_position() -> None:
    # the fake vehicle teleports: no jump detection
    cfg = make_config(failsafe={"max_speed_mps": 1000.0, "max_position_jump_m": 1000.0})
    async with running(cfg=cfg) as (svc, ap, box):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 5)
        ap.set_mode(LOITER)
        await asyncio.sleep(0.2)
        ap.lon += 10.0 / (6_378_137.0 * math.cos(math.radians(HOME[0]))) * 180 / math.pi
        await asyncio.sleep(0.2)
        ap.set_mode(GUIDED)
        await until(lambda: len(box.made) == 2)
        start = box.made[1].x_d
        assert start[0] == pytest.approx(10.0, abs=0.5)


async def test_disarm_releases() -> None:
    async with running() as (svc, ap, _):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 3)
        ap.armed = False
        ap.heartbeat()
        await until(lambda: svc.status().owner.value == "released")


async def test_heartbeat_loss_stops_commanding_and_recovers() -> None:
    async with running() as (svc, ap, _):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 5)
        ap.heartbeat_enabled = False
        ap.telemetry_enabled = False
        await until(lambda: svc.status().health is Health.EMERGENCY, 2.0)
        n = len(ap.setpoints())
        await asyncio.sleep(0.3)
        # nothing new is commanded: only the brake, the last target again at rest
        during = [s.msg for s in ap.setpoints()[n:]]
        assert all((m.vx, m.vy, m.vz) == (0.0, 0.0, 0.0) for m in during)
        assert len({(m.lat_int, m.lon_int, m.alt) for m in during}) <= 1
        intervals_before = sum(1 for c in ap.commands if int(c.command) == 511)
        ap.heartbeat_enabled = True
        ap.telemetry_enabled = True
        await until(lambda: svc.status().health is Health.ACTIVE, 3.0)
        m = len(ap.setpoints())
        await ap.wait_for(lambda: len(ap.setpoints()) > m + 3, 3.0)
        # the autopilot might have rebooted: message rates are requested again
        await ap.wait_for(
            lambda: sum(1 for c in ap.commands if int(c.command) == 511) > intervals_before
        )


async def test_stale_sensor_holds_at_current_position_then_resumes() -> None:
    async with running() as (svc, ap, box):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 5)
        steps = len(box.made[0].inputs)
        ap.sensors_enabled = {0, 1}  # back surface sensor goes quiet
        await until(lambda: svc.status().health is Health.CRITICAL, 2.0)
        n = len(ap.setpoints())
        await ap.wait_for(lambda: len(ap.setpoints()) >= n + 5)
        hold = ap.setpoints()[-1].msg
        assert (hold.vx, hold.vy, hold.vz) == (0.0, 0.0, 0.0)
        east, north = enu_of(hold)
        assert abs(east) < 0.05 and abs(north) < 0.05  # where the vehicle is
        frozen = len(box.made[0].inputs)
        assert frozen - steps < 15  # the planner is not stepped while holding
        await asyncio.sleep(0.2)
        assert len(box.made[0].inputs) == frozen
        texts = [r.msg.text for r in ap.of_type("STATUSTEXT")]
        assert any(t.startswith("HOLD: sensor 2 (h2) stale") for t in texts)
        ap.sensors_enabled = None
        await until(lambda: svc.status().health is Health.ACTIVE, 2.0)
        await until(lambda: len(box.made[0].inputs) > frozen)
        assert any(r.msg.text.startswith("resumed") for r in ap.of_type("STATUSTEXT"))
        for _, ranges, _ in box.made[0].inputs:
            assert np.all(np.isfinite(ranges))  # NaN never reaches the planner here


async def test_stale_position_stops_commanding() -> None:
    async with running() as (svc, ap, _):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 5)
        ap.telemetry_enabled = False  # heartbeats go on, position stops
        await until(lambda: svc.status().health is Health.EMERGENCY, 2.0)
        n = len(ap.setpoints())
        await asyncio.sleep(0.3)
        # nothing new is commanded: only the brake, the last target again at rest
        during = [s.msg for s in ap.setpoints()[n:]]
        assert all((m.vx, m.vy, m.vz) == (0.0, 0.0, 0.0) for m in during)
        assert len({(m.lat_int, m.lon_int, m.alt) for m in during}) <= 1
        assert svc.status().verdict.reason == "position stale"


async def test_nan_attitude_rejected_counted_and_never_reaches_planner() -> None:
    async with running() as (svc, ap, box):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 3)
        ap.roll = math.nan
        await until(lambda: svc.counter_values().get("input.rejected_attitude_nonfinite", 0) > 5)
        await until(
            lambda: svc.status().health is Health.CRITICAL, 2.0
        )  # attitude goes stale: hold
        ap.roll = math.inf
        await asyncio.sleep(0.1)
        ap.roll = 0.0
        await until(lambda: svc.status().health is Health.ACTIVE, 2.0)
        for state, _, _ in box.made[0].inputs:
            assert math.isfinite(state.roll_rad)


async def test_distance_sensor_mapping_units_and_orientation_check() -> None:
    async with running() as (svc, ap, box):
        await until(lambda: svc.status().configured)
        ap.ranges_cm = {0: 350, 1: 5, 2: 1000}  # 3.5 m; below min; at max
        ap.set_mode(GUIDED)
        await until(lambda: len(box.made) == 1 and len(box.made[0].inputs) > 3)
        _, ranges, _ = box.made[0].inputs[-1]
        # below min = too close to measure: the minimum range; at max: nothing detected = 0.0
        np.testing.assert_allclose(ranges, [3.5, 0.1, 0.0])
        ap.orientations[0] = (2, [0, 0, 0, 0])  # now claims YAW_90: not our front sensor
        await until(
            lambda: svc.counter_values().get("input.rejected_sensor_orientation_mismatch", 0) > 3
        )
        await until(lambda: svc.status().health is Health.CRITICAL, 2.0)


async def test_garbage_and_malformed_frames_do_not_crash() -> None:
    async with running() as (svc, ap, _):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 3)
        rng = np.random.default_rng(1)
        good = ap.codec.encode(ap.codec.mav.attitude_encode(1, 0, 0, 0, 0, 0, 0))
        bad_crc = bytearray(good)
        bad_crc[-1] ^= 0xFF
        for _ in range(200):
            svc.link.inject(rng.bytes(int(rng.integers(1, 300))))  # type: ignore[attr-defined]
        svc.link.inject(bytes(bad_crc))  # type: ignore[attr-defined]
        svc.link.inject(good[:7])  # type: ignore[attr-defined]
        svc.link.inject(b"\xfd\xff" + bytes(20))  # type: ignore[attr-defined]
        n = len(ap.setpoints())
        await ap.wait_for(lambda: len(ap.setpoints()) > n + 5)
        c = svc.counter_values()
        assert c["codec.garbage"] > 0 and c["codec.bad_crc"] >= 1 and c["codec.truncated"] >= 1
        assert svc.status().health is Health.ACTIVE


async def test_interval_request_denied_is_counted_and_service_goes_on() -> None:
    async with running(command_results={511: 4}) as (svc, ap, _):  # MAV_RESULT_FAILED
        await until(lambda: svc.status().configured)
        assert svc.counter_values()["service.interval_request_failed"] == 4
        await ap.wait_for(
            lambda: any("rate request failed" in r.msg.text for r in ap.of_type("STATUSTEXT"))
        )


async def test_planner_exception_holds_instead_of_crashing() -> None:
    async with running() as (svc, ap, box):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await until(lambda: len(box.made) == 1 and len(box.made[0].inputs) > 2)
        box.made[0].fail = True
        await until(lambda: svc.counter_values().get("service.planner_errors", 0) > 2)
        assert svc.status().health is Health.CRITICAL
        hold = ap.setpoints()[-1].msg
        assert (hold.vx, hold.vy, hold.vz) == (0.0, 0.0, 0.0)


async def test_mission_route_skips_ardupilot_home() -> None:
    cfg = make_config(route={"source": "mission", "points": None})
    dlat = 20.0 / 6_378_137.0 * 180 / math.pi
    mission = [(HOME[0] + dlat, HOME[1]), (HOME[0] + 2 * dlat, HOME[1])]
    async with running(cfg=cfg, mission=mission) as (svc, ap, box):
        await until(lambda: svc.status().configured)
        assert svc.status().route_points_xy is not None
        np.testing.assert_allclose(svc.status().route_points_xy, [[0, 20], [0, 40]], atol=0.2)
        assert ap.of_type("MISSION_ACK")
        ap.set_mode(GUIDED)
        await until(lambda: len(box.made) == 1)


async def test_px4_auto_start_streams_before_offboard() -> None:
    cfg = make_config(control={"auto_start": {"enabled": True, "prestream_s": 0.3}})
    async with running(cfg=cfg, kind="px4", armed=False, alt_amsl=HOME[2]) as (_svc, ap, box):
        await until(lambda: len(box.made) == 1, 8.0)
        set_modes = [c for c in ap.commands if int(c.command) == 176]
        assert len(set_modes) == 1 and int(set_modes[0].param2) == 6
        t_mode = next(r.t for r in ap.of_type("COMMAND_LONG") if int(r.msg.command) == 176)
        before = [r for r in ap.setpoints() if r.t < t_mode]
        assert len(before) >= 3  # PX4 needs a stream before OFFBOARD
        assert all(r.msg.coordinate_frame == 5 for r in ap.setpoints())
        assert before[-1].msg.alt == pytest.approx(HOME[2] + 2.0, abs=0.1)  # AMSL
        takeoff = next(c for c in ap.commands if int(c.command) == 22)
        assert takeoff.param7 == pytest.approx(HOME[2] + 2.0)


async def test_ardupilot_auto_start_guided_arm_takeoff() -> None:
    cfg = make_config(control={"auto_start": {"enabled": True}})
    async with running(cfg=cfg, armed=False, alt_amsl=HOME[2]) as (_svc, ap, box):
        await until(lambda: len(box.made) == 1, 8.0)
        order = [int(c.command) for c in ap.commands if int(c.command) in (176, 400, 22)]
        assert order == [176, 400, 22]
        assert next(c for c in ap.commands if int(c.command) == 22).param7 == 2.0


async def test_arming_refused_then_accepted_is_retried() -> None:
    cfg = make_config(
        control={"auto_start": {"enabled": True, "arm_timeout_s": 10, "arm_retry_s": 0.1}}
    )
    async with running(cfg=cfg, armed=False, alt_amsl=HOME[2], command_results={400: 4}) as (
        _svc,
        ap,
        box,
    ):
        await until(lambda: sum(1 for c in ap.commands if int(c.command) == 400) >= 1)
        ap.command_results[400] = 0
        await until(lambda: len(box.made) == 1, 8.0)


async def test_set_desired_height_reaches_planner() -> None:
    async with running() as (svc, ap, box):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await until(lambda: len(box.made) == 1 and svc.planner is not None)
        svc.set_desired_height(3.5)
        assert box.made[0].h_d == 3.5
        with pytest.raises(ValueError):
            svc.set_desired_height(math.nan)


async def test_status_is_a_frozen_snapshot_of_what_the_service_does() -> None:
    async with running() as (svc, ap, _box):
        before = svc.status()
        assert before.health is Health.BOOT and before.planner.value == "none"
        assert before.freshness.heartbeat_age_s is None and before.last_setpoint is None
        with pytest.raises(dataclasses.FrozenInstanceError):
            before.health = Health.ACTIVE  # type: ignore[misc]
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 5)
        s = svc.status()
        assert s.owner.value == "engaged" and s.planner.value == "flying"
        assert s.mode == "GUIDED" and s.target_system == 1
        assert not s.holding and s.hold_reason == "" and s.last_setpoint_kind == "planner"
        assert s.last_setpoint is not None and s.h_d_m == svc.cfg.planner.h_d_m
        assert s.freshness.position_age_s is not None and s.freshness.position_age_s < 1.0
        assert len(s.freshness.range_ages_s) == 3 and s.freshness.stale_sensor_ids == ()
        assert s.counters["service.setpoints_sent"] >= 5
        assert before.health is Health.BOOT  # the old snapshot did not change
        ap.sensors_enabled = {0, 1}  # sensor 2 goes quiet: hold, and the snapshot says why
        await until(lambda: svc.status().holding, 3.0)
        s = svc.status()
        assert "sensor" in s.hold_reason and s.freshness.stale_sensor_ids == (2,)
