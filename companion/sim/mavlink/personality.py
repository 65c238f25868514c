"""What makes the simulator look like ArduCopter, ArduSub or PX4 on the wire.

A `Personality` is data: HEARTBEAT type and autopilot, the custom flight modes with their
base_mode flags and what the simulated vehicle does in each (`Behaviour`), the default
message rates, and the COMMAND_ACK result codes each autopilot uses when it refuses. The
flight logic that uses it lives in `companion.sim.mavlink.autopilot`; SET_POSITION_TARGET_GLOBAL_INT
decoding per autopilot in `companion.sim.mavlink.setpoints`.

Custom modes: ArduPilot puts the mode number in custom_mode (ArduCopter GUIDED = 4).
PX4 packs main and sub mode as custom_mode = main << 16 | sub << 24 (OFFBOARD = main 6,
AUTO.LOITER = main 4 sub 3) and takes them as param2/param3 of MAV_CMD_DO_SET_MODE.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.sim.mavlink.config import PersonalityName

_CUSTOM = int(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
_MANUAL = mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
_STABILIZE = mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
_GUIDED = mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
_AUTO = mavlink.MAV_MODE_FLAG_AUTO_ENABLED
_ARMED = int(mavlink.MAV_MODE_FLAG_SAFETY_ARMED)


class Behaviour(enum.Enum):
    """What the simulated vehicle does in a mode (there is no pilot on the sticks)."""

    HOLD = "hold"
    """Stop and hold position (manual, altitude/position hold, loiter, unsimulated auto)."""
    GUIDED = "guided"
    """Follow SET_POSITION_TARGET_GLOBAL_INT (ArduPilot GUIDED, PX4 OFFBOARD)."""
    TAKEOFF = "takeoff"
    """Climb to the takeoff altitude (PX4 AUTO.TAKEOFF)."""
    LAND = "land"
    RTL = "rtl"
    """Climb to the return altitude, fly home, land."""
    SURFACE = "surface"
    """ArduSub SURFACE: rise to the water surface (world z of home)."""


@dataclass(frozen=True, slots=True)
class FlightMode:
    name: str
    custom_mode: int
    behaviour: Behaviour
    base_flags: int
    """base_mode flags apart from CUSTOM_MODE_ENABLED and SAFETY_ARMED."""
    armable: bool = True
    needs_position: bool = True
    """Refused until the estimator is ready (the pre-arm delay)."""


def px4_custom_mode(main: int, sub: int = 0) -> int:
    return (main << 16) | (sub << 24)


@dataclass(frozen=True, slots=True)
class Personality:
    name: PersonalityName
    family: Literal["ardupilot", "px4"]
    """Wire conventions shared by ArduCopter and ArduSub, or PX4's."""
    mav_type: int
    autopilot: int
    modes: tuple[FlightMode, ...]
    default_mode: str
    guided_mode: str
    hold_mode: str
    land_mode: str | None
    rtl_mode: str | None
    takeoff_mode: str | None
    """PX4 switches to AUTO.TAKEOFF on NAV_TAKEOFF; ArduCopter takes off inside GUIDED."""
    after_takeoff_mode: str | None
    """Mode entered when a takeoff completes (None: stay)."""
    supports_takeoff: bool
    is_submarine: bool
    has_home_mission_item: bool
    set_mode_ack_command: int
    """COMMAND_ACK.command sent in reply to a SET_MODE message."""
    result_refused: int
    """COMMAND_ACK result for arming, mode and takeoff refusals."""
    flight_sw_version: int
    default_rates_hz: Mapping[str, float] = field(default_factory=dict)

    def mode(self, name: str) -> FlightMode:
        key = name.upper()
        for m in self.modes:
            if m.name == key:
                return m
        alias = _ALIASES[self.family].get(key)
        if alias is not None:
            return self.mode(alias)
        raise ValueError(
            f"{self.name.value} has no mode {name!r}; known: {[m.name for m in self.modes]}"
        )

    def mode_for_custom(self, custom_mode: int) -> FlightMode | None:
        if self.family == "px4":
            main = (custom_mode >> 16) & 0xFF
            sub = (custom_mode >> 24) & 0xFF if main == _PX4_AUTO else 0
            custom_mode = px4_custom_mode(main, sub)
        for m in self.modes:
            if m.custom_mode == custom_mode:
                return m
        return None

    def mode_from_spec(self, spec: str | int) -> FlightMode:
        """A mode by name or by custom_mode number (ValueError if unknown)."""
        if isinstance(spec, int) or spec.isdigit():
            found = self.mode_for_custom(int(spec))
            if found is None:
                raise ValueError(f"{self.name.value} has no custom_mode {spec}")
            return found
        return self.mode(spec)

    def mode_from_command(self, param1: float, param2: float, param3: float) -> FlightMode | None:
        """MAV_CMD_DO_SET_MODE: param1 base mode, param2 custom (PX4: main) mode, param3 sub."""
        if not int(param1) & _CUSTOM:
            return None
        if self.family == "px4":
            return self.mode_for_custom(px4_custom_mode(int(param2), int(param3)))
        return self.mode_for_custom(int(param2))

    def base_mode(self, mode: FlightMode, armed: bool) -> int:
        return _CUSTOM | mode.base_flags | (_ARMED if armed else 0)

    def system_status(self, armed: bool, failsafe: bool) -> int:
        if failsafe:
            return int(mavlink.MAV_STATE_CRITICAL)
        return int(mavlink.MAV_STATE_ACTIVE if armed else mavlink.MAV_STATE_STANDBY)


# PX4's main modes (px4_custom_mode.h) are not in MAVLink's XML, so pymavlink has no enum for them.
_PX4_AUTO = 4
_ALIASES: dict[str, dict[str, str]] = {
    "ardupilot": {"HOLD": "LOITER", "POSCTL": "LOITER", "OFFBOARD": "GUIDED"},
    "px4": {
        "HOLD": "AUTO.LOITER",
        "LOITER": "AUTO.LOITER",
        "RTL": "AUTO.RTL",
        "LAND": "AUTO.LAND",
        "TAKEOFF": "AUTO.TAKEOFF",
        "MISSION": "AUTO.MISSION",
        "GUIDED": "OFFBOARD",
        "POSITION": "POSCTL",
        "ALTITUDE": "ALTCTL",
    },
}

_COPTER_POS = _STABILIZE | _MANUAL | _GUIDED
_COPTER_MAN = _STABILIZE | _MANUAL
B = Behaviour

ARDUCOPTER_MODES = (
    FlightMode(
        "STABILIZE", mavlink.COPTER_MODE_STABILIZE, B.HOLD, _COPTER_MAN, needs_position=False
    ),
    FlightMode("ACRO", mavlink.COPTER_MODE_ACRO, B.HOLD, _COPTER_MAN, needs_position=False),
    FlightMode("ALT_HOLD", mavlink.COPTER_MODE_ALT_HOLD, B.HOLD, _COPTER_MAN, needs_position=False),
    FlightMode("AUTO", mavlink.COPTER_MODE_AUTO, B.HOLD, _COPTER_POS, armable=False),
    FlightMode("GUIDED", mavlink.COPTER_MODE_GUIDED, B.GUIDED, _COPTER_POS),
    FlightMode("LOITER", mavlink.COPTER_MODE_LOITER, B.HOLD, _COPTER_POS),
    FlightMode("RTL", mavlink.COPTER_MODE_RTL, B.RTL, _COPTER_POS, armable=False),
    FlightMode("CIRCLE", mavlink.COPTER_MODE_CIRCLE, B.HOLD, _COPTER_POS, armable=False),
    FlightMode(
        "LAND", mavlink.COPTER_MODE_LAND, B.LAND, _COPTER_MAN, armable=False, needs_position=False
    ),
    FlightMode("DRIFT", mavlink.COPTER_MODE_DRIFT, B.HOLD, _COPTER_MAN),
    FlightMode("SPORT", mavlink.COPTER_MODE_SPORT, B.HOLD, _COPTER_MAN, needs_position=False),
    FlightMode("POSHOLD", mavlink.COPTER_MODE_POSHOLD, B.HOLD, _COPTER_POS),
    FlightMode("BRAKE", mavlink.COPTER_MODE_BRAKE, B.HOLD, _COPTER_POS, armable=False),
    FlightMode("SMART_RTL", mavlink.COPTER_MODE_SMART_RTL, B.RTL, _COPTER_POS, armable=False),
)

ARDUSUB_MODES = (
    FlightMode("STABILIZE", mavlink.SUB_MODE_STABILIZE, B.HOLD, _COPTER_MAN, needs_position=False),
    FlightMode("ACRO", mavlink.SUB_MODE_ACRO, B.HOLD, _COPTER_MAN, needs_position=False),
    FlightMode("ALT_HOLD", mavlink.SUB_MODE_ALT_HOLD, B.HOLD, _COPTER_MAN, needs_position=False),
    FlightMode("AUTO", mavlink.SUB_MODE_AUTO, B.HOLD, _COPTER_POS),
    FlightMode("GUIDED", mavlink.SUB_MODE_GUIDED, B.GUIDED, _COPTER_POS),
    FlightMode("CIRCLE", mavlink.SUB_MODE_CIRCLE, B.HOLD, _COPTER_POS),
    FlightMode("SURFACE", mavlink.SUB_MODE_SURFACE, B.SURFACE, _COPTER_MAN, needs_position=False),
    FlightMode("POSHOLD", mavlink.SUB_MODE_POSHOLD, B.HOLD, _COPTER_POS),
    FlightMode("MANUAL", mavlink.SUB_MODE_MANUAL, B.HOLD, _MANUAL, needs_position=False),
    FlightMode("SURFTRAK", mavlink.SUB_MODE_SURFTRAK, B.HOLD, _COPTER_MAN, needs_position=False),
)

_PX4_AUTO_FLAGS = _AUTO | _STABILIZE | _GUIDED
PX4_MODES = (
    FlightMode("MANUAL", px4_custom_mode(1), B.HOLD, _MANUAL | _STABILIZE, needs_position=False),
    FlightMode("ALTCTL", px4_custom_mode(2), B.HOLD, _MANUAL | _STABILIZE, needs_position=False),
    FlightMode("POSCTL", px4_custom_mode(3), B.HOLD, _MANUAL | _STABILIZE | _GUIDED),
    FlightMode("AUTO.TAKEOFF", px4_custom_mode(4, 2), B.TAKEOFF, _PX4_AUTO_FLAGS),
    FlightMode("AUTO.LOITER", px4_custom_mode(4, 3), B.HOLD, _PX4_AUTO_FLAGS),
    FlightMode("AUTO.MISSION", px4_custom_mode(4, 4), B.HOLD, _PX4_AUTO_FLAGS),
    FlightMode("AUTO.RTL", px4_custom_mode(4, 5), B.RTL, _PX4_AUTO_FLAGS, armable=False),
    FlightMode("AUTO.LAND", px4_custom_mode(4, 6), B.LAND, _PX4_AUTO_FLAGS, armable=False),
    FlightMode("ACRO", px4_custom_mode(5), B.HOLD, _MANUAL, needs_position=False),
    FlightMode("OFFBOARD", px4_custom_mode(6), B.GUIDED, _PX4_AUTO_FLAGS),
    FlightMode(
        "STABILIZED", px4_custom_mode(7), B.HOLD, _MANUAL | _STABILIZE, needs_position=False
    ),
)

_DEV = mavlink.FIRMWARE_VERSION_TYPE_DEV
_OFFICIAL = mavlink.FIRMWARE_VERSION_TYPE_OFFICIAL
# Versions as AUTOPILOT_VERSION.flight_sw_version: major << 24 | minor << 16 | patch << 8 | type.
_AP_VERSION = (4 << 24) | (7 << 16) | (0 << 8) | _DEV
_SUB_VERSION = (4 << 24) | (5 << 16) | (0 << 8) | _OFFICIAL
_PX4_VERSION = (1 << 24) | (18 << 16) | (0 << 8) | _OFFICIAL

# A plain client of ArduPilot SITL gets only HEARTBEAT until it asks; PX4's onboard link
# (MAVLINK_MODE_ONBOARD) streams these on its own.
_AP_RATES = {"HEARTBEAT": 1.0}
_PX4_RATES = {
    "HEARTBEAT": 1.0,
    "SYS_STATUS": 1.0,
    "ATTITUDE": 100.0,
    "GLOBAL_POSITION_INT": 50.0,
    "LOCAL_POSITION_NED": 30.0,
    "DISTANCE_SENSOR": 10.0,
    "HOME_POSITION": 0.5,
    "EXTENDED_SYS_STATE": 5.0,
    "TIMESYNC": 10.0,
    "SYSTEM_TIME": 1.0,
}

ARDUCOPTER = Personality(
    name=PersonalityName.ARDUPILOT,
    family="ardupilot",
    mav_type=mavlink.MAV_TYPE_QUADROTOR,
    autopilot=mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
    modes=ARDUCOPTER_MODES,
    default_mode="STABILIZE",
    guided_mode="GUIDED",
    hold_mode="LOITER",
    land_mode="LAND",
    rtl_mode="RTL",
    takeoff_mode=None,
    after_takeoff_mode=None,
    supports_takeoff=True,
    is_submarine=False,
    has_home_mission_item=True,
    set_mode_ack_command=mavlink.MAVLINK_MSG_ID_SET_MODE,
    result_refused=mavlink.MAV_RESULT_FAILED,
    flight_sw_version=_AP_VERSION,
    default_rates_hz=_AP_RATES,
)

ARDUSUB = Personality(
    name=PersonalityName.ARDUSUB,
    family="ardupilot",
    mav_type=mavlink.MAV_TYPE_SUBMARINE,
    autopilot=mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
    modes=ARDUSUB_MODES,
    default_mode="MANUAL",
    guided_mode="GUIDED",
    hold_mode="POSHOLD",
    land_mode=None,
    rtl_mode="SURFACE",
    takeoff_mode=None,
    after_takeoff_mode=None,
    supports_takeoff=False,
    is_submarine=True,
    has_home_mission_item=True,
    set_mode_ack_command=mavlink.MAVLINK_MSG_ID_SET_MODE,
    result_refused=mavlink.MAV_RESULT_FAILED,
    flight_sw_version=_SUB_VERSION,
    default_rates_hz=_AP_RATES,
)

PX4 = Personality(
    name=PersonalityName.PX4,
    family="px4",
    mav_type=mavlink.MAV_TYPE_QUADROTOR,
    autopilot=mavlink.MAV_AUTOPILOT_PX4,
    modes=PX4_MODES,
    default_mode="POSCTL",
    guided_mode="OFFBOARD",
    hold_mode="AUTO.LOITER",
    land_mode="AUTO.LAND",
    rtl_mode="AUTO.RTL",
    takeoff_mode="AUTO.TAKEOFF",
    after_takeoff_mode="AUTO.LOITER",
    supports_takeoff=True,
    is_submarine=False,
    has_home_mission_item=False,
    set_mode_ack_command=mavlink.MAV_CMD_DO_SET_MODE,
    result_refused=mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
    flight_sw_version=_PX4_VERSION,
    default_rates_hz=_PX4_RATES,
)

PERSONALITIES: dict[PersonalityName, Personality] = {p.name: p for p in (ARDUCOPTER, ARDUSUB, PX4)}


def personality(name: PersonalityName | str) -> Personality:
    return PERSONALITIES[PersonalityName(name)]
