"""Flight modes of ArduPilot and PX4, and who may command the vehicle.

ArduPilot puts the vehicle's mode number in HEARTBEAT.custom_mode (ArduCopter and ArduSub:
GUIDED = 4). PX4 packs main and sub mode: main = (custom_mode >> 16) & 0xff, sub =
(custom_mode >> 24) & 0xff; OFFBOARD is main mode 6. Either way the custom mode only counts
when base_mode has MAV_MODE_FLAG_CUSTOM_MODE_ENABLED.

`Ownership` is the service's rule for commanding: it engages when the vehicle is armed, in
GUIDED/OFFBOARD and high enough; the moment any of mode or armed state goes it releases and
stops commanding; it never changes the mode back itself. A pilot who selects GUIDED/OFFBOARD
again re-engages it (unless `reengage` is off).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from companion.service.codec import mavlink2

MAV_AUTOPILOT_ARDUPILOTMEGA: int = mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA
MAV_AUTOPILOT_PX4: int = mavlink2.MAV_AUTOPILOT_PX4
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED: int = mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
MAV_MODE_FLAG_SAFETY_ARMED: int = mavlink2.MAV_MODE_FLAG_SAFETY_ARMED
MAV_TYPE_SUBMARINE: int = mavlink2.MAV_TYPE_SUBMARINE
MAV_TYPE_GROUND_ROVER: int = mavlink2.MAV_TYPE_GROUND_ROVER
MAV_TYPE_SURFACE_BOAT: int = mavlink2.MAV_TYPE_SURFACE_BOAT
MAV_TYPE_FIXED_WING: int = mavlink2.MAV_TYPE_FIXED_WING


class AutopilotKind(enum.StrEnum):
    ARDUPILOT = "ardupilot"
    PX4 = "px4"


def autopilot_kind(heartbeat_autopilot: int) -> AutopilotKind | None:
    """ArduPilot or PX4 from HEARTBEAT.autopilot; None for anything else."""
    if heartbeat_autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return AutopilotKind.ARDUPILOT
    if heartbeat_autopilot == MAV_AUTOPILOT_PX4:
        return AutopilotKind.PX4
    return None


COPTER_MODES = {
    0: "STABILIZE", 1: "ACRO", 2: "ALT_HOLD", 3: "AUTO", 4: "GUIDED", 5: "LOITER", 6: "RTL",
    7: "CIRCLE", 9: "LAND", 11: "DRIFT", 13: "SPORT", 14: "FLIP", 15: "AUTOTUNE",
    16: "POSHOLD", 17: "BRAKE", 18: "THROW", 19: "AVOID_ADSB", 20: "GUIDED_NOGPS",
    21: "SMART_RTL", 22: "FLOWHOLD", 23: "FOLLOW", 24: "ZIGZAG", 25: "SYSTEMID",
    26: "AUTOROTATE", 27: "AUTO_RTL", 28: "TURTLE",
}  # fmt: skip
SUB_MODES = {
    0: "STABILIZE", 1: "ACRO", 2: "ALT_HOLD", 3: "AUTO", 4: "GUIDED", 7: "CIRCLE",
    9: "SURFACE", 16: "POSHOLD", 19: "MANUAL", 20: "MOTOR_DETECT", 21: "SURFTRAK",
}  # fmt: skip
ARDUPILOT_GUIDED = 4
ARDUPILOT_LAND = {"copter": 9, "sub": 9}  # ArduSub's 9 is SURFACE: the safe way out
ARDUPILOT_RTL = {"copter": 6, "sub": 9}

PX4_MAIN = {
    1: "MANUAL", 2: "ALTCTL", 3: "POSCTL", 4: "AUTO", 5: "ACRO", 6: "OFFBOARD",
    7: "STABILIZED", 8: "RATTITUDE", 9: "SIMPLE", 10: "TERMINATION",
}  # fmt: skip
PX4_AUTO_SUB = {
    1: "READY", 2: "TAKEOFF", 3: "LOITER", 4: "MISSION", 5: "RTL", 6: "LAND", 7: "RTGS",
    8: "FOLLOW_TARGET", 9: "PRECLAND", 10: "VTOL_TAKEOFF",
}  # fmt: skip
PX4_OFFBOARD = 6
PX4_AUTO = 4
PX4_AUTO_LAND = 6
PX4_AUTO_RTL = 5


def px4_main_sub(custom_mode: int) -> tuple[int, int]:
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


def mode_name(kind: AutopilotKind, vehicle_type: int, base_mode: int, custom_mode: int) -> str:
    """A readable mode name (e.g. "GUIDED", "AUTO.RTL"), or "MODE(n)" when unknown."""
    if not base_mode & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
        return f"BASE({base_mode})"
    if kind is AutopilotKind.PX4:
        main, sub = px4_main_sub(custom_mode)
        name = PX4_MAIN.get(main, f"MAIN({main})")
        if main == PX4_AUTO:
            name += "." + PX4_AUTO_SUB.get(sub, str(sub))
        return name
    table = SUB_MODES if vehicle_type == MAV_TYPE_SUBMARINE else COPTER_MODES
    return table.get(custom_mode, f"MODE({custom_mode})")


def is_guided(kind: AutopilotKind, base_mode: int, custom_mode: int) -> bool:
    """True in ArduPilot GUIDED (copter/sub) or PX4 OFFBOARD."""
    if not base_mode & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
        return False
    if kind is AutopilotKind.PX4:
        return px4_main_sub(custom_mode)[0] == PX4_OFFBOARD
    return custom_mode == ARDUPILOT_GUIDED


def is_armed(base_mode: int) -> bool:
    return bool(base_mode & MAV_MODE_FLAG_SAFETY_ARMED)


def set_mode_params(
    kind: AutopilotKind, target: str, vehicle_type: int = 2
) -> tuple[float, float, float]:
    """MAV_CMD_DO_SET_MODE params 1-3 for target "guided", "land" or "rtl"."""
    flag = float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
    if kind is AutopilotKind.PX4:
        if target == "guided":
            return flag, float(PX4_OFFBOARD), 0.0
        sub = {"land": PX4_AUTO_LAND, "rtl": PX4_AUTO_RTL}[target]
        return flag, float(PX4_AUTO), float(sub)
    family = "sub" if vehicle_type == MAV_TYPE_SUBMARINE else "copter"
    number = {
        "guided": ARDUPILOT_GUIDED,
        "land": ARDUPILOT_LAND[family],
        "rtl": ARDUPILOT_RTL[family],
    }[target]
    return flag, float(number), 0.0


class OwnState(enum.StrEnum):
    WAITING = "waiting"
    """Not yet flown: waiting for the pilot (or auto start) to hand over."""
    ENGAGED = "engaged"
    """Vehicle in GUIDED/OFFBOARD and ours to command."""
    RELEASED = "released"
    """Taken away (mode change or disarm): silent until the pilot hands over again."""


@dataclass(frozen=True, slots=True)
class VehicleMode:
    """What the ownership rule needs from the latest heartbeat and position."""

    guided: bool
    armed: bool
    high_enough: bool
    name: str


class Ownership:
    """Engage/release rule. `update` returns the pilot-worthy events it caused."""

    def __init__(self, reengage: bool = True) -> None:
        self.state = OwnState.WAITING
        self.reengage = reengage
        self.engagements = 0
        self._last_wait_reason = ""

    @property
    def engaged(self) -> bool:
        return self.state is OwnState.ENGAGED

    def update(self, mode: VehicleMode, allow_engage: bool = True) -> list[str]:
        events: list[str] = []
        if self.state is OwnState.ENGAGED:
            if not mode.guided or not mode.armed:
                self.state = OwnState.RELEASED
                why = mode.name if mode.armed else "disarmed"
                events.append(f"{why}: stopped commanding")
            return events
        may = self.state is OwnState.WAITING or self.reengage
        if may and mode.guided and mode.armed and allow_engage:
            if mode.high_enough:
                self.state = OwnState.ENGAGED
                self.engagements += 1
                events.append("flying route" if self.engagements == 1 else "re-engaged")
                self._last_wait_reason = ""
            elif self._last_wait_reason != "low":
                self._last_wait_reason = "low"
                events.append("waiting: too low to take over")
        return events

    def release(self, reason: str) -> list[str]:
        """Release for a reason of our own (e.g. route finished and autopilot told to land)."""
        if self.state is OwnState.ENGAGED:
            self.state = OwnState.RELEASED
            return [reason]
        return []
