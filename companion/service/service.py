"""The companion service: MAVLink in, planner cycle, setpoints out.

Life cycle (`Service.run`):

1. open the link; heartbeat at `identity.heartbeat_hz` from the start (MAV_STATE BOOT);
2. wait for an autopilot heartbeat, tell ArduPilot from PX4, lock onto its (system,
   component) id and take its system id as ours unless configured;
3. configure: request the message rates (MAV_CMD_SET_MESSAGE_INTERVAL, acks checked) and
   HOME_POSITION (MAV_CMD_REQUEST_MESSAGE), wait for home and position, get the route
   (config points, or the autopilot's mission);
4. STANDBY until the vehicle is armed, in GUIDED/OFFBOARD and above `min_engage_height_m`
   (or, with `auto_start`, arm/take off/switch mode itself), then fly: each cycle step the
   planner and send its setpoint (ACTIVE);
5. on failsafes hold (CRITICAL) or stop commanding (EMERGENCY), on a mode change stop at once
   and never switch back; when the autopilot heartbeat returns after a loss, configure again.

Cycles run on the monotonic clock at `control.rate_hz`, or, with `control.time_source: sim`,
on the simulator's lockstep TIMESYNC ticks: the tick's time becomes the service clock, a cycle
runs if one is due, its setpoint is sent, and only then is the TIMESYNC answered, so a
faster-than-real-time simulation sees exactly the cycles a real-time flight would.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import math
import signal
import sys
import time
from collections import Counter
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from companion.config import (
    ConfigError,
    ServiceConfig,
    latlon_points_xy,
    load_config,
    route_problem,
)
from companion.geo import GeoPoint, LocalFrame
from companion.planner.frames import attitude_ned_to_enu, wrap_pi
from companion.planner.params import PlannerParams
from companion.planner.route import Route
from companion.planner.sensors import SensorTable
from companion.planner.types import FloatArray, Setpoint, StepResult, VehicleState
from companion.service.clock import MonotonicClock, SimClock
from companion.service.codec import MavCodec, MAVLinkMessage, mavlink2
from companion.service.commands import CommandClient, CommandDeniedError, CommandError
from companion.service.connection import Connection, waiting_hint
from companion.service.failsafe import Assessment, Failsafe, Limits, Verdict, assess
from companion.service.flightlog import FlightLogWriter
from companion.service.identity import Health, companion_system_id, heartbeat_message
from companion.service.link import Link, open_link
from companion.service.mission import (
    MissionError,
    download_mission,
    latlon_to_xy,
    mission_waypoints,
)
from companion.service.modes import (
    AutopilotKind,
    Ownership,
    OwnState,
    VehicleMode,
    autopilot_kind,
    is_armed,
    is_guided,
    mode_name,
    set_mode_params,
)
from companion.service.notify import SystemdNotifier
from companion.service.setpoints import SetpointFrame, position_target
from companion.service.signing import SigningKeyError, SigningState, load_key, timestamp_now
from companion.service.statustext import Severity, StatusTexts, statustext_messages
from companion.service.telemetry import Telemetry

log = logging.getLogger("companion.service")

STREAM_IDS = {
    "ATTITUDE": mavlink2.MAVLINK_MSG_ID_ATTITUDE,
    "GLOBAL_POSITION_INT": mavlink2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
    "DISTANCE_SENSOR": mavlink2.MAVLINK_MSG_ID_DISTANCE_SENSOR,
    "HOME_POSITION": mavlink2.MAVLINK_MSG_ID_HOME_POSITION,
}
STREAMS_LOST_S = 2.0
"""Heartbeats without position this long: request the message rates again."""
EXIT_LINK = 3
"""`run`'s exit status when the link's port cannot be had (systemd: RestartPreventExitStatus)."""
LINK_RETRY_S = 2.0
"""A link that cannot be opened yet (serial device missing, host unknown): retried this often."""
_LINK_FATAL_ERRNOS = frozenset({errno.EADDRINUSE, errno.EACCES, errno.EADDRNOTAVAIL, errno.EPERM})
HEARTBEAT_WAIT_SAY_S = 2.0
"""No autopilot heard this long after start: say so (once)."""
MISSION_RETRY_S = 5.0
"""Auto start with an empty mission: download it again this often."""
MIN_BASE_POINT_SPACING_M = 0.5
"""Base points closer than this to the vehicle when it takes over are taken as passed."""


class PlannerLike(Protocol):
    """What the service needs of `companion.planner.Planner`."""

    def step(self, state: VehicleState, ranges_m: FloatArray, dt_s: float) -> StepResult: ...

    def set_desired_height(self, h_d_m: float) -> None: ...


PlannerFactory = Callable[[PlannerParams, SensorTable, Route, FloatArray], PlannerLike]


def default_planner_factory(
    params: PlannerParams, sensors: SensorTable, route: Route, start_position_enu: FloatArray
) -> PlannerLike:
    from companion.planner import Planner

    planner: PlannerLike = Planner(params, sensors, route, start_position_enu)
    return planner


@dataclass(frozen=True, slots=True)
class _Hold:
    position_enu: FloatArray
    yaw_rad: float


class ServiceCounters(Counter[str]):
    """All counters by dotted name: link.*, codec.*, conn.*, input.*, signing.*, service.*."""


class Service:
    """The companion service around one autopilot link.

    config: a validated ServiceConfig. link: an unopened Link (`open_link(...)` or a
    `MemoryLink`). planner_factory: builds the planner (default `companion.planner.Planner`).
    notifier: systemd notification (default from the environment).
    """

    def __init__(
        self,
        config: ServiceConfig,
        link: Link,
        *,
        planner_factory: PlannerFactory | None = None,
        notifier: SystemdNotifier | None = None,
    ) -> None:
        self.cfg = config
        self.link = link
        self.planner_factory = planner_factory or default_planner_factory
        self.notifier = notifier or SystemdNotifier()
        self.sim_time = config.control.time_source == "sim"
        self.clock: MonotonicClock | SimClock = SimClock() if self.sim_time else MonotonicClock()
        self.sensors = config.sensor_table()
        self.params = config.planner.to_params()
        self.period_s = 1.0 / config.control.rate_hz

        ident = config.identity
        sid = ident.system_id if isinstance(ident.system_id, int) else 1
        self.codec = MavCodec(sid, ident.component_id)
        self.conn = Connection(link, self.codec, self.clock.now)
        self.conn.on_message = self._on_message
        self.conn.on_unlocked = self._on_unlocked_heartbeat
        self.conn.on_other = self._on_other_heartbeat
        self._heard: dict[int, float] = {}
        self._listen_since: float | None = None
        self._ambiguous_said: list[int] = []
        self._strangers: set[int] = set()
        self._stranger_blocks = False
        fs = config.failsafe
        self.tel = Telemetry(
            self.sensors,
            max_speed_mps=fs.max_speed_mps,
            jump_accept_s=fs.jump_accept_s,
            max_jump_m=fs.max_position_jump_m,
            max_accepted_jump_m=fs.max_accepted_jump_m,
            median_samples=fs.range_median_samples,
        )
        ap = config.autopilot
        self.commands = CommandClient(self.conn, ap.command_timeout_s, ap.command_retries)
        self.ownership = Ownership(config.control.reengage)
        self.failsafe = Failsafe(fs.resume_after_s)
        self.limits = Limits(
            ap.heartbeat_timeout_s,
            fs.position_max_age_s,
            fs.attitude_max_age_s,
            fs.sensor_max_age_s,
        )
        optional = set(fs.optional_sensor_ids)
        self.required_sensors = [
            i for i, s in enumerate(self.sensors.specs) if s.sensor_id not in optional
        ]
        st = config.statustext
        self.texts = StatusTexts(st.max_per_s, st.burst, st.repeat_interval_s)
        self.flight_log: FlightLogWriter | None = None
        if config.logging.flight_log_dir is not None:
            self.flight_log = FlightLogWriter(
                config.logging.flight_log_dir,
                int(config.logging.max_file_mb * 1e6),
                config.logging.keep_files,
            )
        self.signing_state = SigningState(config.signing.state_file)

        self.counters = Counter[str]()
        self.kind: AutopilotKind | None = None
        self.vehicle_type = 0
        self.setpoint_frame: SetpointFrame | None = None
        self.health = Health.BOOT
        self.configured = False
        self.frame: LocalFrame | None = None
        self.frame_frozen = False
        self._frame_key: tuple[GeoPoint, int] | None = None
        self.route_source_points: FloatArray | None = None
        """Base points (n, 2) in `frame`, or None until known."""
        self._mission_geo: list[tuple[float, float]] | None = None
        self.planner: PlannerLike | None = None
        self.next_point = 0
        self._seg_start: FloatArray | None = None
        self.last_result: StepResult | None = None
        self.last_setpoint: Setpoint | None = None
        self.last_verdict = Assessment(Verdict.STOP, "starting")
        self.route_finished = asyncio.Event()
        self._finish_handled = False
        self._hold: _Hold | None = None
        self._planner_failed = False
        self._building = False
        self._build_gen = 0
        self._build_task: asyncio.Task[Any] | None = None
        self._route_error = ""
        self._built_h_d = self.params.h_d_m
        self._shift = np.zeros(3)
        """Sum of the accepted position jumps: planner frame = estimate - shift (ENU m)."""
        self._last_planner_xd: FloatArray | None = None
        self._configured_at = 0.0
        self._priming = False
        self._auto_busy = False
        self._auto_done = False
        self._auto_task: asyncio.Task[None] | None = None
        self._auto_allowed: set[str] | None = None
        self._auto_armed = False
        self._ap_text: tuple[float, str] | None = None
        self._ap_chunks: dict[int, dict[int, str]] = {}
        """The autopilot's latest STATUSTEXT of WARNING or worse: (time.monotonic, text)."""
        self._planner_t: float | None = None
        self._next_cycle_t: float | None = None
        self._last_cycle_wall: float | None = None
        self._last_hb_rx: float | None = None
        self._t0_wall = time.monotonic()
        self._stop = asyncio.Event()
        self._autopilot_seen = asyncio.Event()
        self._reconfigure = asyncio.Event()
        self._tasks: list[asyncio.Task[Any]] = []
        self._fatal: BaseException | None = None
        self._counter_snapshot: dict[str, int] = {}
        self._text_id = 0
        self._log_failing_said = ""

    # === public ============================================================================

    async def run(self) -> int:
        """Run until `stop()`; 0 on a clean stop, 1 after a fatal error, 2 for a bad signing
        key, EXIT_LINK (3) when the link's port cannot be had."""
        try:
            self._setup_signing()
        except SigningKeyError as exc:
            log.error("%s", exc)
            return 2
        failed = await self._open_link()
        if failed is not None:
            return failed
        log.info(
            "companion service on %s (%s time, %.0f Hz)",
            self.link.name,
            "simulator" if self.sim_time else "monotonic",
            self.cfg.control.rate_hz,
        )
        if self.flight_log is not None:
            self.flight_log.header(self._log_header())
        self._spawn(self._heartbeat_loop(), "heartbeat")
        self._spawn(self._supervise(), "supervisor")
        self._spawn(self._housekeeping(), "housekeeping")
        if not self.sim_time:
            self._spawn(self._cycle_loop(), "cycle")
        self.notifier.ready("waiting for autopilot")
        try:
            await self._stop.wait()
        finally:
            await self._shutdown()
        if self._fatal is not None:
            return 1
        return 0

    async def _open_link(self) -> int | None:
        """Open the link; None when open. A port that cannot be had (in use, not allowed,
        not an address of this machine) will not come free by retrying: one error line and
        EXIT_LINK, which the systemd unit does not restart on. Anything else (a serial device
        not there yet, a host name that does not resolve yet) is said once and retried every
        LINK_RETRY_S until it opens or the service is stopped (then 0)."""
        said = False
        while True:
            try:
                await self.conn.open()
                if said:
                    log.info("%s open", self.link.name)
                return None
            except OSError as exc:
                why = exc.strerror or str(exc)
                if exc.errno in _LINK_FATAL_ERRNOS:
                    log.error("cannot open %s: %s", self.link.name, why)
                    return EXIT_LINK
                if not said:
                    said = True
                    log.error(
                        "cannot open %s: %s; retrying every %.0f s",
                        self.link.name,
                        why,
                        LINK_RETRY_S,
                    )
                    self.notifier.ready(f"cannot open {self.link.name}: {why}; retrying")
            self.notifier.watchdog()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), LINK_RETRY_S)
            if self._stop.is_set():
                return 0

    def stop(self) -> None:
        """Ask `run` to return (safe from signal handlers and other tasks)."""
        self._stop.set()

    def set_desired_height(self, h_d_m: float) -> None:
        """Change H_d in flight; the planner ramps to it."""
        if not (math.isfinite(h_d_m) and h_d_m > 0):
            raise ValueError(f"h_d_m must be positive, got {h_d_m}")
        from dataclasses import replace

        self.params = replace(self.params, h_d_m=h_d_m)
        if self.planner is not None:
            self.planner.set_desired_height(h_d_m)

    def counter_values(self) -> dict[str, int]:
        """Every counter by dotted name (see docs/service.md)."""
        out: dict[str, int] = {}
        out.update({f"link.{k}": v for k, v in self.link.refresh_stats().as_dict().items()})
        out.update({f"codec.{k}": getattr(self.codec.counters, k) for k in _codec_fields()})
        out.update({f"conn.{k}": v for k, v in self.conn.counters.items()})
        out.update({f"input.{k}": v for k, v in self.tel.counters.items()})
        s = self.codec.mav.signing
        if self.codec.signing_enabled:
            out.update(
                {
                    "signing.good": int(s.goodsig_count),
                    "signing.bad": int(s.badsig_count),
                    "signing.unsigned_accepted": int(s.unsigned_count),
                    "signing.rejected": int(s.reject_count),
                }
            )
        out.update({f"statustext.{k}": getattr(self.texts, k) for k in ("sent", "dropped")})
        out.update({f"service.{k}": v for k, v in self.counters.items()})
        return out

    # === setup and shutdown ================================================================

    def _setup_signing(self) -> None:
        sg = self.cfg.signing
        if not sg.enabled:
            return
        assert sg.key_file is not None
        key = load_key(sg.key_file)
        allowed = [getattr(mavlink2, f"MAVLINK_MSG_ID_{n}") for n in sg.allow_unsigned]
        self.codec.enable_signing(
            key,
            link_id=sg.link_id,
            timestamp=self.signing_state.initial_timestamp(),
            allow_unsigned_msgids=allowed,
        )
        log.info("MAVLink signing on (link id %d)", sg.link_id)

    def _spawn(self, coro: Any, name: str) -> None:
        task = asyncio.create_task(coro, name=name)
        task.add_done_callback(self._task_done)
        self._tasks.append(task)

    def _task_done(self, task: asyncio.Task[Any]) -> None:
        if task.cancelled():
            return
        exc = task.exception()
        if exc is not None:
            log.error("task %s failed", task.get_name(), exc_info=exc)
            self._fatal = exc
            self._stop.set()

    async def _shutdown(self) -> None:
        self.notifier.stopping()
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        self._tasks.clear()
        self.conn.send(heartbeat_message(Health.POWEROFF))
        await asyncio.sleep(0)
        if self.codec.signing_enabled:
            self.signing_state.save(self.codec.signing_timestamp)
        if self.flight_log is not None:
            self.flight_log.write(
                {"type": "counters", "t": self.clock.now(), "counters": self.counter_values()}
            )
            self.flight_log.close()
        await self.conn.close()
        log.info("stopped")

    # === receive ===========================================================================

    def _on_unlocked_heartbeat(self, msg: MAVLinkMessage, t_rx: float) -> None:
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        ap = self.cfg.autopilot
        if isinstance(ap.system_id, int) and src_sys != ap.system_id:
            return
        if src_comp != ap.component_id:
            return
        kind = autopilot_kind(int(msg.autopilot))
        if kind is None or (ap.type != "auto" and kind.value != ap.type):
            self.counters["unsupported_autopilot"] += 1
            if self.counters["unsupported_autopilot"] == 1:
                log.warning(
                    "ignoring system %d: autopilot type %d (%s expected)",
                    src_sys,
                    int(msg.autopilot),
                    ap.type,
                )
            return
        if ap.system_id == "auto" and not self._choose_autopilot(src_sys, t_rx):
            return
        self.kind = kind
        self.vehicle_type = int(msg.type)
        self.conn.lock(src_sys, src_comp)
        sid = companion_system_id(self.cfg.identity.system_id, src_sys)
        self.codec.set_source(sid, self.cfg.identity.component_id)
        frame = self.cfg.autopilot.setpoint_frame
        if frame == "auto":
            self.setpoint_frame = (
                SetpointFrame.GLOBAL
                if kind is AutopilotKind.PX4
                else SetpointFrame.GLOBAL_RELATIVE_ALT
            )
        else:
            self.setpoint_frame = (
                SetpointFrame.GLOBAL if frame == "global" else SetpointFrame.GLOBAL_RELATIVE_ALT
            )
        log.info(
            "autopilot: %s (MAV_TYPE %d) at system %d component %d; we are %d/%d; "
            "setpoints in frame %d",
            kind.value,
            self.vehicle_type,
            src_sys,
            src_comp,
            sid,
            self.cfg.identity.component_id,
            int(self.setpoint_frame),
        )
        self._autopilot_seen.set()

    def _choose_autopilot(self, src_sys: int, t_rx: float) -> bool:
        """`autopilot.system_id: auto`: True when `src_sys` is the only autopilot heard for
        auto_id_listen_s since the first heartbeat; with more than one, choose none."""
        listen = self.cfg.autopilot.auto_id_listen_s
        self._heard[src_sys] = t_rx
        if self._listen_since is None:
            self._listen_since = t_rx
            if listen > 0:
                log.info(
                    "autopilot heartbeat from system %d: listening %.1f s for others",
                    src_sys,
                    listen,
                )
        if t_rx - self._listen_since < listen:
            return False
        recent = sorted(s for s, t in self._heard.items() if t_rx - t <= 2 * listen + 1.0)
        if len(recent) > 1:
            if self._ambiguous_said != recent:
                self._ambiguous_said = recent
                log.error(
                    "autopilots of systems %s heard and autopilot.system_id is auto: not "
                    "choosing one; set autopilot.system_id to the one this companion is wired to",
                    ", ".join(map(str, recent)),
                )
                self.notifier.status(f"several autopilots heard: {recent}; set system_id")
            return False
        return True

    def _on_other_heartbeat(self, msg: MAVLinkMessage, t_rx: float) -> None:
        """A heartbeat of another system after the lock: another autopilot means this
        companion may not be where it thinks; with system_id auto, no take-over from now."""
        if autopilot_kind(int(msg.autopilot)) is None or int(msg.type) in (6, 18):
            return  # a ground station or onboard computer
        sys_id = msg.get_srcSystem()
        if sys_id in self._strangers:
            return
        self._strangers.add(sys_id)
        if self.cfg.autopilot.system_id == "auto":
            self._stranger_blocks = True
            log.error(
                "a second autopilot (system %d) is heard besides system %s: no take-over and no "
                "auto start until autopilot.system_id is set",
                sys_id,
                self.conn.target_system,
            )
            self._say(f"second autopilot {sys_id} heard: set system_id", Severity.CRITICAL)
        else:
            log.warning("another autopilot (system %d) is heard; ignored", sys_id)

    def _on_message(self, msg: MAVLinkMessage, t_rx: float) -> None:
        mtype = msg.get_type()
        if mtype == "TIMESYNC":
            self._on_timesync(msg)
            return
        if mtype == "HEARTBEAT":
            self._on_autopilot_heartbeat(t_rx)
        reboots, jumps = self.tel.reboots, self.tel.jumps_accepted
        self.tel.update(msg, t_rx)
        if self.tel.notices:
            for text in self.tel.notices:
                self._say(text, Severity.ERROR)
            self.tel.notices.clear()
        if self.tel.reboots != reboots:
            log.warning("autopilot time went backwards: reboot? reconfiguring")
            self._reconfigure.set()
        if self.tel.jumps_accepted != jumps:
            self._position_jumped()
        if mtype == "HEARTBEAT":
            if self.ownership.engaged:
                self._update_ownership(self.clock.now(), allow_engage=False)
            self._watch_auto_start()
        elif mtype == "STATUSTEXT" and int(msg.severity) <= Severity.WARNING:
            self._autopilot_text(msg)

    def _autopilot_text(self, msg: MAVLinkMessage) -> None:
        """Keep the autopilot's latest warning, its chunks (MAVLink 2 id/chunk_seq) joined."""
        raw = msg.text
        text = (raw if isinstance(raw, str) else bytes(raw).decode("utf-8", "replace")).rstrip(
            "\x00"
        )
        text_id, seq = int(getattr(msg, "id", 0)), int(getattr(msg, "chunk_seq", 0))
        if text_id:
            parts = self._ap_chunks.setdefault(text_id, {})
            if len(self._ap_chunks) > 8:  # bounded: keep the newest few
                self._ap_chunks.pop(next(iter(self._ap_chunks)))
            if seq < 16:
                parts[seq] = text
            text = "".join(parts[i] for i in sorted(parts))
        self._ap_text = (time.monotonic(), text)

    def _position_jumped(self) -> None:
        """The position estimate jumped for good (estimator reset). The planner keeps its
        own frame, continuous through the jump (as ArduPilot's position controller shifts
        its targets on an EKF reset): positions given to it are the estimate minus the
        jumps so far, its setpoints are sent plus them. A plan, the obstacles it remembers
        and the route stay where they were in the world; a hold restarts where the vehicle
        is now."""
        jump = self.tel.last_jump_enu
        self._shift = self._shift + jump
        self._hold = None
        log.warning(
            "position estimate jumped %s m: the planner's frame moves with it", np.round(jump, 2)
        )
        self._say("position jump: plan kept", Severity.WARNING)

    def _on_autopilot_heartbeat(self, t_rx: float) -> None:
        last = self._last_hb_rx
        if last is not None and t_rx - last > self.limits.heartbeat_timeout_s:
            log.warning("autopilot heartbeat back after %.1f s", t_rx - last)
            self._reconfigure.set()
        self._last_hb_rx = t_rx

    def _on_timesync(self, msg: MAVLinkMessage) -> None:
        if int(msg.tc1) != 0:
            return  # an answer to someone's request; we send none
        ts1 = int(msg.ts1)
        if self.sim_time:
            self.clock.set(ts1 * 1e-9)  # type: ignore[union-attr]
            self._sim_tick(self.clock.now())
            tc1 = max(1, ts1)
        else:
            tc1 = max(1, time.monotonic_ns())
        self.conn.send(mavlink2.MAVLink_timesync_message(tc1, ts1))

    # === tasks =============================================================================

    async def _heartbeat_loop(self) -> None:
        period = 1.0 / self.cfg.identity.heartbeat_hz
        while True:
            self.conn.send(heartbeat_message(self.health))
            await asyncio.sleep(period)

    async def _cycle_loop(self) -> None:
        next_t = self.clock.now()
        while True:
            now = self.clock.now()
            self._safe_tick(now)
            next_t += self.period_s
            delay = next_t - self.clock.now()
            if delay < 0:
                self.counters["cycle_overruns"] += 1
                next_t = self.clock.now()
                delay = 0.0
            await asyncio.sleep(delay)

    def _sim_tick(self, now: float) -> None:
        if self._next_cycle_t is None or now >= self._next_cycle_t - 1e-9:
            self._safe_tick(now)
            nxt = (self._next_cycle_t if self._next_cycle_t is not None else now) + self.period_s
            self._next_cycle_t = nxt if nxt > now else now + self.period_s

    async def _housekeeping(self) -> None:
        """Once a second (wall time): watchdog, flight log, signing state, counters."""
        wd = self.notifier.watchdog_interval_s
        period = min(1.0, wd) if wd else 1.0
        last_save = time.monotonic()
        last_counters = time.monotonic()
        while True:
            await asyncio.sleep(period)
            wall = time.monotonic()
            if self._loop_healthy(wall):
                self.notifier.watchdog()
            if self.codec.signing_enabled:
                self.codec.advance_signing_clock(timestamp_now())
                if wall - last_save >= 10.0:
                    self.signing_state.save(self.codec.signing_timestamp)
                    last_save = wall
            if wall - last_counters >= 10.0:
                last_counters = wall
                self._report_counters()
            if self.flight_log is not None:
                self.flight_log.flush()
                failing = self.flight_log.failing
                if failing != self._log_failing_said:
                    if failing:
                        self._say(f"flight log failing: {failing}", Severity.WARNING)
                    else:
                        self._say("flight log writing again")
                    self._log_failing_said = failing

    def _loop_healthy(self, wall: float) -> bool:
        if self.sim_time:
            return True  # ticks come from the simulator; this task running is the proof
        last = self._last_cycle_wall
        return last is not None and wall - last < max(1.0, 5 * self.period_s)

    def _report_counters(self) -> None:
        values = self.counter_values()
        for name, value in values.items():
            prev = self._counter_snapshot.get(name, 0)
            if value > prev and _is_problem(name):
                log.warning("%s: +%d (total %d)", name, value - prev, value)
        self._counter_snapshot = values
        if self.flight_log is not None:
            self.flight_log.write({"type": "counters", "t": self.clock.now(), "counters": values})

    # === supervisor: configure, route, auto start ==========================================

    async def _supervise(self) -> None:
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._autopilot_seen.wait(), HEARTBEAT_WAIT_SAY_S)
        if not self._autopilot_seen.is_set():
            waiting = f"waiting for autopilot heartbeat on {self.link.name}"
            log.warning("%s (%s)", waiting, waiting_hint(self.link.name))
            self.notifier.status(waiting)
            await self._autopilot_seen.wait()
            log.info("autopilot heartbeat heard on %s", self.link.name)
        while True:
            self._reconfigure.clear()
            self.configured = False
            try:
                await self._configure()
            except (CommandError, MissionError) as exc:
                log.warning("configuration failed: %s; retrying", exc)
                self._say(f"config failed: {exc}", Severity.WARNING)
                await asyncio.sleep(2.0)
                continue
            self.configured = True
            self._configured_at = self.clock.now()
            self.notifier.status("ready")
            if self.cfg.control.auto_start.enabled and not self._auto_done:
                self._auto_done = True
                await self._auto_start()
            await self._reconfigure.wait()

    async def _configure(self) -> None:
        failed = []
        for name, rate in self.cfg.autopilot.streams_hz.model_dump().items():
            try:
                await self.commands.set_message_interval(STREAM_IDS[name], float(rate))
            except CommandError as exc:
                self.counters["interval_request_failed"] += 1
                failed.append(name)
                log.warning("message interval for %s: %s", name, exc)
        if failed:
            self._say(f"rate request failed: {','.join(failed)}", Severity.WARNING)
        home_id = STREAM_IDS["HOME_POSITION"]
        said = False
        while True:
            try:
                await self.commands.request_message(home_id)
            except CommandError as exc:
                self.counters["home_request_failed"] += 1
                log.warning("HOME_POSITION request: %s", exc)
            ready = await self._wait_for(
                lambda: self.tel.home is not None and self.tel.position is not None, 2.0
            )
            if ready:
                break
            if not said:
                said = True
                self._say("waiting for home and position")
        self._update_frame()
        if self.cfg.route.source == "mission":
            await self._load_mission()
        self._update_frame()

    async def _load_mission(self, quiet: bool = False) -> None:
        """Download the autopilot's mission; a mission that breaks the route bounds counts
        as no mission (said, never flown). quiet: say nothing when it is still empty."""
        items = await download_mission(
            self.conn, self.cfg.autopilot.command_timeout_s, self.cfg.autopilot.command_retries
        )
        assert self.kind is not None
        geo = mission_waypoints(items, self.kind)
        problem = route_problem(latlon_points_xy(geo), origin_is_home=False) if geo else ""
        if problem:
            self._say(f"mission refused: {problem}", Severity.ERROR)
            geo = []
        self._mission_geo = geo
        n = len(geo)
        if n == 0:
            if not quiet:
                self._say("mission has no waypoints", Severity.WARNING)
        else:
            self._say(f"mission: {n} waypoints")
        self._update_frame()

    async def _wait_for(self, pred: Callable[[], bool], timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not pred():
            if time.monotonic() >= deadline:
                return False
            # short polls: in simulator time the world moves on while we wait
            await asyncio.sleep(0.002 if self.sim_time else 0.02)
        return True

    async def _sleep_service_time(self, duration_s: float) -> None:
        """Sleep on the service clock (simulated time in sim mode)."""
        if not self.sim_time:
            await asyncio.sleep(duration_s)
            return
        end = self.clock.now() + duration_s
        while self.clock.now() < end:
            await asyncio.sleep(0.001)

    async def _auto_start(self) -> None:
        """Run auto start as a task that a mode change by anyone else cancels at once."""
        task = asyncio.create_task(self._auto_start_steps(), name="auto-start")
        self._auto_task = task
        try:
            await asyncio.wait({task})
        finally:
            if not task.done():  # we are being cancelled (shutdown): so is it
                task.cancel()
            self._auto_task = None
            self._auto_allowed = None
            self._auto_busy = False
            self._priming = False
        if task.cancelled():
            self.counters["auto_start_aborted"] += 1
            return
        exc = task.exception()
        if exc is not None:  # a bug in auto start must not end the process: report it
            self.counters["auto_start_failed"] += 1
            log.error("auto start failed", exc_info=exc)
            self._say(f"auto start failed: internal error {type(exc).__name__}", Severity.ERROR)

    def _allow_modes(self, *names: str) -> None:
        """Auto start: the modes the vehicle may be in now; any other aborts it."""
        self._auto_allowed = set(names)

    def _current_mode(self) -> str | None:
        hb = self.tel.heartbeat
        if hb is None or self.kind is None:
            return None
        return mode_name(self.kind, self.vehicle_type, hb.base_mode, hb.custom_mode)

    def _watch_auto_start(self) -> None:
        """On each autopilot heartbeat during auto start: a mode we did not ask for (a pilot,
        a ground station, a failsafe) or a disarm after arming ends auto start at once."""
        task, allowed = self._auto_task, self._auto_allowed
        if task is None or task.done() or allowed is None:
            return
        hb = self.tel.heartbeat
        mode = self._current_mode()
        if hb is None or mode is None:
            return
        why = ""
        if mode not in allowed:
            why = f"mode changed to {mode}"
        elif self._auto_armed and not hb.armed:
            why = "disarmed"
        if why:
            self._auto_allowed = None
            task.cancel()
            self._say(f"auto start aborted: {why}", Severity.WARNING)

    async def _wait_ready_to_arm(self, deadline: float) -> None:
        """Until every required input (heartbeat, position, attitude, each required range
        sensor) is fresh, saying once what is missing; CommandError at the deadline."""
        said = ""
        while True:
            a = assess(self.clock.now(), self.tel, self.limits, self.required_sensors)
            if a.verdict is Verdict.RUN:
                return
            if time.monotonic() >= deadline:
                raise CommandError(400, f"not arming: {a.reason}")
            if a.reason != said:
                said = a.reason
                self._say(f"auto start: waiting, {a.reason}")
            await asyncio.sleep(0.05)

    async def _wait_for_route(self) -> bool:
        """Until there is a base point to fly to (farther than MIN_BASE_POINT_SPACING_M from
        the vehicle), saying so once; a mission is downloaded again every MISSION_RETRY_S.
        False when the configured route has nothing to fly (it will not change)."""
        said = False
        while True:
            self._update_frame()
            state = self._vehicle_state()
            pts = self.route_source_points
            if state is not None and pts is not None and len(pts):
                gaps = np.hypot(*(pts - state.position_enu[:2]).T)
                if float(np.max(gaps)) >= MIN_BASE_POINT_SPACING_M:
                    return True
            if not said:
                said = True
                what = "mission empty" if self.cfg.route.source == "mission" else "at the end"
                self._say(f"auto start: no route ({what}): not taking off", Severity.WARNING)
            if self.cfg.route.source != "mission":
                return False
            await asyncio.sleep(MISSION_RETRY_S)
            try:
                await self._load_mission(quiet=True)
            except MissionError as exc:
                log.info("mission download: %s", exc)

    async def _auto_start_steps(self) -> None:
        """Arm, take off and hand over to the route. Refusals (denied, pre-arm checks, no
        answer) are retried until arm_timeout_s; the autopilot's reason is shown in full."""
        assert self.kind is not None
        a = self.cfg.control.auto_start
        alt = a.takeoff_alt_m if a.takeoff_alt_m is not None else self.params.h_d_m
        hb = self.tel.heartbeat
        if hb is not None and hb.armed:
            self._say("auto start: already armed, waiting for pilot")
            return
        initial = self._current_mode()
        if initial is None:
            return
        if self._stranger_blocks:
            self._say("auto start: not with a second autopilot heard", Severity.ERROR)
            return
        self._auto_busy = True
        self._auto_armed = False
        self._allow_modes(initial)
        deadline = time.monotonic() + a.arm_timeout_s
        try:
            if not await self._wait_for_route():
                return
            self._say("auto start")
            await self._wait_ready_to_arm(deadline)
            if self.kind is AutopilotKind.ARDUPILOT:
                # GUIDED is refused until the autopilot has a position estimate: retry.
                guided = set_mode_params(self.kind, "guided", self.vehicle_type)
                self._allow_modes(initial, "GUIDED")
                await self._with_retries(
                    "GUIDED", lambda: self.commands.set_mode(guided), deadline, a.arm_retry_s
                )
                if not await self._wait_for(self._guided, 5.0):
                    raise CommandError(176, "mode did not change to GUIDED")
                self._allow_modes("GUIDED")
            await self._wait_ready_to_arm(deadline)
            await self._with_retries(
                "arming", lambda: self.commands.arm(True), deadline, a.arm_retry_s
            )
            await self._wait_for(
                lambda: self.tel.heartbeat is not None and self.tel.heartbeat.armed, 3
            )
            self._auto_armed = True
            home = self.tel.home
            assert home is not None
            target = alt if self.kind is AutopilotKind.ARDUPILOT else home.alt_amsl_m + alt
            if self.kind is AutopilotKind.PX4:
                self._allow_modes(initial, "AUTO.TAKEOFF", "AUTO.LOITER")
            try:
                await self.commands.takeoff(target)
            except CommandDeniedError:
                # A retry after a lost ack is refused once the first attempt has the vehicle
                # climbing (ArduCopter: "already flying"); that is success.
                if not self._climbing():
                    raise
                log.info("take-off retry refused while climbing: the first attempt worked")
            ok = await self._wait_for(
                lambda: (
                    self.tel.position is not None and self.tel.position.relative_alt_m >= 0.9 * alt
                ),
                a.takeoff_timeout_s,
            )
            if not ok:
                raise CommandError(22, "take-off did not reach its altitude")
            if self.kind is AutopilotKind.PX4:
                self._priming = True
                await self._sleep_service_time(a.prestream_s)
                self._allow_modes(initial, "AUTO.TAKEOFF", "AUTO.LOITER", "OFFBOARD")
                await self.commands.set_mode(set_mode_params(self.kind, "guided"))
                if not await self._wait_for(self._guided, 5.0):
                    raise CommandError(176, "mode did not change to OFFBOARD")
        except CommandError as exc:
            self.counters["auto_start_failed"] += 1
            why = self._autopilot_reason()
            self._say(f"auto start failed: {exc}" + (f" ({why})" if why else ""), Severity.ERROR)

    def _autopilot_reason(self) -> str:
        """The autopilot's latest STATUSTEXT of warning or worse in the last 10 s, in full."""
        if self._ap_text is None:
            return ""
        t, text = self._ap_text
        return text if time.monotonic() - t <= 10.0 else ""

    async def _with_retries(
        self, what: str, command: Callable[[], Awaitable[Any]], deadline: float, retry_s: float
    ) -> None:
        """Send a command until the autopilot accepts it or the (time.monotonic) deadline
        passes: a refusal (DENIED, FAILED, TEMPORARILY_REJECTED), a pre-arm STATUSTEXT and
        no answer are all retried; each new reason is logged in full."""
        last = ""
        while True:
            try:
                await command()
                return
            except CommandError as exc:
                if time.monotonic() >= deadline:
                    raise
                why = self._autopilot_reason()
                reason = f"{exc}" + (f"; autopilot: {why}" if why else "")
                if reason != last:
                    last = reason
                    log.warning("%s refused (%s); retrying until arm_timeout_s", what, reason)
                await self._sleep_service_time(retry_s)  # simulated time in sim mode

    def _climbing(self) -> bool:
        pos = self.tel.position
        return pos is not None and (pos.relative_alt_m > 0.3 or pos.velocity_ned_mps[2] < -0.2)

    def _guided(self) -> bool:
        hb = self.tel.heartbeat
        return (
            hb is not None
            and self.kind is not None
            and is_guided(self.kind, hb.base_mode, hb.custom_mode)
        )

    # === the cycle =========================================================================

    def _safe_tick(self, now: float) -> None:
        """`_tick`, but a bug in it holds the vehicle and is reported instead of ending the
        process (which would leave the vehicle in GUIDED/OFFBOARD with nobody commanding)."""
        try:
            self._tick(now)
        except Exception:
            self.counters["cycle_errors"] += 1
            if self.counters["cycle_errors"] <= 5:
                log.exception("cycle failed; holding")
            self._say("internal error: holding", Severity.CRITICAL)
            with contextlib.suppress(Exception):
                if self.ownership.engaged:
                    sp = self._hold_setpoint()
                    if sp is not None:
                        self._send_setpoint(sp, now)
                self._send_texts(now)

    def _tick(self, now: float) -> None:
        """One cycle at service time `now`: ownership, failsafe, planner or hold, setpoint."""
        self._last_cycle_wall = time.monotonic()
        self.counters["cycles"] += 1
        if not self.frame_frozen:
            self._update_frame()
        self._check_streams(now)
        events = self._update_ownership(
            now,
            allow_engage=self.configured and not self._auto_busy and not self._stranger_blocks,
        )
        assessment = assess(now, self.tel, self.limits, self.required_sensors)
        verdict, fs_events = self.failsafe.update(now, assessment)
        commanding = self.ownership.engaged or self._priming
        if commanding:
            for e in fs_events:
                sev = Severity.INFO if e.startswith("resumed") else Severity.CRITICAL
                self._say(e, sev)
        result: StepResult | None = None
        sp: Setpoint | None = None
        sp_kind: str | None = None
        if self.ownership.engaged:
            if verdict.verdict is Verdict.RUN:
                result = self._step_planner(now)
                if result is not None:
                    sp, sp_kind = result.setpoint, "planner"
                else:
                    sp, sp_kind = self._hold_setpoint(), "hold"
            elif verdict.verdict is Verdict.HOLD:
                sp, sp_kind = self._hold_setpoint(), "hold"
                self._planner_t = None
            else:
                self._planner_t = None
            if sp_kind == "hold":
                self.counters["hold_cycles"] += 1
        elif self._priming and verdict.verdict is not Verdict.STOP:
            sp, sp_kind = self._hold_setpoint(), "prime"
        if verdict.verdict is Verdict.RUN and sp_kind != "hold":
            self._hold = None
        if sp is not None:
            self._send_setpoint(sp, now)
        self.health = self._health(verdict.verdict, sp_kind)
        self.last_verdict = verdict
        self._send_texts(now)
        if self.flight_log is not None:
            self.flight_log.write(self._cycle_record(now, verdict, result, sp, sp_kind, events))

    def _send_texts(self, now: float) -> None:
        for sev, text in self.texts.drain(now):
            self._text_id = self._text_id % 65535 + 1
            for msg in statustext_messages(sev, text, self._text_id):
                self.conn.send(msg)

    def _check_streams(self, now: float) -> None:
        """Heartbeats but no position for STREAMS_LOST_S: the autopilot forgot our message
        rates (a reboot shorter than the heartbeat timeout, before any stamped message could
        show time going back): ask for them again."""
        hb, pos = self.tel.heartbeat, self.tel.position
        if not self.configured or hb is None or now - hb.t_rx > self.limits.heartbeat_timeout_s:
            return
        if pos is not None and now - pos.t_rx <= STREAMS_LOST_S:
            return
        if now - self._configured_at <= STREAMS_LOST_S:
            return
        self.counters["streams_rerequested"] += 1
        log.warning(
            "heartbeats but no position for %.1f s: requesting the rates again", STREAMS_LOST_S
        )
        self._configured_at = now
        self._reconfigure.set()

    def _health(self, verdict: Verdict, sp_kind: str | None) -> Health:
        if self.ownership.engaged:
            if verdict is Verdict.STOP:
                return Health.EMERGENCY
            if verdict is Verdict.HOLD or self._planner_failed:
                return Health.CRITICAL
            return Health.ACTIVE
        if self._priming:
            return Health.ACTIVE
        return Health.STANDBY if self.configured else Health.BOOT

    def _update_ownership(self, now: float, allow_engage: bool) -> list[str]:
        hb = self.tel.heartbeat
        if hb is None or self.kind is None or now - hb.t_rx > self.limits.heartbeat_timeout_s:
            return []
        pos = self.tel.position
        mode = VehicleMode(
            guided=is_guided(self.kind, hb.base_mode, hb.custom_mode),
            armed=is_armed(hb.base_mode),
            high_enough=pos is not None
            and pos.relative_alt_m >= self.cfg.control.min_engage_height_m,
            name=mode_name(self.kind, self.vehicle_type, hb.base_mode, hb.custom_mode),
        )
        before = self.ownership.state
        events = self.ownership.update(mode, allow_engage=allow_engage)
        after = self.ownership.state
        engaging = before is not OwnState.ENGAGED and after is OwnState.ENGAGED
        if engaging and not self._engage(now):
            self.ownership.release("cannot fly: no route")
        elif engaging and self.failsafe.current.verdict is not Verdict.RUN:
            # a hold (or stop) that began before the take-over: announced like any other
            f = self.failsafe.current
            self._say(f"{f.verdict.value.upper()}: {f.reason}", Severity.CRITICAL)
        if before is OwnState.ENGAGED and after is not OwnState.ENGAGED:
            self.counters["released"] += 1
            self._planner_t = None
        for e in events:
            self._say(e, Severity.NOTICE if after is OwnState.ENGAGED else Severity.WARNING)
        return events

    def _vehicle_state(self) -> VehicleState | None:
        pos, att = self.tel.position, self.tel.attitude
        if pos is None or att is None or self.frame is None:
            return None
        e, n, u = self.frame.to_enu(GeoPoint(pos.lat_deg, pos.lon_deg, pos.alt_amsl_m))
        r, p, y = attitude_ned_to_enu(att.roll_rad, att.pitch_rad, att.yaw_rad)
        return VehicleState(np.array([e, n, u]), r, p, y)

    def _update_frame(self) -> None:
        """Anchor the local frame at home (until the first take-over freezes it)."""
        home = self.tel.home
        if home is None or self.frame_frozen:
            return
        origin = GeoPoint(home.lat_deg, home.lon_deg, home.alt_amsl_m)
        key = (origin, id(self._mission_geo))
        if key == self._frame_key:
            return
        self._frame_key = key
        self.frame = LocalFrame(origin)
        r = self.cfg.route
        if r.source == "config":
            if r.points is not None:
                self.route_source_points = np.array(r.points, dtype=np.float64).reshape(-1, 2)
            else:
                assert r.points_latlon is not None
                self.route_source_points = latlon_to_xy(list(r.points_latlon), self.frame)
        elif self._mission_geo is not None:
            self.route_source_points = latlon_to_xy(self._mission_geo, self.frame)

    def _engage(self, now: float) -> bool:
        """Build the planner from the vehicle's position; False if there is nothing to fly."""
        self._update_frame()
        state = self._vehicle_state()
        if state is None or self.route_source_points is None:
            return False
        if not self.frame_frozen:
            self.frame_frozen = True
            assert self.frame is not None
            o = self.frame.origin
            if self.flight_log is not None:
                self.flight_log.write(
                    {
                        "type": "frame",
                        "t": now,
                        "origin": [o.lat_deg, o.lon_deg, o.alt_m],
                        "route": self.route_source_points,
                    }
                )
        self._start_planner(self._to_planner(state))
        return True

    def _to_planner(self, state: VehicleState) -> VehicleState:
        if not self._shift.any():
            return state
        return VehicleState(
            state.position_enu - self._shift, state.roll_rad, state.pitch_rad, state.yaw_rad
        )

    def _from_planner(self, result: StepResult) -> StepResult:
        if not self._shift.any():
            return result
        sp = result.setpoint
        moved = Setpoint(sp.position_enu + self._shift, sp.velocity_enu, sp.yaw_rad, sp.pitch_rad)
        return StepResult(moved, result.diagnostics)

    def _start_planner(self, state: VehicleState) -> None:
        """A new planner from `state` (in the planner's frame, see `_position_jumped`)."""
        pts = self.route_source_points
        assert pts is not None
        here = state.position_enu[:2]
        remaining = pts[self.next_point :]
        while len(remaining) and np.hypot(*(remaining[0] - here)) < MIN_BASE_POINT_SPACING_M:
            remaining = remaining[1:]
            self.next_point += 1
        if len(remaining) == 0:
            self.planner = None
            self._say("route complete: holding")
            self._hold = _Hold(state.position_enu + self._shift, state.yaw_rad)
            self.route_finished.set()
            return
        arrival = self.cfg.route.arrival_heading_deg
        points = np.vstack([here, remaining])
        heading = state.yaw_rad
        arrival_rad = None if arrival is None else math.radians(arrival)
        start = state.position_enu.copy()
        self.planner = None
        self._build_gen += 1
        gen = self._build_gen
        self._built_h_d = self.params.h_d_m
        self._seg_start = here.copy()
        self._planner_t = None
        self.last_setpoint = None  # X_d starts at the vehicle: nothing to compare on resume
        self._last_planner_xd = None

        params = self.params

        def build() -> tuple[PlannerLike, Route]:
            route = Route(points, heading, arrival_rad)
            return self.planner_factory(params, self.sensors, route, start), route

        if self.sim_time:
            # lockstep: the simulator waits for us, so building here costs no real-time cycle
            try:
                self._planner_built(gen, *build())
            except Exception as exc:
                self._route_failed(exc)
            return
        # real time: a long route must not stop heartbeats and setpoints (hold meanwhile)
        self._building = True
        task = asyncio.get_running_loop().create_task(asyncio.to_thread(build))
        task.add_done_callback(lambda t: self._build_done(gen, t))
        self._build_task = task

    def _build_done(self, gen: int, task: asyncio.Task[tuple[PlannerLike, Route]]) -> None:
        if gen != self._build_gen or task.cancelled():
            return
        self._building = False
        exc = task.exception()
        if exc is not None:
            self._route_failed(exc)
            return
        self._planner_built(gen, *task.result())

    def _planner_built(self, gen: int, planner: PlannerLike, route: Route) -> None:
        if gen != self._build_gen:
            return
        self.planner = planner
        self._route_error = ""
        if self.params.h_d_m != self._built_h_d:  # changed while it was being built
            planner.set_desired_height(self.params.h_d_m)
        if self.flight_log is not None:
            self.flight_log.write(
                {
                    "type": "route",
                    "t": self.clock.now(),
                    "points": route.base_points,
                    "start_heading_rad": route.start_heading_rad,
                    "arrival_heading_rad": route.arrival_heading_rad,
                }
            )
        self.counters["planner_starts"] += 1
        log.info(
            "planner started at %s with %d base points",
            np.round(route.base_points[0], 2),
            len(route.base_points) - 1,
        )

    def _route_failed(self, exc: BaseException) -> None:
        """The route or planner could not be built: hold where the vehicle is and say why
        (never end the process with the vehicle in GUIDED/OFFBOARD)."""
        self.planner = None
        self._building = False
        self._planner_failed = True
        self._route_error = str(exc)
        self.counters["route_build_failed"] += 1
        log.error("cannot fly the route: %s; holding", exc)
        self._say(f"cannot fly route: {exc}: holding", Severity.CRITICAL)

    def _step_planner(self, now: float) -> StepResult | None:
        estimate = self._vehicle_state()
        if estimate is None:
            return None
        state = self._to_planner(estimate)
        if (
            self._planner_t is None
            and self.planner is not None
            and self._last_planner_xd is not None
        ):
            # resuming after a hold, stop or release: restart if X_d is far from the vehicle
            gap = float(np.linalg.norm(self._last_planner_xd - state.position_enu))
            if gap > self.cfg.control.restart_distance_m:
                log.info("X_d %.1f m from the vehicle: restarting the planner here", gap)
                self._start_planner(state)
        if self.planner is None:
            return None  # route complete, being built, or not flyable: the caller holds
        dt = self.period_s if self._planner_t is None else now - self._planner_t
        dt = min(max(dt, 0.0), 3.0 * self.period_s)
        self._planner_t = now
        ranges = self.tel.range_vector(now, self.limits.sensor_max_age_s)
        try:
            result = self.planner.step(state, ranges, dt)
            if not _finite_setpoint(result.setpoint):
                raise FloatingPointError(f"non-finite setpoint {result.setpoint}")
            self._planner_failed = False
        except Exception:  # a planner bug must not crash the service: hold instead
            self._planner_failed = True
            self.counters["planner_errors"] += 1
            if self.counters["planner_errors"] <= 5:
                log.exception("planner step failed; holding")
            self._say("planner error: holding", Severity.CRITICAL)
            return None
        self._last_planner_xd = np.array(result.setpoint.position_enu, dtype=np.float64)
        result = self._from_planner(result)
        self.last_result = result
        d = result.diagnostics
        for e in d.events:
            self._say(e, Severity.NOTICE)
        self._advance_progress(state.position_enu[:2])
        if d.finished and not self._finish_handled:
            self._finish_handled = True
            self.route_finished.set()
            self._on_finish()
        return result

    def _advance_progress(self, xy: FloatArray) -> None:
        """Count base points passed (projection past the point, or within 1 m of it)."""
        pts = self.route_source_points
        if pts is None or self._seg_start is None:
            return
        while self.next_point < len(pts):
            a, b = self._seg_start, pts[self.next_point]
            ab = b - a
            length2 = float(ab @ ab)
            t = float((xy - a) @ ab) / length2 if length2 > 1e-9 else 1.0
            if t < 1.0 and np.hypot(*(b - xy)) > 1.0:
                return
            self._seg_start = b.copy()
            self.next_point += 1

    def _on_finish(self) -> None:
        action = self.cfg.control.on_finish
        if action == "hold":
            self._say("route complete: holding")
            return
        self._say(f"route complete: {action}")
        assert self.kind is not None
        params = set_mode_params(self.kind, action, self.vehicle_type)

        async def change() -> None:
            try:
                await self.commands.set_mode(params)
            except CommandError as exc:
                self._say(f"{action} refused: {exc}", Severity.ERROR)

        self._spawn(change(), f"on-finish-{action}")

    def _hold_setpoint(self) -> Setpoint | None:
        if self._hold is None:
            state = self._vehicle_state()
            if state is None:
                pos = self.tel.position
                if pos is None or self.frame is None:
                    return None
                e, n, u = self.frame.to_enu(GeoPoint(pos.lat_deg, pos.lon_deg, pos.alt_amsl_m))
                yaw = 0.0 if self.last_setpoint is None else self.last_setpoint.yaw_rad
                self._hold = _Hold(np.array([e, n, u]), yaw)
            else:
                self._hold = _Hold(state.position_enu.copy(), state.yaw_rad)
        h = self._hold
        return Setpoint(h.position_enu, np.zeros(3), wrap_pi(h.yaw_rad), 0.0)

    def _send_setpoint(self, sp: Setpoint, now: float) -> None:
        home = self.tel.home
        if self.frame is None or home is None or self.setpoint_frame is None:
            return
        if not _finite_setpoint(sp):  # never on the wire, whatever produced it
            self.counters["setpoints_refused_nonfinite"] += 1
            return
        ts, tc = self.conn.target_system, self.conn.target_component
        assert ts is not None and tc is not None
        msg = position_target(
            sp.position_enu,
            sp.velocity_enu,
            sp.yaw_rad,
            frame=self.frame,
            mav_frame=self.setpoint_frame,
            home_alt_amsl_m=home.alt_amsl_m,
            time_boot_ms=self._boot_ms(now),
            target_system=ts,
            target_component=tc,
        )
        self.conn.send(msg)
        self.last_setpoint = sp
        self.counters["setpoints_sent"] += 1

    def _boot_ms(self, now: float) -> int:
        return int((now if self.sim_time else now - self._t0_wall) * 1000.0)

    # === output helpers ====================================================================

    def _say(self, text: str, severity: Severity = Severity.INFO) -> None:
        self.texts.post(self.clock.now(), text, severity)

    def _cycle_record(
        self,
        now: float,
        verdict: Assessment,
        result: StepResult | None,
        sp: Setpoint | None,
        sp_kind: str | None,
        events: list[str],
    ) -> dict[str, Any]:
        state = self._vehicle_state()
        d = result.diagnostics if result is not None else None
        return {
            "type": "cycle",
            "t": now,
            "health": self.health.name.lower(),
            "own": self.ownership.state.value,
            "verdict": verdict.verdict.value,
            "reason": verdict.reason,
            "pos": None if state is None else state.position_enu,
            "rpy": None if state is None else [state.roll_rad, state.pitch_rad, state.yaw_rad],
            "ranges": self.tel.range_vector(now, self.limits.sensor_max_age_s),
            "sp": None
            if sp is None
            else {
                "p": sp.position_enu,
                "v": sp.velocity_enu,
                "yaw": sp.yaw_rad,
                "pitch": sp.pitch_rad,
            },
            "sp_kind": sp_kind,
            "decision": None if d is None else str(d.decision),
            "mode": None if d is None else str(d.mode),
            "side": None if d is None else str(d.side),
            "min_range": None if d is None else d.min_range_m,
            "phi_star": None if d is None else d.phi_star_rad,
            "phi_star_threshold": None if d is None else d.threshold_rad,
            "phi_d": None if d is None else d.phi_d_rad,
            "v_ref": None if d is None else d.speed_ref_mps,
            "replanned": bool(d.replanned) if d is not None else False,
            "finished": bool(d.finished) if d is not None else False,
            "events": list(events) + (list(d.events) if d is not None else []),
        }

    def _log_header(self) -> dict[str, Any]:
        return {
            "link": self.link.name,
            "rate_hz": self.cfg.control.rate_hz,
            "time_source": self.cfg.control.time_source,
            "sensors": [
                {
                    "id": s.sensor_id,
                    "name": s.name,
                    "role": s.role.value,
                    "group": s.group.value,
                    "boresight_flu": s.boresight_flu,
                    "min_range_m": s.min_range_m,
                    "max_range_m": s.max_range_m,
                }
                for s in self.sensors.specs
            ],
            "planner": self.cfg.planner.model_dump(mode="json"),
            "route": self.cfg.route.model_dump(mode="json"),
        }


def _finite_setpoint(sp: Setpoint) -> bool:
    return bool(
        np.all(np.isfinite(sp.position_enu))
        and np.all(np.isfinite(sp.velocity_enu))
        and math.isfinite(sp.yaw_rad)
    )


def _codec_fields() -> tuple[str, ...]:
    from dataclasses import fields

    from companion.service.codec import CodecCounters

    return tuple(f.name for f in fields(CodecCounters))


_PROBLEM_PREFIXES = (
    "codec.garbage",
    "codec.bad_",
    "codec.unsigned",
    "codec.unknown",
    "codec.truncated",
    "codec.parser",
    "conn.other",
    "conn.handler",
    "input.rejected",
    "input.out_of_order",
    "input.duplicate",
    "input.time_boot",
    "input.position_jump",
    "input.rejected_position_jump_fault",
    "link.send_dropped",
    "link.oversized",
    "link.kernel_dropped",
    "link.errors",
    "signing.bad",
    "signing.rejected",
    "service.cycle_overruns",
    "service.cycle_errors",
    "service.route_build_failed",
    "service.planner_errors",
    "service.setpoints_refused",
    "statustext.dropped",
)


def _is_problem(name: str) -> bool:
    return name.startswith(_PROBLEM_PREFIXES)


# === entry point ===========================================================================


def configure_logging(level: str, environ: Mapping[str, str] | None = None) -> None:
    import os

    env = os.environ if environ is None else environ
    fmt = "%(levelname)s %(name)s: %(message)s"
    if "JOURNAL_STREAM" not in env:  # journald adds its own time stamps
        fmt = "%(asctime)s " + fmt
    logging.basicConfig(level=level.upper(), format=fmt, stream=sys.stderr, force=True)


async def _run_with_signals(service: Service) -> int:
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, service.stop)
    return await service.run()


def main(config_path: Path, connection: str | None = None, log_level: str | None = None) -> int:
    """`companion run --config FILE`: exit 0 on SIGTERM/SIGINT, 2 on a bad config, 3 when the
    link's port cannot be had (in use), 1 on another error.

    connection, log_level: the command line's `--connection` and `--log-level`.
    """
    try:
        cfg = load_config(Path(config_path), connection)
    except ConfigError as exc:
        print(f"{config_path}: invalid configuration", file=sys.stderr)
        for line in exc.errors:
            print(f"  {line}", file=sys.stderr)
        return 2
    configure_logging(log_level or cfg.logging.level)
    service = Service(cfg, open_link(cfg.link.spec))
    return asyncio.run(_run_with_signals(service))
