"""Safety defects found by attacking the running service (issue "safety"), one test each.

Each test drives the service over UDP on 127.0.0.1 against the scripted fake autopilot of
`tests/service_fakes.py` (or checks the config path), and fails on the behaviour found by
the attack: a crash at take-over, a fight with the pilot's mode change, an obstacle below the
minimum range taken for free space, a stranger followed, a forged timestamp stopping the
vehicle, an unlimited position jump re-basing the plan, a take-off with no sensor or no route.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import itertools
import logging
import math
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from companion.config import ConfigError, ServiceConfig, check_config, parse_config
from companion.service import Service
from companion.service.codec import mavlink2
from companion.service.identity import Health
from companion.service.link import UdpInLink, UdpOutLink
from companion.service.notify import SystemdNotifier
from tests.service_fakes import HOME, SENSORS, FakeAutopilot, PlannerBox, make_config

pytestmark = pytest.mark.timeout(40)

M = mavlink2
GUIDED = 4
LOITER = 5
RTL = 6


async def until(pred: Any, timeout: float = 8.0) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not pred():
        if loop.time() > deadline:
            raise TimeoutError("condition not met")
        await asyncio.sleep(0.01)


@contextlib.asynccontextmanager
async def over_udp(
    cfg: ServiceConfig | None = None, factory: Any = None, **ap_kwargs: Any
) -> AsyncIterator[tuple[Service, FakeAutopilot, asyncio.Task[int]]]:
    """The service on a UDP port and the fake autopilot sending to it; yields the run task."""
    link = UdpInLink("127.0.0.1", 0)
    svc = Service(
        cfg or make_config(),
        link,
        planner_factory=factory or PlannerBox(),
        notifier=SystemdNotifier({}),
    )
    task = asyncio.create_task(svc.run())
    await until(lambda: link.is_open)
    host, port = link.local_address
    ap = FakeAutopilot(UdpOutLink(host, port), **ap_kwargs)
    await ap.start()
    try:
        yield svc, ap, task
    finally:
        svc.stop()
        rc = await asyncio.wait_for(task, 10)
        await ap.stop()
        assert rc == 0, "the service ended with an error"


def pilot_texts(ap: FakeAutopilot) -> list[str]:
    return [r.msg.text for r in ap.of_type("STATUSTEXT")]


# === 1. nothing that can fail at take-over ends the process =================================


def test_check_config_refuses_equal_consecutive_points(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    data = {"route": {"source": "config", "points": [[30, 0], [30, 0], [30, 30]]}}
    path.write_text(yaml.safe_dump({**data, "sensors": SENSORS}))
    out = io.StringIO()
    assert check_config(path, out) == 2
    assert "base points 0 and 1 are 0.00 m apart" in out.getvalue()


def test_check_config_builds_the_planner_it_will_fly(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """check-config builds the route and planner a take-over builds: what they refuse, it
    refuses (here a planner that cannot be built from the tuning)."""
    import companion.planner as planner_pkg

    class Refusing:
        def __init__(self, *a: Any) -> None:
            raise ValueError("v_d_mps too high for this sensor table")

    monkeypatch.setattr(planner_pkg, "Planner", Refusing)
    path = tmp_path / "c.yaml"
    path.write_text(
        yaml.safe_dump({"route": {"source": "config", "points": [[30, 0]]}, "sensors": SENSORS})
    )
    out = io.StringIO()
    assert check_config(path, out) == 2
    assert "cannot be built at take-over: v_d_mps too high" in out.getvalue()


async def test_take_over_failure_holds_and_says_why(caplog: pytest.LogCaptureFixture) -> None:
    """A route the planner refuses at take-over (as `Route` refused equal points): the service
    keeps running, holds where the vehicle is (hold setpoints, CRITICAL) and says why."""

    def refusing(*a: Any) -> Any:
        raise ValueError("consecutive base points must differ")

    async with over_udp(factory=refusing) as (svc, ap, task):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await until(lambda: svc.counters["route_build_failed"] >= 1)
        n = len(ap.setpoints())
        await ap.wait_for(lambda: len(ap.setpoints()) >= n + 10)
        assert not task.done()
        assert svc.status().health is Health.CRITICAL
        east = [r.msg.lon_int for r in ap.setpoints()[n:]]
        assert max(east) - min(east) <= 1  # a hold: the same point every time
        assert any("cannot fly route" in t for t in pilot_texts(ap))
        assert "consecutive base points must differ" in caplog.text


# === 5. routes bounded; planner construction off the event loop =============================


@pytest.mark.parametrize(
    ("route", "expected"),
    [
        ({"points": [[1e9, 0.0]]}, "km from home"),
        ({"points": [[float(i), 0.0] for i in range(1, 1502)]}, "longer than 1000"),
        ({"points": [[10.0, 0.0], [10.2, 0.0]]}, "0.20 m apart"),
        ({"points_latlon": [[47.0, 8.0], [48.0, 8.0]]}, "km from the first point"),
    ],
    ids=["far", "too_many", "too_close", "latlon_far"],
)
def test_route_bounds(route: dict[str, Any], expected: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config({"route": {"source": "config", **route}, "sensors": SENSORS})
    assert expected in str(err.value)


async def test_planner_built_off_the_event_loop() -> None:
    """A slow planner construction (a long route) does not stop heartbeats or setpoints."""
    import threading
    import time

    made = threading.Event()

    def slow(*a: Any) -> Any:
        time.sleep(1.5)
        made.set()
        return PlannerBox()(*a)

    async with over_udp(factory=slow) as (svc, ap, _):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await until(lambda: svc.status().owner == "engaged")
        t0 = asyncio.get_running_loop().time()
        n_hb = len(ap.of_type("HEARTBEAT"))
        n_sp = len(ap.setpoints())
        await until(made.is_set)
        waited = asyncio.get_running_loop().time() - t0
        assert waited > 1.0
        # heartbeats (1 Hz) and hold setpoints went on while the planner was being built
        assert len(ap.of_type("HEARTBEAT")) >= n_hb + 1
        assert len(ap.setpoints()) >= n_sp + 5


# === 3. an obstacle closer than the minimum range is not free space ========================


@pytest.mark.parametrize(
    ("cm", "limits", "expect"),
    [
        (250, (300, 1000), "refused"),  # (a) the message claims a 3 m minimum
        (5, (10, 1000), "at_min"),  # (b) closer than the configured 0.1 m minimum
        (150, (1, 2), "refused"),  # (c) message limits 1-2 cm
    ],
    ids=["msg_min_300cm", "below_configured_min", "msg_limits_1_2cm"],
)
async def test_close_obstacle_never_free_space(
    cm: int, limits: tuple[int, int], expect: str
) -> None:
    box = PlannerBox()
    async with over_udp(factory=box, ranges_cm={0: 800, 1: 700, 2: 700}) as (svc, ap, _):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await until(lambda: bool(box.made) and len(box.made[-1].inputs) >= 5)
        ap.ranges_cm[0] = cm
        ap.limits_cm[0] = limits
        await asyncio.sleep(1.5)
        planner = box.made[-1]
        n_before = len(planner.inputs)
        await asyncio.sleep(1.0)
        front = [float(r[0]) for _, r, _ in planner.inputs[-10:]]
        assert 0.0 not in front, front  # never "nothing detected"
        if expect == "at_min":
            assert front[-1] == pytest.approx(0.1)  # an obstacle at the minimum range
        else:
            # refused: the sensor is stale, the planner is not stepped, the vehicle holds
            assert len(planner.inputs) == n_before
            assert svc.status().verdict.verdict.value == "hold"
            assert any(t.startswith("sensor 0 refused") for t in pilot_texts(ap))
            assert svc.counter_values()["input.rejected_sensor_limits"] > 0


# === 2, 8, 9 and refusals: auto start ======================================================

PX4_POSCTL = 3 << 16
PX4_RTL = (4 << 16) | (5 << 24)
STABILIZE = 0


def auto_cfg(**control: Any) -> ServiceConfig:
    auto = {"enabled": True, "arm_timeout_s": 20.0, "arm_retry_s": 0.2, "prestream_s": 0.3}
    auto.update(control.pop("auto_start", {}))
    return make_config(control={"auto_start": auto, **control})


def on_ground(**kw: Any) -> dict[str, Any]:
    return {"armed": False, "alt_amsl": HOME[2], **kw}


def commands(ap: FakeAutopilot, cmd: int) -> list[Any]:
    return [m for m in ap.commands if int(m.command) == cmd]


def offboard_requests(ap: FakeAutopilot) -> list[Any]:
    return [m for m in commands(ap, 176) if int(m.param2) in (4, 6)]


@pytest.mark.parametrize("kind", ["ardupilot", "px4"])
@pytest.mark.parametrize("phase", ["arming", "climb"])
async def test_auto_start_aborts_on_a_mode_change_by_anyone_else(kind: str, phase: str) -> None:
    """A ground station changes the mode (RTL) while auto start retries the arm command or
    while the vehicle climbs: auto start stops at once: no more arm, take-off or mode
    commands, never OFFBOARD/GUIDED afterwards, never a take-over."""
    rtl = PX4_RTL if kind == "px4" else RTL
    script = {400: [1] * 1000} if phase == "arming" else {}
    async with over_udp(auto_cfg(), kind=kind, result_script=script, **on_ground()) as (
        svc,
        ap,
        _,
    ):
        if phase == "arming":
            await until(lambda: len(commands(ap, 400)) >= 2)
        else:
            await until(lambda: ap.climb_to is not None and ap.alt_amsl > HOME[2] + 0.5)
        n_cmds = len(ap.commands)
        ap.set_mode(rtl)
        await until(lambda: svc.counters["auto_start_aborted"] >= 1)
        await asyncio.sleep(max(1.5, 3 * 0.3))  # PX4 would ask for OFFBOARD 0.3 s after climbing
        later = ap.commands[n_cmds:]
        assert not [m for m in later if int(m.command) in (400, 22, 176)], later
        assert svc.status().owner != "engaged" and ap.custom_mode == rtl
        assert any("auto start aborted: mode changed to" in t for t in pilot_texts(ap))


async def test_auto_start_waits_for_every_required_sensor_before_arming() -> None:
    async with over_udp(auto_cfg(), sensors_enabled={1, 2}, **on_ground()) as (svc, ap, _):
        await until(lambda: svc.status().configured)
        await until(lambda: any("waiting, sensor 0 (front) stale" in t for t in pilot_texts(ap)))
        await asyncio.sleep(1.0)
        assert not commands(ap, 400) and not commands(ap, 176)  # neither armed nor GUIDED
        ap.sensors_enabled = None  # the front sensor starts reporting
        await until(lambda: bool(commands(ap, 400)))
        await until(lambda: svc.status().owner == "engaged", 15.0)


async def test_hold_before_take_over_is_announced(caplog: pytest.LogCaptureFixture) -> None:
    """The pilot hands over while a required sensor has never reported: the take-over says
    it holds, and why (not just "flying route")."""
    async with over_udp(sensors_enabled={1, 2}) as (svc, ap, _):
        await until(lambda: svc.status().configured)
        await until(lambda: svc.status().verdict.verdict.value == "hold")
        await asyncio.sleep(0.5)  # the hold began well before the hand-over
        ap.set_mode(GUIDED)
        await until(lambda: svc.status().owner == "engaged")
        await until(lambda: "HOLD: sensor 0 (front) stale" in pilot_texts(ap))
        assert svc.status().health is Health.CRITICAL


async def test_auto_start_with_an_empty_mission_does_not_take_off(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import companion.service.supervisor as service_mod

    monkeypatch.setattr(service_mod, "MISSION_RETRY_S", 0.5)
    cfg = make_config(
        route={"source": "mission", "points": None},
        control={"auto_start": {"enabled": True, "arm_retry_s": 0.2, "prestream_s": 0.3}},
    )
    async with over_udp(cfg, mission=[], **on_ground()) as (_svc, ap, _):
        await until(lambda: any("no route (mission empty)" in t for t in pilot_texts(ap)))
        await asyncio.sleep(1.5)  # a few downloads later: still nothing to fly
        assert not commands(ap, 400) and not commands(ap, 22) and not commands(ap, 176)
        assert "route complete: holding" not in pilot_texts(ap)
        ap.mission = [(HOME[0] + 0.0003, HOME[1])]  # a waypoint ~33 m north appears
        await until(lambda: bool(commands(ap, 400)), 10.0)


@pytest.mark.parametrize("kind", ["ardupilot", "px4"])
async def test_auto_start_waits_for_the_vehicle_state_before_judging_the_route(
    kind: str,
) -> None:
    """Home and position known, no ATTITUDE yet: the vehicle's state is unknown, and auto
    start waits instead of saying "no route (at the end)" and giving up (it gave up on PX4
    SITL, started as soon as PX4 was armable)."""
    cfg = make_config(
        control={"auto_start": {"enabled": True, "arm_retry_s": 0.2, "prestream_s": 0.3}}
    )
    async with over_udp(cfg, kind=kind, attitude_enabled=False, **on_ground()) as (_, ap, _):
        await asyncio.sleep(1.0)
        assert not commands(ap, 400)  # not armed without an attitude
        ap.attitude_enabled = True
        await until(lambda: bool(commands(ap, 400)), 10.0)
        assert not any("no route" in t for t in pilot_texts(ap))


LONG_REASON = "PreArm: Rangefinder 1: No Data; Compass not calibrated; Battery 1 below minimum"


async def test_auto_start_retries_every_refusal_and_shows_the_full_reason(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """TEMPORARILY_REJECTED, FAILED, DENIED and no answer, each with a pre-arm STATUSTEXT:
    retried until accepted; the autopilot's whole reason is in the log."""
    caplog.set_level(logging.INFO, logger="companion")
    script = {400: [1, 4, 2, -1, -1, -1, -1]}
    async with over_udp(
        auto_cfg(), result_script=script, refusal_text=LONG_REASON, **on_ground()
    ) as (svc, ap, _):
        await until(lambda: svc.status().owner == "engaged", 25.0)
        assert len(commands(ap, 400)) >= 5
        for name in ("TEMPORARILY_REJECTED", "FAILED", "DENIED", "no ack"):
            assert name in caplog.text
        assert LONG_REASON in caplog.text  # not cut at 50 characters


async def test_auto_start_gives_up_at_arm_timeout_with_the_full_reason() -> None:
    cfg = auto_cfg(auto_start={"arm_timeout_s": 1.5})
    async with over_udp(cfg, command_results={400: 2}, refusal_text=LONG_REASON, **on_ground()) as (
        svc,
        ap,
        _,
    ):
        await until(lambda: svc.counters["auto_start_failed"] >= 1, 15.0)
        await asyncio.sleep(0.3)
        chunks = [r.msg for r in ap.of_type("STATUSTEXT")]
        failed = [m for m in chunks if m.text.startswith("auto start failed")]
        assert failed
        joined = "".join(m.text for m in chunks if m.id == failed[0].id)
        assert "DENIED" in joined and LONG_REASON in joined
        assert svc.status().owner != "engaged"


# === 7. a bound on accepted position jumps ================================================


async def test_position_jump_over_the_limit_stops_and_is_never_accepted() -> None:
    cfg = make_config(failsafe={"resume_after_s": 0.2, "max_accepted_jump_m": 50.0})
    async with over_udp(cfg) as (svc, ap, task):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 10)
        ap.alt_amsl += 1000.0  # the estimate says 1 km higher, and stays there
        await until(lambda: svc.counter_values().get("input.rejected_position_jump_fault", 0) > 5)
        await asyncio.sleep(1.0)
        n = len(ap.setpoints())
        await asyncio.sleep(0.5)
        # stopped commanding: nothing new, only the brake (the last target again, at rest)
        during = [s.msg for s in ap.setpoints()[n:]]
        assert all((m.vx, m.vy, m.vz) == (0.0, 0.0, 0.0) for m in during)
        assert len({(m.lat_int, m.lon_int, m.alt) for m in during}) <= 1
        assert not svc.status().shift_enu.any()  # the plan was not re-based on it
        assert svc.counter_values().get("input.position_jump_accepted", 0) == 0
        assert svc.status().health is Health.EMERGENCY and not task.done()
        assert any("position jump of 1000 m over the 50 m limit" in t for t in pilot_texts(ap))
        ap.alt_amsl -= 1000.0  # the estimate comes back: flying resumes
        await until(lambda: svc.status().health is Health.ACTIVE, 5.0)
        m = len(ap.setpoints())
        await ap.wait_for(lambda: len(ap.setpoints()) >= m + 5, 5.0)


async def test_position_jump_within_the_limit_is_still_accepted() -> None:
    async with over_udp() as (svc, ap, _):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 10)
        ap.alt_amsl += 20.0  # an estimator reset of 20 m
        await until(lambda: svc.counter_values().get("input.position_jump_accepted", 0) == 1)
        assert svc.status().shift_enu[2] == pytest.approx(20.0, abs=1.0)


# === 6. one forged timestamp neither resets nor stops ======================================


def _max_gap(times: list[float]) -> float:
    return max((b - a for a, b in itertools.pairwise(times)), default=0.0)


@pytest.mark.parametrize("attack", ["attitude_far_future", "position_2_5_s_ahead"])
async def test_single_forged_timestamp_neither_resets_nor_stops(attack: str) -> None:
    box = PlannerBox()
    async with over_udp(factory=box) as (svc, ap, _):
        ap._boot -= 30.0
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 10)
        t0 = __import__("time").monotonic()  # the fake stamps receipts with time.monotonic
        n0 = len(ap.setpoints())
        for _ in range(3):  # repeated every 0.7 s
            tb = ap.time_boot_ms()
            if attack == "attitude_far_future":
                ap.send(M.MAVLink_attitude_message(0xFFFFFFF0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
            else:
                ap.send(
                    M.MAVLink_global_position_int_message(
                        tb + 2500,
                        round(ap.lat * 1e7),
                        round(ap.lon * 1e7),
                        round(ap.alt_amsl * 1000),
                        round((ap.alt_amsl - HOME[2]) * 1000),
                        0,
                        0,
                        0,
                        0,
                    )
                )
            await asyncio.sleep(0.7)
        await asyncio.sleep(0.5)
        sp = [r.t for r in ap.setpoints()[n0:]]
        assert svc.counter_values().get("input.time_boot_backwards", 0) == 0
        assert svc.counter_values()["input.time_boot_suspect"] >= 3
        assert len(box.made) == 1  # never restarted
        assert svc.counters["released"] == 0
        assert _max_gap(sp) < 0.4, "setpoints stopped"  # 20 Hz: no stop of any length
        assert sp[-1] - t0 > 2.0
        later = [r.msg.text for r in ap.of_type("STATUSTEXT") if r.t >= t0]
        assert not [t for t in later if "STOP" in t or "HOLD" in t], later


async def test_a_real_reboot_is_still_recognised(caplog: pytest.LogCaptureFixture) -> None:
    async with over_udp() as (svc, ap, _):
        ap._boot -= 30.0
        await until(lambda: svc.status().configured)
        ap._boot = __import__("time").monotonic()  # the autopilot's clock restarts at 0
        await until(lambda: svc.counter_values().get("input.time_boot_backwards", 0) == 1)
        assert "reboot? reconfiguring" in caplog.text
        await until(lambda: svc.status().configured)


# === 4. system_id auto never picks a stranger ==============================================


async def test_auto_system_id_with_two_autopilots_chooses_none(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A second vehicle (system 2, 100 m away) heard first: neither is flown."""
    cfg = make_config(autopilot={"auto_id_listen_s": 1.0})
    async with over_udp(cfg, sysid=2, lat=HOME[0] + 0.0009) as (svc, stranger, _):
        own = FakeAutopilot(UdpOutLink(*svc.link.local_address))  # type: ignore[attr-defined]
        await own.start()
        try:
            await asyncio.sleep(2.5)
            assert svc.status().target_system is None and not svc.status().configured
            own.set_mode(GUIDED)
            await asyncio.sleep(0.5)
            assert not stranger.setpoints() and not own.setpoints()
            assert "autopilots of systems 1, 2 heard" in caplog.text
        finally:
            await own.stop()


async def test_second_autopilot_after_the_choice_blocks_take_over(
    caplog: pytest.LogCaptureFixture,
) -> None:
    async with over_udp() as (svc, own, _):
        await until(lambda: svc.status().configured)
        assert svc.status().target_system == 1
        stranger = FakeAutopilot(UdpOutLink(*svc.link.local_address), sysid=2)  # type: ignore[attr-defined]
        await stranger.start()
        try:
            await until(lambda: "a second autopilot (system 2)" in caplog.text)
            own.set_mode(GUIDED)
            await asyncio.sleep(0.8)
            assert (
                svc.status().owner != "engaged" and not own.setpoints() and not stranger.setpoints()
            )
            assert svc.status().target_system == 1  # never switched
            assert any("second autopilot 2 heard" in t for t in pilot_texts(own))
        finally:
            await stranger.stop()


# === issue 11: nothing heard; autopilot killed mid-flight and restarted ====================


async def test_nothing_heard_is_said_once(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="companion")
    link = UdpInLink("127.0.0.1", 0)
    svc = Service(make_config(), link, planner_factory=PlannerBox(), notifier=SystemdNotifier({}))
    task = asyncio.create_task(svc.run())
    await asyncio.sleep(5.0)
    svc.stop()
    assert await asyncio.wait_for(task, 10) == 0
    said = [r for r in caplog.records if "waiting for autopilot heartbeat on" in r.getMessage()]
    assert len(said) == 1 and "udpin:127.0.0.1:" in said[0].getMessage()
    assert "the autopilot must send here first" in said[0].getMessage()


async def test_autopilot_killed_mid_flight_and_restarted(caplog: pytest.LogCaptureFixture) -> None:
    """Killed while flying (auto start done): the service stops commanding and says why;
    the new boot (on the ground, disarmed) is neither armed nor taken off again."""
    async with over_udp(auto_cfg(), **on_ground()) as (svc, ap, task):
        await until(lambda: svc.status().owner == "engaged", 20.0)
        addr = svc.link.local_address  # type: ignore[attr-defined]
        await ap.stop()  # killed
        await until(lambda: svc.status().health is Health.EMERGENCY)
        await until(lambda: "STOP: autopilot heartbeat lost" in caplog.text)
        await asyncio.sleep(1.0)
        reborn = FakeAutopilot(UdpOutLink(*addr), **on_ground(custom_mode=STABILIZE))
        await reborn.start()
        try:
            await until(lambda: svc.status().configured and svc.tel.heartbeat is not None, 10.0)
            await asyncio.sleep(2.0)
            assert not commands(reborn, 400) and not commands(reborn, 22)
            assert not commands(reborn, 176) and not reborn.setpoints()
            assert svc.status().owner != "engaged" and not task.done()
        finally:
            await reborn.stop()


# === fuzzing what a byte fuzzer cannot reach: timestamps and sensor limits ==================

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from companion.service.telemetry import Telemetry  # noqa: E402

LAT, LON = round(HOME[0] * 1e7), round(HOME[1] * 1e7)
FORGED = st.lists(
    st.tuples(
        st.integers(0, 199),  # before which legitimate step
        st.sampled_from(["ATTITUDE", "GLOBAL_POSITION_INT", "DISTANCE_SENSOR"]),
        st.one_of(
            st.integers(0, 2**32 - 1),  # anywhere
            st.integers(-20_000, 20_000),  # near the true clock (offset from it)
        ),
        st.booleans(),  # absolute (True) or relative to the true stamp
    ),
    max_size=40,
    unique_by=lambda f: f[0],  # at most one forged message between two good ones
)


def _stamped(kind: str, tb: int) -> Any:
    tb &= 0xFFFFFFFF
    if kind == "ATTITUDE":
        return M.MAVLink_attitude_message(tb, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    if kind == "GLOBAL_POSITION_INT":
        return M.MAVLink_global_position_int_message(tb, LAT, LON, 493_000, 5000, 0, 0, 0, 0)
    return M.MAVLink_distance_sensor_message(tb, 10, 1000, 300, 0, 1, 39, 0, 0.0, 0.0, [0.0] * 4)


@pytest.mark.timeout(600)
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(base=st.integers(1_000, 2**31), forged=FORGED)
def test_fuzz_forged_timestamps_never_reset_nor_starve(
    base: int, forged: list[tuple[int, str, int, bool]]
) -> None:
    """200 steps of a good 20 Hz stream (attitude, position, a range) with single forged
    stamps (any value, or near the true clock) between them: never a reboot, and the
    attitude, position and range are never older than 0.4 s (the maximum ages are 0.5 s:
    no stop, no hold)."""
    t = Telemetry(make_config().sensor_table())
    by_step = {f[0]: f for f in forged}
    for k in range(200):
        now = 10.0 + 0.05 * k
        tb = base + 50 * k
        if k in by_step:
            _, kind, stamp, absolute = by_step[k]
            t.update(_stamped(kind, stamp if absolute else tb + stamp), now - 0.01)
        for kind in ("ATTITUDE", "GLOBAL_POSITION_INT", "DISTANCE_SENSOR"):
            t.update(_stamped(kind, tb), now)
        if k > 0:
            assert t.reboots == 0
            assert t.attitude is not None and now - t.attitude.t_rx <= 0.4
            assert t.position is not None and now - t.position.t_rx <= 0.4
            assert t.ranges[1] is not None and now - t.ranges[1].t_rx <= 0.4


@pytest.mark.timeout(600)
@settings(max_examples=300, deadline=None)
@given(
    min_cm=st.integers(0, 65535),
    max_cm=st.integers(0, 65535),
    cur_cm=st.integers(0, 65535),
)
def test_fuzz_sensor_limits_never_turn_something_into_nothing(
    min_cm: int, max_cm: int, cur_cm: int
) -> None:
    """Any min/max/current_distance on a sensor configured 0.1-10 m: a reading that reports
    something nearer than the configured maximum is never stored as "nothing" (0.0); no
    stored reading is in (0, min) (which the planner would also take as nothing); limits
    that shrink the configured range are refused."""
    t = Telemetry(make_config().sensor_table())
    msg = M.MAVLink_distance_sensor_message(
        1000, min_cm, max_cm, cur_cm, 0, 0, 0, 0, 0.0, 0.0, [0.0] * 4
    )
    stored = t.update(msg, 1.0) is not None
    given_limits = max_cm not in (0, 65535)
    shrinks = given_limits and (min_cm >= max_cm or min_cm > 15 or max_cm < 995)
    if shrinks:
        assert not stored and t.counters["rejected_sensor_limits"] == 1
        return
    assert stored
    d = t.ranges[0].distance_m if t.ranges[0] is not None else math.nan
    if 0 < cur_cm < 1000:
        assert d >= 0.1  # something there: at its distance, or at the minimum if closer
    else:
        assert d == 0.0  # 0, 65535 or at/over the maximum: nothing detected


# === 10. link and flight log faults ========================================================


async def test_port_in_use_is_one_line_and_an_exit_systemd_does_not_restart(
    caplog: pytest.LogCaptureFixture,
) -> None:
    import socket

    from companion.service.service import EXIT_LINK

    busy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    busy.bind(("127.0.0.1", 0))
    try:
        port = busy.getsockname()[1]
        cfg = make_config(link={"connection": f"udpin:127.0.0.1:{port}"})
        svc = Service(cfg, UdpInLink("127.0.0.1", port), notifier=SystemdNotifier({}))
        rc = await asyncio.wait_for(svc.run(), 10)
    finally:
        busy.close()
    assert rc == EXIT_LINK == 3
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "Address already in use" in errors[0].getMessage()
    assert errors[0].exc_info is None  # no traceback
    unit = (Path(__file__).resolve().parents[1] / "systemd" / "companion.service").read_text()
    prevent = [ln for ln in unit.splitlines() if ln.startswith("RestartPreventExitStatus=")]
    assert prevent and "3" in prevent[0].split("=", 1)[1].split()


async def test_missing_serial_device_is_said_and_retried(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from companion.service.link import open_link

    device = tmp_path / "ttyACM9"
    cfg = make_config(link={"connection": f"serial:{device}:57600"})
    path = tmp_path / "c.yaml"
    path.write_text(
        yaml.safe_dump(
            {
                "link": {"connection": f"serial:{device}:57600"},
                "route": {"source": "config", "points": [[30, 0]]},
                "sensors": SENSORS,
            }
        )
    )
    out = io.StringIO()
    assert check_config(path, out) == 0  # a USB device may come later: a note, not an error
    assert "No such file or directory" in out.getvalue()
    svc = Service(cfg, open_link(cfg.link.spec), notifier=SystemdNotifier({}))
    task = asyncio.create_task(svc.run())
    await asyncio.sleep(5.0)  # two retries
    assert not task.done()
    svc.stop()
    assert await asyncio.wait_for(task, 10) == 0
    said = [r for r in caplog.records if "cannot open serial:" in r.getMessage()]
    assert len(said) == 1 and "retrying" in said[0].getMessage()


async def test_flight_log_failing_mid_flight_keeps_flying_and_says_so(tmp_path: Path) -> None:
    cfg = make_config(logging={"flight_log_dir": str(tmp_path / "log")})
    async with over_udp(cfg) as (svc, ap, task):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 10)
        writer = svc.flight_log
        assert writer is not None
        await until(lambda: writer.path is not None and writer.path.exists())

        class Full:
            def write(self, data: str) -> int:
                raise OSError(28, "No space left on device")

            def flush(self) -> None: ...

            def close(self) -> None:
                raise OSError(28, "No space left on device")

        real_open = writer._open

        def full_open() -> None:
            writer._file = Full()

        writer.flush()
        writer._file.close()  # the real file, replaced by a full disk
        writer._file = Full()
        writer._open = full_open  # type: ignore[method-assign]
        await until(lambda: any("flight log failing" in t for t in pilot_texts(ap)), 5.0)
        n = len(ap.setpoints())
        await ap.wait_for(lambda: len(ap.setpoints()) >= n + 20)  # still flying
        assert svc.status().owner == "engaged" and not task.done()
        writer._open = real_open  # type: ignore[method-assign]
        writer._file = None
        await until(lambda: "flight log writing again" in pilot_texts(ap), 5.0)
        texts = pilot_texts(ap)
        assert sum("flight log failing" in t for t in texts) == 1  # said once, not every second
