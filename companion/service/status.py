"""`Service.status()`: a frozen snapshot of what the service is doing, instead of reading its
attributes. Times are seconds on the service clock; positions ENU metres in the service's
local frame (origin at home).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass

from companion.planner.types import FloatArray, Setpoint
from companion.service.failsafe import Assessment
from companion.service.identity import Health
from companion.service.modes import AutopilotKind, OwnState
from companion.service.setpoints import SetpointFrame


class PlannerState(enum.StrEnum):
    NONE = "none"
    """Not engaged yet (or nothing to fly)."""
    BUILDING = "building"
    FLYING = "flying"
    FAILED = "failed"
    """The route could not be built or the last step raised: holding."""
    FINISHED = "finished"


@dataclass(frozen=True, slots=True)
class SensorFreshness:
    """Age of the latest input of each kind at the snapshot (seconds; None = never heard)."""

    heartbeat_age_s: float | None
    position_age_s: float | None
    attitude_age_s: float | None
    range_ages_s: tuple[float | None, ...]
    """One per sensor, in sensor-table order."""
    stale_sensor_ids: tuple[int, ...]
    """DISTANCE_SENSOR ids older than failsafe.sensor_max_age_s (or never heard)."""


@dataclass(frozen=True, slots=True)
class ServiceStatus:
    """A snapshot of the service (see the module docstring for units and frames)."""

    t: float
    """Service time of the snapshot."""
    health: Health
    """What our heartbeat says (MAV_STATE)."""
    configured: bool
    autopilot: AutopilotKind | None
    vehicle_type: int
    target_system: int | None
    setpoint_frame: SetpointFrame | None
    mode: str | None
    """The autopilot's flight mode by name (e.g. GUIDED, OFFBOARD), None before a heartbeat."""
    owner: OwnState
    """Who commands the vehicle: standby (the pilot), engaged (us), released (the pilot took
    it back)."""
    verdict: Assessment
    """The failsafe's verdict of the last cycle (run, hold, stop) with its reason."""
    holding: bool
    """The last cycle sent a hold setpoint (or none while engaged)."""
    hold_reason: str
    """Why the vehicle is held or not flown; "" when the planner flies it."""
    planner: PlannerState
    planner_starts: int
    next_point: int
    """Index of the next base point of the route."""
    route_points_xy: FloatArray | None
    """The route's base points (n, 2), ENU metres, once known (copy)."""
    route_finished: bool
    h_d_m: float
    """H_d at run time."""
    shift_enu: FloatArray
    """Sum of the accepted position jumps (the planner's frame = estimate - shift)."""
    last_setpoint: Setpoint | None
    last_setpoint_kind: str | None
    """planner, hold, prime, or None (nothing sent in the last cycle)."""
    freshness: SensorFreshness
    auto_start_busy: bool
    counters: Mapping[str, int]
    """Every counter by dotted name (as `counter_values()`)."""
    speed_mps: float | None = None
    """The vehicle's ground speed (norm of the reported velocity), m/s; None if unknown."""
    nearest_m: float | None = None
    """The nearest range any fresh sensor detects, m; None when nothing is detected."""
    decision: str | None = None
    """The planner's decision in the last cycle it ran."""


def _f(value: float | None, unit: str) -> str:
    return "-" if value is None else f"{value:.1f} {unit}"


def status_line(st: ServiceStatus) -> str:
    """One line of plain words for a terminal and systemd's STATUS=: mode, owner, flying
    or holding (and why), H_d, speed, nearest obstacle, the planner's decision."""
    if st.target_system is None:
        return "waiting for autopilot heartbeat"
    doing = f"holding: {st.hold_reason}" if st.holding else st.planner.value
    if not st.holding and st.hold_reason and st.owner is not OwnState.ENGAGED:
        doing = st.hold_reason
    parts = [
        f"mode {st.mode or '?'}",
        st.owner.value,
        doing,
        f"H_d {st.h_d_m:.1f} m",
        f"v {_f(st.speed_mps, 'm/s')}",
        f"nearest {_f(st.nearest_m, 'm')}",
        f"decision {st.decision or '-'}",
    ]
    return " | ".join(parts)


__all__ = ["PlannerState", "SensorFreshness", "ServiceStatus", "status_line"]
