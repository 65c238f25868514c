"""The service's YAML configuration: schema, loading and `check-config`.

One file holds everything a user tunes. Sections:

    link:      connection string (pymavlink form)
    identity:  our system/component id
    autopilot: which autopilot, timeouts, message rates, setpoint frame
    control:   loop rate, time source (monotonic or simulator), auto start, engagement
    route:     base points (local ENU metres from home, or lat/lon) or the autopilot's mission
    planner:   companion.tuning.PlannerConfig (shared with the simulator's scenarios)
    sensors:   list of companion.tuning.SensorConfig (shared with the scenarios)
    failsafe:  maximum ages of position, attitude and range readings; hold/resume behaviour
    signing:   MAVLink 2 signing key file and timestamp state file
    logging:   log level, flight log directory and rotation
    statustext: rate limits of the messages to the pilot

Relative paths (key file, state file, flight log directory) are relative to the config file's
directory. Every key has a default in the schema except `sensors`; `config/default.yaml`
spells all of them out. Validation errors name the key path, what was expected and what was
found, e.g. ``planner.h_d_m: expected a number greater than 0, found -1``.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal, TextIO

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from companion.connection import LinkSpec, parse_connection
from companion.geo import latlon_to_enu_xy
from companion.planner.sensors import SensorTable
from companion.tuning import PlannerConfig, SensorConfig, include_sensors_file, sensor_table

Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
SystemId = Annotated[int, Field(ge=1, le=254)]
ComponentId = Annotated[int, Field(ge=1, le=255)]
RateHz = Annotated[float, Field(gt=0, le=400, allow_inf_nan=False)]


class Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class LinkConfig(Section):
    """`link:` where the autopilot is."""

    connection: str = "udpin:0.0.0.0:14540"

    @field_validator("connection")
    @classmethod
    def _parse(cls, v: str) -> str:
        parse_connection(v)
        return v

    @property
    def spec(self) -> LinkSpec:
        return parse_connection(self.connection)


class IdentityConfig(Section):
    """`identity:` how the service appears on the MAVLink network.

    system_id: "auto" takes the autopilot's (a companion belongs to its vehicle); never 255,
    which is the ground station's and would mask its failsafe.
    """

    system_id: SystemId | Literal["auto"] = "auto"
    component_id: ComponentId = 191
    heartbeat_hz: Annotated[float, Field(ge=0.2, le=10)] = 1.0


StreamName = Literal["ATTITUDE", "GLOBAL_POSITION_INT", "DISTANCE_SENSOR", "HOME_POSITION"]


class StreamsConfig(Section):
    """`autopilot.streams_hz:` rates requested with MAV_CMD_SET_MESSAGE_INTERVAL."""

    ATTITUDE: RateHz = 20.0
    GLOBAL_POSITION_INT: RateHz = 20.0
    DISTANCE_SENSOR: RateHz = 20.0
    HOME_POSITION: RateHz = 0.5


class AutopilotConfig(Section):
    """`autopilot:` which autopilot to fly and how to talk to it.

    type: "auto" detects ArduPilot or PX4 from the heartbeat.
    system_id: "auto" flies the only autopilot heard: after its first heartbeat the service
        listens auto_id_listen_s for others; with more than one it chooses none (an error
        says which were heard) and waits for system_id to be set. Once chosen it never
        switches; another autopilot heard later is reported and no take-over (nor auto
        start) happens until system_id is set.
    setpoint_frame: "auto" = relative altitude (6) on ArduPilot, global AMSL (5) on PX4,
        whose frame 6 applies the home/origin altitude difference with the wrong sign.
        Terrain frames are not offered: ArduCopter rejects them with velocity.
    acceleration_feedforward: send X_d's acceleration with its position and velocity
        (ArduCopter GUIDED and PX4 OFFBOARD feed it forward; without it a multicopter lags a
        climbing or turning X_d); false masks it out of every setpoint.
    """

    type: Literal["auto", "ardupilot", "px4"] = "auto"
    system_id: SystemId | Literal["auto"] = "auto"
    auto_id_listen_s: Annotated[float, Field(ge=0, le=30)] = 1.5
    component_id: ComponentId = 1
    heartbeat_timeout_s: Annotated[float, Field(gt=0, le=60)] = 3.0
    command_timeout_s: Annotated[float, Field(gt=0, le=30)] = 1.0
    command_retries: Annotated[int, Field(ge=0, le=10)] = 3
    streams_hz: StreamsConfig = StreamsConfig()
    setpoint_frame: Literal["auto", "global_relative_alt", "global"] = "auto"
    acceleration_feedforward: bool = True


class AutoStartConfig(Section):
    """`control.auto_start:` arm, take off and switch mode without a pilot (SITL, demos).

    takeoff_alt_m: above home; default the planner's H_d.
    arm_timeout_s: keep retrying the arm command (every arm_retry_s) this long; ArduCopter
        SITL needs ~45 s to be armable.
    """

    enabled: bool = False
    takeoff_alt_m: Positive | None = None
    arm_timeout_s: Annotated[float, Field(gt=0, le=600)] = 120.0
    arm_retry_s: Annotated[float, Field(ge=0.1, le=60)] = 2.0
    takeoff_timeout_s: Annotated[float, Field(gt=0, le=600)] = 60.0
    prestream_s: Annotated[float, Field(ge=0.1, le=10)] = 1.0
    """PX4: how long setpoints stream before OFFBOARD is requested."""


class ControlConfig(Section):
    """`control:` the loop.

    time_source: "monotonic" runs at rate_hz on the computer's monotonic clock; "sim" runs a
        cycle when the simulator's TIMESYNC lockstep tick says one is due in simulated time.
    min_engage_height_m: the vehicle must be this far above home (relative altitude) before
        the service takes over (ArduCopter ignores GUIDED targets on the ground).
    reengage: when the pilot puts the vehicle back in GUIDED/OFFBOARD after taking it away,
        fly on (from the current position, with the base points not yet passed).
    restart_distance_m: on resuming, a planner whose X_d is farther than this from the
        vehicle restarts from the vehicle's position instead of pulling it back.
    on_finish: what to do at the last base point: hold there, or ask the autopilot to land or
        return (the only mode changes the service makes besides auto start).
    face_route_deg: on taking over, a vehicle whose heading is more than this from the
        bearing of the first base point turns in place to face it before the route starts
        (its forward sensors then look the way it will fly, and the first spline does not
        swing out along the old heading); 180 never turns.
    """

    rate_hz: Annotated[float, Field(ge=1, le=100)] = 20.0
    time_source: Literal["monotonic", "sim"] = "monotonic"
    auto_start: AutoStartConfig = AutoStartConfig()
    min_engage_height_m: NonNegative = 1.0
    reengage: bool = True
    restart_distance_m: Positive = 3.0
    on_finish: Literal["hold", "land", "rtl"] = "hold"
    face_route_deg: Annotated[float, Field(ge=0, le=180)] = 30.0


class RouteSection(Section):
    """`route:` where to fly.

    source: "config" flies `points` (local ENU x east, y north, metres from the home
        position) or `points_latlon` ([lat, lon] degrees); "mission" downloads the
        autopilot's mission and flies its waypoints (ArduPilot's item 0 is home and skipped).
    The vehicle's position when the service takes over is prepended as the first base point,
    with the vehicle's heading as the start heading (after turning to face the first base
    point: `control.face_route_deg`).
    arrival_heading_deg: ENU degrees (counter-clockwise from east), optional.
    Bounds (as for a downloaded mission): at most MAX_ROUTE_POINTS points, each within
    MAX_ROUTE_EXTENT_M of home (points) or of the first point (points_latlon), consecutive
    points at least MIN_ROUTE_SPACING_M apart.
    """

    source: Literal["config", "mission"] = "config"
    points: list[tuple[Finite, Finite]] | None = None
    points_latlon: (
        list[
            tuple[
                Annotated[float, Field(ge=-90, le=90, allow_inf_nan=False)],
                Annotated[float, Field(ge=-180, le=180, allow_inf_nan=False)],
            ]
        ]
        | None
    ) = None
    arrival_heading_deg: Finite | None = None

    @model_validator(mode="after")
    def _points_for_source(self) -> RouteSection:
        given = (self.points is not None) + (self.points_latlon is not None)
        if self.source == "config":
            if given != 1:
                raise ValueError("source 'config' needs exactly one of points, points_latlon")
            pts = self.points if self.points is not None else self.points_latlon
            assert pts is not None
            if not pts:
                raise ValueError("route needs at least one base point")
            if self.points is not None:
                xy = [(float(x), float(y)) for x, y in self.points]
            else:
                xy = latlon_points_xy([(float(a), float(b)) for a, b in pts])
            problem = route_problem(xy, origin_is_home=self.points is not None)
            if problem:
                raise ValueError(problem)
        elif given:
            raise ValueError("source 'mission' takes its points from the autopilot; remove points")
        return self


MAX_ROUTE_POINTS = 1000
"""Base points a route may have (the mission download's limit too)."""
MAX_ROUTE_EXTENT_M = 50_000.0
"""How far from home (or the first lat/lon point) a base point may be."""
MIN_ROUTE_SPACING_M = 1.0
"""Consecutive base points closer than this are refused (the route needs distinct points)."""


def latlon_points_xy(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """(lat, lon) degrees -> east/north metres from the first point, in the tangent plane
    at it (`companion.geo`, the one geodesy)."""
    return latlon_to_enu_xy(points)


def route_problem(xy: list[tuple[float, float]], origin_is_home: bool = True) -> str:
    """Why these base points (x east, y north, metres) cannot be flown, or "" if they can."""
    if len(xy) > MAX_ROUTE_POINTS:
        return f"route of {len(xy)} base points is longer than {MAX_ROUTE_POINTS}"
    where = "home" if origin_is_home else "the first point"
    for i, (x, y) in enumerate(xy):
        if not (math.isfinite(x) and math.isfinite(y)):
            return f"base point {i} is not finite"
        if math.hypot(x, y) > MAX_ROUTE_EXTENT_M:
            return (
                f"base point {i} is {math.hypot(x, y) / 1000:.0f} km from {where} "
                f"(at most {MAX_ROUTE_EXTENT_M / 1000:.0f} km)"
            )
    for i in range(1, len(xy)):
        gap = math.hypot(xy[i][0] - xy[i - 1][0], xy[i][1] - xy[i - 1][1])
        if gap < MIN_ROUTE_SPACING_M:
            return (
                f"base points {i - 1} and {i} are {gap:.2f} m apart "
                f"(consecutive points at least {MIN_ROUTE_SPACING_M:g} m apart)"
            )
    return ""


class FailsafeConfig(Section):
    """`failsafe:` when inputs are too old.

    A range reading older than sensor_max_age_s (or an attitude older than its age) makes
    the service hold at the current position and say why; a position older than
    position_max_age_s stops commanding anything new (the last target is sent again at rest
    for 3 s, a brake, then nothing; the autopilot keeps that target).
    optional_sensor_ids: sensors whose absence is passed to the planner as "no reading"
    instead of causing a hold.
    resume_after_s: inputs must be good this long before a hold ends.
    max_speed_mps: a position implying a faster jump is rejected as a glitch (accepted
    after jump_accept_s if it persists, e.g. an EKF reset).
    max_position_jump_m: so is a position this far off the path the reported velocity
    predicts (more after a gap in the data: 5 m/s^2 times its square).
    max_accepted_jump_m: a jump that persists is accepted as an estimator reset (the plan
    moves with it) only up to this size; a larger one is a fault: the service stops
    commanding, says why, and stays stopped until the position is back near the last good one.
    range_median_samples: a range reading that agrees within range_spike_m with none of its
    sensor's last this many readings ("nothing detected" counting as farthest), and does
    not continue the line through the two before it, is replaced by their median (or by
    nothing new, the last reading passed holding, when that agrees with none either): a
    single spike or dropout of one reading never reaches the planner, and a real step
    arrives (n - 1) / 2 readings late. 1: off.
    range_spike_m: that agreement, metres: above the sensors' noise. Every other reading
    reaches the planner at once, with the attitude and position of its own time; 0 makes a
    plain median filter, whose readings are up to (n - 1) / 2 readings old and are placed
    from where the vehicle is now (with 0.05 m of noise it raised the height error's p95
    from 0.041 to 0.064 m: docs/service.md).
    """

    position_max_age_s: Positive = 0.5
    attitude_max_age_s: Positive = 0.5
    sensor_max_age_s: Positive = 0.5
    optional_sensor_ids: list[Annotated[int, Field(ge=0, le=255)]] = []
    resume_after_s: NonNegative = 1.0
    max_speed_mps: Positive = 40.0
    jump_accept_s: Positive = 1.0
    max_position_jump_m: Positive = 2.0
    max_accepted_jump_m: Positive = 50.0
    range_median_samples: Annotated[int, Field(ge=1, le=9)] = 3
    range_spike_m: NonNegative = 0.3


class SigningConfig(Section):
    """`signing:` MAVLink 2 signing.

    key_file: 64 hex characters or 32 raw bytes. state_file: where the signing timestamp is
    kept across restarts. allow_unsigned: message names still accepted unsigned (default none:
    every unsigned or badly signed message is rejected and counted).
    """

    enabled: bool = False
    key_file: Path | None = None
    state_file: Path | None = None
    link_id: Annotated[int, Field(ge=0, le=255)] = 0
    allow_unsigned: list[str] = []

    @model_validator(mode="after")
    def _key_when_enabled(self) -> SigningConfig:
        if self.enabled and self.key_file is None:
            raise ValueError("signing is enabled: key_file is required")
        return self

    @field_validator("allow_unsigned")
    @classmethod
    def _known_messages(cls, v: list[str]) -> list[str]:
        from pymavlink.dialects.v20 import ardupilotmega as mavlink2

        for name in v:
            if not hasattr(mavlink2, f"MAVLINK_MSG_ID_{name}"):
                raise ValueError(f"unknown MAVLink message name {name!r}")
        return v


class LoggingConfig(Section):
    """`logging:` the text log (stderr, journald under systemd) and the flight log.

    flight_log_dir: one JSON line per cycle (inputs, decision, setpoint) in
    flight-YYYYmmdd-HHMMSS.jsonl files, rotated at max_file_mb, at most keep_files kept.
    Empty (null) disables the flight log.
    """

    level: Literal["debug", "info", "warning", "error"] = "info"
    flight_log_dir: Path | None = None
    max_file_mb: Annotated[float, Field(gt=0, le=10_000)] = 50.0
    keep_files: Annotated[int, Field(ge=1, le=10_000)] = 20


class StatustextConfig(Section):
    """`statustext:` messages to the pilot: a token bucket plus a repeat filter."""

    max_per_s: Annotated[float, Field(gt=0, le=50)] = 2.0
    burst: Annotated[int, Field(ge=1, le=100)] = 5
    repeat_interval_s: NonNegative = 5.0


class ServiceConfig(Section):
    """The whole file. `base_dir` (not a YAML key) resolves relative paths."""

    link: LinkConfig = LinkConfig()
    identity: IdentityConfig = IdentityConfig()
    autopilot: AutopilotConfig = AutopilotConfig()
    control: ControlConfig = ControlConfig()
    route: RouteSection = RouteSection(source="mission")
    planner: PlannerConfig = PlannerConfig()
    sensors: Annotated[list[SensorConfig], Field(min_length=1)]
    failsafe: FailsafeConfig = FailsafeConfig()
    signing: SigningConfig = SigningConfig()
    logging: LoggingConfig = LoggingConfig()
    statustext: StatustextConfig = StatustextConfig()

    @field_validator("sensors")
    @classmethod
    def _table(cls, v: list[SensorConfig]) -> list[SensorConfig]:
        sensor_table(v)  # ValueError: duplicate ids, missing forward/back surface sensor, ...
        return v

    @model_validator(mode="after")
    def _optional_ids_exist(self) -> ServiceConfig:
        ids = {s.id for s in self.sensors}
        unknown = sorted(set(self.failsafe.optional_sensor_ids) - ids)
        if unknown:
            raise ValueError(f"failsafe.optional_sensor_ids {unknown} are not in sensors")
        return self

    def sensor_table(self) -> SensorTable:
        return sensor_table(self.sensors)

    def resolve_paths(self, base_dir: Path) -> ServiceConfig:
        """A copy with relative file paths made relative to `base_dir`."""

        def fix(p: Path | None) -> Path | None:
            return None if p is None or p.is_absolute() else base_dir / p

        signing = self.signing.model_copy(
            update={
                "key_file": fix(self.signing.key_file),
                "state_file": fix(self.signing.state_file),
            }
        )
        logging_ = self.logging.model_copy(
            update={"flight_log_dir": fix(self.logging.flight_log_dir)}
        )
        return self.model_copy(update={"signing": signing, "logging": logging_})


# --- loading and error messages ------------------------------------------------------------


class ConfigError(ValueError):
    """A config file that cannot be used; `errors` holds one line per problem."""

    def __init__(self, path: Path | None, errors: list[str]) -> None:
        self.path = path
        self.errors = errors
        where = f"{path}: " if path else ""
        super().__init__(where + "; ".join(errors))


def _describe(value: Any) -> str:
    if isinstance(value, dict):
        return "a mapping" if value else "an empty mapping"
    if isinstance(value, list):
        return f"a list of {len(value)}"
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _expected(err: dict[str, Any]) -> str:
    kind = err["type"]
    msg = str(err["msg"])
    if kind == "missing":
        return "a value (required key)"
    if kind == "extra_forbidden":
        return "no such key (misspelt or not in this section)"
    if kind in ("value_error", "assertion_error"):
        return "a valid value: " + msg.split(", ", 1)[-1]
    msg = msg.removeprefix("Input should be ")
    if kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        return "a number " + msg
    return msg


def format_errors(exc: ValidationError) -> list[str]:
    """One `key.path: expected ..., found ...` line per pydantic error."""
    lines = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "(top level)"
        found = "nothing" if err["type"] == "missing" else _describe(err.get("input"))
        lines.append(f"{loc}: expected {_expected(dict(err))}, found {found}")
    return lines


def planner_with(planner: PlannerConfig, changes: Mapping[str, float]) -> PlannerConfig:
    """`planner` with `changes` (its own key names and units) applied, validated by the rules
    of the file's `planner:` section (the same model, so no second copy of a range).
    ValueError names each problem as check-config does, e.g. ``planner.h_d_m: expected a
    number greater than 0, found -1.0``."""
    unknown = sorted(set(changes) - set(PlannerConfig.model_fields))
    if unknown:
        raise ValueError(f"planner: no key {', '.join(unknown)}")
    try:
        return PlannerConfig.model_validate({**planner.model_dump(), **changes})
    except ValidationError as exc:
        raise ValueError("; ".join(f"planner.{line}" for line in format_errors(exc))) from None


def parse_config(data: Any, path: Path | None = None) -> ServiceConfig:
    """Validate already-parsed YAML; ConfigError lists every problem."""
    if not isinstance(data, dict):
        raise ConfigError(
            path, [f"(top level): expected a mapping of sections, found {_describe(data)}"]
        )
    try:
        cfg = ServiceConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(path, format_errors(exc)) from None
    return cfg.resolve_paths(path.parent) if path is not None else cfg


def load_config(path: Path, connection: str | None = None) -> ServiceConfig:
    """Read and validate a config file; ConfigError names each problem.

    connection: replaces the file's `link.connection` (the command line's `--connection`).
    """
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(path, [f"cannot read the file: {exc.strerror or exc}"]) from None
    except UnicodeDecodeError as exc:
        raise ConfigError(
            path, [f"cannot read the file: not UTF-8 text (byte {exc.start})"]
        ) from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(path, [f"(YAML) {where}{problem}"]) from None
    if isinstance(data, dict):
        try:
            include_sensors_file(data, path.parent)
        except ValueError as exc:
            raise ConfigError(path, [str(exc)]) from None
    if connection is not None and isinstance(data, dict):
        link = data.get("link")
        data["link"] = {**(link if isinstance(link, dict) else {}), "connection": connection}
    return parse_config(data, path)


def check_config(path: Path, out: TextIO | None = None, connection: str | None = None) -> int:
    """`companion check-config`: 0 and a one-line summary if valid, else 2 and the errors.

    A serial device that does not exist or a host name that does not resolve is reported as
    a warning (exit 0): a USB autopilot may appear, and the network come up, after boot, and
    the service waits for them.
    """
    stream = out if out is not None else sys.stderr
    try:
        cfg = load_config(path, connection)
        _check_files(cfg)
        _check_takeover(cfg)
    except ConfigError as exc:
        print(f"{path}: invalid configuration", file=stream)
        for line in exc.errors:
            print(f"  {line}", file=stream)
        return 2
    print(
        f"{path}: OK ({len(cfg.sensors)} sensors, route from {cfg.route.source}, "
        f"link {cfg.link.spec})",
        file=out if out is not None else sys.stdout,
    )
    print(
        f"{path}: sensor layout: {layout_summary(cfg)}", file=out if out is not None else sys.stdout
    )
    for warning in link_warnings(cfg.link.spec):
        print(f"{path}: warning: link.connection: {warning}", file=stream)
    return 0


def layout_summary(cfg: ServiceConfig) -> str:
    """What the sensor layout can see, for a person (`companion.planner.sight`): how far
    ahead it flags a wall as steep at H_d, where ahead no obstacle sensor looks level, and
    how far the heading swings across the gaps while moving."""
    from companion.planner.sight import (
        describe_level_gaps,
        describe_sweep,
        sweep_amplitude_rad,
        wall_flag_distance_m,
    )

    params = cfg.planner.to_params()
    table = cfg.sensor_table()
    flag = wall_flag_distance_m(table, params.h_d_m, params.phi_max_rad)
    if flag > 0.0:
        ahead = f"flags a wall ahead as steep {flag:.1f} m out"
    else:
        ahead = "never flags a wall ahead as steep"
    period = params.yaw_sweep_period_m
    swing = sweep_amplitude_rad(table) if period > 0.0 else 0.0
    if swing > 0.0:
        sweep = f"moving, {describe_sweep(swing, period)} (yaw_sweep_period_m)"
    else:
        sweep = "the heading stays on the path"
    return f"{ahead}; {describe_level_gaps(table)}; {sweep}"


def link_warnings(spec: LinkSpec) -> list[str]:
    """What will stop the link from opening now: a missing serial device, an unknown host."""
    import os
    import socket
    import stat

    if spec.kind == "serial":
        try:
            mode = os.stat(spec.device).st_mode
        except OSError as exc:
            return [f"serial device {spec.device}: {exc.strerror or exc}"]
        if not stat.S_ISCHR(mode):
            return [f"{spec.device} is not a serial (character) device"]
        return []
    try:
        socket.getaddrinfo(spec.host, spec.port, type=socket.SOCK_DGRAM)
    except (OSError, UnicodeError) as exc:
        return [f"host {spec.host!r} does not resolve ({getattr(exc, 'strerror', None) or exc})"]
    return []


def takeover_problem(cfg: ServiceConfig) -> str:
    """Build what a take-over builds (the route and the planner) as if the vehicle took
    over at home (at H_d, heading east); the error it raises, or "" if none. A mission route
    is only known in flight: the service checks it then, and holds if it cannot be flown."""
    import numpy as np

    from companion.planner import Planner
    from companion.planner.route import Route

    r = cfg.route
    if r.source != "config":
        return ""
    if r.points is not None:
        xy = np.array(r.points, dtype=np.float64).reshape(-1, 2)
    else:
        assert r.points_latlon is not None
        xy = np.array(latlon_points_xy(list(r.points_latlon)), dtype=np.float64).reshape(-1, 2)
    here = np.zeros(2)
    # the vehicle's position becomes the first base point; points it is on are taken as passed
    while len(xy) and float(np.hypot(*(xy[0] - here))) < 0.5:
        xy = xy[1:]
    if len(xy) == 0:
        return ""
    params = cfg.planner.to_params()
    try:
        arrival = None if r.arrival_heading_deg is None else math.radians(r.arrival_heading_deg)
        route = Route(np.vstack([here, xy]), 0.0, arrival)
        Planner(params, cfg.sensor_table(), route, np.array([0.0, 0.0, params.h_d_m]))
    except (ValueError, ArithmeticError) as exc:
        return f"route/planner cannot be built at take-over: {exc}"
    return ""


def _check_takeover(cfg: ServiceConfig) -> None:
    problem = takeover_problem(cfg)
    if problem:
        raise ConfigError(None, [problem])


def _check_files(cfg: ServiceConfig) -> None:
    """Files the service will need at start: the signing key must be readable and valid."""
    if cfg.signing.enabled and cfg.signing.key_file is not None:
        from companion.signing_key import SigningKeyError, load_key

        try:
            load_key(cfg.signing.key_file)
        except SigningKeyError as exc:
            raise ConfigError(None, [f"signing.key_file: {exc}"]) from None


__all__ = [
    "AutoStartConfig",
    "AutopilotConfig",
    "ConfigError",
    "ControlConfig",
    "FailsafeConfig",
    "IdentityConfig",
    "LinkConfig",
    "LoggingConfig",
    "RouteSection",
    "ServiceConfig",
    "SigningConfig",
    "StatustextConfig",
    "StreamsConfig",
    "check_config",
    "format_errors",
    "layout_summary",
    "load_config",
    "parse_config",
    "planner_with",
]
