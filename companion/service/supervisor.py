"""The supervisor: configure the autopilot, get the route, auto start, and watch for reboots.

After the autopilot's heartbeat is heard: request the message rates (acks checked) and
HOME_POSITION, wait for home and position, download the mission when the route comes from
it; then, with `auto_start`, arm, take off and hand over to the route (any mode change by
someone else aborts that at once). A heartbeat back after a loss, autopilot time going back,
or heartbeats without position (rates forgotten) configure again.

Deadlines and waits are on the service clock (simulated time in sim mode).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import Counter
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass
from typing import Any

from companion.config import ServiceConfig, latlon_points_xy, route_problem
from companion.service.autopilot import AutopilotFinder, AutopilotInfo
from companion.service.clock import Clock
from companion.service.codec import MAVLinkMessage, mavlink2
from companion.service.commands import CommandClient, CommandDeniedError, CommandError
from companion.service.connection import Connection, waiting_hint
from companion.service.failsafe import Limits, Verdict, assess
from companion.service.host import PlannerHost
from companion.service.mission import MissionError, download_mission, mission_waypoints
from companion.service.modes import AutopilotKind, is_guided, mode_name, set_mode_params
from companion.service.notify import SystemdNotifier
from companion.service.statustext import Severity
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
HEARTBEAT_WAIT_SAY_S = 2.0
"""No autopilot heard this long after start: say so (once)."""
MISSION_RETRY_S = 5.0
"""Auto start with an empty mission: download it again this often."""
CONFIG_RETRY_S = 2.0
"""A failed configuration is tried again after this long."""
AUTOPILOT_TEXT_S = 10.0
"""The autopilot's warning is quoted as the reason for a refusal this long after it came."""
TAKEOFF_NEAR_M = 0.1
"""The take-off is done within this of its altitude (relative, metres) ..."""
TAKEOFF_SHORT_FRACTION = 0.9
"""... or above this fraction of it once the climb has stopped: |vz| below TAKEOFF_STILL_MPS
for TAKEOFF_STILL_S (an autopilot that ends its take-off a little short is not waited on
until the timeout). Handing over at 90 % alone started the route up to 10 % of the take-off
altitude low: 0.9 m of a 9 m take-off on ArduCopter and PX4 SITL."""
TAKEOFF_STILL_MPS = 0.1
TAKEOFF_STILL_S = 1.0


@dataclass
class TakeoffWatch:
    """When a take-off to alt_m (above home, metres) is done: within TAKEOFF_NEAR_M of it, or
    above TAKEOFF_SHORT_FRACTION of it with the climb stopped for TAKEOFF_STILL_S."""

    alt_m: float
    _still_since: float | None = None

    def done(self, relative_alt_m: float, vz_down_mps: float, now_s: float) -> bool:
        if relative_alt_m >= self.alt_m - TAKEOFF_NEAR_M:
            return True
        high = relative_alt_m >= TAKEOFF_SHORT_FRACTION * self.alt_m
        if not high or abs(vz_down_mps) >= TAKEOFF_STILL_MPS:
            self._still_since = None
            return False
        if self._still_since is None:
            self._still_since = now_s
        return now_s - self._still_since >= TAKEOFF_STILL_S


Say = Callable[[str, Severity], None]
Spawn = Callable[[Coroutine[Any, Any, None], str], None]


class Supervisor:
    """Configure, route and auto start for one autopilot (see the module docstring).

    State read by the control cycle: `configured`, `auto_busy` (auto start is commanding:
    no take-over), `priming` (PX4: setpoints before OFFBOARD).
    """

    def __init__(
        self,
        cfg: ServiceConfig,
        conn: Connection,
        commands: CommandClient,
        tel: Telemetry,
        host: PlannerHost,
        finder: AutopilotFinder,
        clock: Clock,
        *,
        limits: Limits,
        required_sensors: list[int],
        notifier: SystemdNotifier,
        counters: Counter[str],
        say: Say,
        spawn: Spawn,
        sim_time: bool,
    ) -> None:
        self.cfg = cfg
        self.conn = conn
        self.commands = commands
        self.tel = tel
        self.host = host
        self.finder = finder
        self.info: AutopilotInfo = finder.info
        self.clock = clock
        self.limits = limits
        self.required_sensors = required_sensors
        self.notifier = notifier
        self.counters = counters
        self._say = say
        self._spawn = spawn
        self.sim_time = sim_time
        self.configured = False
        self.configured_at = 0.0
        self.reconfigure = asyncio.Event()
        self.priming = False
        self.auto_busy = False
        self._auto_done = False
        self._auto_task: asyncio.Task[None] | None = None
        self._auto_allowed: set[str] | None = None
        self._auto_armed = False
        self._ap_text: tuple[float, str] | None = None
        """The autopilot's latest STATUSTEXT of WARNING or worse: (service time, text)."""
        self._ap_chunks: dict[int, dict[int, str]] = {}
        self._last_hb_rx: float | None = None

    @property
    def stranger_blocks(self) -> bool:
        """A second autopilot was heard with system_id auto: no take-over."""
        return self.finder.stranger_blocks

    # --- the task --------------------------------------------------------------------------

    async def run(self, link_name: str) -> None:
        """Wait for the autopilot, then configure it (again whenever asked); never returns."""
        seen = self.finder.seen
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(seen.wait(), HEARTBEAT_WAIT_SAY_S)
        if not seen.is_set():
            waiting = f"waiting for autopilot heartbeat on {link_name}"
            log.warning("%s (%s)", waiting, waiting_hint(link_name))
            self.notifier.status(waiting)
            await seen.wait()
            log.info("autopilot heartbeat heard on %s", link_name)
        while True:
            self.reconfigure.clear()
            self.configured = False
            try:
                await self._configure()
            except (CommandError, MissionError) as exc:
                log.warning("configuration failed: %s; retrying", exc)
                self._say(f"config failed: {exc}", Severity.WARNING)
                await asyncio.sleep(CONFIG_RETRY_S)
                continue
            self.configured = True
            self.configured_at = self.clock.now()
            self.notifier.status("ready")
            if self.cfg.control.auto_start.enabled and not self._auto_done:
                self._auto_done = True
                await self._auto_start()
            await self.reconfigure.wait()

    # --- inputs from the receive path and the cycle ----------------------------------------

    def autopilot_heartbeat(self, t_rx: float) -> None:
        """A heartbeat of our autopilot: back after a loss means configure again."""
        last = self._last_hb_rx
        if last is not None and t_rx - last > self.limits.heartbeat_timeout_s:
            log.warning("autopilot heartbeat back after %.1f s", t_rx - last)
            self.reconfigure.set()
        self._last_hb_rx = t_rx

    def autopilot_rebooted(self) -> None:
        log.warning("autopilot time went backwards: reboot? reconfiguring")
        self.reconfigure.set()

    def check_streams(self, now: float) -> None:
        """Heartbeats but no position for STREAMS_LOST_S: the autopilot forgot our message
        rates (a reboot shorter than the heartbeat timeout, before any stamped message could
        show time going back): ask for them again."""
        hb, pos = self.tel.heartbeat, self.tel.position
        if not self.configured or hb is None or now - hb.t_rx > self.limits.heartbeat_timeout_s:
            return
        if pos is not None and now - pos.t_rx <= STREAMS_LOST_S:
            return
        if now - self.configured_at <= STREAMS_LOST_S:
            return
        self.counters["streams_rerequested"] += 1
        log.warning(
            "heartbeats but no position for %.1f s: requesting the rates again", STREAMS_LOST_S
        )
        self.configured_at = now
        self.reconfigure.set()

    def autopilot_text(self, msg: MAVLinkMessage) -> None:
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
        self._ap_text = (self.clock.now(), text)

    def route_finished(self) -> None:
        """The planner finished the route: `control.on_finish` (hold, or a mode change)."""
        action = self.cfg.control.on_finish
        if action == "hold":
            self._say("route complete: holding", Severity.INFO)
            return
        self._say(f"route complete: {action}", Severity.INFO)
        kind = self.info.kind
        assert kind is not None
        params = set_mode_params(kind, action, self.info.vehicle_type)

        async def change() -> None:
            try:
                await self.commands.set_mode(params)
            except CommandError as exc:
                self._say(f"{action} refused: {exc}", Severity.ERROR)

        self._spawn(change(), f"on-finish-{action}")

    # --- configure -------------------------------------------------------------------------

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
            ready = await self.wait_for(
                lambda: self.tel.home is not None and self.tel.position is not None, 2.0
            )
            if ready:
                break
            if not said:
                said = True
                self._say("waiting for home and position", Severity.INFO)
        self.host.update_frame()
        if self.cfg.route.source == "mission":
            await self._load_mission()
        self.host.update_frame()

    async def _load_mission(self, quiet: bool = False) -> None:
        """Download the autopilot's mission; a mission that breaks the route bounds counts
        as no mission (said, never flown). quiet: say nothing when it is still empty."""
        items = await download_mission(
            self.conn, self.cfg.autopilot.command_timeout_s, self.cfg.autopilot.command_retries
        )
        assert self.info.kind is not None
        geo = mission_waypoints(items, self.info.kind)
        problem = route_problem(latlon_points_xy(geo), origin_is_home=False) if geo else ""
        if problem:
            self._say(f"mission refused: {problem}", Severity.ERROR)
            geo = []
        n = len(geo)
        if n == 0:
            if not quiet:
                self._say("mission has no waypoints", Severity.WARNING)
        else:
            self._say(f"mission: {n} waypoints", Severity.INFO)
        self.host.set_mission(geo)

    async def wait_for(self, pred: Callable[[], bool], timeout_s: float) -> bool:
        """Until pred() is true (True) or timeout_s of service time have passed (False)."""
        deadline = self.clock.now() + timeout_s
        while not pred():
            if self.clock.now() >= deadline:
                return False
            # short polls; in simulator time the next tick (the simulator waits for us)
            await self.clock.sleep(0.002 if self.sim_time else 0.02)
        return True

    # --- auto start ------------------------------------------------------------------------

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
            self.auto_busy = False
            self.priming = False
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

    def current_mode(self) -> str | None:
        """The autopilot's flight mode by name, or None before its heartbeat."""
        hb = self.tel.heartbeat
        kind = self.info.kind
        if hb is None or kind is None:
            return None
        return mode_name(kind, self.info.vehicle_type, hb.base_mode, hb.custom_mode)

    def watch_auto_start(self) -> None:
        """On each autopilot heartbeat during auto start: a mode we did not ask for (a pilot,
        a ground station, a failsafe) or a disarm after arming ends auto start at once."""
        task, allowed = self._auto_task, self._auto_allowed
        if task is None or task.done() or allowed is None:
            return
        hb = self.tel.heartbeat
        mode = self.current_mode()
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
            if self.clock.now() >= deadline:
                raise CommandError(mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, f"not arming: {a.reason}")
            if a.reason != said:
                said = a.reason
                self._say(f"auto start: waiting, {a.reason}", Severity.INFO)
            await self.clock.sleep(0.05)

    async def _wait_for_route(self) -> bool:
        """Until there is a base point to fly to (farther than MIN_BASE_POINT_SPACING_M from
        the vehicle), saying so once; a mission is downloaded again every MISSION_RETRY_S.
        Waits while the vehicle's position or home (the frame of the route) is unknown.
        False when the configured route has nothing to fly (it will not change)."""
        said = False
        while True:
            self.host.update_frame()
            state = self.host.vehicle_state()
            if state is None or self.host.route_source_points is None:
                # the vehicle's state not known yet (configuring waits for home and position;
                # PX4 SITL's first ATTITUDE came after them): nothing to judge the route by,
                # which is not "at the end"
                await self.clock.sleep(0.1)
                continue
            if self.host.remaining_points(state.position_enu[:2]):
                return True
            if not said:
                said = True
                what = "mission empty" if self.cfg.route.source == "mission" else "at the end"
                self._say(f"auto start: no route ({what}): not taking off", Severity.WARNING)
            if self.cfg.route.source != "mission":
                return False
            await self.clock.sleep(MISSION_RETRY_S)
            try:
                await self._load_mission(quiet=True)
            except MissionError as exc:
                log.info("mission download: %s", exc)

    async def _auto_start_steps(self) -> None:
        """Arm, take off and hand over to the route. Refusals (denied, pre-arm checks, no
        answer) are retried until arm_timeout_s; the autopilot's reason is shown in full."""
        kind = self.info.kind
        assert kind is not None
        a = self.cfg.control.auto_start
        alt = a.takeoff_alt_m if a.takeoff_alt_m is not None else self.host.h_d_m
        hb = self.tel.heartbeat
        if hb is not None and hb.armed:
            self._say("auto start: already armed, waiting for pilot", Severity.INFO)
            return
        initial = self.current_mode()
        if initial is None:
            return
        if self.finder.stranger_blocks:
            self._say("auto start: not with a second autopilot heard", Severity.ERROR)
            return
        self.auto_busy = True
        self._auto_armed = False
        self._allow_modes(initial)
        deadline = self.clock.now() + a.arm_timeout_s
        try:
            if not await self._wait_for_route():
                return
            self._say("auto start", Severity.INFO)
            await self._wait_ready_to_arm(deadline)
            if kind is AutopilotKind.ARDUPILOT:
                # GUIDED is refused until the autopilot has a position estimate: retry.
                guided = set_mode_params(kind, "guided", self.info.vehicle_type)
                self._allow_modes(initial, "GUIDED")
                await self._with_retries(
                    "GUIDED", lambda: self.commands.set_mode(guided), deadline, a.arm_retry_s
                )
                if not await self.wait_for(self._guided, 5.0):
                    raise CommandError(
                        mavlink2.MAV_CMD_DO_SET_MODE, "mode did not change to GUIDED"
                    )
                self._allow_modes("GUIDED")
            await self._wait_ready_to_arm(deadline)
            await self._with_retries(
                "arming", lambda: self.commands.arm(True), deadline, a.arm_retry_s
            )
            await self.wait_for(
                lambda: self.tel.heartbeat is not None and self.tel.heartbeat.armed, 3
            )
            self._auto_armed = True
            home = self.tel.home
            assert home is not None
            target = alt if kind is AutopilotKind.ARDUPILOT else home.alt_amsl_m + alt
            if kind is AutopilotKind.PX4:
                self._allow_modes(initial, "AUTO.TAKEOFF", "AUTO.LOITER")
            try:
                await self.commands.takeoff(target)
            except CommandDeniedError:
                # A retry after a lost ack is refused once the first attempt has the vehicle
                # climbing (ArduCopter: "already flying"); that is success.
                if not self._climbing():
                    raise
                log.info("take-off retry refused while climbing: the first attempt worked")
            ok = await self.wait_for(self._takeoff_done(alt), a.takeoff_timeout_s)
            if not ok:
                raise CommandError(
                    mavlink2.MAV_CMD_NAV_TAKEOFF, "take-off did not reach its altitude"
                )
            if kind is AutopilotKind.PX4:
                self.priming = True
                await self.clock.sleep(a.prestream_s)
                self._allow_modes(initial, "AUTO.TAKEOFF", "AUTO.LOITER", "OFFBOARD")
                await self.commands.set_mode(set_mode_params(kind, "guided"))
                if not await self.wait_for(self._guided, 5.0):
                    raise CommandError(
                        mavlink2.MAV_CMD_DO_SET_MODE, "mode did not change to OFFBOARD"
                    )
        except CommandError as exc:
            self.counters["auto_start_failed"] += 1
            why = self._autopilot_reason()
            self._say(f"auto start failed: {exc}" + (f" ({why})" if why else ""), Severity.ERROR)

    def _autopilot_reason(self) -> str:
        """The autopilot's latest STATUSTEXT of warning or worse in the last
        AUTOPILOT_TEXT_S, in full."""
        if self._ap_text is None:
            return ""
        t, text = self._ap_text
        return text if self.clock.now() - t <= AUTOPILOT_TEXT_S else ""

    async def _with_retries(
        self, what: str, command: Callable[[], Awaitable[Any]], deadline: float, retry_s: float
    ) -> None:
        """Send a command until the autopilot accepts it or the deadline (service time)
        passes: a refusal (DENIED, FAILED, TEMPORARILY_REJECTED), a pre-arm STATUSTEXT and
        no answer are all retried; each new reason is logged in full."""
        last = ""
        while True:
            try:
                await command()
                return
            except CommandError as exc:
                if self.clock.now() >= deadline:
                    raise
                why = self._autopilot_reason()
                reason = f"{exc}" + (f"; autopilot: {why}" if why else "")
                if reason != last:
                    last = reason
                    log.warning("%s refused (%s); retrying until arm_timeout_s", what, reason)
                await self.clock.sleep(retry_s)  # simulated time in sim mode

    def _takeoff_done(self, alt_m: float) -> Callable[[], bool]:
        """A predicate on the telemetry: the take-off to alt_m (above home) is done."""
        watch = TakeoffWatch(alt_m)

        def done() -> bool:
            pos = self.tel.position
            return pos is not None and watch.done(
                pos.relative_alt_m, pos.velocity_ned_mps[2], self.clock.now()
            )

        return done

    def _climbing(self) -> bool:
        pos = self.tel.position
        return pos is not None and (pos.relative_alt_m > 0.3 or pos.velocity_ned_mps[2] < -0.2)

    def _guided(self) -> bool:
        hb = self.tel.heartbeat
        kind = self.info.kind
        return hb is not None and kind is not None and is_guided(kind, hb.base_mode, hb.custom_mode)


__all__ = ["STREAMS_LOST_S", "STREAM_IDS", "Supervisor"]
