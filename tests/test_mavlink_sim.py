"""The MAVLink simulator through real UDP on 127.0.0.1, driven by a plain pymavlink client.

The simulator runs faster than real time in a background thread (ThreadedSim); clients pace
their setpoint streams by the simulator's time_boot_ms, not by wall-clock time.
"""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.planner.sensors import boresight_from_quaternion_frd
from companion.sim.mavlink import ThreadedSim
from companion.sim.mavlink.setpoints import ACC_IGNORE, VEL_IGNORE, YAW_IGNORE, YAW_RATE_IGNORE
from tests.test_mavlink_sim_support import (
    Client,
    enu_of,
    frame_of,
    latlon_int,
    make_server,
    sensors,
    wall_world,
)

pytestmark = [pytest.mark.sim, pytest.mark.timeout(60)]

POS_ONLY = VEL_IGNORE | ACC_IGNORE | YAW_IGNORE | YAW_RATE_IGNORE
POS_VEL = ACC_IGNORE | YAW_IGNORE | YAW_RATE_IGNORE
MSG = {
    "ATTITUDE": mavlink.MAVLINK_MSG_ID_ATTITUDE,
    "GLOBAL_POSITION_INT": mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
    "DISTANCE_SENSOR": mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR,
    "HOME_POSITION": mavlink.MAVLINK_MSG_ID_HOME_POSITION,
}
R = mavlink


def _until_accepted(c: Client, cmd: int, *params: float) -> None:
    for _ in range(100):  # through the pre-arm delay
        if c.command(cmd, *params) == R.MAV_RESULT_ACCEPTED:
            return
        time.sleep(0.02)
    raise AssertionError(f"command {cmd} never accepted")


def _guided_takeoff(c: Client, alt: float = 5.0) -> None:
    """ArduCopter: GUIDED, arm, take off."""
    _until_accepted(c, R.MAV_CMD_DO_SET_MODE, 1, 4)
    _until_accepted(c, R.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    assert c.command(R.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, alt) == R.MAV_RESULT_ACCEPTED


def _stream(c: Client, send: Any, until: Any, period_ms: int = 100, timeout: float = 20.0) -> Any:
    """Call send() every period_ms of simulated time (by GLOBAL_POSITION_INT.time_boot_ms)
    until until(msg) holds; returns that message."""
    next_ms = -1
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg = c.recv("GLOBAL_POSITION_INT", timeout=5)
        if msg.time_boot_ms >= next_ms:
            send()
            next_ms = msg.time_boot_ms + period_ms
        if until(msg):
            return msg
    raise TimeoutError("condition not reached")


def test_ardupilot_heartbeat_and_message_intervals() -> None:
    with ThreadedSim(lambda: make_server(speedup=10.0)) as sim, Client(sim.port) as c:
        hb = c.recv("HEARTBEAT")
        assert hb.autopilot == R.MAV_AUTOPILOT_ARDUPILOTMEGA and hb.type == R.MAV_TYPE_QUADROTOR
        assert hb.custom_mode == 0 and hb.base_mode & R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
        # A plain client gets nothing but HEARTBEAT until it asks.
        assert c.conn.recv_match(type="ATTITUDE", blocking=True, timeout=0.3) is None
        assert c.set_interval(MSG["ATTITUDE"], 20.0) == R.MAV_RESULT_ACCEPTED
        # not streamed by sim/: answered as ArduCopter SITL answers for a message it cannot stream
        assert c.set_interval(R.MAVLINK_MSG_ID_VFR_HUD, 20.0) == R.MAV_RESULT_DENIED
        times = [c.recv("ATTITUDE").time_boot_ms for _ in range(41)]
        rate = 40 / ((times[-1] - times[0]) / 1000.0)
        assert rate == pytest.approx(20.0, rel=0.05)
        assert c.command(R.MAV_CMD_GET_MESSAGE_INTERVAL, MSG["ATTITUDE"]) == R.MAV_RESULT_ACCEPTED
        assert c.recv("MESSAGE_INTERVAL").interval_us == 50_000
        assert c.command(R.MAV_CMD_REQUEST_MESSAGE, MSG["HOME_POSITION"]) == R.MAV_RESULT_ACCEPTED
        home = c.recv("HOME_POSITION")
        assert home.latitude == pytest.approx(-353632610, abs=2)
        assert c.command(R.MAV_CMD_DO_SET_MODE, 1, 99) == R.MAV_RESULT_FAILED
        assert c.command(R.MAV_CMD_USER_1, 1) == R.MAV_RESULT_UNSUPPORTED
        c.mav.set_mode_send(1, R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 5)
        ack = c.recv("COMMAND_ACK")
        assert ack.command == R.MAVLINK_MSG_ID_SET_MODE and ack.result == R.MAV_RESULT_ACCEPTED
        assert c.recv("HEARTBEAT", cond=lambda m: m.custom_mode == 5).custom_mode == 5


def test_ardupilot_guided_flight_and_distance_sensors() -> None:
    with (
        ThreadedSim(lambda: make_server(speedup=20.0, prearm_delay_s=3.0)) as sim,
        Client(sim.port) as c,
    ):
        c.recv("HEARTBEAT")
        assert c.command(R.MAV_CMD_COMPONENT_ARM_DISARM, 1) == R.MAV_RESULT_FAILED  # pre-arm
        c.recv("STATUSTEXT", cond=lambda m: "PreArm" in m.text)
        for name in ("GLOBAL_POSITION_INT", "DISTANCE_SENSOR"):
            assert c.set_interval(MSG[name], 10.0) == R.MAV_RESULT_ACCEPTED
        _guided_takeoff(c, alt=5.0)
        frame = frame_of(sim.server)
        c.recv("GLOBAL_POSITION_INT", timeout=10, cond=lambda m: m.relative_alt > 4900)
        lat, lon = latlon_int(frame, 0.0, 6.0)  # 6 m north, 5 m up; the wall is at x = 10

        def send() -> None:
            c.mav.set_position_target_global_int_send(
                0,
                1,
                1,
                R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                POS_ONLY,
                lat,
                lon,
                5.0,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
                0,
            )

        msg = _stream(c, send, lambda m: np.linalg.norm(enu_of(frame, m) - [0, 6, 5]) < 0.2)
        assert abs(msg.vx) < 1000 and msg.hdg == 9000  # yaw 0 ENU = east = 90 deg
        # DISTANCE_SENSOR against the wall 10 m east, at 5 m over flat ground.
        seen: dict[int, Any] = {}
        while len(seen) < 5:
            d = c.recv("DISTANCE_SENSOR")
            seen[d.id] = d
        assert seen[3].orientation == 0 and abs(seen[3].current_distance - 1000) <= 2
        assert seen[4].orientation == 100
        q_bore = boresight_from_quaternion_frd(seen[4].quaternion)
        assert q_bore == pytest.approx(sensors()[1].boresight_frd, abs=1e-5)
        assert abs(seen[4].current_distance - 1000 / math.cos(math.radians(15))) <= 2
        assert seen[5].current_distance == 1300 and seen[5].max_distance == 1200
        assert seen[7].orientation == R.MAV_SENSOR_ROTATION_PITCH_315
        assert abs(seen[7].current_distance - 500 * math.sqrt(2)) <= 2
        assert seen[3].min_distance == 10 and seen[3].type == R.MAV_DISTANCE_SENSOR_LASER
    truth = sim.server.truth
    assert truth[-1].armed and truth[-1].mode == "GUIDED"
    assert max(s.position_enu[2] for s in truth) < 5.3


def test_ardupilot_rejections() -> None:
    with ThreadedSim(lambda: make_server(speedup=20.0)) as sim, Client(sim.port) as c:
        c.recv("HEARTBEAT")
        c.set_interval(MSG["GLOBAL_POSITION_INT"], 20.0)
        frame = frame_of(sim.server)
        lat, lon = latlon_int(frame, 30.0, 0.0)
        # Outside GUIDED setpoints are ignored (the vehicle is disarmed in STABILIZE).
        c.mav.set_position_target_global_int_send(0, 1, 1, 6, POS_ONLY, lat, lon, 5, *[0] * 8)
        _guided_takeoff(c, alt=4.0)
        c.recv("GLOBAL_POSITION_INT", timeout=10, cond=lambda m: m.relative_alt > 3900)
        lat, lon = latlon_int(frame, -30.0, 0.0)
        c.mav.set_position_target_global_int_send(
            0, 1, 1, R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, POS_ONLY, lat, lon, 4.0, *[0] * 8
        )
        c.recv("GLOBAL_POSITION_INT", cond=lambda m: enu_of(frame, m)[0] < -3.0)
        # Position + velocity in a terrain frame: rejected, the vehicle stops.
        c.mav.set_position_target_global_int_send(
            0,
            1,
            1,
            R.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
            POS_VEL,
            lat,
            lon,
            4.0,
            -1.0,
            0,
            0,
            0,
            0,
            0,
            0,
            0,
        )
        stopped = c.recv("GLOBAL_POSITION_INT", timeout=10, cond=lambda m: abs(m.vy) < 5)
        x_stop = enu_of(frame, stopped)[0]
        t_stop = stopped.time_boot_ms
        later = c.recv("GLOBAL_POSITION_INT", cond=lambda m: m.time_boot_ms > t_stop + 3000)
        assert enu_of(frame, later)[0] == pytest.approx(x_stop, abs=0.1)
        assert x_stop > -25.0  # stopped well short of the target at -30 m
        # Back to STABILIZE: setpoints ignored again, the vehicle holds.
        assert c.command(R.MAV_CMD_DO_SET_MODE, 1, 0) == R.MAV_RESULT_ACCEPTED
        lat, lon = latlon_int(frame, 0.0, 30.0)
        c.mav.set_position_target_global_int_send(0, 1, 1, 6, POS_ONLY, lat, lon, 4, *[0] * 8)
        t0 = c.recv("GLOBAL_POSITION_INT").time_boot_ms
        held = c.recv("GLOBAL_POSITION_INT", cond=lambda m: m.time_boot_ms > t0 + 2000)
        assert enu_of(frame, held)[1] == pytest.approx(0.0, abs=0.1)
    decisions = [d.reason for d in sim.server.stats.decisions]
    assert "not in GUIDED" in decisions
    assert any("terrain" in r for r in decisions)


def test_px4_offboard() -> None:
    make = lambda: make_server(  # noqa: E731
        personality="px4", speedup=5.0, rates_hz={"ATTITUDE": 10, "GLOBAL_POSITION_INT": 20}
    )
    with ThreadedSim(make) as sim, Client(sim.port) as c:
        hb = c.recv("HEARTBEAT")
        assert hb.autopilot == R.MAV_AUTOPILOT_PX4
        assert hb.custom_mode == 3 << 16  # POSCTL
        c.recv("GLOBAL_POSITION_INT")  # PX4 streams on its own
        frame = frame_of(sim.server)
        rejected = R.MAV_RESULT_TEMPORARILY_REJECTED
        assert c.command(R.MAV_CMD_DO_SET_MODE, 1, 6, 0) == rejected
        c.recv("STATUSTEXT", cond=lambda m: "Offboard" in m.text)
        lat, lon = latlon_int(frame, 0.0, 0.0)
        # Wrong frame for PX4: ignored, with a message.
        c.mav.set_position_target_global_int_send(0, 1, 1, 3, POS_ONLY, lat, lon, 5, *[0] * 8)
        c.recv("STATUSTEXT", cond=lambda m: "bad frame 3" in m.text)
        amsl = sim.server.config.home_or_default.alt_m + 6.0

        def send() -> None:
            c.mav.set_position_target_global_int_send(
                0, 1, 1, R.MAV_FRAME_GLOBAL_INT, POS_ONLY, lat, lon, amsl, *[0] * 8
            )

        _stream(c, send, lambda m: m.time_boot_ms > 1000)
        state: dict[str, int] = {}

        def switch_and_arm() -> None:
            send()
            if "mode" not in state:
                state["mode"] = c.command(R.MAV_CMD_DO_SET_MODE, 1, 6, 0)
            elif "arm" not in state:
                state["arm"] = c.command(R.MAV_CMD_COMPONENT_ARM_DISARM, 1)

        _stream(c, switch_and_arm, lambda m: m.relative_alt > 5800)
        assert state == {"mode": R.MAV_RESULT_ACCEPTED, "arm": R.MAV_RESULT_ACCEPTED}
        assert c.recv("HEARTBEAT").custom_mode == 6 << 16
        # The stream stops: PX4 leaves OFFBOARD after COM_OF_LOSS_T and holds.
        last = c.recv("GLOBAL_POSITION_INT").time_boot_ms
        text = c.recv("STATUSTEXT", timeout=10, cond=lambda m: "offboard" in m.text)
        assert "Failsafe" in text.text
        hb = c.recv("HEARTBEAT", cond=lambda m: m.custom_mode != 6 << 16)
        assert hb.custom_mode == (4 << 16) | (3 << 24)  # AUTO.LOITER
        assert hb.system_status == R.MAV_STATE_CRITICAL
        after = c.recv("GLOBAL_POSITION_INT")
        assert after.time_boot_ms > last and after.relative_alt > 5500  # holding


def test_ardusub_dives_in_guided() -> None:
    world = wall_world(wall_x=50.0, floor_z=-20.0)
    make = lambda: make_server(personality="ardusub", speedup=20.0, world=world)  # noqa: E731
    with ThreadedSim(make) as sim, Client(sim.port) as c:
        hb = c.recv("HEARTBEAT")
        assert hb.type == R.MAV_TYPE_SUBMARINE and hb.custom_mode == 19  # MANUAL
        assert c.command(R.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5) == R.MAV_RESULT_UNSUPPORTED
        c.set_interval(MSG["GLOBAL_POSITION_INT"], 20)
        c.set_interval(MSG["DISTANCE_SENSOR"], 10)
        _until_accepted(c, R.MAV_CMD_DO_SET_MODE, 1, 4)
        assert c.command(R.MAV_CMD_COMPONENT_ARM_DISARM, 1) == R.MAV_RESULT_ACCEPTED
        lat, lon = latlon_int(frame_of(sim.server), 5.0, 0.0)
        home_alt = sim.server.config.home_or_default.alt_m
        c.mav.set_position_target_global_int_send(
            0, 1, 1, R.MAV_FRAME_GLOBAL_INT, POS_ONLY, lat, lon, home_alt - 8.0, *[0] * 8
        )
        deep = c.recv("GLOBAL_POSITION_INT", timeout=10, cond=lambda m: m.relative_alt < -7900)
        assert deep.alt == pytest.approx((home_alt - 8.0) * 1000, abs=150)
        down = c.recv("DISTANCE_SENSOR", cond=lambda m: m.id == 7)  # forward, 45 deg down
        assert down.current_distance == 1100  # seafloor 12 m below: 17 m away, beyond 10 m
    assert sim.server.truth[0].position_enu[2] == 0.0  # started at the surface


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_mission_round_trip(personality: str) -> None:
    with (
        ThreadedSim(lambda: make_server(personality=personality, speedup=10.0)) as sim,
        Client(sim.port) as c,
    ):
        c.recv("HEARTBEAT")
        frame = frame_of(sim.server)
        points = [latlon_int(frame, 10.0 * i, 5.0 * i) for i in range(4)]
        c.mav.mission_count_send(1, 1, len(points), 0)
        while True:
            msg = c.recv(["MISSION_REQUEST_INT", "MISSION_ACK"])
            if msg.get_type() == "MISSION_ACK":
                assert msg.type == R.MAV_MISSION_ACCEPTED
                break
            lat, lon = points[msg.seq]
            c.mav.mission_item_int_send(
                1,
                1,
                msg.seq,
                6,
                R.MAV_CMD_NAV_WAYPOINT,
                0,
                1,
                0,
                0,
                0,
                0,
                lat,
                lon,
                10.0 + msg.seq,
            )
        c.mav.mission_request_list_send(1, 1)
        count = c.recv("MISSION_COUNT").count
        assert count == 4
        items = []
        for seq in range(count):
            c.mav.mission_request_int_send(1, 1, seq)
            items.append(c.recv("MISSION_ITEM_INT", cond=lambda m, s=seq: m.seq == s))
        c.mav.mission_ack_send(1, 1, R.MAV_MISSION_ACCEPTED)
        for item, (lat, lon) in list(zip(items, points, strict=True))[1:]:
            assert (item.x, item.y, item.frame) == (lat, lon, 6)
        if personality == "ardupilot":  # seq 0 is home
            home = sim.server.config.home_or_default
            assert items[0].z == pytest.approx(home.alt_m, abs=0.01)
        else:
            assert (items[0].x, items[0].y, items[0].z) == (*points[0], 10.0)
    assert len(sim.server.mission_items()) == 4


def _lockstep_run() -> tuple[list[Any], list[tuple[Any, ...]]]:
    """A deterministic companion: acts only between a TIMESYNC request and its answer."""
    faults = {
        "seed": 3,
        "sensors": [{"noise_std_m": 0.05}],
        "outgoing": {"loss_probability": 0.05},
    }
    server_cfg = {
        "speedup": math.inf,
        "lockstep": {"enabled": True, "period_s": 0.05, "timeout_s": 2.0},
        "faults": faults,
    }
    seen: list[tuple[Any, ...]] = []
    with (
        ThreadedSim(lambda: make_server(**server_cfg), until_s=6.0) as sim,
        Client(sim.port) as c,
    ):
        frame = frame_of(sim.server)
        last_pos: Any = None
        done: set[str] = set()
        while True:
            msg = c.recv(["TIMESYNC", "GLOBAL_POSITION_INT", "DISTANCE_SENSOR", "COMMAND_ACK"])
            kind = msg.get_type()
            if kind == "GLOBAL_POSITION_INT":
                last_pos = msg
                seen.append((kind, msg.time_boot_ms, msg.lat, msg.lon, msg.alt))
            elif kind == "DISTANCE_SENSOR":
                seen.append((kind, msg.time_boot_ms, msg.id, msg.current_distance))
            elif kind == "COMMAND_ACK":
                seen.append((kind, msg.command, msg.result))
            elif msg.tc1 == 0:
                t = msg.ts1 * 1e-9
                steps = [
                    (
                        0.1,
                        "rates",
                        lambda: [
                            c.mav.command_long_send(1, 1, 511, 0, m, 50_000, 0, 0, 0, 0, 0)
                            for m in (MSG["GLOBAL_POSITION_INT"], MSG["DISTANCE_SENSOR"])
                        ],
                    ),
                    (
                        0.3,
                        "mode",
                        lambda: c.mav.command_long_send(1, 1, 176, 0, 1, 4, *[0] * 5),
                    ),
                    (0.5, "arm", lambda: c.mav.command_long_send(1, 1, 400, 0, 1, *[0] * 6)),
                    (0.6, "takeoff", lambda: c.mav.command_long_send(1, 1, 22, 0, *[0] * 6, 3)),
                ]
                for at, name, act in steps:
                    if t >= at and name not in done:
                        done.add(name)
                        act()
                if t >= 3.0 and last_pos is not None:
                    # Feedback: 1.5 m east of where the vehicle says it is, 3 m up.
                    east, north, _ = enu_of(frame, last_pos)
                    lat, lon = latlon_int(frame, east + 1.5, north)
                    c.mav.set_position_target_global_int_send(
                        0, 1, 1, 6, POS_ONLY, lat, lon, 3.0, *[0] * 8
                    )
                c.mav.timesync_send(int(time.monotonic_ns()) or 1, msg.ts1)
                if t >= 6.0 - 1e-9:
                    break
    assert sim.server.stats.lockstep_stalls == 0
    return sim.server.truth, seen


def test_lockstep_gives_identical_traces() -> None:
    truth_a, seen_a = _lockstep_run()
    truth_b, seen_b = _lockstep_run()
    assert len(truth_a) == len(truth_b) == 601
    assert truth_a[-1].position_enu[0] > 3.0  # it flew
    for a, b in zip(truth_a, truth_b, strict=True):
        assert a.t_s == b.t_s and a.mode == b.mode and a.armed == b.armed
        assert np.array_equal(a.position_enu, b.position_enu)
    assert seen_a == seen_b
    assert any(k[0] == "DISTANCE_SENSOR" for k in seen_a)


def test_lockstep_waits_for_the_companion() -> None:
    cfg = {"speedup": math.inf, "lockstep": {"enabled": True, "timeout_s": 0.2}}
    with ThreadedSim(lambda: make_server(**cfg)) as sim:
        time.sleep(0.5)  # nobody connected: about 0.2 s per 0.05 s of simulated time
        assert sim.server.t_s <= 0.2 + 1e-9
        assert sim.server.stats.lockstep_stalls >= 1


def test_faults_loss_reboot_and_mode_change() -> None:
    faults = {
        "outgoing": {"loss_probability": 0.3},
        "reboots": [{"at_s": 4.0, "duration_s": 0.5}],
        "mode_changes": [{"at_s": 2.0, "mode": "AUTO.LOITER"}],
    }
    cfg = {"personality": "px4", "speedup": 10.0, "rates_hz": {"ATTITUDE": 50}, "faults": faults}
    with ThreadedSim(lambda: make_server(**cfg)) as sim, Client(sim.port) as c:
        times: list[int] = []
        while True:
            msg = c.recv("ATTITUDE")
            if times and msg.time_boot_ms < times[-1]:
                break  # rebooted
            times.append(msg.time_boot_ms)
        assert 300 < msg.time_boot_ms < 1500  # time_boot_ms restarted (silent for 0.5 s)
        hb = c.recv("HEARTBEAT")
        assert hb.custom_mode == 3 << 16  # back to POSCTL after the reboot
    span = [t for t in times if t > 500]
    expected = (span[-1] - span[0]) / 20.0 + 1
    assert len(span) / expected == pytest.approx(0.7, abs=0.08)
    modes = [s.mode for s in sim.server.truth]
    assert modes[150] == "POSCTL" and modes[250] == "AUTO.LOITER" and modes[-1] == "POSCTL"
    assert sim.server.stats.reboots == 1 and sim.server.outgoing_faults.stats.dropped > 0


def test_link_cut_and_reboot_command() -> None:
    cfg = {"speedup": 10.0, "faults": {"link_cuts": [[1.0, 2.0]]}}
    with ThreadedSim(lambda: make_server(**cfg)) as sim, Client(sim.port) as c:
        c.set_interval(MSG["ATTITUDE"], 20)
        t_before = c.recv("ATTITUDE").time_boot_ms
        gap = []
        prev = t_before
        while prev < 2500:
            now = c.recv("ATTITUDE").time_boot_ms
            gap.append(now - prev)
            prev = now
        assert max(gap) >= 950  # nothing got through for a second
        assert c.command(R.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1) == R.MAV_RESULT_ACCEPTED
        c.recv("HEARTBEAT", timeout=5)
    assert sim.server.stats.reboots == 1


def test_from_scenario_with_the_real_world() -> None:
    from companion.sim.mavlink import SimServer

    load_scenario = pytest.importorskip("companion.sim.scenario").load_scenario

    path = Path(__file__).resolve().parent.parent / "config/scenarios/smooth-hill.yaml"
    scenario = load_scenario(path)

    def make() -> SimServer:
        return SimServer.from_scenario(
            scenario, path.parent, port=0, speedup=10.0, personality="px4"
        )

    with ThreadedSim(make) as sim, Client(sim.port) as c:
        d = c.recv("DISTANCE_SENSOR", timeout=5)
        assert d.max_distance in (1000, 1200)
        assert c.recv("HEARTBEAT").autopilot == R.MAV_AUTOPILOT_PX4
    assert sim.server.truth[0].position_enu[:2] == pytest.approx(scenario.route.points[0])


def test_cli_help() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "companion.sim", "serve", "--help"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    for option in ("--personality", "--speedup", "--lockstep", "--port", "--target"):
        assert option in out
    out = subprocess.run(
        [sys.executable, "-m", "companion.sim", "bridge", "--help"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "--connect" in out and "--send-to" in out


def test_cli_serves_a_scenario(tmp_path: Path) -> None:
    pytest.importorskip("companion.sim.scenario")
    scenario = Path(__file__).resolve().parent.parent / "config/scenarios/smooth-hill.yaml"
    truth = tmp_path / "truth.csv"
    args = ["serve", str(scenario), "--port", "0", "--speedup", "inf", "--duration", "0.5"]
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "companion.sim",
            *args,
            "--personality",
            "px4",
            "--truth-csv",
            str(truth),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    assert "px4 simulator on udp 127.0.0.1:" in result.stdout
    rows = truth.read_text().splitlines()
    assert rows[0].startswith("t_s,x_m") and len(rows) == 52
    bad = subprocess.run(
        [sys.executable, "-m", "companion.sim", *args, "--physics-dt", "0.5"],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "physics_dt_s" in bad.stderr


def test_threaded_sim_reports_start_failures() -> None:
    def broken() -> Any:
        raise ValueError("no world")

    with pytest.raises(RuntimeError, match="failed to start"), ThreadedSim(broken):
        pass
    assert threading.active_count() >= 1


def _lockstep_datagrams(datagram_bytes: int, periods: int = 12) -> list[list[Any]]:
    """The messages of each datagram the simulator sends in lockstep over its first periods,
    a raw UDP client answering every TIMESYNC request at once."""
    import socket

    cfg = {
        "speedup": math.inf,
        "lockstep": {"enabled": True, "period_s": 0.05, "datagram_bytes": datagram_bytes},
        "rates_hz": {"DISTANCE_SENSOR": 20.0, "ATTITUDE": 50.0, "GLOBAL_POSITION_INT": 50.0},
    }
    mav = mavlink.MAVLink(None, srcSystem=42, srcComponent=191)
    parser = mavlink.MAVLink(None)
    datagrams: list[list[Any]] = []
    with (
        ThreadedSim(lambda: make_server(**cfg), until_s=periods * 0.05) as sim,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock,
    ):
        sock.settimeout(5.0)
        addr = ("127.0.0.1", sim.port)
        sock.sendto(mav.heartbeat_encode(6, 8, 0, 0, 4).pack(mav), addr)
        answered = 0
        while answered < periods:
            msgs = parser.parse_buffer(sock.recv(65536)) or []
            datagrams.append(msgs)
            for m in msgs:
                if m.get_type() == "TIMESYNC" and m.tc1 == 0:
                    sock.sendto(mav.timesync_encode(1, m.ts1).pack(mav), addr)
                    answered += 1
    return datagrams


def test_lockstep_sends_a_period_in_one_datagram() -> None:
    packed = _lockstep_datagrams(8192)
    single = _lockstep_datagrams(0)
    assert all(len(d) == 1 for d in single)
    # one datagram per period, its TIMESYNC request last
    requests = [d for d in packed if any(m.get_type() == "TIMESYNC" for m in d)]
    assert len(requests) == len(packed) == 12
    for d in packed:
        assert d[-1].get_type() == "TIMESYNC" and d[-1].tc1 == 0
        assert all(m.get_type() != "TIMESYNC" for m in d[:-1])
    assert max(len(d) for d in packed) > 10  # telemetry and sensors, packed

    def key(m: Any) -> tuple[Any, ...]:  # SYSTEM_TIME carries the computer's clock
        return (m.get_type(), getattr(m, "time_boot_ms", None), getattr(m, "ts1", None))

    # the same messages in the same order either way
    assert [key(m) for d in packed for m in d] == [key(m) for d in single for m in d]


def test_lockstep_datagrams_stay_within_their_size() -> None:
    packed = _lockstep_datagrams(300, periods=4)
    assert len(packed) > 4  # a period's messages did not fit one datagram
    for d in packed:
        assert sum(len(m.get_msgbuf()) for m in d) <= 300 or len(d) == 1
