"""Vehicle models that fly the planner's setpoints in the simulator.

Frames as in `companion.planner.types`: world local ENU (metres), body FLU; yaw from +x
(east) counter-clockwise, pitch nose-up positive, roll right-wing-down positive, radians.

- `IdealTracker`: the paper's assumption, the vehicle is exactly at the setpoint with the
  path tangent's attitude.
- `Multicopter`: point mass with a position + velocity tracking controller, acceleration,
  speed, climb and yaw-rate limits; roll and pitch follow from the horizontal acceleration,
  so the attitude is not aligned with the path.
"""

from __future__ import annotations

import math
from typing import Literal, Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from companion.planner.types import FloatArray, Setpoint, VehicleState

__all__ = [
    "GRAVITY_MPS2",
    "IdealTracker",
    "Multicopter",
    "Vehicle",
    "VehicleModelConfig",
    "make_vehicle",
]

GRAVITY_MPS2 = 9.80665
MAX_SUBSTEP_S = 0.02


def _wrap_pi(angle_rad: float) -> float:
    """Wrap an angle to [-pi, pi) (unchanged if already there)."""
    if -math.pi <= angle_rad < math.pi:
        return angle_rad
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def _check_dt(dt_s: float) -> float:
    dt = float(dt_s)
    if not (math.isfinite(dt) and dt >= 0.0):
        raise ValueError(f"dt_s must be finite and >= 0, got {dt_s}")
    return dt


def norm(v: FloatArray) -> float:
    """|v| of a float vector as numpy's linalg norm computes it (the square root of v.v),
    without its Python layer: the same value, bit for bit."""
    r = v.ravel(order="K")
    return math.sqrt(float(r.dot(r)))


class Vehicle(Protocol):
    """What the simulation loop needs from a vehicle model."""

    @property
    def state(self) -> VehicleState: ...

    def step(self, setpoint: Setpoint, dt_s: float) -> VehicleState: ...


class VehicleModelConfig(BaseModel):
    """Which vehicle model flies the setpoints, and the multicopter's gains and limits.

    kp_per_s2: position gain (1/s^2); kv_per_s: velocity gain (1/s). Limits in m/s, m/s^2
    and rad/s. With the reference's velocity and acceleration fed forward the multicopter
    tracks it without steady-state lag; its error dynamics are e'' + kv e' + kp e = 0 (a
    reference accelerating at a with no acceleration given lags by a / kp).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    model: Literal["ideal", "multicopter"] = "ideal"
    kp_per_s2: float = Field(1.5, gt=0.0)
    kv_per_s: float = Field(2.5, gt=0.0)
    max_speed_mps: float = Field(5.0, gt=0.0)
    """Horizontal speed limit."""
    max_climb_mps: float = Field(2.5, gt=0.0)
    """Vertical speed limit, up and down."""
    max_accel_mps2: float = Field(3.0, gt=0.0)
    """Limit on the norm of the commanded 3-D acceleration."""
    max_yaw_rate_rad_s: float = Field(1.5, gt=0.0)


_ALONG_MPS = 0.05
"""Below this horizontal speed (m/s) the ideal tracker's pitch is the setpoint's."""
_TANGENT_MPS = 0.25
"""From this horizontal speed (m/s) up, its pitch is the tangent's; between the two, a blend,
so the pitch never jumps when motion starts (a MAVLink target carries no pitch, so the
setpoint's is 0, and a shaped velocity's tangent at 0.06 m/s can be 0.5 rad)."""


class IdealTracker:
    """Perfect tracking, the paper's assumption: position = setpoint.position_enu, yaw the
    setpoint's, roll 0, and pitch along the trajectory's tangent: from the velocity
    feed-forward when there is one (a MAVLink position target carries no pitch), else the
    setpoint's pitch, blended into the tangent's as motion starts (_TANGENT_MPS)."""

    def __init__(self, initial: VehicleState) -> None:
        self._state = initial

    @property
    def state(self) -> VehicleState:
        return self._state

    def step(self, setpoint: Setpoint, dt_s: float) -> VehicleState:
        """Jump to the setpoint; dt_s (s) is only checked."""
        _check_dt(dt_s)
        v = np.asarray(setpoint.velocity_enu, dtype=np.float64)
        horizontal = math.hypot(float(v[0]), float(v[1]))
        # Only while moving along: a vertical climb (take-off) is not a 90-degree pitch.
        pitch = float(setpoint.pitch_rad)
        if horizontal > _ALONG_MPS and bool(np.isfinite(v).all()):
            tangent = math.atan2(float(v[2]), horizontal)
            w = (horizontal - _ALONG_MPS) / (_TANGENT_MPS - _ALONG_MPS)
            pitch = tangent if w >= 1.0 else pitch + w * (tangent - pitch)
        self._state = VehicleState(
            position_enu=np.asarray(setpoint.position_enu, dtype=np.float64).copy(),
            roll_rad=0.0,
            pitch_rad=pitch,
            yaw_rad=_wrap_pi(float(setpoint.yaw_rad)),
        )
        return self._state


class Multicopter:
    """Point-mass multicopter with a position + velocity tracking controller.

    Each substep (<= MAX_SUBSTEP_S): a = a_ff + kp (X_d - x) + kv (v_ff - v), norm clipped to
    max_accel; semi-implicit Euler v += a dt (horizontal speed clipped to max_speed,
    vertical to max_climb), x += v dt. Yaw turns towards setpoint.yaw_rad at no more than
    max_yaw_rate. Attitude from the step's mean horizontal acceleration in the heading frame:
    pitch = -atan(a_forward / g) (nose down to speed up), roll = atan(a_right / g).
    """

    def __init__(
        self,
        initial: VehicleState,
        config: VehicleModelConfig | None = None,
        initial_velocity_enu: FloatArray | None = None,
    ) -> None:
        self.config = config if config is not None else VehicleModelConfig(model="multicopter")
        self._pos = np.array(initial.position_enu, dtype=np.float64)
        v0 = np.zeros(3) if initial_velocity_enu is None else initial_velocity_enu
        self._vel = np.array(v0, dtype=np.float64).reshape(3)
        self._acc = np.zeros(3)
        self._yaw = _wrap_pi(float(initial.yaw_rad))
        self._state = initial

    @property
    def state(self) -> VehicleState:
        return self._state

    @property
    def velocity_enu(self) -> FloatArray:
        """Current velocity (3,), m/s, ENU."""
        return self._vel.copy()

    @property
    def acceleration_enu(self) -> FloatArray:
        """Mean acceleration achieved over the last step (3,), m/s^2, ENU."""
        return self._acc.copy()

    def step(self, setpoint: Setpoint, dt_s: float) -> VehicleState:
        """Advance dt_s seconds towards the setpoint; returns the new state."""
        dt = _check_dt(dt_s)
        if dt == 0.0:
            return self._state
        c = self.config
        x_d = np.asarray(setpoint.position_enu, dtype=np.float64).reshape(3)
        v_ff = np.asarray(setpoint.velocity_enu, dtype=np.float64).reshape(3)
        a_ff = np.asarray(setpoint.acceleration_enu, dtype=np.float64).reshape(3)
        if not (np.isfinite(x_d).all() and np.isfinite(v_ff).all() and np.isfinite(a_ff).all()):
            raise ValueError("setpoint position, velocity and acceleration must be finite")
        n = max(1, math.ceil(dt / MAX_SUBSTEP_S - 1e-9))
        h = dt / n
        max_dyaw = c.max_yaw_rate_rad_s * h
        v_start = self._vel.copy()
        for _ in range(n):
            a = a_ff + c.kp_per_s2 * (x_d - self._pos) + c.kv_per_s * (v_ff - self._vel)
            a_norm = norm(a)
            if a_norm > c.max_accel_mps2:
                a *= c.max_accel_mps2 / a_norm
            v = self._vel + a * h
            v_h = math.hypot(v[0], v[1])
            if v_h > c.max_speed_mps:
                v[:2] *= c.max_speed_mps / v_h
            v[2] = min(max(v[2], -c.max_climb_mps), c.max_climb_mps)
            self._vel = v
            self._pos = self._pos + v * h
            err = _wrap_pi(float(setpoint.yaw_rad) - self._yaw)
            self._yaw = _wrap_pi(self._yaw + min(max(err, -max_dyaw), max_dyaw))
        self._acc = (self._vel - v_start) / dt
        cy, sy = math.cos(self._yaw), math.sin(self._yaw)
        a_fwd = self._acc[0] * cy + self._acc[1] * sy
        a_right = self._acc[0] * sy - self._acc[1] * cy
        self._state = VehicleState(
            position_enu=self._pos.copy(),
            roll_rad=math.atan(a_right / GRAVITY_MPS2),
            pitch_rad=-math.atan(a_fwd / GRAVITY_MPS2),
            yaw_rad=self._yaw,
        )
        return self._state


def make_vehicle(
    cfg: VehicleModelConfig | None, initial: VehicleState
) -> IdealTracker | Multicopter:
    """The vehicle model cfg names (ideal if cfg is None), starting at `initial`."""
    if cfg is None or cfg.model == "ideal":
        return IdealTracker(initial)
    return Multicopter(initial, cfg)
