"""The control cycle without a link, on a manual clock: ownership -> failsafe -> planner or
hold -> setpoint (`companion.service.cycle`, with the planner's host and a fake planner).

Inputs go straight into the telemetry with receipt times from the manual clock, the cycle's
messages into a list; no test here waits on the wall clock.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from companion.service.autopilot import AutopilotInfo
from companion.service.clock import ManualClock
from companion.service.codec import MavCodec
from companion.service.cycle import STOP_BRAKE_S, ControlCycle
from companion.service.failsafe import Limits, Verdict
from companion.service.host import PlannerHost
from companion.service.identity import Health
from companion.service.link import Link, Receiver
from companion.service.modes import AutopilotKind, OwnState
from companion.service.setpoints import SetpointFrame
from companion.service.statustext import Severity, StatusTexts
from companion.service.telemetry import Telemetry
from tests.service_fakes import FakeAutopilot, PlannerBox, make_config

GUIDED, LOITER = 4, 5
PERIOD_S = 0.05  # make_config's 20 Hz


class Tap(Link):
    """The fake autopilot's link: every frame it sends is decoded into the telemetry at once,
    stamped with the manual clock."""

    def __init__(self, tel: Telemetry, clock: ManualClock) -> None:
        super().__init__("tap")
        self.tel, self.clock, self.codec = tel, clock, MavCodec(255, 190)

    async def open(self, receiver: Receiver) -> None:
        pass

    def send(self, data: bytes) -> None:
        for msg in self.codec.decode(data, True):
            self.tel.update(msg, self.clock.now())

    async def close(self) -> None:
        pass


class ClockedAutopilot(FakeAutopilot):
    """time_boot_ms from the manual clock, so stamps and receipt times agree."""

    clock: ManualClock

    def time_boot_ms(self) -> int:
        return 1000 + round(self.clock.now() * 1000)


@dataclass
class Gate:
    configured: bool = True
    auto_busy: bool = False
    priming: bool = False
    stranger_blocks: bool = False
    checks: list[float] = field(default_factory=list)

    def check_streams(self, now: float) -> None:
        self.checks.append(now)


@dataclass
class Outbox:
    target_system: int | None = 1
    target_component: int | None = 1
    sent: list[Any] = field(default_factory=list)

    def send(self, msg: Any) -> None:
        self.sent.append(msg)

    def of_type(self, mtype: str) -> list[Any]:
        return [m for m in self.sent if m.get_type() == mtype]


@dataclass
class Rig:
    clock: ManualClock
    ap: ClockedAutopilot
    cycle: ControlCycle
    host: PlannerHost
    gate: Gate
    outbox: Outbox
    box: PlannerBox
    counters: Counter[str]

    def run(self, seconds: float, telemetry: bool = True) -> None:
        """Cycles every PERIOD_S for `seconds`, the autopilot streaming before each."""
        for _ in range(round(seconds / PERIOD_S)):
            self.clock.advance(PERIOD_S)
            self.ap.heartbeat()
            if telemetry:
                self.ap.telemetry()
            self.cycle.tick(self.clock.now())

    def setpoints(self) -> list[Any]:
        return self.outbox.of_type("SET_POSITION_TARGET_GLOBAL_INT")

    def texts(self) -> list[str]:
        return [m.text for m in self.outbox.of_type("STATUSTEXT")]


def rig(**sections: Any) -> Rig:
    cfg = make_config(**sections)
    clock = ManualClock(100.0)
    sensors = cfg.sensor_table()
    fs = cfg.failsafe
    tel = Telemetry(sensors, median_samples=fs.range_median_samples)
    limits = Limits(
        cfg.autopilot.heartbeat_timeout_s,
        fs.position_max_age_s,
        fs.attitude_max_age_s,
        fs.sensor_max_age_s,
    )
    counters: Counter[str] = Counter()
    texts = StatusTexts(50, 50, 0.0)

    def say(text: str, severity: Severity) -> None:
        texts.post(clock.now(), text, severity)

    box = PlannerBox()
    host = PlannerHost(
        cfg,
        sensors,
        tel,
        clock,
        planner_factory=box,
        say=say,
        counters=counters,
        flight_log=None,
        sim_time=True,  # build the planner in place
        period_s=PERIOD_S,
        sensor_max_age_s=limits.sensor_max_age_s,
        on_finish=lambda: None,
    )
    info = AutopilotInfo(AutopilotKind.ARDUPILOT, 2, SetpointFrame.GLOBAL_RELATIVE_ALT)
    gate, outbox = Gate(), Outbox()
    cycle = ControlCycle(
        cfg,
        tel,
        host,
        gate,
        info,
        outbox,
        limits=limits,
        required_sensors=list(range(len(sensors))),
        texts=texts,
        counters=counters,
        flight_log=None,
        wall=clock,
        boot_s=clock.now(),
        sim_time=False,
    )
    ap = ClockedAutopilot(Tap(tel, clock), custom_mode=LOITER)
    ap.clock = clock
    return Rig(clock, ap, cycle, host, gate, outbox, box, counters)


def test_standby_until_guided_then_the_planner_flies_at_the_clocks_period() -> None:
    r = rig()
    r.run(0.5)
    assert r.cycle.health is Health.STANDBY and r.setpoints() == []
    assert r.cycle.ownership.state is OwnState.WAITING
    r.ap.custom_mode = GUIDED
    r.run(1.0)
    assert r.cycle.ownership.state is OwnState.ENGAGED
    assert r.cycle.health is Health.ACTIVE and r.cycle.last_kind == "planner"
    (planner,) = r.box.made
    dts = [dt for _, _, dt in planner.inputs]
    assert len(dts) == 20 and dts == pytest.approx([PERIOD_S] * 20, abs=1e-9)
    assert len(r.setpoints()) == 20
    # time_boot_ms of the setpoints: the service clock since the cycle's boot, in ms
    stamps = [int(m.time_boot_ms) for m in r.setpoints()[:2]]
    assert stamps == pytest.approx([550, 600], abs=1)  # truncated to whole ms
    assert r.gate.checks[-1] == pytest.approx(r.clock.now())


def test_nothing_is_engaged_before_the_supervisor_has_configured() -> None:
    r = rig()
    r.gate.configured = False
    r.ap.custom_mode = GUIDED
    r.run(0.5)
    assert r.cycle.health is Health.BOOT and r.setpoints() == [] and r.box.made == []


def test_a_stale_sensor_holds_and_good_inputs_resume_after_resume_after_s() -> None:
    r = rig()
    r.ap.custom_mode = GUIDED
    r.run(0.5)
    r.ap.sensors_enabled = {0, 1}  # sensor 2 goes quiet
    r.run(1.0)
    assert r.cycle.last_verdict.verdict is Verdict.HOLD
    assert "sensor" in r.cycle.last_verdict.reason and r.cycle.health is Health.CRITICAL
    assert r.cycle.last_kind == "hold" and r.counters["hold_cycles"] > 0
    hold = r.setpoints()[-1]
    assert (hold.vx, hold.vy, hold.vz) == (0.0, 0.0, 0.0)
    assert any(t.startswith("HOLD") for t in r.texts())
    r.ap.sensors_enabled = None
    r.run(0.1)
    assert r.cycle.last_kind == "hold"  # good, but not yet for resume_after_s (0.2 s)
    r.run(0.3)
    assert r.cycle.last_kind == "planner" and r.cycle.health is Health.ACTIVE


def _heartbeats_only(r: Rig, seconds: float) -> None:
    for _ in range(round(seconds / PERIOD_S)):
        r.clock.advance(PERIOD_S)
        r.ap.heartbeat()
        r.cycle.tick(r.clock.now())


def test_the_position_going_stale_brakes_at_the_last_target_then_stops_commanding() -> None:
    """STOP sends no new target: the last one, at rest, for STOP_BRAKE_S (the autopilot would
    otherwise run on along its velocity), then nothing."""
    r = rig()
    r.ap.custom_mode = GUIDED
    r.run(0.5)
    moving = r.setpoints()[-1]
    assert (moving.vx, moving.vy) != (0.0, 0.0)  # the planner was flying
    n = len(r.setpoints())
    _heartbeats_only(r, 1.0)
    assert r.cycle.last_verdict.verdict is Verdict.STOP
    assert r.cycle.health is Health.EMERGENCY and r.cycle.last_kind == "brake"
    after = r.setpoints()[n:]
    # position_max_age_s (0.5 s) of planner setpoints, then the brake: the last target, at rest
    kinds = [(m.vx, m.vy, m.vz) == (0.0, 0.0, 0.0) for m in after]
    first_brake = kinds.index(True)
    assert all(kinds[first_brake:]) and first_brake <= 10
    last_planner = after[first_brake - 1] if first_brake else moving
    brakes = after[first_brake:]
    assert {(m.lat_int, m.lon_int, m.alt) for m in brakes} == {
        (last_planner.lat_int, last_planner.lon_int, last_planner.alt)
    }
    assert brakes[0].yaw == last_planner.yaw
    _heartbeats_only(r, STOP_BRAKE_S)
    m = len(r.setpoints())
    _heartbeats_only(r, 1.0)
    assert len(r.setpoints()) == m  # after STOP_BRAKE_S: silence
    assert r.counters["brake_cycles"] == pytest.approx(STOP_BRAKE_S / PERIOD_S, abs=2)


def test_no_brake_when_nothing_was_commanded() -> None:
    r = rig()
    r.run(0.5)  # LOITER: never engaged
    _heartbeats_only(r, 1.0)
    assert r.setpoints() == [] and r.counters["brake_cycles"] == 0


def test_a_mode_change_releases_at_once_and_for_good() -> None:
    r = rig()
    r.ap.custom_mode = GUIDED
    r.run(0.5)
    r.ap.custom_mode = LOITER
    r.run(0.05)
    n = len(r.setpoints())
    assert r.cycle.ownership.state is OwnState.RELEASED and r.counters["released"] == 1
    r.run(0.5)
    assert len(r.setpoints()) == n


def test_a_planner_exception_holds_instead_of_crashing() -> None:
    r = rig()
    r.ap.custom_mode = GUIDED
    r.run(0.2)
    r.box.made[0].fail = True
    r.run(0.2)
    assert r.cycle.health is Health.CRITICAL and r.cycle.last_kind == "hold"
    assert r.counters["planner_errors"] == 4 and r.cycle.hold_reason() == "planner error"
    r.box.made[0].fail = False
    r.run(0.05)
    assert r.cycle.health is Health.ACTIVE and r.cycle.hold_reason() == ""


def test_set_desired_height_reaches_the_planner_and_rejects_nonsense() -> None:
    r = rig()
    r.ap.custom_mode = GUIDED
    r.run(0.1)
    r.host.set_desired_height(3.5)
    assert r.box.made[0].h_d == 3.5 and r.host.h_d_m == 3.5
    with pytest.raises(ValueError, match="h_d_m: expected a number greater than 0"):
        r.host.set_desired_height(-1.0)
    assert r.host.h_d_m == 3.5


def test_non_finite_setpoints_never_reach_the_wire() -> None:
    r = rig()
    r.ap.custom_mode = GUIDED
    r.run(0.1)
    from companion.planner.types import Setpoint

    n = len(r.setpoints())
    r.cycle.send_setpoint(Setpoint(np.array([np.nan, 0, 0]), np.zeros(3), 0.0, 0.0), 1.0)
    assert len(r.setpoints()) == n and r.counters["setpoints_refused_nonfinite"] == 1
    bad_accel = Setpoint(np.zeros(3), np.zeros(3), 0.0, 0.0, np.array([0.0, np.inf, 0.0]))
    r.cycle.send_setpoint(bad_accel, 1.0)
    assert len(r.setpoints()) == n and r.counters["setpoints_refused_nonfinite"] == 2


@pytest.mark.parametrize("feedforward", [True, False])
def test_the_acceleration_goes_out_unless_configured_off(feedforward: bool) -> None:
    from companion.planner.types import Setpoint

    r = rig(autopilot={"acceleration_feedforward": feedforward})
    r.ap.custom_mode = GUIDED
    r.run(0.1)
    sp = Setpoint(np.zeros(3), np.array([1.0, 0.0, 0.0]), 0.0, 0.0, np.array([0.5, 0.0, 0.2]))
    r.cycle.send_setpoint(sp, 1.0)
    msg = r.setpoints()[-1]
    if feedforward:
        assert msg.type_mask & 0b111000000 == 0
        assert (msg.afx, msg.afy, msg.afz) == pytest.approx((0.0, 0.5, -0.2))  # NED
    else:
        assert msg.type_mask & 0b111000000 == 0b111000000
        assert (msg.afx, msg.afy, msg.afz) == (0.0, 0.0, 0.0)


def take_over_after_landing(r: Rig) -> None:
    """Disarmed for 0.2 s, then armed in GUIDED: the next take-over is a flight's first."""
    r.ap.armed = False
    r.run(0.2)
    r.ap.armed = True
    r.ap.custom_mode = GUIDED


def test_the_vehicle_turns_to_face_the_route_before_the_planner_starts() -> None:
    """Facing north with the route east: hold at the take-over point with the yaw on the
    first leg's bearing, say so, and build the planner once the heading is within 10 deg."""
    r = rig(control={"face_route_deg": 30.0})
    take_over_after_landing(r)  # seen on the ground: a flight's first take-over
    r.run(1.0)
    assert r.box.made == [] and r.cycle.last_kind == "hold"
    assert r.cycle.hold_reason() == "turning to face the route"
    assert any("turning 90 deg to face the route" in t for t in r.texts())
    sp = r.setpoints()[-1]
    assert abs(sp.yaw - np.pi / 2) < 1e-3  # MAVLink yaw: east, clockwise from north
    r.ap.yaw = np.radians(85.0)  # within 10 deg of the bearing
    r.run(0.5)
    assert len(r.box.made) == 1 and r.cycle.last_kind == "planner"
    assert r.host.facing is None


def test_a_turn_the_vehicle_does_not_follow_ends_after_its_timeout() -> None:
    r = rig(control={"face_route_deg": 30.0})
    take_over_after_landing(r)
    r.run(29.0)
    assert r.box.made == []
    r.run(1.5)
    assert len(r.box.made) == 1 and r.cycle.last_kind == "planner"
    assert any("not done in 30 s" in t for t in r.texts())


def test_no_turn_within_face_route_deg() -> None:
    r = rig(control={"face_route_deg": 30.0})
    r.ap.yaw = np.radians(70.0)  # 20 deg off the route's bearing (east)
    take_over_after_landing(r)
    r.run(1.0)
    assert len(r.box.made) == 1 and not any("face the route" in t for t in r.texts())


def test_no_turn_in_mid_flight_nor_near_an_obstacle() -> None:
    """A take-over of a vehicle never seen disarmed (a service restarted in flight), and one
    with an obstacle reading within 3 D_min, start from the heading the vehicle has."""
    r = rig(control={"face_route_deg": 30.0})
    r.ap.custom_mode = GUIDED
    r.run(1.0)
    assert len(r.box.made) == 1 and not any("face the route" in t for t in r.texts())

    r = rig(control={"face_route_deg": 30.0})
    r.ap.ranges_cm = {0: 450, 1: 700, 2: 700}  # the obstacle sensor at 4.5 m < 3 D_min
    take_over_after_landing(r)
    r.run(1.0)
    assert len(r.box.made) == 1 and not any("face the route" in t for t in r.texts())
