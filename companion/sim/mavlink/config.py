"""The `mavlink:` section of a scenario: how the MAVLink vehicle simulator behaves.

Every field has a default, so `mavlink: {}` (or no section at all) gives an ArduCopter on
UDP 127.0.0.1:14580 running in real time. Times are simulated seconds unless a name says
otherwise (`timeout_s` of lockstep is wall-clock). Validation refuses unknown keys and
out-of-range values with the key path, as the rest of the scenario does.
"""

from __future__ import annotations

import enum
import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.sim.mavlink.streams import STREAMED_MESSAGES

Finite = Annotated[float, Field(allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Probability = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]
MAX_UDP_PAYLOAD_BYTES = 65507
Window = tuple[NonNegative, NonNegative]
"""[start_s, end_s) of simulated time."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _check_windows(windows: list[Window]) -> list[Window]:
    for start, end in windows:
        if not start < end:
            raise ValueError(f"time window [{start}, {end}] must have start < end")
    return windows


class PersonalityName(enum.StrEnum):
    ARDUPILOT = "ardupilot"
    """ArduCopter: MAV_AUTOPILOT_ARDUPILOTMEGA, GUIDED = 4, mission seq 0 = home."""
    PX4 = "px4"
    """PX4 multicopter: MAV_AUTOPILOT_PX4, main/sub custom modes, OFFBOARD."""
    ARDUSUB = "ardusub"
    """ArduSub: MAV_TYPE_SUBMARINE, depth as negative altitude, no takeoff."""


class HomeConfig(_Strict):
    """Geodetic position of the world's local ENU origin (x = y = z = 0)."""

    lat_deg: Annotated[float, Field(ge=-90, le=90, allow_inf_nan=False)]
    lon_deg: Annotated[float, Field(ge=-180, le=180, allow_inf_nan=False)]
    alt_m: Finite
    """Metres above mean sea level of world z = 0."""


DEFAULT_HOMES: dict[PersonalityName, HomeConfig] = {
    # ArduPilot SITL's default location (CMAC, Canberra) and PX4 SITL's (Zurich).
    PersonalityName.ARDUPILOT: HomeConfig(lat_deg=-35.363261, lon_deg=149.165230, alt_m=584.0),
    PersonalityName.PX4: HomeConfig(lat_deg=47.397742, lon_deg=8.545594, alt_m=488.0),
    PersonalityName.ARDUSUB: HomeConfig(lat_deg=33.810313, lon_deg=-118.393867, alt_m=0.0),
}


class LockstepConfig(_Strict):
    """Lockstep: physics advances only when the companion has answered the current tick.

    Every `period_s` of simulated time the simulator sends TIMESYNC(tc1=0, ts1=sim time in ns)
    and waits for TIMESYNC(tc1 != 0, ts1 = the same value). `timeout_s` is wall-clock time;
    when it runs out the simulator carries on and counts a stall.
    """

    enabled: bool = False
    period_s: Positive = 0.05
    timeout_s: Positive = 2.0
    datagram_bytes: Annotated[int, Field(ge=0, le=MAX_UDP_PAYLOAD_BYTES)] = 8192
    """A period's messages (its ticks' telemetry and replies, then the TIMESYNC request) go
    out together, packed whole into datagrams of at most this many bytes (MAVLink over UDP
    carries any number of whole frames in a datagram): one wake-up of the companion per
    period instead of one per message. 0: one datagram per message, as outside lockstep."""


class MotionLimits(_Strict):
    """The simulated autopilot's position controller (WPNAV_* / MPC_* in spirit)."""

    speed_xy_mps: Positive = 10.0
    speed_up_mps: Positive = 2.5
    speed_down_mps: Positive = 1.5
    accel_mps2: Positive = 2.5
    position_gain: Positive = 1.0
    """Proportional gain of the position loop, 1/s (ArduPilot PSC_POSXY_P)."""
    yaw_rate_dps: Positive = 90.0
    land_speed_mps: Positive = 0.5


class SensorFaultConfig(_Strict):
    """Faults of one range sensor (`sensor_id`) or, with no id, of all of them."""

    sensor_id: Annotated[int, Field(ge=0, le=255)] | None = None
    noise_std_m: NonNegative = 0.0
    dropout_probability: Probability = 0.0
    """Chance that a reading is not sent at all."""
    dropout_windows: list[Window] = Field(default_factory=list)
    stuck_windows: list[Window] = Field(default_factory=list)
    """During a window the sensor repeats the reading it had when the window opened."""
    spike_probability: Probability = 0.0
    spike_range_m: tuple[NonNegative, NonNegative] | None = None
    """A spike replaces the reading with a uniform draw from this range (default: the
    sensor's [min, max) range)."""

    @field_validator("dropout_windows", "stuck_windows")
    @classmethod
    def _windows(cls, v: list[Window]) -> list[Window]:
        return _check_windows(v)


class LinkFaultConfig(_Strict):
    """Faults of one direction of the link, drawn per message."""

    loss_probability: Probability = 0.0
    duplicate_probability: Probability = 0.0
    reorder_probability: Probability = 0.0
    """Chance that a message is held back and delivered after the next one."""
    windows: list[Window] = Field(default_factory=list)
    """[start_s, end_s) of simulated time when these faults apply (empty: always)."""

    @field_validator("windows")
    @classmethod
    def _windows(cls, v: list[Window]) -> list[Window]:
        return _check_windows(v)


class RebootFault(_Strict):
    """The autopilot reboots at `at_s`: silent for `duration_s`, then time_boot_ms restarts."""

    at_s: NonNegative
    duration_s: NonNegative = 1.0


class ModeChangeFault(_Strict):
    """A pilot switches the flight mode at `at_s` (name such as LOITER, POSCTL, AUTO.RTL, or
    the custom_mode number)."""

    at_s: NonNegative
    mode: str | int


class PositionJumpFault(_Strict):
    """The autopilot's position estimate jumps by `offset_m` (ENU metres) at `at_s`: a GPS
    glitch (`duration_s` given: the estimate comes back after it) or an estimator reset onto
    a shifted GPS solution (`duration_s` omitted: for the rest of the run).

    The vehicle does not move: the reported GLOBAL_POSITION_INT and LOCAL_POSITION_NED shift,
    and position targets received meanwhile are read in the shifted estimate (a target at the
    reported position holds the vehicle where it is), as ArduPilot and PX4 shift their
    targets on an estimator reset. HOME_POSITION does not move."""

    at_s: NonNegative
    offset_m: tuple[Finite, Finite, Finite]
    duration_s: Positive | None = None


class FaultsConfig(_Strict):
    """Deterministic fault injection: the same seed gives the same faults."""

    seed: int = 0
    sensors: list[SensorFaultConfig] = Field(default_factory=list)
    outgoing: LinkFaultConfig = LinkFaultConfig()
    """Simulator -> companion."""
    incoming: LinkFaultConfig = LinkFaultConfig()
    """Companion -> simulator."""
    link_cuts: list[Window] = Field(default_factory=list)
    reboots: list[RebootFault] = Field(default_factory=list)
    mode_changes: list[ModeChangeFault] = Field(default_factory=list)
    position_jumps: list[PositionJumpFault] = Field(default_factory=list)

    @field_validator("link_cuts")
    @classmethod
    def _windows(cls, v: list[Window]) -> list[Window]:
        return _check_windows(v)


class BridgeConfig(_Strict):
    """Sensor bridge for a real SITL (`python -m companion.sim bridge`): see sim.mavlink.bridge."""

    connect: str = "udpin:127.0.0.1:14550"
    """pymavlink-style connection string of the autopilot's MAVLink stream (udpin:, udpout:,
    tcp:)."""
    send_to: Literal["autopilot", "companion"] = "autopilot"
    """autopilot: DISTANCE_SENSOR goes back over `connect` for the autopilot to use and
    re-publish; companion: straight to `companion_address`."""
    companion_address: str | None = None
    """host:port for send_to = companion."""
    rate_hz: Positive = 10.0
    """Wall-clock rate; at SITL speed-up N the autopilot sees rate_hz / N per simulated s."""
    system_id: Annotated[int, Field(ge=1, le=254)] = 1
    component_id: Annotated[int, Field(ge=1, le=255)] = mavlink.MAV_COMP_ID_PERIPHERAL
    anchor_xy: tuple[Finite, Finite] = (0.0, 0.0)
    """World x, y (ENU metres) of the autopilot's home."""
    anchor_z: Finite | None = None
    """World z (ENU metres) of the autopilot's home, where its own flat ground is; None: the
    terrain height at anchor_xy. Below the start, a vehicle that takes off there climbs
    through the virtual ground first, and relief down to it can be flown."""

    @model_validator(mode="after")
    def _companion_needs_address(self) -> BridgeConfig:
        if self.send_to == "companion" and not self.companion_address:
            raise ValueError("send_to: companion needs companion_address (host:port)")
        return self


class MavlinkSimConfig(_Strict):
    """`mavlink:` section of a scenario."""

    personality: PersonalityName = PersonalityName.ARDUPILOT
    system_id: Annotated[int, Field(ge=1, le=254)] = 1
    component_id: Annotated[int, Field(ge=1, le=255)] = 1
    home: HomeConfig | None = None
    """World origin; default: the personality's usual SITL location."""
    bind_host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=0, le=65535)] = 14580
    """UDP port the simulator listens on (0: any free port)."""
    target: str | None = None
    """host:port to send to; default: whoever sent the last datagram (like SITL)."""
    physics_dt_s: Annotated[float, Field(gt=0, le=0.1, allow_inf_nan=False)] = 0.01
    speedup: Annotated[float, Field(gt=0)] = 1.0
    """Simulated seconds per wall-clock second; inf runs as fast as possible."""
    lockstep: LockstepConfig = LockstepConfig()
    rates_hz: dict[str, NonNegative] = Field(default_factory=dict)
    """Start-up message rates by name, over the personality's defaults (0 = off)."""
    prearm_delay_s: NonNegative = 2.0
    """Arming and position modes are refused for this long after boot (real SITL: ~42 s
    for ArduCopter, ~4.4 s for PX4 with SIH)."""
    guided_timeout_s: Positive = 3.0
    """ArduPilot GUID_TIMEOUT: velocity targets older than this stop the vehicle."""
    offboard_loss_timeout_s: Positive = 1.0
    """PX4 COM_OF_LOSS_T."""
    offboard_min_rate_hz: Positive = 2.0
    """PX4 refuses OFFBOARD unless setpoints arrive at least this often."""
    offboard_loss_action: Literal["hold", "land", "rtl"] = "hold"
    """What PX4 does when the offboard stream is lost (real SITL without RC flew RTL)."""
    rtl_altitude_m: Positive = 15.0
    takeoff_altitude_m: Positive = 2.5
    """PX4 MIS_TAKEOFF_ALT, used when NAV_TAKEOFF gives no altitude."""
    home_above_origin_m: Finite = 0.0
    """How far home lies above the estimator origin. Non-zero reproduces PX4's wrong-sign
    frame-6 (relative altitude) conversion seen on real SITL."""
    distance_sensor_quaternion: bool = True
    """Fill DISTANCE_SENSOR.quaternion for ROTATION_CUSTOM sensors (real ArduPilot and PX4
    re-reports leave it zero; set false to imitate that)."""
    limits: MotionLimits = MotionLimits()
    faults: FaultsConfig = FaultsConfig()
    bridge: BridgeConfig = BridgeConfig()
    truth_every_n_ticks: Annotated[int, Field(ge=1)] = 1

    @field_validator("speedup")
    @classmethod
    def _speedup_not_nan(cls, v: float) -> float:
        if math.isnan(v):
            raise ValueError("speedup must be a number (inf for as fast as possible)")
        return v

    @field_validator("target")
    @classmethod
    def _host_port(cls, v: str | None) -> str | None:
        if v is not None:
            parse_host_port(v)
        return v

    @field_validator("rates_hz")
    @classmethod
    def _known_messages(cls, v: dict[str, float]) -> dict[str, float]:
        unknown = sorted(set(v) - set(STREAMED_MESSAGES))
        if unknown:
            raise ValueError(f"unknown messages {unknown}; known: {sorted(STREAMED_MESSAGES)}")
        return v

    @model_validator(mode="after")
    def _lockstep_fits_ticks(self) -> MavlinkSimConfig:
        ratio = self.lockstep.period_s / self.physics_dt_s
        if self.lockstep.enabled and (ratio < 1 - 1e-9 or abs(ratio - round(ratio)) > 1e-6):
            raise ValueError(
                f"lockstep.period_s ({self.lockstep.period_s}) must be a whole multiple of "
                f"physics_dt_s ({self.physics_dt_s})"
            )
        return self

    @property
    def home_or_default(self) -> HomeConfig:
        return self.home if self.home is not None else DEFAULT_HOMES[self.personality]


def parse_host_port(text: str) -> tuple[str, int]:
    """'host:port' -> (host, port); ValueError otherwise."""
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"expected host:port, got {text!r}")
    return host, int(port)
