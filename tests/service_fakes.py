"""Test doubles for the service tests: a small fake autopilot and a fake planner.

The fake autopilot speaks real MAVLink through pymavlink's codec over any Link (in-memory or
UDP). It answers COMMAND_LONG (results configurable per command), serves a mission, streams
HEARTBEAT/ATTITUDE/GLOBAL_POSITION_INT/HOME_POSITION/DISTANCE_SENSOR from a background task,
and records everything it receives with its receipt time.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.config import ServiceConfig, parse_config
from companion.planner.sensors import quaternion_from_boresight_frd
from companion.planner.types import (
    Decision,
    Diagnostics,
    PathMode,
    Setpoint,
    Side,
    StepResult,
    VehicleState,
)
from companion.service.codec import MavCodec, mavlink2
from companion.service.link import Link

HOME = (47.397742, 8.545594, 488.0)  # lat, lon, alt AMSL (PX4's SITL home)

SENSORS = [
    {"id": 0, "name": "front", "role": "obstacle", "group": "F", "orientation": "NONE"},
    {"id": 1, "name": "h1", "role": "surface", "group": "forward", "orientation": "PITCH_315"},
    {"id": 2, "name": "h2", "role": "surface", "group": "back", "rpy_deg": [0, 315, 180]},
]


def make_config(**sections: Any) -> ServiceConfig:
    """A test config: fast timeouts, three sensors, a short route; override by section."""
    data: dict[str, Any] = {
        "link": {"connection": "udpin:127.0.0.1:0"},
        "autopilot": {
            "heartbeat_timeout_s": 0.6,
            "command_timeout_s": 0.3,
            "auto_id_listen_s": 0.3,
        },
        # the fake autopilot faces north and the route goes east: no turn to face it here
        # (tests/test_service_cycle.py turns)
        "control": {"rate_hz": 20.0, "min_engage_height_m": 1.0, "face_route_deg": 180.0},
        "route": {"source": "config", "points": [[20.0, 0.0], [40.0, 0.0]]},
        "sensors": SENSORS,
        "failsafe": {"resume_after_s": 0.2},
        "statustext": {"max_per_s": 50, "burst": 50, "repeat_interval_s": 0.0},
    }
    for key, value in sections.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    return parse_config(data)


@dataclass
class Received:
    t: float
    msg: Any


@dataclass
class FakeAutopilot:
    """kind: "ardupilot" or "px4". Position/attitude/ranges are plain attributes to change."""

    link: Link
    kind: str = "ardupilot"
    sysid: int = 1
    compid: int = 1
    vehicle_type: int = 2  # quadrotor
    armed: bool = True
    custom_mode: int = 5  # ArduCopter LOITER
    lat: float = HOME[0]
    lon: float = HOME[1]
    alt_amsl: float = HOME[2] + 5.0
    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0
    ranges_cm: dict[int, int] = field(default_factory=lambda: {0: 0, 1: 700, 2: 700})
    orientations: dict[int, tuple[int, list[float]]] = field(default_factory=dict)
    limits_cm: dict[int, tuple[int, int]] = field(default_factory=dict)
    """Per sensor id (min_distance, max_distance) cm; default (10, 1000)."""
    rate_hz: float = 40.0
    heartbeat_enabled: bool = True
    telemetry_enabled: bool = True
    sensors_enabled: set[int] | None = None
    command_results: dict[int, int] = field(default_factory=dict)
    result_script: dict[int, list[int]] = field(default_factory=dict)
    """Per command: results used first, one per COMMAND_LONG (-1 = no answer), then
    command_results."""
    refusal_text: str | None = None
    """Sent as STATUSTEXT (CRITICAL, chunked like ArduPilot's) with each refused command."""
    mission: list[tuple[float, float]] = field(default_factory=list)
    follow_setpoints: bool = False
    answer_timesync: bool = True
    received: list[Received] = field(default_factory=list)
    commands: list[Any] = field(default_factory=list)
    signing_key: bytes | None = None
    climb_to: float | None = None
    attitude_enabled: bool = True
    """False: no ATTITUDE (yet), the rest of the telemetry as usual."""

    def __post_init__(self) -> None:
        self.codec = MavCodec(self.sysid, self.compid)
        if self.signing_key is not None:
            self.codec.enable_signing(self.signing_key, timestamp=10**12)
        self._task: asyncio.Task[None] | None = None
        self._boot = time.monotonic()
        if self.kind == "px4":
            self.custom_mode = 3 << 16  # POSCTL
        if not self.orientations:
            # sensor 2 is tilted back-down: CUSTOM with its quaternion, as a real table would
            from companion.tuning import SensorConfig

            spec = SensorConfig.model_validate(SENSORS[2]).to_spec()
            q = quaternion_from_boresight_frd(spec.boresight_frd).tolist()
            self.orientations = {0: (0, [0, 0, 0, 0]), 1: (39, [0, 0, 0, 0]), 2: (100, q)}

    # -- lifecycle --------------------------------------------------------------------------

    async def start(self) -> None:
        await self.link.open(self._on_bytes)
        self._task = asyncio.create_task(self._stream())

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        await self.link.close()

    # -- sending ----------------------------------------------------------------------------

    def send(self, msg: Any) -> None:
        self.link.send(self.codec.encode(msg))

    def time_boot_ms(self) -> int:
        return int((time.monotonic() - self._boot) * 1000)

    @property
    def base_mode(self) -> int:
        return 1 | (128 if self.armed else 0)

    def heartbeat(self) -> None:
        autopilot = 3 if self.kind == "ardupilot" else 12
        self.send(
            mavlink2.MAVLink_heartbeat_message(
                self.vehicle_type, autopilot, self.base_mode, self.custom_mode, 4, 3
            )
        )

    def set_mode(self, custom_mode: int) -> None:
        """Change the mode and announce it at once (as autopilots do)."""
        self.custom_mode = custom_mode
        self.heartbeat()

    def telemetry(self) -> None:
        tb = self.time_boot_ms()
        if self.attitude_enabled:
            self.send(
                mavlink2.MAVLink_attitude_message(
                    tb, self.roll, self.pitch, self.yaw, 0.0, 0.0, 0.0
                )
            )
        self.send(
            mavlink2.MAVLink_global_position_int_message(
                tb,
                round(self.lat * 1e7),
                round(self.lon * 1e7),
                round(self.alt_amsl * 1000),
                round((self.alt_amsl - HOME[2]) * 1000),
                0,
                0,
                0,
                0,
            )
        )
        self.send(
            mavlink2.MAVLink_home_position_message(
                round(HOME[0] * 1e7),
                round(HOME[1] * 1e7),
                round(HOME[2] * 1000),
                0.0,
                0.0,
                0.0,
                [1.0, 0.0, 0.0, 0.0],
                0.0,
                0.0,
                0.0,
            )
        )
        for sid, cm in self.ranges_cm.items():
            if self.sensors_enabled is not None and sid not in self.sensors_enabled:
                continue
            orientation, q = self.orientations[sid]
            lo, hi = self.limits_cm.get(sid, (10, 1000))
            self.send(
                mavlink2.MAVLink_distance_sensor_message(
                    tb, lo, hi, cm, 0, sid, orientation, 0, 0.0, 0.0, q
                )
            )

    async def _stream(self) -> None:
        period = 1.0 / self.rate_hz
        n = 0
        while True:
            if self.heartbeat_enabled and n % max(1, int(self.rate_hz / 5)) == 0:
                self.heartbeat()
            if self.climb_to is not None:
                step = 10.0 * period
                self.alt_amsl = min(self.climb_to, self.alt_amsl + step)
            if self.telemetry_enabled:
                self.telemetry()
            n += 1
            await asyncio.sleep(period)

    # -- receiving --------------------------------------------------------------------------

    def _on_bytes(self, data: bytes, peer: Any) -> None:
        now = time.monotonic()
        for msg in self.codec.decode(data, self.link.datagram):
            self.received.append(Received(now, msg))
            handler = getattr(self, "_on_" + msg.get_type().lower(), None)
            if handler is not None:
                handler(msg)

    def _ack(self, msg: Any, result: int) -> None:
        self.send(
            mavlink2.MAVLink_command_ack_message(
                int(msg.command), result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
            )
        )

    def _on_command_long(self, msg: Any) -> None:
        self.commands.append(msg)
        cmd = int(msg.command)
        script = self.result_script.get(cmd)
        result = script.pop(0) if script else self.command_results.get(cmd, 0)
        if result != 0 and self.refusal_text is not None:
            raw = self.refusal_text.encode()
            for seq, i in enumerate(range(0, len(raw), 50)):
                self.send(mavlink2.MAVLink_statustext_message(2, raw[i : i + 50], 7, seq))
        if result == -1:
            return  # never answer
        self._ack(msg, result)
        if result != 0:
            return
        if cmd == 176:  # DO_SET_MODE
            self.custom_mode = (
                int(msg.param2) if self.kind == "ardupilot" else int(msg.param2) << 16
            )
            self.heartbeat()
        elif cmd == 400:
            self.armed = msg.param1 == 1.0
            self.heartbeat()
        elif cmd == 22:  # take-off: climb there at 10 m/s
            target = msg.param7 if self.kind == "px4" else HOME[2] + msg.param7
            self.climb_to = float(target)

    def _on_mission_request_list(self, msg: Any) -> None:
        n = len(self.mission) + (1 if self.kind == "ardupilot" else 0)
        self.send(mavlink2.MAVLink_mission_count_message(255, 190, n, 0))

    def _on_mission_request_int(self, msg: Any) -> None:
        seq = int(msg.seq)
        items = ([HOME[:2]] if self.kind == "ardupilot" else []) + self.mission
        lat, lon = items[seq]
        self.send(
            mavlink2.MAVLink_mission_item_int_message(
                255, 190, seq, 6, 16, 0, 1, 0, 0, 0, 0, round(lat * 1e7), round(lon * 1e7), 10.0
            )
        )

    def _on_set_position_target_global_int(self, msg: Any) -> None:
        if self.follow_setpoints:
            self.lat, self.lon = msg.lat_int * 1e-7, msg.lon_int * 1e-7

    # -- queries ----------------------------------------------------------------------------

    def of_type(self, mtype: str) -> list[Received]:
        return [r for r in self.received if r.msg.get_type() == mtype]

    def setpoints(self) -> list[Received]:
        return self.of_type("SET_POSITION_TARGET_GLOBAL_INT")

    async def wait_for(self, pred: Any, timeout: float = 5.0) -> None:
        deadline = time.monotonic() + timeout
        while not pred():
            if time.monotonic() > deadline:
                raise TimeoutError("condition not met")
            await asyncio.sleep(0.01)


class FakePlanner:
    """Moves X_d east at v_d from the start position; records what it was given."""

    def __init__(self, params: Any, sensors: Any, route: Any, start: np.ndarray) -> None:
        self.params = params
        self.route = route
        self.x_d = np.array(start, dtype=float)
        self.inputs: list[tuple[VehicleState, np.ndarray, float]] = []
        self.h_d = params.h_d_m
        self.fail = False

    def set_desired_height(self, h_d_m: float) -> None:
        self.h_d = h_d_m

    def step(self, state: VehicleState, ranges_m: np.ndarray, dt_s: float) -> StepResult:
        if self.fail:
            raise RuntimeError("planner bug")
        self.inputs.append((state, ranges_m.copy(), dt_s))
        v = np.array([self.params.v_d_mps, 0.0, 0.0])
        self.x_d = self.x_d + v * dt_s
        events = ("first step",) if len(self.inputs) == 1 else ()
        return StepResult(
            Setpoint(self.x_d.copy(), v, 0.0, 0.0),
            Diagnostics(
                Decision.VERTICAL,
                PathMode.ROUTE,
                Side.NONE,
                np.zeros(1),
                np.zeros(1),
                0.0,
                0,
                0.0,
                1.0,
                0.0,
                True,
                False,
                False,
                events,
            ),
        )


class PlannerBox:
    """A factory that remembers the planners it made."""

    def __init__(self) -> None:
        self.made: list[FakePlanner] = []

    def __call__(self, params: Any, sensors: Any, route: Any, start: np.ndarray) -> FakePlanner:
        p = FakePlanner(params, sensors, route, start)
        self.made.append(p)
        return p


def enu_of(msg: Any) -> tuple[float, float]:
    """East/north metres of a setpoint relative to HOME (small-area approximation)."""
    lat, lon = msg.lat_int * 1e-7, msg.lon_int * 1e-7
    north = math.radians(lat - HOME[0]) * 6_378_137.0
    east = math.radians(lon - HOME[1]) * 6_378_137.0 * math.cos(math.radians(HOME[0]))
    return east, north
