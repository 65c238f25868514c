"""SET_POSITION_TARGET_GLOBAL_INT as ArduCopter and PX4 read it.

`decode_ardupilot` follows ArduCopter's GCS_MAVLINK_Copter handler: frames 0/5 (AMSL), 3/6
(above home) and 10/11 (above terrain); any invalid input -- an unknown frame with a
position, a bad latitude, position + velocity in a terrain frame, force-set accelerations --
makes the vehicle stop (mode_guided.init), it is not ignored. `decode_px4` follows PX4's
mavlink_receiver: only frames 5, 6 and 11; anything else is logged and ignored. PX4 turns a
frame-6 altitude into a local z with the home/origin difference of the wrong sign (observed
on SITL, see docs/autopilots.md); that is reproduced when home is not at the origin altitude.

Both return a `Decision`; whether the vehicle is in GUIDED/OFFBOARD is the autopilot's
business. Targets come out in the world's local ENU frame (metres, yaw counter-clockwise
from east).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.geo import GeoPoint, LocalFrame
from companion.planner.frames import ned_to_enu, yaw_ned_to_enu
from companion.planner.types import FloatArray

POS_IGNORE = (
    mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE
)
VEL_IGNORE = (
    mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE
)
ACC_IGNORE = (
    mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE
)
FORCE_SET = mavlink.POSITION_TARGET_TYPEMASK_FORCE_SET
YAW_IGNORE = mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
YAW_RATE_IGNORE = mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE

FRAMES_AMSL = (mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT)
FRAMES_RELATIVE = (mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
FRAMES_TERRAIN = (mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT, mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT)
PX4_FRAMES = (
    mavlink.MAV_FRAME_GLOBAL_INT,
    mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
    mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
)


class Outcome(enum.Enum):
    ACCEPT = "accept"
    STOP = "stop"
    """Invalid input: ArduCopter re-initialises GUIDED, i.e. stops where it is."""
    IGNORE = "ignore"


@dataclass(frozen=True, slots=True)
class GuidedTarget:
    """A position and/or velocity target in the world frame.

    position_enu: (3,) metres or None; velocity_enu: (3,) m/s or None; yaw_enu_rad: heading
    (ENU, from +x, CCW) or None; yaw_rate_radps: CCW positive or None; received_s: sim time;
    acceleration_enu: (3,) m/s^2 feed-forward or None.
    """

    position_enu: FloatArray | None
    velocity_enu: FloatArray | None
    yaw_enu_rad: float | None
    yaw_rate_radps: float | None
    received_s: float
    acceleration_enu: FloatArray | None = None


@dataclass(frozen=True, slots=True)
class Decision:
    outcome: Outcome
    target: GuidedTarget | None = None
    reason: str = ""


@dataclass(frozen=True, slots=True)
class FrameContext:
    """What a global target is converted with.

    frame: the world's local ENU frame. home_enu / origin_enu: home and estimator origin in
    it (metres). terrain_height(x, y): terrain z (metres, world ENU).
    """

    frame: LocalFrame
    home_enu: FloatArray
    origin_enu: FloatArray
    terrain_height: Callable[[float, float], float]

    def amsl(self, point_enu: FloatArray) -> float:
        return self.frame.to_geodetic(*(float(v) for v in point_enu)).alt_m


def _enu(ctx: FrameContext, lat_int: int, lon_int: int, alt_amsl_m: float) -> FloatArray:
    e, n, u = ctx.frame.to_enu(GeoPoint(lat_int * 1e-7, lon_int * 1e-7, alt_amsl_m))
    return np.array([e, n, u])


def _yaw(msg: Any) -> tuple[float | None, float | None]:
    yaw = None if msg.type_mask & YAW_IGNORE else yaw_ned_to_enu(float(msg.yaw))
    rate = None if msg.type_mask & YAW_RATE_IGNORE else -float(msg.yaw_rate)
    if yaw is not None and not math.isfinite(yaw):
        yaw = None
    if rate is not None and not math.isfinite(rate):
        rate = None
    return yaw, rate


def _velocity(msg: Any) -> FloatArray:
    return ned_to_enu(np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64))


def _acceleration(msg: Any) -> FloatArray:
    return ned_to_enu(np.array([msg.afx, msg.afy, msg.afz], dtype=np.float64))


def decode_ardupilot(msg: Any, ctx: FrameContext, now_s: float) -> Decision:
    """ArduCopter's reading of SET_POSITION_TARGET_GLOBAL_INT (see module docstring)."""
    mask = int(msg.type_mask)
    pos_ignore = bool(mask & POS_IGNORE)
    vel_ignore = bool(mask & VEL_IGNORE)
    acc_ignore = bool(mask & ACC_IGNORE)
    if mask & FORCE_SET and not acc_ignore:
        return Decision(Outcome.STOP, reason="force set is not supported")

    position = None
    frame = int(msg.coordinate_frame)
    if not pos_ignore:
        if abs(msg.lat_int) > 900_000_000 or abs(msg.lon_int) > 1_800_000_000:
            return Decision(Outcome.STOP, reason="invalid latitude/longitude")
        if frame in FRAMES_AMSL:
            alt_amsl = float(msg.alt)
        elif frame in FRAMES_RELATIVE:
            alt_amsl = ctx.amsl(ctx.home_enu) + float(msg.alt)
        elif frame in FRAMES_TERRAIN:
            alt_amsl = math.nan  # resolved below, after the horizontal position
        else:
            return Decision(Outcome.STOP, reason=f"unknown coordinate frame {frame}")
        if frame in FRAMES_TERRAIN:
            horizontal = _enu(ctx, msg.lat_int, msg.lon_int, ctx.frame.origin.alt_m)
            ground = ctx.terrain_height(float(horizontal[0]), float(horizontal[1]))
            position = np.array([horizontal[0], horizontal[1], ground + float(msg.alt)])
        else:
            position = _enu(ctx, msg.lat_int, msg.lon_int, alt_amsl)

    velocity = None
    if not vel_ignore:
        velocity = _velocity(msg)
        if not (np.all(np.isfinite(velocity)) and np.all(np.abs(velocity) < 1000.0)):
            return Decision(Outcome.STOP, reason="invalid velocity")

    acceleration = None
    if not acc_ignore:
        acceleration = _acceleration(msg)
        if not (np.all(np.isfinite(acceleration)) and np.all(np.abs(acceleration) < 1000.0)):
            return Decision(Outcome.STOP, reason="invalid acceleration")

    yaw, yaw_rate = _yaw(msg)
    if position is not None and velocity is not None:
        if frame in FRAMES_TERRAIN:
            return Decision(
                Outcome.STOP, reason="position+velocity is not supported in a terrain frame"
            )
    elif position is None and velocity is None:
        reason = "acceleration targets are not simulated" if not acc_ignore else "no target"
        return Decision(Outcome.STOP, reason=reason)
    elif position is not None and not acc_ignore:
        return Decision(Outcome.STOP, reason="position+acceleration without velocity")
    target = GuidedTarget(position, velocity, yaw, yaw_rate, now_s, acceleration)
    return Decision(Outcome.ACCEPT, target)


def decode_px4(msg: Any, ctx: FrameContext, now_s: float) -> Decision:
    """PX4's reading of SET_POSITION_TARGET_GLOBAL_INT (see module docstring)."""
    mask = int(msg.type_mask)
    position = None
    if not mask & POS_IGNORE:
        frame = int(msg.coordinate_frame)
        origin_amsl = ctx.amsl(ctx.origin_enu)
        if frame == mavlink.MAV_FRAME_GLOBAL_INT:
            position = _enu(ctx, msg.lat_int, msg.lon_int, float(msg.alt))
        elif frame == mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT:
            # PX4: z = (home.alt - alt) - ref_alt, so AMSL = 2 ref_alt - home.alt + alt.
            home_amsl = ctx.amsl(ctx.home_enu)
            position = _enu(
                ctx, msg.lat_int, msg.lon_int, 2.0 * origin_amsl - home_amsl + float(msg.alt)
            )
        elif frame == mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT:
            horizontal = _enu(ctx, msg.lat_int, msg.lon_int, ctx.frame.origin.alt_m)
            ground = ctx.terrain_height(float(horizontal[0]), float(horizontal[1]))
            position = np.array([horizontal[0], horizontal[1], ground + float(msg.alt)])
        else:
            return Decision(
                Outcome.IGNORE,
                reason=f"SET_POSITION_TARGET_GLOBAL_INT: bad frame {frame}",
            )
    velocity = None if mask & VEL_IGNORE else _velocity(msg)
    if position is None and velocity is None:
        return Decision(Outcome.IGNORE, reason="neither position nor velocity given")
    acceleration = None if mask & ACC_IGNORE else _acceleration(msg)
    if acceleration is not None and not np.isfinite(acceleration).all():
        acceleration = None
    yaw, yaw_rate = _yaw(msg)
    target = GuidedTarget(position, velocity, yaw, yaw_rate, now_s, acceleration)
    return Decision(Outcome.ACCEPT, target)
