"""What the loop may do this cycle, from the ages and validity of its inputs.

    RUN    all inputs fresh: step the planner and send its setpoint
    HOLD   a required range sensor or the attitude is stale: send a position setpoint at the
           position where the hold began, zero velocity (the planner is not stepped)
    STOP   the autopilot heartbeat, home or position is missing or stale, or the position
           jumped and is being judged: command nothing new. For `cycle.STOP_BRAKE_S` the last
           target is sent again at rest (a brake that needs no input), then nothing: the
           autopilot keeps that target and its own failsafes take over

`Failsafe` adds hysteresis: a hold or stop ends only after the inputs have been good for
`resume_after_s`, and each change of verdict or reason yields one message for the pilot.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass

from companion.planner.sensors import SensorTable
from companion.service.telemetry import Telemetry


class Verdict(enum.StrEnum):
    RUN = "run"
    HOLD = "hold"
    STOP = "stop"


@dataclass(frozen=True, slots=True)
class Assessment:
    verdict: Verdict
    reason: str = ""


RUN = Assessment(Verdict.RUN)


@dataclass(frozen=True, slots=True)
class Limits:
    heartbeat_timeout_s: float
    position_max_age_s: float
    attitude_max_age_s: float
    sensor_max_age_s: float


def sensor_label(sensors: SensorTable, index: int) -> str:
    spec = sensors.specs[index]
    return f"sensor {spec.sensor_id}" + (f" ({spec.name})" if spec.name else "")


def assess(
    now: float,
    tel: Telemetry,
    limits: Limits,
    required: Sequence[int],
) -> Assessment:
    """The verdict for this cycle. `required`: sensor table indices whose absence holds."""
    hb = tel.heartbeat
    if hb is None or now - hb.t_rx > limits.heartbeat_timeout_s:
        return Assessment(Verdict.STOP, "autopilot heartbeat lost")
    if tel.home is None:
        return Assessment(Verdict.STOP, "no home position")
    pos = tel.position
    if pos is None or now - pos.t_rx > limits.position_max_age_s:
        return Assessment(Verdict.STOP, "position stale")
    if tel.position_in_doubt:
        return Assessment(Verdict.STOP, tel.jump_fault or "position jump")
    att = tel.attitude
    if att is None or now - att.t_rx > limits.attitude_max_age_s:
        return Assessment(Verdict.HOLD, "attitude stale")
    stale = [i for i in tel.stale_sensors(now, limits.sensor_max_age_s) if i in required]
    if stale:
        label = sensor_label(tel.sensors, stale[0])
        more = f" +{len(stale) - 1}" if len(stale) > 1 else ""
        return Assessment(Verdict.HOLD, f"{label} stale{more}")
    return RUN


class Failsafe:
    """Verdict with hysteresis on the way back to RUN."""

    def __init__(self, resume_after_s: float) -> None:
        self.resume_after_s = resume_after_s
        self.current = RUN
        self._good_since: float | None = None

    def update(self, now: float, a: Assessment) -> tuple[Assessment, list[str]]:
        """The verdict to act on and the messages it caused (e.g. "HOLD: sensor 3 stale")."""
        events: list[str] = []
        if a.verdict is not Verdict.RUN:
            self._good_since = None
            if a != self.current:
                events.append(f"{a.verdict.value.upper()}: {a.reason}")
                self.current = a
            return self.current, events
        if self.current.verdict is Verdict.RUN:
            return RUN, events
        if self._good_since is None:
            self._good_since = now
        if now - self._good_since >= self.resume_after_s:
            events.append(f"resumed after {self.current.reason}")
            self.current = RUN
            self._good_since = None
        return self.current, events

    def reset(self) -> None:
        self.current = RUN
        self._good_since = None
