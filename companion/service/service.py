"""The companion service: wiring and life cycle around one autopilot link.

Life cycle (`Service.run`):

1. open the link; heartbeat at `identity.heartbeat_hz` from the start (MAV_STATE BOOT);
2. wait for an autopilot heartbeat, tell ArduPilot from PX4, lock onto its (system,
   component) id and take its system id as ours unless configured (`autopilot.py`);
3. configure: message rates, HOME_POSITION, home and position, the route (`supervisor.py`);
4. STANDBY until the vehicle is armed, in GUIDED/OFFBOARD and above `min_engage_height_m`
   (or, with `auto_start`, arm/take off/switch mode itself), then fly: each cycle steps the
   planner and sends its setpoint (ACTIVE) (`cycle.py`, `host.py`);
5. on failsafes hold (CRITICAL) or stop commanding (EMERGENCY), on a mode change stop at once
   and never switch back; when the autopilot heartbeat returns after a loss, configure again.

Cycles run on the injected clock at `control.rate_hz`, or, with `control.time_source: sim`,
on the simulator's lockstep TIMESYNC ticks: the tick's time becomes the service clock, a cycle
runs if one is due, its setpoint is sent, and only then is the TIMESYNC answered, so a
faster-than-real-time simulation sees exactly the cycles a real-time flight would.

This module wires the parts, runs the tasks (heartbeat, supervisor, housekeeping, cycle
timer), dispatches received messages (a ground station's parameter requests to
`params.py`), and answers `status()`.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import math
from collections.abc import Callable, Coroutine
from typing import Any

from companion.config import ServiceConfig, layout_summary
from companion.planner.types import VehicleState
from companion.service.autopilot import AutopilotFinder, AutopilotInfo
from companion.service.clock import Clock, MonotonicClock, SimClock
from companion.service.codec import MavCodec, MAVLinkMessage, mavlink2
from companion.service.commands import CommandClient
from companion.service.connection import Connection
from companion.service.counters import ProblemReporter, ServiceCounters, collect
from companion.service.cycle import ControlCycle
from companion.service.failsafe import Limits
from companion.service.flightlog import FlightLogWriter
from companion.service.host import (
    PlannerFactory,
    PlannerHost,
    PlannerLike,
    default_planner_factory,
)
from companion.service.identity import Health, heartbeat_message
from companion.service.link import Link
from companion.service.modes import Ownership
from companion.service.notify import SystemdNotifier
from companion.service.params import ParamServer
from companion.service.signing import SigningKeyError, SigningState, load_key, timestamp_now
from companion.service.status import PlannerState, SensorFreshness, ServiceStatus, status_line
from companion.service.statustext import Severity, StatusTexts
from companion.service.supervisor import Supervisor
from companion.service.telemetry import Telemetry

log = logging.getLogger("companion.service")

EXIT_LINK = 3
"""`run`'s exit status when the link's port cannot be had (systemd: RestartPreventExitStatus)."""
LINK_RETRY_S = 2.0
"""A link that cannot be opened yet (serial device missing, host unknown): retried this often."""
_LINK_FATAL_ERRNOS = frozenset({errno.EADDRINUSE, errno.EACCES, errno.EADDRNOTAVAIL, errno.EPERM})
COUNTERS_EVERY_S = 10.0
TRIGGER_DEADLINE_PERIODS = 1.5
RATE_BURST_PERIODS = 2.0
"""Real time: the most cycle credit the loop may save up (periods)."""
"""Real time: a cycle whose inputs do not all arrive runs this many periods after the last."""
"""Problem counters are logged, and the signing timestamp saved, this often (wall time)."""


class Service:
    """The companion service around one autopilot link.

    config: a validated ServiceConfig. link: an unopened Link (`open_link(...)` or a
    `MemoryLink`). planner_factory: builds the planner (default `companion.planner.Planner`).
    notifier: systemd notification (default from the environment). clock: the service clock
    (default: the simulator's ticks with `control.time_source: sim`, else monotonic).
    wall: the clock of the watchdog and housekeeping (default monotonic; a test passes its
    fake clock for both).
    """

    def __init__(
        self,
        config: ServiceConfig,
        link: Link,
        *,
        planner_factory: PlannerFactory | None = None,
        notifier: SystemdNotifier | None = None,
        clock: Clock | None = None,
        wall: Clock | None = None,
    ) -> None:
        self.cfg = config
        self.link = link
        self.notifier = notifier or SystemdNotifier()
        self.status_sink: Callable[[str], None] | None = None
        """Where the status line goes once a second (wall time), e.g. a terminal; systemd's
        STATUS= gets the same text through the notifier once the autopilot is configured."""
        self.sim_time = config.control.time_source == "sim"
        if clock is None:
            clock = SimClock() if self.sim_time else MonotonicClock()
        self.clock: Clock = clock
        self.wall: Clock = wall if wall is not None else MonotonicClock()
        self.sensors = config.sensor_table()
        self.period_s = 1.0 / config.control.rate_hz
        self._trigger: asyncio.Future[bool | None] | None = None
        """Set when the inputs the next cycle waits for have all arrived (real time only)."""
        self._awaited: set[int] = set()
        """The DISTANCE_SENSOR burst the next cycle waits for: the ids of the sensors that
        reported in each of the last two (a sensor slower than the loop, or one whose datagram
        was lost, is not waited for: a lossy link must not hold the loop to its deadline)."""
        self._arrived: set[int] = set()
        self._arrived_before: set[int] = set()
        self._burst_ms = 0
        """The newest stamp of the burst so far (autopilot ms; 0: not stamped)."""
        self._attitude_covers = False
        """An ATTITUDE at or after the burst's time has arrived (its attitude is known)."""
        self._attitude_streams = False
        """An ATTITUDE arrived during the last cycle period."""
        self._attitude_seen = False
        self._trigger_t = 0.0
        """When the inputs of the awaited cycle were complete (service clock, s)."""

        ident = config.identity
        sid = ident.system_id if isinstance(ident.system_id, int) else 1
        self.codec = MavCodec(sid, ident.component_id)
        self.conn = Connection(link, self.codec, self.clock.now)
        fs = config.failsafe
        self.tel = Telemetry(
            self.sensors,
            max_speed_mps=fs.max_speed_mps,
            jump_accept_s=fs.jump_accept_s,
            max_jump_m=fs.max_position_jump_m,
            max_accepted_jump_m=fs.max_accepted_jump_m,
            median_samples=fs.range_median_samples,
            spike_m=fs.range_spike_m,
        )
        ap = config.autopilot
        self.commands = CommandClient(self.conn, ap.command_timeout_s, ap.command_retries)
        limits = Limits(
            ap.heartbeat_timeout_s,
            fs.position_max_age_s,
            fs.attitude_max_age_s,
            fs.sensor_max_age_s,
        )
        self.limits = limits
        optional = set(fs.optional_sensor_ids)
        required = [i for i, s in enumerate(self.sensors.specs) if s.sensor_id not in optional]
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
        self.counters = ServiceCounters()
        """The service's own counters (`service.*` in `counter_values()`)."""
        self.info = AutopilotInfo()
        self.finder = AutopilotFinder(
            config,
            self.conn,
            self.codec,
            self.info,
            notifier=self.notifier,
            counters=self.counters,
            say=self._say,
        )
        self.host = PlannerHost(
            config,
            self.sensors,
            self.tel,
            self.clock,
            planner_factory=planner_factory or default_planner_factory,
            say=self._say,
            counters=self.counters,
            flight_log=self.flight_log,
            sim_time=self.sim_time,
            period_s=self.period_s,
            sensor_max_age_s=limits.sensor_max_age_s,
            on_finish=self._route_finished,
        )
        self.supervisor = Supervisor(
            config,
            self.conn,
            self.commands,
            self.tel,
            self.host,
            self.finder,
            self.clock,
            limits=limits,
            required_sensors=required,
            notifier=self.notifier,
            counters=self.counters,
            say=self._say,
            spawn=self._spawn,
            sim_time=self.sim_time,
        )
        self.cycle = ControlCycle(
            config,
            self.tel,
            self.host,
            self.supervisor,
            self.info,
            self.conn,
            limits=limits,
            required_sensors=required,
            texts=self.texts,
            counters=self.counters,
            flight_log=self.flight_log,
            wall=self.wall,
            boot_s=self.clock.now(),
            sim_time=self.sim_time,
        )
        self.params = ParamServer(self.host, self.codec, self.conn.send, self._say)
        """The planner's tunables as MAVLink parameters of our component (`params.py`)."""
        self.conn.on_request = self.params.handle
        self.conn.on_message = self._on_message
        self.conn.on_unlocked = self.finder.on_unlocked
        self.conn.on_other = self.finder.on_other
        self._next_cycle_t: float | None = None
        self._stop = asyncio.Event()
        self._tasks: list[asyncio.Task[Any]] = []
        self._fatal: BaseException | None = None
        self._problems = ProblemReporter()
        self._log_failing_said = ""

    # === public ============================================================================

    @property
    def route_finished(self) -> asyncio.Event:
        """Set when the route is complete (the planner finished, or nothing was left)."""
        return self.host.route_finished

    @property
    def planner(self) -> PlannerLike | None:
        """The planner flying the route now, if any."""
        return self.host.planner

    @property
    def ownership(self) -> Ownership:
        """Who commands the vehicle (read-only use; `status().owner` is the snapshot)."""
        return self.cycle.ownership

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
        log.info("sensor layout: %s", layout_summary(self.cfg))
        if self.flight_log is not None:
            self.flight_log.header(self._log_header())
        self._spawn(self._heartbeat_loop(), "heartbeat")
        self._spawn(self.supervisor.run(self.link.name), "supervisor")
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

    def stop(self) -> None:
        """Ask `run` to return (safe from signal handlers and other tasks)."""
        self._stop.set()

    async def abandon(self) -> None:
        """End every task and close the link without a word (no POWEROFF heartbeat, no last
        counters): what the autopilot sees of a companion that crashed or was killed."""
        for t in self._tasks:
            t.cancel()
        with contextlib.suppress(Exception):
            await self.conn.close()
        if self.flight_log is not None:
            self.flight_log.close()

    def set_desired_height(self, h_d_m: float) -> None:
        """Change H_d in flight (metres); the planner ramps to it. ValueError if not > 0."""
        self.host.set_desired_height(h_d_m)

    def counter_values(self) -> dict[str, int]:
        """Every counter by dotted name (see docs/service.md)."""
        return collect(self.link, self.codec, self.conn, self.tel, self.texts, self.counters)

    def vehicle_state(self) -> VehicleState | None:
        """The vehicle's state in the service's frame (ENU m, ENU rad), or None."""
        return self.host.vehicle_state()

    def status(self) -> ServiceStatus:
        """A frozen snapshot of what the service is doing now."""
        now = self.clock.now()
        host, cycle, tel = self.host, self.cycle, self.tel
        max_age = self.limits.sensor_max_age_s
        if host.route_finished.is_set():
            planner = PlannerState.FINISHED
        elif host.route_error or host.planner_failed:
            planner = PlannerState.FAILED
        elif host.building:
            planner = PlannerState.BUILDING
        elif host.planner is not None:
            planner = PlannerState.FLYING
        else:
            planner = PlannerState.NONE
        ranges = tuple(None if r is None else now - r.t_rx for r in tel.ranges)
        stale = tuple(self.sensors.specs[i].sensor_id for i in tel.stale_sensors(now, max_age))

        def age(item: Any) -> float | None:
            return None if item is None else now - item.t_rx

        pts = host.route_source_points
        kind = cycle.last_kind
        pos = tel.position
        speed = None if pos is None else math.hypot(*pos.velocity_ned_mps)
        seen = [r for r in tel.range_vector(now, max_age) if r > 0.0]  # NaN, 0: nothing
        nearest = min(seen) if seen else None
        return ServiceStatus(
            t=now,
            health=cycle.health,
            configured=self.supervisor.configured,
            autopilot=self.info.kind,
            vehicle_type=self.info.vehicle_type,
            target_system=self.conn.target_system,
            setpoint_frame=self.info.setpoint_frame,
            mode=self.supervisor.current_mode(),
            owner=cycle.ownership.state,
            verdict=cycle.last_verdict,
            holding=cycle.ownership.engaged and kind != "planner",
            hold_reason=cycle.hold_reason(),
            planner=planner,
            planner_starts=self.counters["planner_starts"],
            next_point=host.next_point,
            route_points_xy=None if pts is None else pts.copy(),
            route_finished=host.route_finished.is_set(),
            h_d_m=host.h_d_m,
            shift_enu=host.shift.copy(),
            last_setpoint=host.last_setpoint,
            last_setpoint_kind=kind,
            freshness=SensorFreshness(
                age(tel.heartbeat), age(tel.position), age(tel.attitude), ranges, stale
            ),
            auto_start_busy=self.supervisor.auto_busy,
            counters=self.counter_values(),
            speed_mps=speed,
            nearest_m=None if nearest is None else float(nearest),
            decision=cycle.last_decision,
        )

    def _publish_status(self) -> None:
        """The status line to the sink (every call) and to systemd (once configured: before
        that the supervisor's own STATUS= words stand)."""
        sink, notifier = self.status_sink, self.notifier
        to_systemd = notifier.enabled and self.supervisor.configured
        if sink is None and not to_systemd:
            return
        text = status_line(self.status())
        if sink is not None:
            sink(text)
        if to_systemd:
            notifier.status(text)

    # === setup and shutdown ================================================================

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

    def _spawn(self, coro: Coroutine[Any, Any, Any], name: str) -> None:
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

    def _on_message(self, msg: MAVLinkMessage, t_rx: float) -> None:
        mtype = msg.get_type()
        if mtype == "TIMESYNC":
            self._on_timesync(msg)
            return
        if mtype == "HEARTBEAT":
            self.supervisor.autopilot_heartbeat(t_rx)
        tel = self.tel
        reboots, jumps = tel.reboots, tel.jumps_accepted
        kind = tel.update(msg, t_rx)
        if kind is not None and self._trigger is not None:
            self._input_arrived(kind, msg)
        if tel.notices:
            for text in tel.notices:
                self._say(text, Severity.ERROR)
            tel.notices.clear()
        if tel.reboots != reboots:
            self.supervisor.autopilot_rebooted()
        if tel.jumps_accepted != jumps:
            self.host.position_jumped(tel.last_jump_enu)
        if mtype == "HEARTBEAT":
            if self.cycle.ownership.engaged:
                self.cycle.update_ownership(self.clock.now(), allow_engage=False)
            self.supervisor.watch_auto_start()
        elif mtype == "STATUSTEXT" and int(msg.severity) <= Severity.WARNING:
            self.supervisor.autopilot_text(msg)

    def _on_timesync(self, msg: MAVLinkMessage) -> None:
        if int(msg.tc1) != 0:
            return  # an answer to someone's request; we send none
        ts1 = int(msg.ts1)
        clock = self.clock
        if not (self.sim_time and isinstance(clock, SimClock)):
            tc1 = max(1, int(clock.now() * 1e9))
            self.conn.send(mavlink2.MAVLink_timesync_message(tc1, ts1))
            return
        clock.set(ts1 * 1e-9)  # wakes what sleeps on the service clock (the supervisor)
        self._sim_tick(clock.now())
        answer = mavlink2.MAVLink_timesync_message(max(1, ts1), ts1)
        # Answer only after the tasks this tick woke have run up to their next wait, so what
        # they send (commands) lands in this tick: the simulator waits for the answer, and
        # the same scenario gives the same flight whatever the machine's load.
        loop = asyncio.get_running_loop()
        loop.call_soon(loop.call_soon, self.conn.send, answer)

    # === tasks =============================================================================

    async def _heartbeat_loop(self) -> None:
        period = 1.0 / self.cfg.identity.heartbeat_hz
        while True:
            self.conn.send(heartbeat_message(self.cycle.health))
            await asyncio.sleep(period)

    def _input_arrived(self, kind: str, msg: MAVLinkMessage) -> None:
        """An accepted input: when it completes what the next cycle waits for, wake the loop.
        That is the end of the DISTANCE_SENSOR burst (every awaited sensor has reported since
        the last cycle) with the attitude of its time known (an ATTITUDE stamped at or after
        the burst; by arrival when unstamped), so the ranges pair with their own attitude
        (`pairing.py`). When ATTITUDE does not stream, the burst alone."""
        if kind == "DISTANCE_SENSOR":
            stamp = int(msg.time_boot_ms)
            self._arrived.add(int(msg.id))
            self._burst_ms = max(self._burst_ms, stamp)
            att = self.tel.attitude
            self._attitude_covers = (
                att is not None and stamp > 0 and att.time_boot_ms >= self._burst_ms
            )
        elif kind == "ATTITUDE":
            stamp = int(msg.time_boot_ms)
            self._attitude_seen = True
            self._attitude_covers = stamp >= self._burst_ms or stamp == 0
        else:
            return
        trigger = self._trigger
        if trigger is not None and not trigger.done() and self._burst_complete():
            self._trigger_t = self.clock.now()
            trigger.set_result(True)

    def _burst_complete(self) -> bool:
        return (
            bool(self._awaited)
            and self._awaited <= self._arrived
            and (self._attitude_covers or not self._attitude_streams)
        )

    def _next_burst(self) -> None:
        """Inputs from now on count for the next cycle's burst."""
        self._awaited = self._arrived & self._arrived_before
        self._arrived_before, self._arrived = self._arrived, set()
        self._burst_ms = 0
        self._attitude_covers = False
        self._attitude_streams, self._attitude_seen = self._attitude_seen, False

    async def _cycle_loop(self) -> None:
        """Real time: a cycle runs when the inputs it needs have arrived (see
        `_input_arrived`), bounded by a credit of one period per cycle that accrues with time
        up to RATE_BURST_PERIODS (over any span T the loop runs at most T * rate_hz + 1
        cycles: it follows the inputs' jitter without ever running faster than rate_hz on
        average), and at the latest TRIGGER_DEADLINE_PERIODS periods after the last when they
        do not all come. A clock other than the computer's (a test's) keeps the plain
        timer."""
        if not isinstance(self.clock, MonotonicClock):
            await self._timer_loop()
            return
        loop = asyncio.get_running_loop()
        clock, period = self.clock, self.period_s
        cap = RATE_BURST_PERIODS * period
        credit, last = period, clock.now()
        # when the cycle should have started (its inputs complete or its deadline, and the
        # credit there): one ending more than a period after that is an overrun
        due = last
        while True:
            start = clock.now()
            late = start - due
            # the rate bound: a cycle spends one period of credit, credit accrues with time
            credit = min(credit + (start - last), cap) - period
            last = start
            self._trigger = trigger = loop.create_future()
            self.cycle.safe_tick(start)
            if self._burst_complete():  # it came while the rate bound held the loop back
                self._trigger_t = clock.now()
                trigger.set_result(True)
            elapsed = clock.now() - start
            if late + elapsed > period:
                self.counters["cycle_overruns"] += 1
            deadline = start + TRIGGER_DEADLINE_PERIODS * period
            handle = loop.call_later(
                max(TRIGGER_DEADLINE_PERIODS * period - elapsed, 0.0),
                _resolve,
                trigger,
            )
            await trigger
            handle.cancel()
            self._next_burst()
            by_input = trigger.result() is not None
            self.counters["cycles_by_input" if by_input else "cycles_by_timer"] += 1
            woken = self._trigger_t if by_input else deadline
            due = max(min(woken, clock.now()), last + period - credit)
            wait = period - (credit + (clock.now() - last))
            if wait > 0.0:
                await asyncio.sleep(wait)

    async def _timer_loop(self) -> None:
        clock = self.clock
        next_t = clock.now()
        while True:
            self.cycle.safe_tick(clock.now())
            next_t += self.period_s
            delay = next_t - clock.now()
            if delay < 0:
                self.counters["cycle_overruns"] += 1
                next_t = clock.now()
                delay = 0.0
            await clock.sleep(delay)

    def _sim_tick(self, now: float) -> None:
        if self._next_cycle_t is None or now >= self._next_cycle_t - 1e-9:
            self.cycle.safe_tick(now)
            nxt = (self._next_cycle_t if self._next_cycle_t is not None else now) + self.period_s
            self._next_cycle_t = nxt if nxt > now else now + self.period_s

    async def _housekeeping(self) -> None:
        """Once a second (wall time): watchdog, flight log, signing state, counters."""
        wd = self.notifier.watchdog_interval_s
        period = min(1.0, wd) if wd else 1.0
        wall = self.wall
        last_save = last_counters = wall.now()
        while True:
            await wall.sleep(period)
            now = wall.now()
            if self._loop_healthy(now):
                self.notifier.watchdog()
            self._publish_status()
            if self.codec.signing_enabled:
                self.codec.advance_signing_clock(timestamp_now())
                if now - last_save >= COUNTERS_EVERY_S:
                    self.signing_state.save(self.codec.signing_timestamp)
                    last_save = now
            if now - last_counters >= COUNTERS_EVERY_S:
                last_counters = now
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

    def _loop_healthy(self, wall_now: float) -> bool:
        if self.sim_time:
            return True  # ticks come from the simulator; this task running is the proof
        last = self.cycle.last_cycle_wall
        return last is not None and wall_now - last < max(1.0, 5 * self.period_s)

    def _report_counters(self) -> None:
        values = self.counter_values()
        self._problems.report(values)
        if self.flight_log is not None:
            self.flight_log.write({"type": "counters", "t": self.clock.now(), "counters": values})

    # === helpers ===========================================================================

    def _say(self, text: str, severity: Severity = Severity.INFO) -> None:
        self.texts.post(self.clock.now(), text, severity)

    def _route_finished(self) -> None:
        self.supervisor.route_finished()

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


__all__ = ["EXIT_LINK", "Service", "ServiceCounters"]


def _resolve(fut: asyncio.Future[bool | None]) -> None:
    if not fut.done():
        fut.set_result(None)
