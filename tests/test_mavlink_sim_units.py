"""sim.mavlink pieces without sockets: config, personalities, scheduling, setpoint decoding,
the position controller, DISTANCE_SENSOR filling, faults, the mission protocol, the autopilot
state machine and the bridge core."""

from __future__ import annotations

import asyncio
import math
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.geo import GeoPoint, LocalFrame
from companion.planner.frames import yaw_enu_to_ned
from companion.planner.rotations import r_g
from companion.planner.sensors import boresight_from_quaternion_frd
from companion.planner.types import VehicleState
from companion.sim.mavlink import MavlinkSimConfig, SimServer
from companion.sim.mavlink import codec as codec_module
from companion.sim.mavlink.autopilot import Autopilot
from companion.sim.mavlink.bridge import BridgeCore
from companion.sim.mavlink.codec import Codec
from companion.sim.mavlink.config import BridgeConfig, LinkFaultConfig, SensorFaultConfig
from companion.sim.mavlink.control import ReferenceShaper
from companion.sim.mavlink.faults import LinkFaults, SensorFaults, fault_rngs
from companion.sim.mavlink.mission import RETRY_S, MissionItem, MissionServer
from companion.sim.mavlink.personality import ARDUCOPTER, PX4, Behaviour, px4_custom_mode
from companion.sim.mavlink.rangefinder import Rangefinders
from companion.sim.mavlink.setpoints import (
    ACC_IGNORE,
    POS_IGNORE,
    VEL_IGNORE,
    YAW_IGNORE,
    YAW_RATE_IGNORE,
    FrameContext,
    Outcome,
    decode_ardupilot,
    decode_px4,
)
from companion.sim.mavlink.telemetry import MessageScheduler
from tests.test_mavlink_sim_support import PlaneAndWall, make_server, sensors

pytestmark = pytest.mark.timeout(30)

HOME = GeoPoint(-35.363261, 149.165230, 584.0)
FRAME = LocalFrame(HOME)
ENC = mavlink.MAVLink(None, 42, 191)
POS_ONLY = VEL_IGNORE | ACC_IGNORE | YAW_IGNORE | YAW_RATE_IGNORE
POS_VEL = ACC_IGNORE | YAW_IGNORE | YAW_RATE_IGNORE
VEL_ONLY = POS_IGNORE | ACC_IGNORE | YAW_IGNORE | YAW_RATE_IGNORE


def wire(msg: Any) -> Any:
    """Pack and parse, so the message carries a header (source system/component)."""
    rx = mavlink.MAVLink(None)
    return rx.parse_buffer(msg.pack(ENC))[0]


def target(
    frame: int,
    mask: int,
    east: float,
    north: float,
    alt: float,
    vel=(0, 0, 0),
    accel=(0, 0, 0),
) -> Any:
    g = FRAME.to_geodetic(east, north, 0.0)
    return wire(
        ENC.set_position_target_global_int_encode(
            0,
            1,
            1,
            frame,
            mask,
            round(g.lat_deg * 1e7),
            round(g.lon_deg * 1e7),
            alt,
            *vel,
            *accel,
            0,
            0,
        )
    )


def ctx(home_z: float = 0.0, origin_z: float = 0.0) -> FrameContext:
    return FrameContext(
        FRAME, np.array([0.0, 0.0, home_z]), np.array([0.0, 0.0, origin_z]), lambda x, y: 3.0
    )


# ------------------------------------------------------------------------------- config
def test_config_defaults_and_rejections() -> None:
    c = MavlinkSimConfig()
    assert c.personality == "ardupilot" and c.port == 14580 and c.physics_dt_s == 0.01
    assert c.home_or_default.lat_deg == pytest.approx(-35.363261)
    assert MavlinkSimConfig(personality="px4").home_or_default.lat_deg == pytest.approx(47.397742)
    with pytest.raises(ValidationError, match="extra"):
        MavlinkSimConfig.model_validate({"prot": 1})
    with pytest.raises(ValidationError, match="whole multiple"):
        MavlinkSimConfig.model_validate({"lockstep": {"enabled": True, "period_s": 0.015}})
    with pytest.raises(ValidationError, match="host:port"):
        MavlinkSimConfig(target="localhost")
    with pytest.raises(ValidationError, match="unknown messages"):
        MavlinkSimConfig(rates_hz={"ATTITUDE_QUATERNION": 10})
    with pytest.raises(ValidationError, match="start < end"):
        MavlinkSimConfig.model_validate({"faults": {"link_cuts": [[5, 4]]}})
    with pytest.raises(ValidationError, match="companion_address"):
        BridgeConfig(send_to="companion")
    assert math.isinf(MavlinkSimConfig(speedup=math.inf).speedup)


# -------------------------------------------------------------------------- personality
def test_personality_modes() -> None:
    assert ARDUCOPTER.mode("guided").custom_mode == 4
    assert ARDUCOPTER.mode("GUIDED").behaviour is Behaviour.GUIDED
    assert PX4.mode("OFFBOARD").custom_mode == 6 << 16
    assert PX4.mode("hold").custom_mode == px4_custom_mode(4, 3) == (4 << 16) | (3 << 24)
    assert PX4.mode_from_command(1, 6, 0) is PX4.mode("OFFBOARD")
    assert PX4.mode_from_command(0, 6, 0) is None  # custom mode flag missing
    assert ARDUCOPTER.mode_from_command(1, 5, 0) is ARDUCOPTER.mode("LOITER")
    assert ARDUCOPTER.mode_from_spec(4).name == "GUIDED"
    assert PX4.mode_for_custom(3 << 16 | 7 << 24) is PX4.mode("POSCTL")  # sub ignored
    base = ARDUCOPTER.base_mode(ARDUCOPTER.mode("GUIDED"), armed=True)
    assert base & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert base & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    with pytest.raises(ValueError, match="no mode"):
        PX4.mode("SPORT")


# ---------------------------------------------------------------------------- scheduler
def test_scheduler_intervals() -> None:
    s = MessageScheduler({"HEARTBEAT": 1.0})
    ticks = [i * 0.01 for i in range(100)]
    assert sum(mavlink.MAVLINK_MSG_ID_ATTITUDE in s.due(t) for t in ticks) == 0
    assert s.set_interval_us(mavlink.MAVLINK_MSG_ID_ATTITUDE, 100_000, 0.0)
    assert s.interval_us(mavlink.MAVLINK_MSG_ID_ATTITUDE) == 100_000
    # a new interval's first send is one interval later (ArduPilot): 0.1, 0.2, ..., 0.9 s
    assert sum(mavlink.MAVLINK_MSG_ID_ATTITUDE in s.due(t) for t in ticks) == 9
    s.set_interval_us(mavlink.MAVLINK_MSG_ID_ATTITUDE, -1, 1.0)
    assert s.interval_us(mavlink.MAVLINK_MSG_ID_ATTITUDE) == -1
    assert not s.set_interval_us(mavlink.MAVLINK_MSG_ID_VFR_HUD, 100_000, 1.0)
    assert s.interval_us(mavlink.MAVLINK_MSG_ID_VFR_HUD) == 0
    s.set_interval_us(mavlink.MAVLINK_MSG_ID_HEARTBEAT, 0, 1.0)  # back to the default
    assert s.interval_us(mavlink.MAVLINK_MSG_ID_HEARTBEAT) == 1_000_000


ATT = mavlink.MAVLINK_MSG_ID_ATTITUDE
GPI = mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT
DS = mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR
HB = mavlink.MAVLINK_MSG_ID_HEARTBEAT


def _sends(s: MessageScheduler, start: int, stop: int) -> dict[int, list[int]]:
    """Tick index (10 ms ticks) -> messages due at it, for ticks start..stop-1."""
    return {k: d for k in range(start, stop) if (d := s.due(k * 0.01))}


def test_scheduler_buckets_send_one_interval_together_in_ardupilot_order() -> None:
    s = MessageScheduler({"HEARTBEAT": 1.0}, "buckets")
    s.due(0.0)
    # rates set in different ticks, as a companion's commands arrive one after another
    s.set_interval_us(DS, 20_000, 0.01)
    s.set_interval_us(GPI, 20_000, 0.02)
    s.set_interval_us(ATT, 20_000, 0.05)
    s.set_interval_us(mavlink.MAVLINK_MSG_ID_SYS_STATUS, 1_000_000, 0.05)
    sent = _sends(s, 1, 106)
    fast = {k: [m for m in d if m in (ATT, GPI, DS)] for k, d in sent.items()}
    fast = {k: d for k, d in fast.items() if d}
    # one phase, the first one's (set at tick 1, first sent 2 ticks later): every other tick
    assert sorted(fast) == list(range(3, 106, 2))
    assert all(d == [ATT, GPI, DS] for d in fast.values())
    assert [k for k, d in sent.items() if HB in d] == [100]
    assert [k for k, d in sent.items() if mavlink.MAVLINK_MSG_ID_SYS_STATUS in d] == [105]
    # the same interval again keeps the phase; another one opens a group of its own
    s.set_interval_us(GPI, 20_000, 1.061)
    s.set_interval_us(DS, 100_000, 1.061)
    later = _sends(s, 107, 140)
    assert [k for k, d in later.items() if GPI in d] == list(range(107, 140, 2))
    assert [k for k, d in later.items() if DS in d] == [117, 127, 137]
    # a message switched off leaves its group; the others keep their phase
    s.set_interval_us(ATT, -1, 1.40)
    assert [k for k, d in _sends(s, 140, 146).items() if GPI in d] == [141, 143, 145]
    assert not any(ATT in d for d in _sends(s, 146, 200).values())


def test_scheduler_per_stream_phases() -> None:
    s = MessageScheduler({"HEARTBEAT": 1.0, "ATTITUDE": 50.0}, "per_stream")
    assert s.due(0.0) == [HB, ATT]  # the defaults start at boot, together
    s.set_interval_us(GPI, 20_000, 0.01)  # a stream that was off starts at once
    s.set_interval_us(ATT, 20_000, 0.01)  # one that streams keeps its phase
    sent = _sends(s, 1, 9)
    assert [k for k, d in sent.items() if GPI in d] == [1, 3, 5, 7]
    assert [k for k, d in sent.items() if ATT in d] == [2, 4, 6, 8]
    s.set_interval_us(ATT, 50_000, 0.09)  # last sent at tick 8: next at 8 + 5
    assert [k for k, d in _sends(s, 9, 20).items() if ATT in d] == [13, 18]


# ---------------------------------------------------------------------------- setpoints
def test_ardupilot_frames() -> None:
    rel = decode_ardupilot(target(6, POS_ONLY, 10, 20, 5.0), ctx(home_z=2.0), 1.0)
    assert rel.outcome is Outcome.ACCEPT and rel.target is not None
    assert rel.target.position_enu == pytest.approx([10, 20, 7.0], abs=0.02)
    amsl = decode_ardupilot(target(5, POS_ONLY, 10, 20, 590.0), ctx(), 1.0)
    assert amsl.target is not None and amsl.target.position_enu[2] == pytest.approx(6.0, abs=0.02)
    terrain = decode_ardupilot(target(11, POS_ONLY, 10, 20, 2.0), ctx(), 1.0)
    assert terrain.target is not None and terrain.target.position_enu[2] == pytest.approx(5.0)
    assert decode_ardupilot(target(11, POS_VEL, 1, 1, 2.0), ctx(), 1).outcome is Outcome.STOP
    assert decode_ardupilot(target(1, POS_ONLY, 1, 1, 2.0), ctx(), 1).outcome is Outcome.STOP
    vel = decode_ardupilot(target(1, VEL_ONLY, 0, 0, 0, vel=(1, 2, -0.5)), ctx(), 1.0)
    assert vel.outcome is Outcome.ACCEPT and vel.target is not None
    assert vel.target.velocity_enu == pytest.approx([2, 1, 0.5])  # NED -> ENU
    force = target(6, POS_ONLY & ~ACC_IGNORE | 512, 1, 1, 2.0)
    assert decode_ardupilot(force, ctx(), 1).outcome is Outcome.STOP


def test_px4_frames_and_relative_altitude_quirk() -> None:
    assert decode_px4(target(3, POS_ONLY, 1, 1, 5.0), ctx(), 1.0).outcome is Outcome.IGNORE
    assert decode_px4(target(0, POS_ONLY, 1, 1, 5.0), ctx(), 1.0).outcome is Outcome.IGNORE
    good = decode_px4(target(5, POS_ONLY, 1, 1, 599.0), ctx(home_z=10.0), 1.0)
    assert good.target is not None and good.target.position_enu[2] == pytest.approx(15, abs=0.01)
    # Home 10 m above the estimator origin: 15 m relative flies to 5 m above the origin,
    # -5 m relative to home (PX4 SITL flew -4.8 m).
    quirk = decode_px4(target(6, POS_ONLY, 1, 1, 15.0), ctx(home_z=10.0, origin_z=0.0), 1.0)
    assert quirk.target is not None
    assert quirk.target.position_enu[2] - 10.0 == pytest.approx(-5.0, abs=0.01)
    same = decode_px4(target(6, POS_ONLY, 1, 1, 15.0), ctx(home_z=10.0, origin_z=10.0), 1.0)
    assert same.target is not None and same.target.position_enu[2] == pytest.approx(25, abs=0.01)


def test_both_read_the_acceleration_feedforward_unless_masked() -> None:
    pos_vel_acc = POS_VEL & ~ACC_IGNORE
    for decode in (decode_ardupilot, decode_px4):
        msg = target(5, pos_vel_acc, 1, 1, 590.0, vel=(1, 0, 0), accel=(0.2, -0.1, -0.4))
        d = decode(msg, ctx(), 1.0)
        assert d.outcome is Outcome.ACCEPT and d.target is not None
        assert d.target.acceleration_enu == pytest.approx([-0.1, 0.2, 0.4])  # NED -> ENU
        masked = decode(target(5, POS_VEL, 1, 1, 590.0, accel=(0.2, 0, 0)), ctx(), 1.0)
        assert masked.target is not None and masked.target.acceleration_enu is None
    bad = target(5, pos_vel_acc, 1, 1, 590.0, accel=(math.nan, 0, 0))
    assert decode_ardupilot(bad, ctx(), 1.0).outcome is Outcome.STOP


# ------------------------------------------------------------------------------ control
def test_reference_acceleration_is_its_velocity_change_within_the_limit() -> None:
    cfg = MavlinkSimConfig()
    sh = ReferenceShaper(cfg.limits, np.zeros(3), 0.0)
    for k in range(1, 200):
        before = sh.velocity.copy()
        sh.step(None, np.array([0.01 * k, 0.0, 0.0]), None, None, 0.01)  # 1 m/s^2 ramp
        assert sh.acceleration == pytest.approx((sh.velocity - before) / 0.01)
        assert np.linalg.norm(sh.acceleration) <= cfg.limits.accel_mps2 + 1e-9
    assert sh.acceleration == pytest.approx([min(1.0, cfg.limits.accel_mps2), 0.0, 0.0])


def test_reference_reaches_target_within_limits() -> None:
    cfg = MavlinkSimConfig()
    sh = ReferenceShaper(cfg.limits, np.zeros(3), 0.0)
    goal = np.array([30.0, -10.0, 8.0])
    speeds = []
    for _ in range(3000):
        sh.step(goal, None, 1.0, None, 0.01)
        speeds.append(np.linalg.norm(sh.velocity[:2]))
    assert sh.position == pytest.approx(goal, abs=0.01)
    assert max(speeds) <= cfg.limits.speed_xy_mps + 1e-9
    assert sh.yaw_rad == pytest.approx(1.0)


# --------------------------------------------------------------------- distance sensors
def test_distance_sensor_filling() -> None:
    world = PlaneAndWall(wall_x=10.0)
    specs = sensors()
    ap = Rangefinders(specs, world, "ardupilot")
    px4 = Rangefinders(specs, world, "px4")
    state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    ranges = ap.measure(state)
    assert ranges[0] == pytest.approx(10.0)  # forward, into the wall
    assert ranges[1] == pytest.approx(10.0 / math.cos(math.radians(15)))  # tilted up 15 deg
    assert math.isinf(ranges[2])  # backwards: nothing
    assert ranges[3] == pytest.approx(2.0 * math.sqrt(2))  # 45 deg down
    msgs = [wire(ap.message(ENC, i, float(r), 1234)) for i, r in enumerate(ranges)]
    assert [m.id for m in msgs] == [3, 4, 5, 7, 8]  # ArduPilot: the configured ids
    assert [m.id for m in (wire(px4.message(ENC, i, 5.0, 0)) for i in range(5))] == [0, 1, 2, 3, 4]
    assert msgs[0].orientation == mavlink.MAV_SENSOR_ROTATION_NONE
    assert msgs[2].orientation == mavlink.MAV_SENSOR_ROTATION_YAW_180
    assert msgs[3].orientation == mavlink.MAV_SENSOR_ROTATION_PITCH_315
    assert msgs[0].current_distance in (999, 1000) and msgs[0].max_distance == 1200
    assert msgs[2].current_distance == 1300  # ArduPilot: nothing in range = max + 1 m
    custom = msgs[1]
    assert custom.orientation == 100
    assert boresight_from_quaternion_frd(custom.quaternion) == pytest.approx(
        specs[1].boresight_frd, abs=1e-6
    )
    assert msgs[0].quaternion == [0.0, 0.0, 0.0, 0.0]
    # PX4: float32 metres -> cm, truncated; nothing in range = UINT16_MAX / 100 m.
    assert px4.current_cm(0, 0.53) == ap.current_cm(0, 0.53) == 52
    assert px4.current_cm(0, 4.57) == 457
    assert px4.current_cm(2, math.inf) == int(np.float32(655.35) * np.float32(100.0))
    assert px4.current_cm(2, math.inf) >= 65534
    assert ap.current_cm(0, 12.0) == 1300  # at max: out of range


def test_sensor_rays_follow_attitude() -> None:
    world = PlaneAndWall(wall_x=1000.0)
    rf = Rangefinders(sensors(), world, "ardupilot")
    pitched_down = VehicleState(np.array([0.0, 0.0, 5.0]), 0.0, -math.radians(45), 0.0)
    r = rf.measure(pitched_down)
    assert r[0] == pytest.approx(5.0 * math.sqrt(2))  # forward now 45 deg down
    assert r[3] == pytest.approx(5.0)  # forward-45-down now straight down
    u = sensors()[0].boresight_flu @ r_g(0.0, -math.radians(45), 0.0).T
    assert u == pytest.approx([math.sqrt(0.5), 0, -math.sqrt(0.5)])


# ------------------------------------------------------------------------------- faults
def test_link_faults_are_seeded_and_about_as_configured() -> None:
    cfg = LinkFaultConfig(loss_probability=0.2, duplicate_probability=0.1)
    a: LinkFaults[int] = LinkFaults(cfg, fault_rngs(7)[1])
    b: LinkFaults[int] = LinkFaults(cfg, fault_rngs(7)[1])
    out_a = [x for i in range(10_000) for x in a.filter(i)]
    out_b = [x for i in range(10_000) for x in b.filter(i)]
    assert out_a == out_b
    assert a.stats.dropped / 10_000 == pytest.approx(0.2, abs=0.02)
    assert a.stats.duplicated / 8_000 == pytest.approx(0.1, abs=0.02)
    reorder: LinkFaults[int] = LinkFaults(
        LinkFaultConfig(reorder_probability=1.0), fault_rngs(1)[2]
    )
    assert reorder.filter(1) == [] and reorder.filter(2) == [2, 1]


def test_sensor_faults() -> None:
    rng = fault_rngs(3)[0]
    cfgs = [
        SensorFaultConfig(sensor_id=1, stuck_windows=[(1.0, 2.0)]),
        SensorFaultConfig(sensor_id=2, dropout_windows=[(0.0, 5.0)]),
        SensorFaultConfig(sensor_id=3, noise_std_m=0.1),
        SensorFaultConfig(sensor_id=4, spike_probability=1.0, spike_range_m=(0.5, 0.6)),
    ]
    f = SensorFaults(cfgs, [1, 2, 3, 4], np.zeros(4) + 0.1, np.zeros(4) + 10, rng)
    true = np.array([5.0, 5.0, 5.0, 5.0])
    f.apply(1.0, true)
    later, send = f.apply(1.5, true + 1.0)
    assert later[0] == 5.0  # stuck at the value when the window opened
    assert not send[1] and send[0] and send[2]
    assert 0.5 <= later[3] <= 0.6
    noisy = np.array([f.apply(3.0, true)[0][2] for _ in range(2000)])
    assert noisy.std() == pytest.approx(0.1, rel=0.1)
    assert f.apply(2.5, true + 2.0)[0][0] == 7.0  # window closed


# ------------------------------------------------------------------------------ mission
def _mission(home: bool) -> tuple[MissionServer, list[Any]]:
    sent: list[Any] = []
    home_item = MissionItem(0, 0, 16, 0, 1, 0, 0, 0, 0, -353632610, 1491652300, 584.0)
    server = MissionServer(
        mavlink.MAVLink(None, 1, 1), sent.append, (lambda: home_item) if home else None
    )
    return server, sent


def _item(seq: int) -> Any:
    return wire(
        ENC.mission_item_int_encode(
            1, 1, seq, 6, 16, 0, 1, 0, 0, 0, 0, -353632610 + seq, 1491652300, 10.0 + seq, 0
        )
    )


@pytest.mark.parametrize("home", [True, False])
def test_mission_upload_download(home: bool) -> None:
    server, sent = _mission(home)
    n = 3 + int(home)
    server.handle(wire(ENC.mission_count_encode(1, 1, n, 0)), 0.0)
    for seq in range(n):
        req = sent.pop()
        assert req.get_type() == "MISSION_REQUEST_INT" and req.seq == seq
        server.handle(_item(seq), 0.1)
    ack = sent.pop()
    assert ack.get_type() == "MISSION_ACK" and ack.type == mavlink.MAV_MISSION_ACCEPTED
    server.handle(wire(ENC.mission_request_list_encode(1, 1, 0)), 1.0)
    assert sent.pop().count == n
    server.handle(wire(ENC.mission_request_int_encode(1, 1, 1, 0)), 1.0)
    item = sent.pop()
    assert item.get_type() == "MISSION_ITEM_INT" and item.x == -353632610 + 1 and item.z == 11.0
    server.handle(wire(ENC.mission_request_int_encode(1, 1, 0, 0)), 1.0)
    first = sent.pop()
    assert first.z == (584.0 if home else 10.0)  # ArduPilot: item 0 is home


def test_mission_errors_and_retries() -> None:
    server, sent = _mission(True)
    server.handle(wire(ENC.mission_count_encode(1, 1, 2, 0)), 0.0)
    server.handle(_item(1), 0.1)
    assert sent[-1].get_type() == "MISSION_ACK"
    assert sent[-1].type == mavlink.MAV_MISSION_INVALID_SEQUENCE
    n = len(sent)
    server.tick(RETRY_S + 0.01)
    assert sent[-1].get_type() == "MISSION_REQUEST_INT" and sent[-1].seq == 0 and len(sent) > n
    for k in range(2, 8):
        server.tick(k * RETRY_S + 0.02)
    assert sent[-1].type == mavlink.MAV_MISSION_OPERATION_CANCELLED
    server.handle(wire(ENC.mission_count_encode(1, 1, 2, 9)), 20.0)
    assert sent[-1].type == mavlink.MAV_MISSION_UNSUPPORTED


# ---------------------------------------------------------------------------- autopilot
def _autopilot(p: Any = ARDUCOPTER, **cfg: Any) -> tuple[Autopilot, VehicleState]:
    config = MavlinkSimConfig.model_validate({"prearm_delay_s": 1.0, **cfg})
    state = VehicleState(np.zeros(3), 0.0, 0.0, 0.0)
    return Autopilot(p, config, FRAME, lambda x, y: 0.0, state), state


def _fly(ap: Autopilot, state: VehicleState, t0: float, t1: float) -> tuple[VehicleState, float]:
    t = t0
    while t < t1 - 1e-9:
        sp = ap.update(t, 0.01, state)
        if sp is not None:
            state = VehicleState(sp.position_enu, 0.0, 0.0, sp.yaw_rad)
        t += 0.01
    return state, t


def test_ardupilot_arming_takeoff_and_guided_timeout() -> None:
    ap, state = _autopilot()
    assert ap.set_mode(ARDUCOPTER.mode("GUIDED"), 0.5, state) == mavlink.MAV_RESULT_FAILED
    assert ap.set_mode(ARDUCOPTER.mode("GUIDED"), 1.0, state) == mavlink.MAV_RESULT_ACCEPTED
    assert ap.takeoff(5.0, False, 1.0, state) == mavlink.MAV_RESULT_FAILED  # not armed
    assert ap.arm(1.0, state, force=False) == mavlink.MAV_RESULT_ACCEPTED
    assert ap.takeoff(5.0, False, 1.0, state) == mavlink.MAV_RESULT_ACCEPTED
    state, t = _fly(ap, state, 1.0, 8.0)
    assert state.position_enu[2] == pytest.approx(5.0, abs=0.05) and ap.takeoff_z is None
    # Velocity target: flies for GUID_TIMEOUT (3 s), then stops and stays.
    ap.position_target(target(1, VEL_ONLY, 0, 0, 0, vel=(0, 2, 0)), t)
    state, t = _fly(ap, state, t, t + 3.0)
    east_at_timeout = state.position_enu[0]
    assert east_at_timeout > 4.0
    state, t = _fly(ap, state, t, t + 5.0)
    assert state.position_enu[0] - east_at_timeout < 1.5  # braking distance only
    still = state.position_enu[0]
    state, t = _fly(ap, state, t, t + 5.0)
    assert state.position_enu[0] == pytest.approx(still, abs=1e-3)
    # Disarming in the air is refused; LAND touches down and disarms.
    assert ap.disarm(t, force=False) == mavlink.MAV_RESULT_FAILED
    assert ap.set_mode(ARDUCOPTER.mode("LAND"), t, state) == mavlink.MAV_RESULT_ACCEPTED
    state, t = _fly(ap, state, t, t + 15.0)
    assert ap.landed and not ap.armed


def _guided_at_5_m() -> tuple[Autopilot, VehicleState, float]:
    """An ArduCopter in GUIDED, taken off to 5 m: (autopilot, state, sim time)."""
    ap, state = _autopilot()
    ap.set_mode(ARDUCOPTER.mode("GUIDED"), 1.0, state)
    ap.arm(1.0, state, False)
    ap.takeoff(5.0, False, 1.0, state)
    state, t = _fly(ap, state, 1.0, 6.0)
    return ap, state, t


def test_ardupilot_position_velocity_target_is_integrated_until_timeout() -> None:
    ap, state, t = _guided_at_5_m()
    ap.position_target(target(6, POS_VEL, 0, 0, 5.0, vel=(1.0, 0, 0)), t)  # north at 1 m/s
    state, t = _fly(ap, state, t, t + 10.0)
    assert state.position_enu[1] == pytest.approx(3.0, abs=0.05)  # integrated for 3 s only


def test_ardupilot_integrates_the_acceleration_target_too() -> None:
    ap, state, t = _guided_at_5_m()
    mask = POS_VEL & ~ACC_IGNORE
    ap.position_target(target(6, mask, 0, 0, 5.0, vel=(0, 0, 0), accel=(0.2, 0, 0)), t)
    state, t = _fly(ap, state, t, t + 10.0)
    # north along 0.2 t^2 / 2 for the 3 s of GUID_TIMEOUT: 0.9 m
    assert state.position_enu[1] == pytest.approx(0.9, abs=0.05)


def test_auto_disarm_when_not_taking_off() -> None:
    ap, state = _autopilot()
    ap.arm(2.0, state, False)
    _fly(ap, state, 2.0, 11.0)
    assert ap.armed
    _fly(ap, state, 11.0, 12.5)
    assert not ap.armed


def test_px4_offboard_needs_a_stream_and_fails_safe() -> None:
    ap, state = _autopilot(PX4)
    offboard = PX4.mode("OFFBOARD")
    refused = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    assert ap.set_mode(offboard, 2.0, state) == refused
    assert "not available" in ap.texts[-1].text
    ap.position_target(target(5, POS_ONLY, 0, 0, 584.0), 2.0)
    ap.position_target(target(5, POS_ONLY, 0, 0, 584.0), 3.0)  # 1 Hz: too slow
    assert ap.set_mode(offboard, 3.0, state) == refused
    ap.position_target(target(5, POS_ONLY, 0, 0, 590.0), 3.4)
    assert ap.set_mode(offboard, 3.5, state) == mavlink.MAV_RESULT_ACCEPTED
    assert ap.arm(3.5, state, False) == mavlink.MAV_RESULT_ACCEPTED
    t = 3.5
    for _ in range(40):  # 10 Hz stream, lifts off towards 6 m
        ap.position_target(target(5, POS_ONLY, 0, 0, 590.0), t)
        state, t = _fly(ap, state, t, t + 0.1)
    assert ap.mode.name == "OFFBOARD" and state.position_enu[2] > 4.0
    state, t = _fly(ap, state, t, t + 1.5)  # stream stops
    assert ap.mode.name == "AUTO.LOITER" and ap.failsafe
    assert "offboard" in ap.texts[-1].text


def test_px4_takeoff_then_loiter() -> None:
    ap, state = _autopilot(PX4)
    assert ap.arm(1.5, state, False) == mavlink.MAV_RESULT_ACCEPTED
    assert ap.takeoff(math.nan, True, 1.5, state) == mavlink.MAV_RESULT_ACCEPTED
    assert ap.mode.name == "AUTO.TAKEOFF"
    state, _ = _fly(ap, state, 1.5, 8.0)
    assert ap.mode.name == "AUTO.LOITER"
    assert state.position_enu[2] == pytest.approx(2.5, abs=0.05)  # MIS_TAKEOFF_ALT


def test_rtl_returns_home_and_lands() -> None:
    ap, state = _autopilot(rtl_altitude_m=8.0)
    ap.set_mode(ARDUCOPTER.mode("GUIDED"), 1.0, state)
    ap.arm(1.0, state, False)
    ap.takeoff(4.0, False, 1.0, state)
    state, t = _fly(ap, state, 1.0, 5.0)
    ap.position_target(target(6, POS_ONLY, 20, 10, 4.0), t)
    state, t = _fly(ap, state, t, t + 10.0)
    assert state.position_enu[:2] == pytest.approx([20, 10], abs=0.05)
    ap.set_mode(ARDUCOPTER.mode("RTL"), t, state)
    state, t = _fly(ap, state, t, t + 40.0)
    assert ap.landed and not ap.armed
    assert state.position_enu == pytest.approx([0, 0, 0], abs=0.1)


# ------------------------------------------------------------------------------- server
def test_server_runs_without_a_client() -> None:
    server = make_server(speedup=math.inf, faults={"mode_changes": [{"at_s": 0.5, "mode": "LAND"}]})

    async def run() -> None:
        async with server:
            await server.run_until(1.0)

    asyncio.run(run())
    assert server.t_s == pytest.approx(1.0)
    assert len(server.truth) == 101 and server.truth[-1].mode == "LAND"
    assert server.truth[0].position_enu == pytest.approx([0, 0, 0])


# ------------------------------------------------------------------------------- bridge
def test_bridge_core_from_a_fake_stream() -> None:
    world = PlaneAndWall(wall_x=25.0)
    core = BridgeCore(BridgeConfig(anchor_xy=(5.0, 0.0)), world, sensors())
    mav = mavlink.MAVLink(None, 1, 1)
    assert core.distance_messages(mav) == []
    home = FRAME.to_geodetic(0.0, 0.0, 0.0)
    here = FRAME.to_geodetic(10.0, 0.0, 4.0)  # 10 m east of home, 4 m up
    yaw_ned = yaw_enu_to_ned(0.0)
    for msg in (
        ENC.heartbeat_encode(2, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 4, 4, 3),
        ENC.home_position_encode(
            round(home.lat_deg * 1e7),
            round(home.lon_deg * 1e7),
            round(home.alt_m * 1000),
            0,
            0,
            0,
            [1, 0, 0, 0],
            0,
            0,
            0,
        ),
        ENC.global_position_int_encode(
            5000,
            round(here.lat_deg * 1e7),
            round(here.lon_deg * 1e7),
            round(here.alt_m * 1000),
            4000,
            0,
            0,
            0,
            0,
        ),
        ENC.attitude_encode(5000, 0.0, 0.0, yaw_ned, 0, 0, 0),
    ):
        core.handle(wire(msg))
    pose = core.pose()
    assert pose is not None
    assert pose.position_enu == pytest.approx([15.0, 0.0, 4.0], abs=0.01)
    msgs = [wire(m) for m in core.distance_messages(mav)]
    assert [m.id for m in msgs] == [3, 4, 5, 7, 8]
    assert msgs[0].current_distance == pytest.approx(1000, abs=2)  # wall 10 m ahead
    assert msgs[0].time_boot_ms == 5000
    assert msgs[3].current_distance == pytest.approx(400 * math.sqrt(2), abs=2)
    assert isinstance(SimServer, type)


def test_all_readings_at_once_are_each_reading_alone() -> None:
    specs = sensors()
    rng = np.random.default_rng(5)
    for family in ("ardupilot", "px4"):
        rf = Rangefinders(specs, PlaneAndWall(), family)
        n = len(rf)
        for _ in range(300):
            ranges = rng.uniform(-1.0, 1.3 * float(rf.max_m.max()), n)
            for value, share in ((math.inf, 0.2), (math.nan, 0.1), (0.0, 0.1), (-0.0, 0.05)):
                ranges[rng.random(n) < share] = value
            at_max = rng.random(n) < 0.1
            ranges[at_max] = rf.max_m[at_max]
            alone = [rf.current_cm(i, float(r)) for i, r in enumerate(ranges)]
            assert rf.currents_cm(ranges) == alone
        send = np.arange(n) % 2 == 0
        msgs = [wire(m) for m in rf.messages(ENC, np.full(n, 3.0), 77, send)]
        assert [m.id for m in msgs] == [rf.wire[i].mav_id for i in range(0, n, 2)]
        assert all(m.current_distance == 300 and m.time_boot_ms == 77 for m in msgs)


@pytest.mark.parametrize("compiled_crc", [True, False])
def test_packed_distance_sensor_frames_are_the_encoded_messages(
    compiled_crc: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`Rangefinders.frames` gives byte for byte what `Codec.encode` gives for `messages`,
    sequence numbers included (across the 255 -> 0 wrap), for both families, custom
    orientations with their quaternion, readings out of range and dropped sensors; with
    pymavlink's compiled checksum and with its pure-Python one."""
    if not compiled_crc:
        monkeypatch.setattr(codec_module, "_MCRF4XX", None)
    specs = sensors()
    rng = np.random.default_rng(11)
    for family in ("ardupilot", "px4"):
        rf = Rangefinders(specs, PlaneAndWall(), family)
        n = len(rf)
        slow, fast = Codec(3, 1), Codec(3, 1)
        slow.mav.seq = fast.mav.seq = 250
        for k in range(40):
            ranges = rng.uniform(0.0, 1.3 * float(rf.max_m.max()), n)
            ranges[rng.random(n) < 0.2] = math.inf
            send = rng.random(n) < 0.8 if k % 2 else None
            stamp = int(rng.integers(0, 2**32))
            want = [slow.encode(m) for m in rf.messages(slow.mav, ranges, stamp, send)]
            assert rf.frames(fast, ranges, stamp, send) == want
        assert fast.mav.seq == slow.mav.seq
        assert fast.mav.total_bytes_sent == slow.mav.total_bytes_sent
        assert any(wire(m).quaternion != [0.0] * 4 for m in rf.messages(ENC, ranges, 1))
