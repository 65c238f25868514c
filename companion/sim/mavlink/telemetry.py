"""Outgoing telemetry: which message is due when, and how each is filled from the truth.

`MessageScheduler` keeps one interval per message (simulated seconds, as SITL's scheduler
runs in simulated time), changed by MAV_CMD_SET_MESSAGE_INTERVAL: interval_us -1 disables,
0 restores the default, > 0 sets it. `Snapshot` is the vehicle as telemetry sees it; the
`*_message` functions fill MAVLink's NED/FRD fields from it (via companion.planner.frames).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.geo import LocalFrame
from companion.planner.frames import attitude_enu_to_ned, enu_to_ned
from companion.planner.types import FloatArray
from companion.sim.mavlink.personality import FlightMode, Personality
from companion.sim.mavlink.streams import NAME_OF_ID, STREAMED_MESSAGES

_EPS = 1e-9


StreamPhases = Literal["buckets", "per_stream"]
"""How the streams' send times are phased: see `MessageScheduler`."""


@dataclass(slots=True)
class _Group:
    """Messages sent together: one interval, one phase (simulated seconds)."""

    interval_s: float
    next_s: float
    members: set[int] = field(default_factory=set)


class MessageScheduler:
    """Per-message intervals and due times, in simulated seconds.

    phases = "buckets" (ArduPilot, GCS_MAVLINK's deferred message buckets): the messages of
    one interval form one group with one phase, so they go out in the same tick, in the
    order of `STREAMED_MESSAGES` (ATTITUDE, the position, ..., the DISTANCE_SENSORs). A
    message set to an interval no group has opens a group whose first send is one interval
    later; a message set to the interval of a group joins that group's phase; a message set
    again to the interval it has keeps its phase. HEARTBEAT keeps a phase of its own
    (ArduPilot schedules it apart from the buckets).
    phases = "per_stream" (PX4, one MavlinkStream per message): each message has its own
    phase; a stream that was off starts at once, one that streams keeps its phase when its
    interval changes.
    After a (re)boot the default rates start at once, in one group per interval.
    """

    def __init__(
        self, default_rates_hz: Mapping[str, float], phases: StreamPhases = "buckets"
    ) -> None:
        self._defaults: dict[int, float | None] = {
            STREAMED_MESSAGES[name]: (1.0 / hz if hz > 0 else None)
            for name, hz in default_rates_hz.items()
        }
        self.phases: StreamPhases = phases
        self.reset(0.0)

    def reset(self, now_s: float) -> None:
        """Back to the default rates (after a reboot); they start at now_s."""
        self._interval: dict[int, float | None] = {}
        self._group_of: dict[int, _Group] = {}
        self._groups: list[_Group] = []
        for msg_id in STREAMED_MESSAGES.values():
            if msg_id in self._defaults:
                self._assign(msg_id, self._defaults[msg_id], now_s, first_s=now_s)

    def supports(self, msg_id: int) -> bool:
        return msg_id in NAME_OF_ID

    def set_interval_us(self, msg_id: int, interval_us: float, now_s: float) -> bool:
        """MAV_CMD_SET_MESSAGE_INTERVAL semantics; False for a message that is not streamed."""
        if not self.supports(msg_id) or not math.isfinite(interval_us):
            return False
        interval: float | None
        if interval_us < 0:
            interval = None
        elif interval_us == 0:
            interval = self._defaults.get(msg_id)
        else:
            interval = interval_us * 1e-6
        self._assign(msg_id, interval, now_s)
        return True

    def interval_us(self, msg_id: int) -> int:
        """MESSAGE_INTERVAL.interval_us: -1 disabled, 0 not available, else the interval."""
        if not self.supports(msg_id):
            return 0
        interval = self._interval.get(msg_id)
        return -1 if interval is None else round(interval * 1e6)

    def due(self, now_s: float) -> list[int]:
        """Messages to send at now_s, in a fixed order; advances their next due time."""
        groups = [g for g in self._groups if now_s + _EPS >= g.next_s]
        if not groups:
            return []
        # the longest overdue group first (the first opened of a tie), each whole
        groups.sort(key=lambda g: g.next_s)
        out: list[int] = []
        for g in groups:
            out.extend(m for m in _ORDER if m in g.members)
            nxt = g.next_s + g.interval_s
            g.next_s = nxt if nxt > now_s + _EPS else now_s + g.interval_s
        return out

    def _assign(
        self, msg_id: int, interval: float | None, now_s: float, first_s: float | None = None
    ) -> None:
        """Put msg_id in the group of `interval` (None: off). first_s: when a group opened
        here first sends (default: as the phases rule says)."""
        old = self._group_of.get(msg_id)
        self._interval[msg_id] = interval
        if old is not None and interval is not None and _same(old.interval_s, interval):
            return  # already streaming at this interval: the phase stays
        if self.phases == "per_stream" and old is not None and interval is not None:
            # PX4: a streaming message keeps its last send; the next is one new interval on
            old.next_s += interval - old.interval_s
            old.interval_s = interval
            return
        if old is not None:
            old.members.discard(msg_id)
            if not old.members:
                self._groups.remove(old)
            del self._group_of[msg_id]
        if interval is None:
            return
        shared = self.phases == "buckets" and msg_id != _HEARTBEAT
        group = next(
            (
                g
                for g in self._groups
                if shared and _HEARTBEAT not in g.members and _same(g.interval_s, interval)
            ),
            None,
        )
        if group is None:
            if first_s is None:
                first_s = now_s + interval if self.phases == "buckets" else now_s
            group = _Group(interval, first_s)
            self._groups.append(group)
        group.members.add(msg_id)
        self._group_of[msg_id] = group


_HEARTBEAT = STREAMED_MESSAGES["HEARTBEAT"]
_ORDER = tuple(STREAMED_MESSAGES.values())


def _same(a_s: float, b_s: float) -> bool:
    """Two intervals that are the same to the microsecond (MAVLink's interval unit)."""
    return round(a_s * 1e6) == round(b_s * 1e6)


@dataclass(frozen=True, slots=True)
class Snapshot:
    """The vehicle as telemetry reports it. World ENU / body FLU, metres, radians, seconds."""

    time_boot_ms: int
    time_ns: int
    """Time since boot in nanoseconds (TIMESYNC tc1)."""
    position_enu: FloatArray
    velocity_enu: FloatArray
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rates_radps: tuple[float, float, float]
    """Roll, pitch and yaw rate in the MAVLink sense (yaw rate clockwise positive)."""


def heartbeat_message(
    mav: Any, p: Personality, mode: FlightMode, armed: bool, failsafe: bool
) -> Any:
    return mav.heartbeat_encode(
        p.mav_type,
        p.autopilot,
        p.base_mode(mode, armed),
        mode.custom_mode,
        p.system_status(armed, failsafe),
        3,
    )


def attitude_message(mav: Any, s: Snapshot) -> Any:
    roll, pitch, yaw = attitude_enu_to_ned(s.roll_rad, s.pitch_rad, s.yaw_rad)
    return mav.attitude_encode(s.time_boot_ms, roll, pitch, yaw, *s.rates_radps)


def global_position_int_message(
    mav: Any, s: Snapshot, frame: LocalFrame, home_amsl_m: float
) -> Any:
    geo = frame.to_geodetic(*(float(v) for v in s.position_enu))
    vel_ned = enu_to_ned(s.velocity_enu)
    _, _, yaw_ned = attitude_enu_to_ned(s.roll_rad, s.pitch_rad, s.yaw_rad)
    hdg = round(math.degrees(yaw_ned) * 100.0) % 36000
    return mav.global_position_int_encode(
        s.time_boot_ms,
        round(geo.lat_deg * 1e7),
        round(geo.lon_deg * 1e7),
        round(geo.alt_m * 1000.0),
        round((geo.alt_m - home_amsl_m) * 1000.0),
        *(_clamp_i16(round(v * 100.0)) for v in vel_ned),
        hdg,
    )


def local_position_ned_message(mav: Any, s: Snapshot, origin_enu: FloatArray) -> Any:
    pos_ned = enu_to_ned(s.position_enu - origin_enu)
    vel_ned = enu_to_ned(s.velocity_enu)
    return mav.local_position_ned_encode(
        s.time_boot_ms, *(float(v) for v in pos_ned), *(float(v) for v in vel_ned)
    )


def home_position_message(
    mav: Any, frame: LocalFrame, home_enu: FloatArray, origin_enu: FloatArray, time_usec: int
) -> Any:
    geo = frame.to_geodetic(*(float(v) for v in home_enu))
    local = enu_to_ned(home_enu - origin_enu)
    return mav.home_position_encode(
        round(geo.lat_deg * 1e7),
        round(geo.lon_deg * 1e7),
        round(geo.alt_m * 1000.0),
        *(float(v) for v in local),
        [1.0, 0.0, 0.0, 0.0],
        0.0,
        0.0,
        0.0,
        time_usec,
    )


_SENSORS = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS
    | mavlink.MAV_SYS_STATUS_SENSOR_LASER_POSITION
    | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | mavlink.MAV_SYS_STATUS_AHRS
)


def sys_status_message(mav: Any, ready: bool, drops_pct: float) -> Any:
    health = _SENSORS if ready else _SENSORS & ~mavlink.MAV_SYS_STATUS_SENSOR_GPS
    return mav.sys_status_encode(
        _SENSORS, _SENSORS, health, 100, 12600, -1, 100, int(drops_pct * 100), 0, 0, 0, 0, 0
    )


def extended_sys_state_message(mav: Any, landed: bool, armed: bool, climbing: bool) -> Any:
    if landed:
        state = mavlink.MAV_LANDED_STATE_ON_GROUND
    elif climbing:
        state = mavlink.MAV_LANDED_STATE_TAKEOFF
    else:
        state = mavlink.MAV_LANDED_STATE_IN_AIR
    return mav.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED, state)


def autopilot_version_message(mav: Any, p: Personality, system_id: int) -> Any:
    caps = (
        mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
        | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
        | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
        | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
        | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    )
    return mav.autopilot_version_encode(
        caps, p.flight_sw_version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, system_id
    )


def _clamp_i16(v: float) -> int:
    return int(min(max(v, -32768), 32767))
