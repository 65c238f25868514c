"""Who the service is on the network and how healthy it says it is.

HEARTBEAT as MAV_TYPE_ONBOARD_CONTROLLER with MAV_AUTOPILOT_INVALID (a companion is not an
autopilot), and system_status (MAV_STATE) from the service's real health:

    BOOT       waiting for the autopilot, its home position, or configuring it
    STANDBY    ready, not commanding (waiting for GUIDED/OFFBOARD, or released)
    ACTIVE     commanding the planner's setpoints
    CRITICAL   engaged but holding position because an input is stale or invalid
    EMERGENCY  engaged but unable to command at all (position or autopilot lost)
    POWEROFF   shutting down (sent once on the way out)
"""

from __future__ import annotations

import enum

from companion.service.codec import MAVLinkMessage, mavlink2

MAV_TYPE_ONBOARD_CONTROLLER: int = mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
MAV_AUTOPILOT_INVALID: int = mavlink2.MAV_AUTOPILOT_INVALID
MAV_COMP_ID_ONBOARD_COMPUTER: int = mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER
GCS_SYSTEM_ID = 255


class Health(enum.IntEnum):
    """MAV_STATE values the service reports."""

    BOOT = 1
    STANDBY = 3
    ACTIVE = 4
    CRITICAL = 5
    EMERGENCY = 6
    POWEROFF = 7


def heartbeat_message(health: Health) -> MAVLinkMessage:
    return mavlink2.MAVLink_heartbeat_message(
        MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, 0, 0, int(health), 3
    )


def companion_system_id(configured: int | str, autopilot_system_id: int | None) -> int:
    """Our system id: the configured one, else the autopilot's (1 until it is known)."""
    if isinstance(configured, int):
        sid = configured
    else:
        sid = autopilot_system_id if autopilot_system_id is not None else 1
    if not 1 <= sid <= 254:
        raise ValueError(f"companion system id must be 1..254 (255 is the GCS), got {sid}")
    return sid
