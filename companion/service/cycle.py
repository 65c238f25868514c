"""One control cycle: ownership -> failsafe -> planner or hold -> setpoint.

`ControlCycle.tick(now)` runs one cycle at service time `now` (seconds on the injected
clock). It reads the telemetry, decides whether the companion commands the vehicle
(`Ownership`), whether the inputs allow flying (`assess` + `Failsafe`), steps the planner
through the `PlannerHost` (or holds), and hands the setpoint message to an `Outbox` (the
connection in the service; a list in tests), so it runs without a link.
"""

from __future__ import annotations

import contextlib
import logging
from collections import Counter
from typing import Any, Protocol

import numpy as np

from companion.config import ServiceConfig
from companion.planner.types import Setpoint, StepResult
from companion.service.autopilot import AutopilotInfo
from companion.service.clock import Clock
from companion.service.codec import MAVLinkMessage
from companion.service.failsafe import Assessment, Failsafe, Limits, Verdict, assess
from companion.service.flightlog import FlightLogWriter, floats
from companion.service.host import PlannerHost, finite_setpoint
from companion.service.identity import Health
from companion.service.modes import Ownership, OwnState, VehicleMode, is_armed, is_guided, mode_name
from companion.service.setpoints import position_target
from companion.service.statustext import Severity, StatusTexts, statustext_messages
from companion.service.telemetry import Telemetry

log = logging.getLogger("companion.service")

STOP_BRAKE_S = 3.0
"""How long, from the start of a STOP, the cycle keeps sending a brake setpoint: the last
setpoint's position with zero velocity. A STOP means the service cannot trust its inputs, so
it commands nothing new; but the autopilot keeps flying the last position-and-velocity
target (ArduCopter advances the target by its velocity for up to GUID_TIMEOUT, 3 s), and the
brake needs no input at all. After it, silence: the autopilot's own failsafes take over."""


class Outbox(Protocol):
    """Where the cycle's messages go, and to whom (`Connection` is one)."""

    target_system: int | None
    target_component: int | None

    def send(self, msg: MAVLinkMessage) -> None: ...


class Gate(Protocol):
    """What the supervisor tells the cycle (`Supervisor` is one)."""

    @property
    def configured(self) -> bool: ...

    @property
    def auto_busy(self) -> bool: ...

    @property
    def priming(self) -> bool: ...

    @property
    def stranger_blocks(self) -> bool: ...

    def check_streams(self, now: float) -> None: ...


class ControlCycle:
    """The cycle and what it decides: `health`, `last_verdict`, `last_kind` (planner, hold,
    prime or None), `hold_reason`.

    wall: the clock the watchdog judges the loop by (the computer's, even in sim mode).
    """

    def __init__(
        self,
        cfg: ServiceConfig,
        tel: Telemetry,
        host: PlannerHost,
        gate: Gate,
        info: AutopilotInfo,
        outbox: Outbox,
        *,
        limits: Limits,
        required_sensors: list[int],
        texts: StatusTexts,
        counters: Counter[str],
        flight_log: FlightLogWriter | None,
        wall: Clock,
        boot_s: float,
        sim_time: bool,
    ) -> None:
        self.cfg = cfg
        self.tel = tel
        self.host = host
        self.gate = gate
        self.info = info
        self.outbox = outbox
        self.limits = limits
        self.required_sensors = required_sensors
        self.texts = texts
        self.counters = counters
        self.flight_log = flight_log
        self.wall = wall
        self.boot_s = boot_s
        """Service time taken as the companion's boot (time_boot_ms = 0) in real time."""
        self.sim_time = sim_time
        self.ownership = Ownership(cfg.control.reengage)
        self.failsafe = Failsafe(cfg.failsafe.resume_after_s)
        self.health = Health.BOOT
        self.last_verdict = Assessment(Verdict.STOP, "starting")
        self.last_kind: str | None = None
        self.last_decision: str | None = None
        """The planner's decision in the last cycle it ran (None before it has run)."""
        self.last_cycle_wall: float | None = None
        self._text_id = 0
        self._stop_since: float | None = None
        """Service time the current STOP began while commanding (None when not stopped)."""
        self.min_engage_height_m = cfg.control.min_engage_height_m
        self.acceleration_feedforward = cfg.autopilot.acceleration_feedforward
        self._mode_key: tuple[Any, ...] | None = None
        self._mode: VehicleMode | None = None
        """The vehicle mode of the last heartbeat seen by `update_ownership`, and its key."""

    def say(self, now: float, text: str, severity: Severity = Severity.INFO) -> None:
        self.texts.post(now, text, severity)

    # --- the cycle -------------------------------------------------------------------------

    def safe_tick(self, now: float) -> None:
        """`tick`, but a bug in it holds the vehicle and is reported instead of ending the
        process (which would leave the vehicle in GUIDED/OFFBOARD with nobody commanding)."""
        try:
            self.tick(now)
        except Exception:
            self.counters["cycle_errors"] += 1
            if self.counters["cycle_errors"] <= 5:
                log.exception("cycle failed; holding")
            self.say(now, "internal error: holding", Severity.CRITICAL)
            with contextlib.suppress(Exception):
                if self.ownership.engaged:
                    sp = self.host.hold_setpoint()
                    if sp is not None:
                        self.send_setpoint(sp, now)
                self.send_texts(now)

    def tick(self, now: float) -> None:
        """One cycle at service time `now`: ownership, failsafe, planner or hold, setpoint."""
        self.last_cycle_wall = self.wall.now()
        self.counters["cycles"] += 1
        host, gate = self.host, self.gate
        if not host.frame_frozen:
            host.update_frame()
        gate.check_streams(now)
        events = self.update_ownership(
            now,
            allow_engage=gate.configured and not gate.auto_busy and not gate.stranger_blocks,
        )
        assessment = assess(now, self.tel, self.limits, self.required_sensors)
        verdict, fs_events = self.failsafe.update(now, assessment)
        priming = gate.priming
        if self.ownership.engaged or priming:
            for e in fs_events:
                sev = Severity.INFO if e.startswith("resumed") else Severity.CRITICAL
                self.say(now, e, sev)
        result: StepResult | None = None
        sp: Setpoint | None = None
        sp_kind: str | None = None
        if self.ownership.engaged:
            if verdict.verdict is Verdict.RUN:
                result = host.step(now)
                if result is not None:
                    sp, sp_kind = result.setpoint, "planner"
                else:
                    sp, sp_kind = host.hold_setpoint(), "hold"
            elif verdict.verdict is Verdict.HOLD:
                sp, sp_kind = host.hold_setpoint(), "hold"
                host.pause()
            else:
                host.pause()
                sp = self._brake_setpoint(now)
                if sp is not None:
                    sp_kind = "brake"
                    self.counters["brake_cycles"] += 1
            if sp_kind == "hold":
                self.counters["hold_cycles"] += 1
        elif priming and verdict.verdict is not Verdict.STOP:
            sp, sp_kind = host.hold_setpoint(), "prime"
        if verdict.verdict is Verdict.RUN and sp_kind != "hold":
            host.clear_hold()
        if verdict.verdict is not Verdict.STOP or not self.ownership.engaged:
            self._stop_since = None
        if sp is not None:
            self.send_setpoint(sp, now)
        self.health = self._health(verdict.verdict, priming)
        self.last_verdict = verdict
        self.last_kind = sp_kind
        if result is not None:
            self.last_decision = str(result.diagnostics.decision)
        self.send_texts(now)
        if self.flight_log is not None:
            self.flight_log.write(self._record(now, verdict, result, sp, sp_kind, events))

    def _brake_setpoint(self, now: float) -> Setpoint | None:
        """The brake of a STOP (see STOP_BRAKE_S): the last setpoint sent, at rest; None once
        STOP_BRAKE_S has passed, or if nothing was ever sent."""
        if self._stop_since is None:
            self._stop_since = now
        last = self.host.last_setpoint
        if last is None or now - self._stop_since > STOP_BRAKE_S:
            return None
        return Setpoint(last.position_enu, np.zeros(3), last.yaw_rad, 0.0)

    def hold_reason(self) -> str:
        """Why the vehicle holds (or is not commanded) now; "" when the planner flies it."""
        if self.last_kind == "planner":
            return ""
        v = self.last_verdict
        if v.verdict is not Verdict.RUN:
            return v.reason
        host = self.host
        if host.route_error:
            return f"cannot fly route: {host.route_error}"
        if host.planner_failed:
            return "planner error"
        if host.building:
            return "planner being built"
        if host.facing is not None:
            return "turning to face the route"
        if host.route_finished.is_set():
            return "route complete"
        return ""

    def send_setpoint(self, sp: Setpoint, now: float) -> None:
        """Pack and send `sp` (service frame) as SET_POSITION_TARGET_GLOBAL_INT."""
        home = self.tel.home
        frame = self.host.frame
        mav_frame = self.info.setpoint_frame
        if frame is None or home is None or mav_frame is None:
            return
        if not finite_setpoint(sp):  # never on the wire, whatever produced it
            self.counters["setpoints_refused_nonfinite"] += 1
            return
        ts, tc = self.outbox.target_system, self.outbox.target_component
        assert ts is not None and tc is not None
        msg = position_target(
            sp.position_enu,
            sp.velocity_enu,
            sp.yaw_rad,
            sp.acceleration_enu if self.acceleration_feedforward else None,
            frame=frame,
            mav_frame=mav_frame,
            home_alt_amsl_m=home.alt_amsl_m,
            time_boot_ms=self.boot_ms(now),
            target_system=ts,
            target_component=tc,
        )
        self.outbox.send(msg)
        self.host.last_setpoint = sp
        self.counters["setpoints_sent"] += 1

    def boot_ms(self, now: float) -> int:
        """time_boot_ms of our messages: service time in sim mode, since start otherwise."""
        return int((now if self.sim_time else now - self.boot_s) * 1000.0)

    def send_texts(self, now: float) -> None:
        for sev, text in self.texts.drain(now):
            self._text_id = self._text_id % 65535 + 1
            for msg in statustext_messages(sev, text, self._text_id):
                self.outbox.send(msg)

    def _health(self, verdict: Verdict, priming: bool) -> Health:
        if self.ownership.engaged:
            if verdict is Verdict.STOP:
                return Health.EMERGENCY
            if verdict is Verdict.HOLD or self.host.planner_failed:
                return Health.CRITICAL
            return Health.ACTIVE
        if priming:
            return Health.ACTIVE
        return Health.STANDBY if self.gate.configured else Health.BOOT

    # --- ownership -------------------------------------------------------------------------

    def update_ownership(self, now: float, allow_engage: bool) -> list[str]:
        """Follow the autopilot's mode: take over (engage the planner) or let go."""
        hb = self.tel.heartbeat
        kind = self.info.kind
        if hb is None or kind is None or now - hb.t_rx > self.limits.heartbeat_timeout_s:
            return []
        pos = self.tel.position
        high_enough = pos is not None and pos.relative_alt_m >= self.min_engage_height_m
        # the same heartbeat every cycle: its mode is worked out once
        key = (kind, self.info.vehicle_type, hb.base_mode, hb.custom_mode, high_enough)
        mode = self._mode if key == self._mode_key else None
        if mode is None:
            mode = VehicleMode(
                guided=is_guided(kind, hb.base_mode, hb.custom_mode),
                armed=is_armed(hb.base_mode),
                high_enough=high_enough,
                name=mode_name(kind, self.info.vehicle_type, hb.base_mode, hb.custom_mode),
            )
            self._mode_key, self._mode = key, mode
        if not mode.armed:
            self.host.note_on_ground()
        before = self.ownership.state
        events = self.ownership.update(mode, allow_engage=allow_engage)
        after = self.ownership.state
        engaging = before is not OwnState.ENGAGED and after is OwnState.ENGAGED
        if engaging and not self.host.engage(now):
            self.ownership.release("cannot fly: no route")
        elif engaging and self.failsafe.current.verdict is not Verdict.RUN:
            # a hold (or stop) that began before the take-over: announced like any other
            f = self.failsafe.current
            self.say(now, f"{f.verdict.value.upper()}: {f.reason}", Severity.CRITICAL)
        if before is OwnState.ENGAGED and after is not OwnState.ENGAGED:
            self.counters["released"] += 1
            self.host.pause()
        for e in events:
            self.say(now, e, Severity.NOTICE if after is OwnState.ENGAGED else Severity.WARNING)
        return events

    # --- flight log ------------------------------------------------------------------------

    def _record(
        self,
        now: float,
        verdict: Assessment,
        result: StepResult | None,
        sp: Setpoint | None,
        sp_kind: str | None,
        events: list[str],
    ) -> dict[str, Any]:
        # the state the planner stepped with (its ranges' attitude), else the latest
        state = self.host.step_state if result is not None else self.host.vehicle_state()
        d = result.diagnostics if result is not None else None
        return {
            "type": "cycle",
            "t": now,
            "health": self.health.name.lower(),
            "own": self.ownership.state.value,
            "verdict": verdict.verdict.value,
            "reason": verdict.reason,
            "pos": None if state is None else floats(state.position_enu),
            "rpy": None if state is None else [state.roll_rad, state.pitch_rad, state.yaw_rad],
            "ranges": floats(self.tel.range_vector(now, self.limits.sensor_max_age_s)),
            "sp": None
            if sp is None
            else {
                "p": floats(sp.position_enu),
                "v": floats(sp.velocity_enu),
                "a": floats(sp.acceleration_enu),
                "yaw": sp.yaw_rad,
                "pitch": sp.pitch_rad,
            },
            "sp_kind": sp_kind,
            "decision": None if d is None else str(d.decision),
            "mode": None if d is None else str(d.mode),
            "side": None if d is None else str(d.side),
            "min_range": None if d is None else d.min_range_m,
            "phi_star": None if d is None else floats(d.phi_star_rad),
            "phi_star_threshold": None if d is None else floats(d.threshold_rad),
            "phi_d": None if d is None else d.phi_d_rad,
            "v_ref": None if d is None else d.speed_ref_mps,
            "replanned": bool(d.replanned) if d is not None else False,
            "finished": bool(d.finished) if d is not None else False,
            "events": list(events) + (list(d.events) if d is not None else []),
        }


__all__ = ["ControlCycle", "Gate", "Outbox"]
