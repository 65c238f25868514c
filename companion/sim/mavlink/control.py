"""The simulated autopilot's position controller: a kinematic reference for the vehicle model.

The autopilot does not hand a far-away target straight to the vehicle model; like
ArduPilot's and PX4's position controllers it moves a reference towards it within speed and
acceleration limits, and the vehicle model tracks the reference. Targets are per axis: a
finite position component is tracked with ArduPilot's square-root controller (velocity
feed-forward added), a NaN one leaves that axis to the velocity target alone.

World frame ENU, metres, seconds.
"""

from __future__ import annotations

import math

import numpy as np

from companion.planner.frames import wrap_pi
from companion.planner.types import FloatArray
from companion.sim.mavlink.config import MotionLimits
from companion.sim.vehicle import norm


def sqrt_controller(error: float, gain: float, accel_max: float) -> float:
    """Velocity that closes `error` (m) and can still stop at accel_max (ArduPilot's shape).

    Linear (gain * error) near the target, sqrt(2 a d) further out; units m/s.
    """
    linear = accel_max / (gain * gain)
    if error > linear:
        return math.sqrt(2.0 * accel_max * (error - linear / 2.0))
    if error < -linear:
        return -math.sqrt(2.0 * accel_max * (-error - linear / 2.0))
    return error * gain


def stopping_point(position: FloatArray, velocity: FloatArray, accel_max: float) -> FloatArray:
    """Where a vehicle at `velocity` stops braking at accel_max (straight-line estimate)."""
    speed = norm(np.asarray(velocity, dtype=np.float64))
    return np.asarray(position, dtype=np.float64) + velocity * (speed / (2.0 * accel_max))


class ReferenceShaper:
    """Reference position, velocity and yaw moved towards targets within `limits`.

    `acceleration` is the reference's over the last step (m/s^2): what the autopilot feeds
    forward to the vehicle model, as ArduPilot's and PX4's position controllers feed their
    shaped reference's acceleration forward.
    """

    def __init__(self, limits: MotionLimits, position_enu: FloatArray, yaw_rad: float) -> None:
        self.limits = limits
        self.position = np.array(position_enu, dtype=np.float64).reshape(3)
        self.velocity = np.zeros(3)
        self.acceleration = np.zeros(3)
        self.yaw_rad = float(yaw_rad)

    def reset(self, position_enu: FloatArray, yaw_rad: float) -> None:
        self.position = np.array(position_enu, dtype=np.float64).reshape(3)
        self.velocity = np.zeros(3)
        self.acceleration = np.zeros(3)
        self.yaw_rad = float(yaw_rad)

    def step(
        self,
        target_position: FloatArray | None,
        target_velocity: FloatArray | None,
        target_yaw_rad: float | None,
        yaw_rate_radps: float | None,
        dt_s: float,
    ) -> None:
        """Advance the reference by dt_s towards the targets (either may be None)."""
        lim = self.limits
        ff = np.zeros(3) if target_velocity is None else np.asarray(target_velocity, float)
        desired = ff.copy()
        if target_position is not None:
            tp = np.asarray(target_position, dtype=np.float64)
            if np.isfinite(tp[:2]).all():
                err = tp[:2] - self.position[:2]
                dist = norm(err)
                if dist > 1e-9:
                    speed = sqrt_controller(dist, lim.position_gain, lim.accel_mps2)
                    desired[:2] += err / dist * speed
            if math.isfinite(tp[2]):
                desired[2] += sqrt_controller(
                    float(tp[2] - self.position[2]), lim.position_gain, lim.accel_mps2
                )
        speed_xy = norm(desired[:2])
        if speed_xy > lim.speed_xy_mps:
            desired[:2] *= lim.speed_xy_mps / speed_xy
        desired[2] = min(max(desired[2], -lim.speed_down_mps), lim.speed_up_mps)
        dv = desired - self.velocity
        dv_norm = norm(dv)
        max_dv = lim.accel_mps2 * dt_s
        if dv_norm > max_dv:
            dv *= max_dv / dv_norm
        self.velocity = self.velocity + dv
        self.acceleration = dv / dt_s if dt_s > 0.0 else np.zeros(3)
        self.position = self.position + self.velocity * dt_s

        max_turn = math.radians(lim.yaw_rate_dps) * dt_s
        if target_yaw_rad is not None:
            turn = wrap_pi(target_yaw_rad - self.yaw_rad)
            self.yaw_rad = wrap_pi(self.yaw_rad + min(max(turn, -max_turn), max_turn))
        elif yaw_rate_radps is not None:
            turn = yaw_rate_radps * dt_s
            self.yaw_rad = wrap_pi(self.yaw_rad + min(max(turn, -max_turn), max_turn))

    def clamp_above(self, ground_z: float) -> bool:
        """Keep the reference on or above ground_z; True if it was pushed up."""
        if self.position[2] < ground_z:
            self.position[2] = ground_z
            self.velocity[2] = max(self.velocity[2], 0.0)
            self.acceleration[2] = max(self.acceleration[2], 0.0)
            return True
        return False
