"""Helpers for the tests that fly the real ArduCopter SITL (`pytest -m sitl`).

Each SITL gets its own instance number (TCP ports 5762/5763 + 10 I) and UDP port, chosen
free at the time, so several test runs can share a machine.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
import socket
import threading
import time
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.harness.sitl import (
    PX4_MAX_INSTANCE,
    Flight,
    Px4Sitl,
    Sitl,
    SitlFlight,
    find_px4,
    find_sitl,
    fly_on_sitl,
    free_udp_port,
)
from companion.sim.scenario import Scenario, load_scenario

LAUNCHER = find_sitl()
SKIP_REASON = (
    "no ArduCopter SITL at ../shared/sitl/arducopter next to the repository "
    "(the sitl tests fly the real autopilot)"
)
needs_sitl = pytest.mark.skipif(LAUNCHER is None, reason=SKIP_REASON)
PX4_BUNDLE = find_px4()
PX4_SKIP_REASON = "no PX4 SITL at ../shared/sitl/px4/ next to the repository"

_instances = itertools.count(20 + (os.getpid() % 8) * 8)
_lock = threading.Lock()


def _port_free(port: int, kind: int = socket.SOCK_STREAM) -> bool:
    """True when 127.0.0.1:port (TCP, or UDP with kind SOCK_DGRAM) can be bound now."""
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def next_instance() -> int:
    """A SITL instance number whose TCP ports are free now (20..99)."""
    with _lock:
        for _ in range(80):
            i = 20 + (next(_instances) - 20) % 80
            if all(_port_free(5760 + 10 * i + k) for k in range(4)):
                return i
    raise RuntimeError("no free SITL instance")


def next_px4_instance(taken: Collection[int] = ()) -> int:
    """A PX4 instance number, not in `taken`, whose UDP ports (onboard 14540/14580 + I, GCS
    18570 + I) are free now (0..PX4_MAX_INSTANCE)."""
    with _lock:
        for i in range(PX4_MAX_INSTANCE + 1):
            if i in taken:
                continue
            if all(_port_free(base + i, socket.SOCK_DGRAM) for base in (14540, 14580, 18570)):
                return i
    raise RuntimeError("no free PX4 instance")


@contextlib.contextmanager
def running_sitl(
    tmp: Path,
    params: dict[str, float] | None = None,
    fast_ekf: bool = True,
    speedup: float = 1.0,
) -> Iterator[Sitl]:
    """A started SITL whose heartbeat has been seen; killed (process group) on exit."""
    if LAUNCHER is None:
        pytest.skip(SKIP_REASON)
    sitl = Sitl(
        LAUNCHER,
        next_instance(),
        free_udp_port(),
        speedup=speedup,
        fast_ekf=fast_ekf,
        params=params or {},
        workdir=tmp / "sitl",
    )
    try:
        sitl.start()
        sitl.wait_heartbeat(60.0)
        yield sitl
    finally:
        sitl.stop()


def gcs_connect(sitl: Sitl, timeout_s: float = 20.0) -> Any:
    """A ground station (system 255) on SITL's SERIAL1 TCP port, heartbeat seen."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            conn = mavutil.mavlink_connection(
                f"tcp:127.0.0.1:{sitl.gcs_port}",
                source_system=255,
                source_component=mavlink.MAV_COMP_ID_MISSIONPLANNER,
                autoreconnect=False,
            )
            break
        except OSError:
            if time.monotonic() >= deadline:
                raise
            time.sleep(0.2)
    conn.wait_heartbeat(timeout=timeout_s)
    return conn


def gcs_command(conn: Any, command: int, *params: float, timeout_s: float = 5.0) -> int:
    """COMMAND_LONG to the autopilot; the COMMAND_ACK result (-1 without one)."""
    p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
    conn.mav.command_long_send(1, 1, command, 0, *p)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        ack = conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.5)
        if ack is not None and ack.command == command:
            return int(ack.result)
    return -1


# --- jobs run in worker processes (one per SITL, side by side) -----------------------------

REPO = Path(__file__).resolve().parent.parent
SCENARIOS = REPO / "config" / "scenarios"
COPTER_MODE = {"STABILIZE": 0, "GUIDED": 4, "LOITER": 5, "RTL": 6, "LAND": 9}


@dataclass(frozen=True)
class SitlSpec:
    """What a worker needs to talk to a SITL the test process started (and will kill)."""

    launcher: str
    instance: int
    port: int
    speedup: float
    fast_ekf: bool

    def attach(self) -> Sitl:
        return Sitl(Path(self.launcher), self.instance, self.port, self.speedup, self.fast_ekf)


def scenario_for(name: str) -> Scenario:
    """The scenarios the sitl tests fly ("wired-wall": wall with sensors ArduPilot can carry;
    "short": a flat 25 m route for the pilot and boot tests)."""
    if name == "wired-wall":
        base = load_scenario(SCENARIOS / "wall.yaml")
        with (REPO / "config" / "sensors" / "ardupilot-wired.yaml").open(encoding="utf-8") as f:
            sensors = yaml.safe_load(f)
        return Scenario.model_validate({**base.model_dump(), "sensors": sensors})
    if name == "short":
        base = load_scenario(SCENARIOS / "smooth-hill.yaml")
        raw = base.model_dump()
        raw["world"] = {"features": []}
        raw["route"] = {**raw["route"], "points": [[0.0, 0.0], [25.0, 0.0]]}
        raw["duration_s"] = 60.0
        return Scenario.model_validate(raw)
    return load_scenario(SCENARIOS / f"{name}.yaml")


def flight_job(spec: SitlSpec, name: str, topology: str, out: str, ready: bool) -> SitlFlight:
    """Fly scenario `name`; with `ready`, only once SITL can fly GUIDED (see Sitl.wait_ready)."""
    sitl = spec.attach()
    if ready:
        sitl.wait_ready()
    scenario = scenario_for(name)
    timeout = scenario.duration_s + 30.0  # the scenario's own budget, plus the take-off
    return asyncio.run(
        fly_on_sitl(scenario, SCENARIOS, sitl, Path(out), topology, timeout)  # type: ignore[arg-type]
    )


def px4_flight_job(sitl: Px4Sitl, name: str, out: str) -> SitlFlight:
    """Fly scenario `name` on a started PX4 SITL (handed over detached), once it is armable."""
    sitl.wait_ready()
    scenario = scenario_for(name)
    timeout = scenario.duration_s + 30.0
    return asyncio.run(fly_on_sitl(scenario, SCENARIOS, sitl, Path(out), timeout_s=timeout))


PX4_FED = {0: 300, 6: 350, 39: 400}
"""DISTANCE_SENSOR fed to PX4 by px4_claims_job: orientation -> cm (forward, left, forward
45 degrees down), ids 50, 51, 52."""


def px4_claims_job(sitl: Px4Sitl) -> dict[str, Any]:
    """Feed three MAVLink rangefinders to a started PX4 (handed over detached) on the
    bridge's link for 8 s, 10 Hz each, and record the DISTANCE_SENSOR PX4 sends on its
    onboard link: {"seen": {(id, orientation): [cm, ...]}, "seconds": 8.0}."""
    sitl.wait_ready()
    feed = mavutil.mavlink_connection(
        sitl.bridge_link(), source_system=sitl.system_id, source_component=158
    )
    onboard = mavutil.mavlink_connection(
        f"udpin:127.0.0.1:{sitl.port}", source_system=sitl.system_id, source_component=191
    )
    try:
        feed.wait_heartbeat(timeout=10)
        onboard.wait_heartbeat(timeout=10)
        seen: dict[tuple[int, int], list[int]] = {}
        seconds, next_feed = 8.0, 0.0
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            if time.monotonic() >= next_feed:
                next_feed = time.monotonic() + 0.1
                feed.mav.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, 8, 0, 0, 0)
                for k, (orientation, cm) in enumerate(PX4_FED.items()):
                    boot_ms = int(time.monotonic() * 1000) & 0xFFFFFFFF
                    feed.mav.distance_sensor_send(
                        boot_ms, 10, 1000, cm, 0, 50 + k, orientation, 0, 0, 0, [0.0] * 4
                    )
            m = onboard.recv_match(type="DISTANCE_SENSOR", blocking=True, timeout=0.05)
            if m is not None:
                seen.setdefault((int(m.id), int(m.orientation)), []).append(int(m.current_distance))
        return {"seen": seen, "seconds": seconds}
    finally:
        feed.close()
        onboard.close()


def set_mode(conn: Any, mode: str) -> int:
    return gcs_command(
        conn,
        mavlink.MAV_CMD_DO_SET_MODE,
        mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
        COPTER_MODE[mode],
    )


def centre_sticks(conn: Any, stop: threading.Event) -> None:
    """A pilot's hands off the sticks: RC_CHANNELS_OVERRIDE 1500 on roll, pitch, throttle
    and yaw at 5 Hz. Without RC input SITL's throttle reads low, and in LOITER the copter
    then descends and lands (seen), which is not what a pilot taking over would do."""
    while not stop.is_set():
        conn.mav.rc_channels_override_send(1, 1, 1500, 1500, 1500, 1500, 0, 0, 0, 0)
        stop.wait(0.2)


@dataclass
class PilotRun:
    """A flight a ground station interfered with: (monotonic s, what, COMMAND_ACK result)."""

    actions: list[tuple[float, str, int]]
    engaged_again_at: float | None
    flight: SitlFlight


def pilot_job(spec: SitlSpec, out: str) -> PilotRun:
    """Fly "short"; a GCS on SERIAL1: LOITER, GUIDED, disarm attempt, RTL."""
    sitl = spec.attach()
    sitl.wait_ready()
    scenario = scenario_for("short")

    async def main() -> PilotRun:
        flight = Flight(scenario, SCENARIOS, sitl, Path(out))
        actions: list[tuple[float, str, int]] = []
        engaged_again = None
        stop = threading.Event()
        await flight.start()
        try:
            if not await flight.wait(90.0, until=lambda: flight.engaged):
                raise RuntimeError("the service never took over")
            gcs = await asyncio.to_thread(gcs_connect, sitl)
            sticks = threading.Thread(target=centre_sticks, args=(gcs, stop), daemon=True)
            sticks.start()
            await asyncio.sleep(6.0)

            async def act(what: str, fn: Any) -> None:
                t = time.monotonic()
                actions.append((t, what, await asyncio.to_thread(fn)))

            await act("LOITER", lambda: set_mode(gcs, "LOITER"))
            await asyncio.sleep(6.0)
            await act("GUIDED", lambda: set_mode(gcs, "GUIDED"))
            if await flight.wait(20.0, until=lambda: flight.engaged):
                engaged_again = time.monotonic()
            await asyncio.sleep(4.0)
            await act(
                "disarm",
                lambda: gcs_command(gcs, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0),
            )
            await asyncio.sleep(3.0)
            await act("RTL", lambda: set_mode(gcs, "RTL"))
            await asyncio.sleep(8.0)
            stop.set()
            sticks.join(2.0)
            gcs.close()
        finally:
            stop.set()
            await flight.stop()
        return PilotRun(actions, engaged_again, flight.outcome(0.0))

    return asyncio.run(main())


# --- what the real autopilot does on the wire (checked against docs/simulator.md) -----------

WIRED_PARAMS = {
    "RNGFND1_TYPE": 10.0,
    "RNGFND1_ORIENT": 39.0,  # PITCH_315
    "RNGFND1_MAX": 10.0,
    "RNGFND2_TYPE": 10.0,
    "RNGFND2_ORIENT": 25.0,  # PITCH_270, down
    "RNGFND2_MAX": 10.0,
    "PRX1_TYPE": 2.0,
}
PARAM_NAMES = (
    "RNGFND1_MAX",
    "RNGFND1_MAX_CM",
    "RNGFND1_MIN",
    "PRX1_TYPE",
    "PRX_TYPE",
    "GUID_TIMEOUT",
    "DISARM_DELAY",
    "RTL_ALT",
    "LAND_SPEED",
)
# what the feeder sends per orientation: (max_cm, current_cm); PRX sectors 0, 2 and 6
FEED = {39: (1000, 500), 25: (1000, 1100), 0: (1200, 800), 2: (1200, 1300), 6: (1200, 400)}


def _param(conn: Any, name: str) -> float | None:
    conn.mav.param_request_read_send(1, 1, name.encode(), -1)
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        msg = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.5)
        if msg is not None and msg.param_id == name:
            return float(msg.param_value)
    return None


def _collect(conn: Any, types: list[str] | None, seconds: float) -> list[tuple[float, Any]]:
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        msg = conn.recv_match(type=types, blocking=True, timeout=0.2)
        if msg is not None:
            out.append((time.monotonic(), msg))
    return out


def _sensor_table(msgs: list[tuple[float, Any]], seconds: float) -> dict[int, dict[str, Any]]:
    table: dict[int, dict[str, Any]] = {}
    for _, m in msgs:
        if m.get_srcComponent() != 1:
            continue  # SITL also routes the feeder's own messages (component 158) to serial0
        row = table.setdefault(
            int(m.id),
            {"orientation": set(), "min": set(), "max": set(), "current": [], "n": 0},
        )
        row["orientation"].add(int(m.orientation))
        row["min"].add(int(m.min_distance))
        row["max"].add(int(m.max_distance))
        row["current"].append(int(m.current_distance))
        row["quaternion"] = [float(q) for q in m.quaternion]
        row["covariance"] = int(m.covariance)
        row["signal_quality"] = int(m.signal_quality)
        row["n"] += 1
    for row in table.values():
        row["rate_hz"] = row["n"] / seconds
    return table


def _target(conn: Any, frame: int, north_m: float, alt_m: float, home: Any) -> None:
    lat = home.latitude + round(north_m / 111_319.5 * 1e7)
    conn.mav.set_position_target_global_int_send(
        0, 1, 1, frame, 0b0000_1111_1111_1000, lat, home.longitude, alt_m, 0, 0, 0, 0, 0, 0, 0, 0
    )


def _north_m(pos: Any, home: Any) -> float:
    return (pos.lat - home.latitude) * 1e-7 * 111_319.5


def claims_job(spec: SitlSpec) -> dict[str, Any]:
    """Ask the real SITL what docs/simulator.md and docs/service.md claim about ArduPilot."""
    sitl = spec.attach()
    seen: dict[str, Any] = {}
    conn = mavutil.mavlink_connection(
        f"udpin:127.0.0.1:{spec.port}", source_system=1, source_component=191
    )
    hb = conn.wait_heartbeat(timeout=30)
    seen["heartbeat"] = (hb.get_srcSystem(), hb.get_srcComponent(), hb.type, hb.autopilot)
    unasked = _collect(conn, None, 3.0)
    seen["unasked_types"] = sorted({m.get_type() for _, m in unasked} - {"BAD_DATA"})
    seen["params"] = {name: _param(conn, name) for name in PARAM_NAMES}

    feed = dict(FEED)
    stop = threading.Event()
    feeder = mavutil.mavlink_connection(
        f"tcp:127.0.0.1:{sitl.bridge_port}", source_system=1, source_component=158
    )

    def feed_loop() -> None:
        while not stop.is_set():
            for orient, (max_cm, cur) in list(feed.items()):
                feeder.mav.distance_sensor_send(
                    int(time.monotonic() * 1000) % 2**32, 20, max_cm, cur, 0, 50 + orient, orient, 0
                )
            while feeder.recv_msg() is not None:
                pass
            time.sleep(0.05)

    thread = threading.Thread(target=feed_loop, daemon=True)
    thread.start()
    try:
        acks = {}
        for name, msg_id, hz in (
            ("DISTANCE_SENSOR", mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR, 20.0),
            ("HOME_POSITION", mavlink.MAVLINK_MSG_ID_HOME_POSITION, 0.5),
            ("GLOBAL_POSITION_INT", mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 10.0),
            ("unknown id 60000", 60000, 1.0),
        ):
            acks[name] = gcs_command(conn, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)
        seen["set_interval_acks"] = acks
        conn.mav.command_long_send(
            1,
            1,
            mavlink.MAV_CMD_GET_MESSAGE_INTERVAL,
            0,
            mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR,
            0,
            0,
            0,
            0,
            0,
            0,
        )
        got = _collect(conn, ["MESSAGE_INTERVAL", "COMMAND_ACK"], 1.5)
        seen["get_interval"] = [
            (m.get_type(), getattr(m, "interval_us", getattr(m, "result", None))) for _, m in got
        ]
        conn.mav.command_long_send(
            1,
            1,
            mavlink.MAV_CMD_REQUEST_MESSAGE,
            0,
            mavlink.MAVLINK_MSG_ID_HOME_POSITION,
            0,
            0,
            0,
            0,
            0,
            0,
        )
        got = _collect(conn, ["HOME_POSITION", "COMMAND_ACK"], 1.5)
        seen["request_home"] = [m.get_type() for _, m in got][:2]
        time.sleep(1.0)
        seen["sensors"] = _sensor_table(_collect(conn, ["DISTANCE_SENSOR"], 4.0), 4.0)
        feed[6] = (1200, 1300)  # the left sector loses its object
        feed.pop(39)  # the forward-down rangefinder goes silent
        # Wait (bounded) until SITL reports the change, however loaded the machine, then
        # let its 500 ms rangefinder timeout pass: the window below sees the settled state.
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline:
            m = conn.recv_match(type="DISTANCE_SENSOR", blocking=True, timeout=0.2)
            sector_16 = m is not None and m.get_srcComponent() == 1 and int(m.id) == 16
            if sector_16 and int(m.current_distance) == 1200:
                break
        _collect(conn, None, 1.5)  # drain what was queued meanwhile
        seen["sensors_after"] = _sensor_table(_collect(conn, ["DISTANCE_SENSOR"], 2.0), 2.0)

        # GUIDED targets
        sitl.wait_ready(port=sitl.gcs_port)  # SERIAL2 carries the feeder
        home = None
        conn.mav.command_long_send(
            1,
            1,
            mavlink.MAV_CMD_REQUEST_MESSAGE,
            0,
            mavlink.MAVLINK_MSG_ID_HOME_POSITION,
            0,
            0,
            0,
            0,
            0,
            0,
        )
        while home is None:
            home = conn.recv_match(type="HOME_POSITION", blocking=True, timeout=5)
        seen["guided"] = set_mode(conn, "GUIDED")
        seen["arm"] = -1
        for _ in range(10):
            seen["arm"] = gcs_command(conn, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            if seen["arm"] == 0:
                break
            time.sleep(1.0)
        seen["takeoff"] = gcs_command(conn, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 8.0)

        def position_after(seconds: float) -> Any:
            end = time.monotonic() + seconds
            last = None
            while time.monotonic() < end:
                last = conn.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=1) or last
            return last

        position_after(10.0)
        _target(conn, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 10.0, 12.0, home)
        pos = position_after(10.0)
        seen["frame6"] = {
            "relative_alt_m": pos.relative_alt * 1e-3,
            "alt_above_home_m": (pos.alt - home.altitude) * 1e-3,
            "north_m": _north_m(pos, home),
        }
        # leave GUIDED while flying to a target, come back: does the target survive?
        _target(conn, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 40.0, 12.0, home)
        position_after(2.0)
        seen["loiter"] = set_mode(conn, "LOITER")
        at_loiter = _north_m(position_after(3.0), home)
        seen["guided_again"] = set_mode(conn, "GUIDED")
        seen["reenter"] = {
            "north_at_loiter_m": at_loiter,
            "north_after_8s_m": _north_m(position_after(8.0), home),
        }
        # a target in a frame SET_POSITION_TARGET_GLOBAL_INT does not take (MAV_FRAME_LOCAL_NED)
        _target(conn, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 45.0, 12.0, home)
        start = _north_m(position_after(2.0), home)
        _target(conn, mavlink.MAV_FRAME_LOCAL_NED, 0.0, 12.0, home)
        seen["bad_frame"] = {
            "north_when_sent_m": start,
            "north_after_8s_m": _north_m(position_after(8.0), home),
        }
        seen["disarm_in_air"] = gcs_command(conn, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0)
    finally:
        stop.set()
        thread.join(2.0)
        feeder.close()
        conn.close()
    return seen
