"""Planner setpoints (local ENU) -> SET_POSITION_TARGET_GLOBAL_INT.

Position + velocity and acceleration feed-forward + yaw; yaw rate ignored; no force bit.
ArduCopter GUIDED (pos+vel+accel) and PX4 OFFBOARD both take the acceleration as
feed-forward to their position controllers; without it (`acceleration_enu=None`) it is
masked out.
Frames: MAV_FRAME_GLOBAL_INT (5, altitude AMSL) or MAV_FRAME_GLOBAL_RELATIVE_ALT_INT (6,
altitude above the autopilot's current home). Never a terrain frame: ArduCopter rejects
position+velocity there and, without terrain data, has flown into the ground. The local
frame is anchored at the home position when the service took over; the relative altitude is
taken against the autopilot's *current* home altitude, which is what frame 6 means to it.
"""

from __future__ import annotations

import enum

import numpy as np

from companion.geo import LocalFrame
from companion.planner.frames import enu_to_ned, yaw_enu_to_ned
from companion.planner.types import FloatArray
from companion.service.codec import MAVLinkMessage, mavlink2

MAV_FRAME_GLOBAL_INT: int = mavlink2.MAV_FRAME_GLOBAL_INT
MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: int = mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT

IGNORE_ACCELERATION: int = (
    mavlink2.POSITION_TARGET_TYPEMASK_AX_IGNORE
    | mavlink2.POSITION_TARGET_TYPEMASK_AY_IGNORE
    | mavlink2.POSITION_TARGET_TYPEMASK_AZ_IGNORE
)
IGNORE_YAW_RATE: int = mavlink2.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
TYPE_MASK = IGNORE_YAW_RATE
"""Use position, velocity, acceleration and yaw; ignore yaw rate; no FORCE_SET (512)."""
TYPE_MASK_NO_ACCELERATION = IGNORE_ACCELERATION | IGNORE_YAW_RATE
"""Position, velocity and yaw only."""


_NO_ACCELERATION = np.zeros(3)
_NO_ACCELERATION.setflags(write=False)


class SetpointFrame(enum.IntEnum):
    GLOBAL = MAV_FRAME_GLOBAL_INT
    GLOBAL_RELATIVE_ALT = MAV_FRAME_GLOBAL_RELATIVE_ALT_INT


def position_target(
    position_enu: FloatArray,
    velocity_enu: FloatArray,
    yaw_enu_rad: float,
    acceleration_enu: FloatArray | None = None,
    *,
    frame: LocalFrame,
    mav_frame: SetpointFrame,
    home_alt_amsl_m: float,
    time_boot_ms: int,
    target_system: int,
    target_component: int,
) -> MAVLinkMessage:
    """The SET_POSITION_TARGET_GLOBAL_INT for a setpoint in `frame` (ENU metres, m/s, m/s^2,
    rad); acceleration_enu None: acceleration masked out."""
    geo = frame.to_geodetic(float(position_enu[0]), float(position_enu[1]), float(position_enu[2]))
    alt = geo.alt_m if mav_frame is SetpointFrame.GLOBAL else geo.alt_m - home_alt_amsl_m
    v_ned = enu_to_ned(velocity_enu)
    if acceleration_enu is None:
        mask, a_ned = TYPE_MASK_NO_ACCELERATION, _NO_ACCELERATION
    else:
        mask, a_ned = TYPE_MASK, enu_to_ned(acceleration_enu)
    return mavlink2.MAVLink_set_position_target_global_int_message(
        time_boot_ms & 0xFFFFFFFF,
        target_system,
        target_component,
        int(mav_frame),
        mask,
        round(geo.lat_deg * 1e7),
        round(geo.lon_deg * 1e7),
        float(alt),
        float(v_ned[0]),
        float(v_ned[1]),
        float(v_ned[2]),
        float(a_ned[0]),
        float(a_ned[1]),
        float(a_ned[2]),
        float(yaw_enu_to_ned(yaw_enu_rad)),
        0.0,
    )
