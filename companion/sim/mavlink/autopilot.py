"""Flight logic of the simulated autopilot: modes, arming, takeoff, targets, failsafes.

No I/O: the server feeds decoded messages in and takes `Setpoint`s for the vehicle model
out, plus status texts to send. What differs between ArduCopter, ArduSub and PX4 comes from
the `Personality`; the behaviours modelled are the ones a companion's failsafes depend on:

- Arming is refused for `prearm_delay_s` after boot and in modes that are not armable; an
  armed vehicle that has not taken off disarms itself after `auto_disarm_s`.
- ArduCopter GUIDED: NAV_TAKEOFF climbs to param7 m above home; SET_POSITION_TARGET_GLOBAL_INT
  is used only in GUIDED and in the air. A position target persists. Velocity targets (and
  the velocity part of position+velocity targets, which ArduCopter integrates) expire after
  GUID_TIMEOUT (`guided_timeout_s`), then the vehicle stops. Invalid input stops it.
- PX4: setpoints are recorded in any mode (the offboard stream), used only in OFFBOARD.
  OFFBOARD is refused unless the stream runs at >= `offboard_min_rate_hz`; in OFFBOARD a gap
  longer than COM_OF_LOSS_T (`offboard_loss_timeout_s`) triggers the failsafe
  (`offboard_loss_action`). NAV_TAKEOFF switches to AUTO.TAKEOFF, then AUTO.LOITER.
- LAND/RTL descend and disarm on touchdown; the reference never goes below the terrain.

Frames: world ENU (metres), yaw CCW from east, simulated seconds.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.geo import GeoPoint, LocalFrame
from companion.planner.types import FloatArray, Setpoint, VehicleState
from companion.sim.mavlink.config import MavlinkSimConfig
from companion.sim.mavlink.control import ReferenceShaper, stopping_point
from companion.sim.mavlink.personality import Behaviour, FlightMode, Personality
from companion.sim.mavlink.setpoints import (
    Decision,
    FrameContext,
    GuidedTarget,
    Outcome,
    decode_ardupilot,
    decode_px4,
)

ACCEPTED = int(mavlink.MAV_RESULT_ACCEPTED)
UNSUPPORTED = int(mavlink.MAV_RESULT_UNSUPPORTED)
FAILED = int(mavlink.MAV_RESULT_FAILED)

FORCE_MAGIC = 21196.0
"""param2 of MAV_CMD_COMPONENT_ARM_DISARM that forces arming/disarming."""
LANDED_TOLERANCE_M = 0.1
AUTO_DISARM_S = 10.0
"""ArduCopter DISARM_DELAY / PX4 COM_DISARM_PRFLT."""
FAST_DESCENT_ABOVE_M = 10.0
"""ArduCopter LAND: WPNAV_SPEED_DN above this height, LAND_SPEED below."""


@dataclass(frozen=True, slots=True)
class StatusText:
    severity: int
    text: str


class Autopilot:
    """State machine of one simulated autopilot (see module docstring)."""

    def __init__(
        self,
        personality: Personality,
        config: MavlinkSimConfig,
        frame: LocalFrame,
        terrain_height: Callable[[float, float], float],
        start: VehicleState,
        now_s: float = 0.0,
    ) -> None:
        self.p = personality
        self.cfg = config
        self.frame = frame
        self.terrain_height = terrain_height
        start_pos = np.array(start.position_enu, dtype=np.float64)
        self.home_enu = start_pos.copy()
        self.origin_enu = start_pos - np.array([0.0, 0.0, config.home_above_origin_m])
        self.shaper = ReferenceShaper(config.limits, start_pos, start.yaw_rad)
        self.texts: list[StatusText] = []
        self.landed = not personality.is_submarine
        self.armed = False
        self.estimate_offset_enu = np.zeros(3)
        """Position estimate minus truth (a GPS jump fault): reported positions are shifted
        by it and received position targets shifted back."""
        self._boot(now_s, start)

    # ----------------------------------------------------------------- state and queries
    def _boot(self, now_s: float, state: VehicleState) -> None:
        self.boot_s = now_s
        self.mode: FlightMode = self.p.mode(self.p.default_mode)
        self.failsafe = False
        self.target: GuidedTarget | None = None
        self.hold_target = np.array(state.position_enu, dtype=np.float64)
        self.takeoff_z: float | None = None
        self._pending_takeoff_z: float | None = None
        self._armed_s = now_s
        self._rtl_phase = "climb"
        self._rtl_z = 0.0
        self._land_xy = self.hold_target[:2].copy()
        self._stream: deque[float] = deque(maxlen=2)
        self._last_reason_s: dict[str, float] = {}

    @property
    def frame_context(self) -> FrameContext:
        return FrameContext(self.frame, self.home_enu, self.origin_enu, self.terrain_height)

    def ready(self, now_s: float) -> bool:
        """The estimator has a position (arming and position modes allowed)."""
        return now_s - self.boot_s >= self.cfg.prearm_delay_s

    @property
    def frozen(self) -> bool:
        """The vehicle model is not stepped: disarmed, or armed but still on the ground."""
        return self.landed or (self.p.is_submarine and not self.armed)

    def time_boot_ms(self, now_s: float) -> int:
        return round((now_s - self.boot_s) * 1000.0) & 0xFFFFFFFF

    def stream_ok(self, now_s: float) -> bool:
        """PX4's offboard signal: the last two setpoints close enough together and recent."""
        if len(self._stream) < 2:
            return False
        period = 1.0 / self.cfg.offboard_min_rate_hz + 1e-9
        return now_s - self._stream[-1] <= period and self._stream[-1] - self._stream[-2] <= period

    def _say(self, severity: int, text: str) -> None:
        self.texts.append(StatusText(severity, text[:50]))

    def _say_limited(self, severity: int, text: str, now_s: float) -> None:
        last = self._last_reason_s.get(text)
        if last is None or now_s - last >= 1.0:
            self._last_reason_s[text] = now_s
            self._say(severity, text)

    def _ground(self, position: FloatArray) -> float:
        return float(self.terrain_height(float(position[0]), float(position[1])))

    # ------------------------------------------------------------------------- commands
    def set_mode(
        self, mode: FlightMode, now_s: float, state: VehicleState, forced: bool = False
    ) -> int:
        """Switch mode; returns a MAV_RESULT. `forced`: a pilot's switch, no checks."""
        if not forced:
            if mode.needs_position and not self.ready(now_s):
                self._say(mavlink.MAV_SEVERITY_WARNING, self._mode_refused_text(mode))
                return self.p.result_refused
            if (
                self.p.family == "px4"
                and mode.behaviour is Behaviour.GUIDED
                and not self.stream_ok(now_s)
            ):
                self._say(mavlink.MAV_SEVERITY_CRITICAL, self._mode_refused_text(mode))
                return self.p.result_refused
        self._enter(mode, now_s, state)
        return ACCEPTED

    def _mode_refused_text(self, mode: FlightMode) -> str:
        if self.p.family == "px4":
            return f"Switching to {mode.name.title()} is currently not available"
        return f"Mode change to {mode.name} failed: requires position"

    def _enter(self, mode: FlightMode, now_s: float, state: VehicleState) -> None:
        self.mode = mode
        self.failsafe = False
        flying = not self.frozen
        here = self.shaper.position if flying else np.array(state.position_enu, dtype=float)
        self.hold_target = (
            stopping_point(here, self.shaper.velocity, self.cfg.limits.accel_mps2)
            if flying
            else here.copy()
        )
        b = mode.behaviour
        if b is Behaviour.GUIDED and self.p.family == "ardupilot":
            self.target = None
        if b is not Behaviour.GUIDED:
            self.takeoff_z = None
        if b is Behaviour.RTL:
            self._rtl_phase = "climb"
            self._rtl_z = max(float(here[2]), float(self.home_enu[2]) + self.cfg.rtl_altitude_m)
        if b in (Behaviour.LAND, Behaviour.RTL):
            self._land_xy = here[:2].copy()
        if b is Behaviour.TAKEOFF:
            z = self._pending_takeoff_z
            if z is None:
                z = float(self.home_enu[2]) + self.cfg.takeoff_altitude_m
            self.takeoff_z = z
            if self.armed:
                self.landed = False

    def arm(self, now_s: float, state: VehicleState, force: bool) -> int:
        if self.armed:
            return ACCEPTED
        if not force:
            problem = None
            if not self.ready(now_s):
                problem = (
                    "PreArm: Need Position Estimate"
                    if self.p.family == "ardupilot"
                    else "Preflight Fail: no heading reference"
                )
            elif not self.mode.armable:
                problem = (
                    "Arm: Mode not armable"
                    if self.p.family == "ardupilot"
                    else "Arming denied: not possible in this mode"
                )
            elif (
                self.p.family == "px4"
                and self.mode.behaviour is Behaviour.GUIDED
                and not self.stream_ok(now_s)
            ):
                problem = "Arming denied: no offboard signal"
            if problem is not None:
                self._say(mavlink.MAV_SEVERITY_CRITICAL, problem)
                return self.p.result_refused
        self.armed = True
        self._armed_s = now_s
        if self.landed:
            self.home_enu = np.array(state.position_enu, dtype=np.float64)
        if self.p.family == "px4":
            self._say(mavlink.MAV_SEVERITY_INFO, "Armed by external command")
        if self.mode.behaviour is Behaviour.TAKEOFF and self.takeoff_z is not None:
            self.landed = False
        return ACCEPTED

    def disarm(self, now_s: float, force: bool) -> int:
        if not self.armed:
            return ACCEPTED
        if not self.landed and not self.p.is_submarine and not force:
            text = "Disarm: not landed" if self.p.family == "ardupilot" else "Disarming denied"
            self._say(mavlink.MAV_SEVERITY_CRITICAL, text)
            return self.p.result_refused
        self.armed = False
        if self.p.family == "px4":
            self._say(mavlink.MAV_SEVERITY_INFO, "Disarmed by external command")
        return ACCEPTED

    def takeoff(self, altitude: float, amsl: bool, now_s: float, state: VehicleState) -> int:
        """NAV_TAKEOFF. ArduPilot: `altitude` m above home; PX4: AMSL (NaN: default)."""
        if not self.p.supports_takeoff:
            return UNSUPPORTED
        ctx = self.frame_context
        if self.p.family == "px4":
            if not self.ready(now_s):
                self._say(mavlink.MAV_SEVERITY_CRITICAL, "Takeoff denied: no position")
                return self.p.result_refused
            self._pending_takeoff_z = None
            if math.isfinite(altitude):
                above_home = altitude - ctx.amsl(self.home_enu) if amsl else altitude
                self._pending_takeoff_z = float(self.home_enu[2]) + above_home
            assert self.p.takeoff_mode is not None
            self._enter(self.p.mode(self.p.takeoff_mode), now_s, state)
            self._pending_takeoff_z = None
            return ACCEPTED
        if self.mode.behaviour is not Behaviour.GUIDED or not self.armed or not self.landed:
            return FAILED
        if amsl:
            altitude -= ctx.amsl(self.home_enu)
        if not math.isfinite(altitude) or altitude <= 0:
            return FAILED
        self.takeoff_z = float(self.home_enu[2]) + altitude
        self.hold_target = np.array([state.position_enu[0], state.position_enu[1], self.takeoff_z])
        self.landed = False
        self.target = None
        return ACCEPTED

    def set_home(
        self, use_current: bool, lat: float, lon: float, alt: float, state: VehicleState
    ) -> int:
        if use_current:
            self.home_enu = np.array(state.position_enu, dtype=np.float64)
            return ACCEPTED
        if not (math.isfinite(lat) and math.isfinite(lon) and math.isfinite(alt)):
            return FAILED
        self.home_enu = np.array(self.frame.to_enu(GeoPoint(lat, lon, alt)))
        return ACCEPTED

    def position_target(self, msg: Any, now_s: float) -> Decision:
        """Handle SET_POSITION_TARGET_GLOBAL_INT; returns what was decided (for tests/logs)."""
        ctx = self.frame_context
        if self.p.family == "px4":
            decision = self._in_truth(decode_px4(msg, ctx, now_s))
            if decision.outcome is Outcome.ACCEPT:
                self._stream.append(now_s)
                self.target = decision.target
                if self.mode.behaviour is Behaviour.GUIDED and self.armed and self.landed:
                    assert decision.target is not None
                    self._maybe_lift_off(decision.target)
            else:
                self._say_limited(mavlink.MAV_SEVERITY_CRITICAL, decision.reason, now_s)
            return decision
        if self.mode.behaviour is not Behaviour.GUIDED:
            return Decision(Outcome.IGNORE, reason=f"not in {self.p.guided_mode}")
        decision = self._in_truth(decode_ardupilot(msg, ctx, now_s))
        if self.landed and not self.p.is_submarine:
            return Decision(Outcome.IGNORE, reason="landed: take off first")
        if decision.outcome is Outcome.ACCEPT:
            self.target = decision.target
            self.takeoff_z = None
        elif decision.outcome is Outcome.STOP:
            self.target = None
            self.takeoff_z = None
            self.hold_target = stopping_point(
                self.shaper.position, self.shaper.velocity, self.cfg.limits.accel_mps2
            )
        return decision

    def _in_truth(self, decision: Decision) -> Decision:
        """A target read in the (shifted) position estimate, moved into the true frame."""
        target = decision.target
        if target is None or target.position_enu is None or not self.estimate_offset_enu.any():
            return decision
        moved = replace(target, position_enu=target.position_enu - self.estimate_offset_enu)
        return replace(decision, target=moved)

    def _maybe_lift_off(self, target: GuidedTarget) -> None:
        """PX4 OFFBOARD on the ground: a target above the ground (or climbing) lifts off."""
        pos, vel = target.position_enu, target.velocity_enu
        climbs = vel is not None and vel[2] > 0.1
        above = pos is not None and pos[2] > self._ground(pos) + LANDED_TOLERANCE_M * 2
        if climbs or above:
            self.landed = False

    def reboot(self, now_s: float, state: VehicleState) -> None:
        """Autopilot restart: clock, mode and guided state reset; landed vehicles disarm."""
        if self.landed or self.p.is_submarine:
            self.armed = False
        self._boot(now_s, state)
        self.shaper.reset(state.position_enu, state.yaw_rad)

    # --------------------------------------------------------------------------- update
    def update(self, now_s: float, dt_s: float, state: VehicleState) -> Setpoint | None:
        """One control cycle. Returns the setpoint for the vehicle model, or None while the
        vehicle sits still (disarmed, or armed on the ground)."""
        if self.armed and self.landed and now_s - self._armed_s >= AUTO_DISARM_S:
            self.armed = False
            self._say(mavlink.MAV_SEVERITY_INFO, "Auto disarmed")
        self._check_offboard(now_s, state)
        if not self.armed and not self.landed and not self.p.is_submarine:
            return self._fall(dt_s, state)
        if self.frozen:
            self.shaper.reset(state.position_enu, state.yaw_rad)
            self.hold_target = np.array(state.position_enu, dtype=np.float64)
            return None

        target_pos, target_vel, yaw, yaw_rate = self._targets(now_s, state)
        self.shaper.step(target_pos, target_vel, yaw, yaw_rate, dt_s)
        ground = self._ground(self.shaper.position)
        on_ground = self.shaper.clamp_above(ground)
        descending = self.mode.behaviour in (Behaviour.LAND, Behaviour.RTL)
        if on_ground and descending and state.position_enu[2] - ground <= LANDED_TOLERANCE_M:
            self._touch_down()
            return None
        self._check_takeoff_done(now_s, state)
        return Setpoint(
            position_enu=self.shaper.position.copy(),
            velocity_enu=self.shaper.velocity.copy(),
            yaw_rad=self.shaper.yaw_rad,
            pitch_rad=0.0,
            acceleration_enu=self.shaper.acceleration.copy(),
        )

    def _fall(self, dt_s: float, state: VehicleState) -> Setpoint | None:
        """Disarmed in the air: motors off, the reference drops to the ground."""
        self.shaper.velocity[2] = max(self.shaper.velocity[2] - 9.81 * dt_s, -20.0)
        self.shaper.velocity[:2] *= 0.98
        self.shaper.position = self.shaper.position + self.shaper.velocity * dt_s
        if self.shaper.clamp_above(self._ground(self.shaper.position)):
            self.landed = True
            self._say(mavlink.MAV_SEVERITY_CRITICAL, "Crash: vehicle fell to the ground")
            return None
        return Setpoint(
            self.shaper.position.copy(), self.shaper.velocity.copy(), state.yaw_rad, 0.0
        )

    def _touch_down(self) -> None:
        self.landed = True
        self.armed = False
        self.takeoff_z = None
        if self.p.family == "ardupilot":
            self._say(mavlink.MAV_SEVERITY_INFO, "Land complete: disarming")
        else:
            self._say(mavlink.MAV_SEVERITY_INFO, "Landing detected")

    def _check_offboard(self, now_s: float, state: VehicleState) -> None:
        if self.p.family != "px4" or self.mode.behaviour is not Behaviour.GUIDED:
            return
        last = self._stream[-1] if self._stream else -math.inf
        if now_s - last <= self.cfg.offboard_loss_timeout_s:
            return
        action = self.cfg.offboard_loss_action
        name = {"hold": self.p.hold_mode, "land": self.p.land_mode, "rtl": self.p.rtl_mode}[action]
        assert name is not None
        self._enter(self.p.mode(name), now_s, state)
        self.failsafe = True
        self._say(
            mavlink.MAV_SEVERITY_CRITICAL,
            f"Failsafe: no offboard signal, {dict(hold='Hold', land='Land', rtl='Return')[action]}",
        )

    def _check_takeoff_done(self, now_s: float, state: VehicleState) -> None:
        if self.takeoff_z is None:
            return
        if abs(float(state.position_enu[2]) - self.takeoff_z) > 0.3:
            return
        if abs(float(self.shaper.position[2]) - self.takeoff_z) > 0.05:
            return
        self.hold_target = self.shaper.position.copy()
        self.hold_target[2] = self.takeoff_z
        self.takeoff_z = None
        if self.p.after_takeoff_mode is not None and self.mode.behaviour is Behaviour.TAKEOFF:
            self._enter(self.p.mode(self.p.after_takeoff_mode), now_s, state)

    def _targets(
        self, now_s: float, state: VehicleState
    ) -> tuple[FloatArray | None, FloatArray | None, float | None, float | None]:
        """(position, velocity, yaw, yaw rate) to shape towards, by behaviour."""
        b = self.mode.behaviour
        nan = math.nan
        if self.takeoff_z is not None and b in (Behaviour.GUIDED, Behaviour.TAKEOFF):
            return np.array([*self.hold_target[:2], self.takeoff_z]), None, None, None
        if b is Behaviour.GUIDED and self.target is not None:
            return self._guided(now_s)
        if b is Behaviour.LAND or (b is Behaviour.RTL and self._rtl_phase == "land"):
            return self._landing(state)
        if b is Behaviour.RTL:
            here = self.shaper.position
            if self._rtl_phase == "climb":
                if here[2] >= self._rtl_z - 0.1:
                    self._rtl_phase = "return"
                return np.array([*self._land_xy, self._rtl_z]), None, None, None
            home_xy = self.home_enu[:2]
            close = np.linalg.norm(here[:2] - home_xy) < 0.5
            if close and np.linalg.norm(self.shaper.velocity) < 0.3:
                self._rtl_phase = "land"
                self._land_xy = home_xy.copy()
            return np.array([*home_xy, self._rtl_z]), None, None, None
        if b is Behaviour.SURFACE:
            return np.array([nan, nan, float(self.home_enu[2])]), np.zeros(3), None, None
        return self.hold_target, None, None, None

    def _landing(
        self, state: VehicleState
    ) -> tuple[FloatArray | None, FloatArray | None, float | None, float | None]:
        height = float(state.position_enu[2]) - self._ground(state.position_enu)
        lim = self.cfg.limits
        speed = lim.speed_down_mps if height > FAST_DESCENT_ABOVE_M else lim.land_speed_mps
        return np.array([*self._land_xy, math.nan]), np.array([0.0, 0.0, -speed]), None, None

    def _guided(
        self, now_s: float
    ) -> tuple[FloatArray | None, FloatArray | None, float | None, float | None]:
        t = self.target
        assert t is not None
        if self.p.family == "px4":
            return t.position_enu, t.velocity_enu, t.yaw_enu_rad, t.yaw_rate_radps
        age = now_s - t.received_s
        timeout = self.cfg.guided_timeout_s
        if t.velocity_enu is None:
            return t.position_enu, None, t.yaw_enu_rad, None
        if t.position_enu is None:
            if age <= timeout:
                return None, t.velocity_enu, t.yaw_enu_rad, t.yaw_rate_radps
            # GUID_TIMEOUT: stop where the vehicle is and stay there.
            self.target = None
            self.hold_target = stopping_point(
                self.shaper.position, self.shaper.velocity, self.cfg.limits.accel_mps2
            )
            return self.hold_target, None, t.yaw_enu_rad, None
        # ArduCopter integrates the position target along the velocity (and the velocity
        # along the acceleration) until the timeout.
        moved = min(age, timeout)
        position = t.position_enu + t.velocity_enu * moved
        velocity = t.velocity_enu if age <= timeout else np.zeros(3)
        if t.acceleration_enu is not None:
            position = position + 0.5 * t.acceleration_enu * moved * moved
            if age <= timeout:
                velocity = velocity + t.acceleration_enu * moved
        return position, velocity, t.yaw_enu_rad, t.yaw_rate_radps if age <= timeout else None
