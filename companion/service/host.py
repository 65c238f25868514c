"""The planner's host: the planner's life inside the service.

Owns the local frame (ENU metres at home, frozen at the first take-over), the route's base
points in it, the planner (built on engage, rebuilt on a restart far from X_d), the shift that
keeps the planner's frame continuous through accepted position jumps, progress along the base
points, the turn to face the route before it starts, the route's end, the hold point, and
the planner's parameters at run time, H_d among
them (the config's values, changed only by `retune`, validated by the config's own rules,
passed to every planner built).

A change reaches the planner at the next cycle, whole or not at all: a new H_d that leaves
eq. (7)'s side threshold min(arctan(H_d / D_min), phi_max) as it was goes to the running
planner (`set_desired_height`, which ramps to it); any other change rebuilds the planner from
the vehicle's position with the new parameters (as a restart does: the base points not yet
passed, X_d at the vehicle, the speed from 0), so every value derived from them (thresholds,
the speed limits, the clearance cut-off) is computed afresh. A rebuild is refused while the
planner is off the route (going around, shifted, retreating, or still searching): it would
forget the correction it is flying.

It never touches the link: the control cycle calls `step` or `hold_setpoint` and sends what
they return.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

from companion.config import ServiceConfig, planner_with
from companion.geo import GeoPoint, LocalFrame
from companion.planner.frames import attitude_ned_to_enu, wrap_pi
from companion.planner.params import PlannerParams
from companion.planner.route import Route
from companion.planner.sensors import SensorTable
from companion.planner.types import FloatArray, PathMode, Setpoint, StepResult, VehicleState
from companion.service.clock import Clock
from companion.service.flightlog import FlightLogWriter
from companion.service.mission import latlon_to_xy
from companion.service.pairing import AttitudeSample
from companion.service.statustext import Severity
from companion.service.telemetry import Telemetry
from companion.tuning import PlannerConfig

log = logging.getLogger("companion.service")

MIN_BASE_POINT_SPACING_M = 0.5
"""Base points closer than this to the vehicle when it takes over are taken as passed."""

Say = Callable[[str, Severity], None]


class PlannerLike(Protocol):
    """What the service needs of `companion.planner.Planner`."""

    def step(self, state: VehicleState, ranges_m: FloatArray, dt_s: float) -> StepResult: ...

    def set_desired_height(self, h_d_m: float) -> None: ...


class RetuneRefusedError(ValueError):
    """A valid parameter change the planner cannot take now (nothing was changed)."""


PlannerFactory = Callable[[PlannerParams, SensorTable, Route, FloatArray], PlannerLike]


def default_planner_factory(
    params: PlannerParams, sensors: SensorTable, route: Route, start_position_enu: FloatArray
) -> PlannerLike:
    from companion.planner import Planner

    planner: PlannerLike = Planner(params, sensors, route, start_position_enu)
    return planner


FACE_DONE_RAD = math.radians(10.0)
"""The turn to face the route ends once the heading is this close to the first leg's."""
FACE_CLEAR_D_MIN = 3.0
"""No turn to face the route with an obstacle reading within this many D_min: a vehicle taken
over while it was going round something (a restarted companion) keeps the heading that was
taking it round as the route's start heading, instead of turning towards a base point whose
straight line passes the obstacle."""
FACE_TIMEOUT_S = 30.0
"""A turn that has not got there by then ends anyway: the route starts from the heading the
vehicle has (a yaw the autopilot does not follow must not keep it waiting for ever)."""


@dataclass
class Facing:
    """A turn in place before the route: hold `position_enu` (service frame) with the yaw
    `bearing_rad` (ENU) until the vehicle faces it."""

    position_enu: FloatArray
    bearing_rad: float
    since: float


@dataclass(frozen=True, slots=True)
class HoldPoint:
    """Where a hold keeps the vehicle: ENU metres in the service's frame, yaw ENU radians."""

    position_enu: FloatArray
    yaw_rad: float


def height_only(old: PlannerParams, new: PlannerParams) -> bool:
    """True when `new` differs from `old` in H_d at most and leaves eq. (7)'s side threshold
    as it was: a running planner takes that with `set_desired_height`."""
    return replace(old, h_d_m=new.h_d_m) == new and old.side_threshold_rad == new.side_threshold_rad


def finite_setpoint(sp: Setpoint) -> bool:
    """True when position, velocity, acceleration and yaw are all finite (the only setpoints
    sent)."""
    # element by element: cheaper than numpy's reductions for three 3-vectors
    return (
        all(map(math.isfinite, sp.position_enu))
        and all(map(math.isfinite, sp.velocity_enu))
        and all(map(math.isfinite, sp.acceleration_enu))
        and math.isfinite(sp.yaw_rad)
    )


class PlannerHost:
    """Frame, route, planner, jumps, progress and finish for one service.

    sim_time: build planners in place (lockstep: the simulator waits) instead of on a thread.
    on_finish: called once when the planner reports the route finished.
    """

    def __init__(
        self,
        cfg: ServiceConfig,
        sensors: SensorTable,
        tel: Telemetry,
        clock: Clock,
        *,
        planner_factory: PlannerFactory,
        say: Say,
        counters: Counter[str],
        flight_log: FlightLogWriter | None,
        sim_time: bool,
        period_s: float,
        sensor_max_age_s: float,
        on_finish: Callable[[], None],
    ) -> None:
        self.cfg = cfg
        self.sensors = sensors
        self.tel = tel
        self.clock = clock
        self.planner_factory = planner_factory
        self._say = say
        self.counters = counters
        self.flight_log = flight_log
        self.sim_time = sim_time
        self.period_s = period_s
        self.sensor_max_age_s = sensor_max_age_s
        self._on_finish = on_finish
        self.tuning: PlannerConfig = cfg.planner
        """The `planner:` section in force (validated; changed only by `retune`)."""
        self.params: PlannerParams = self.tuning.to_params()
        """The planner's parameters; `params.h_d_m` is H_d at run time (its one owner)."""

        self.frame: LocalFrame | None = None
        self.frame_frozen = False
        self._frame_key: tuple[GeoPoint, int] | None = None
        self.route_source_points: FloatArray | None = None
        """Base points (n, 2) in `frame`, or None until known."""
        self.mission_geo: list[tuple[float, float]] | None = None
        self.planner: PlannerLike | None = None
        self.next_point = 0
        self._seg_start: FloatArray | None = None
        self.last_result: StepResult | None = None
        self.step_state: VehicleState | None = None
        """The state (service frame) the last `step` used: the attitude of its ranges."""
        self.last_setpoint: Setpoint | None = None
        """The last setpoint sent (planner or hold), service frame."""
        self.route_finished = asyncio.Event()
        self._finish_handled = False
        self.hold: HoldPoint | None = None
        self.facing: Facing | None = None
        """Set while the vehicle turns in place to face the route before it starts."""
        self._start_due = False
        """Taken over: the next `step` turns to face the route or starts the planner."""
        self._from_ground = False
        """Seen disarmed since the last take-over: the next take-over is the first of a
        flight, and may turn to face the route."""
        self._may_face = False
        """This take-over is the first of a flight (`_from_ground` when it began)."""
        self.planner_failed = False
        self.building = False
        self._build_gen = 0
        self._build_task: asyncio.Task[Any] | None = None
        self.route_error = ""
        self._built_params = self.params
        self._rebuild_due = False
        """Parameters changed beyond what the running planner can take: rebuild next step."""
        self._shift = np.zeros(3)
        self._shifted = False
        self._last_planner_xd: FloatArray | None = None
        self._planner_t: float | None = None

    @property
    def shift(self) -> FloatArray:
        """Sum of the accepted position jumps: planner frame = estimate - shift (ENU m)."""
        return self._shift

    @shift.setter
    def shift(self, value: FloatArray) -> None:
        self._shift = np.asarray(value, dtype=np.float64)
        self._shifted = bool(self._shift.any())

    # --- H_d -------------------------------------------------------------------------------

    @property
    def h_d_m(self) -> float:
        """H_d at run time, metres."""
        return self.params.h_d_m

    def set_desired_height(self, h_d_m: float) -> None:
        """Change H_d in flight (metres); see `retune`."""
        self.retune({"h_d_m": h_d_m})

    def retune(self, changes: Mapping[str, float]) -> None:
        """Change planner parameters in flight (`planner:` key names, their units); they
        apply at the next cycle (see the module's docstring). ValueError, with nothing
        changed, when a value breaks the config's rules (the message names the key) or the
        planner cannot take it now (`RetuneRefusedError`)."""
        tuning = planner_with(self.tuning, changes)
        params = tuning.to_params()
        if params == self.params:
            self.tuning = tuning
            return
        smooth = height_only(self.params, params)
        if self.planner is not None and not smooth:
            why = self._off_route()
            if why:
                raise RetuneRefusedError(f"the planner is {why}: retry on the route")
        self.tuning, self.params = tuning, params
        if self.flight_log is not None:
            self.flight_log.write(
                {
                    "type": "planner",
                    "t": self.clock.now(),
                    "planner": tuning.model_dump(mode="json"),
                }
            )
        if self.planner is None:
            return  # the next planner built takes them (`_planner_built` if one is building)
        if smooth:
            self.planner.set_desired_height(params.h_d_m)
        else:
            self._rebuild_due = True

    def _off_route(self) -> str:
        """Why the running planner is off its route ("" when on it)."""
        if self._rebuild_due or self.last_result is None:
            return ""
        d = self.last_result.diagnostics
        if d.searching:
            return "searching for a path"
        if d.mode is not PathMode.ROUTE:
            return f"off the route ({d.mode.value})"
        return ""

    # --- frame and state -------------------------------------------------------------------

    def update_frame(self) -> None:
        """Anchor the local frame at home (until the first take-over freezes it)."""
        home = self.tel.home
        if home is None or self.frame_frozen:
            return
        origin = GeoPoint(home.lat_deg, home.lon_deg, home.alt_amsl_m)
        key = (origin, id(self.mission_geo))
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
        elif self.mission_geo is not None:
            self.route_source_points = latlon_to_xy(self.mission_geo, self.frame)

    def set_mission(self, geo: list[tuple[float, float]]) -> None:
        """The autopilot's mission (lat, lon degrees) as the route, when route.source is
        mission; an empty list is no route."""
        self.mission_geo = geo
        self.update_frame()

    def vehicle_state(self, attitude: AttitudeSample | None = None) -> VehicleState | None:
        """The vehicle's state in the service's frame (ENU m, ENU Euler rad), or None.
        attitude: the attitude to use (NED, e.g. that of the ranges' time); default the
        latest."""
        pos, att = self.tel.position, self.tel.attitude
        if pos is None or att is None or self.frame is None:
            return None
        e, n, u = self.frame.to_enu(GeoPoint(pos.lat_deg, pos.lon_deg, pos.alt_amsl_m))
        a = att if attitude is None else attitude
        r, p, y = attitude_ned_to_enu(a.roll_rad, a.pitch_rad, a.yaw_rad)
        return VehicleState(np.array([e, n, u]), r, p, y)

    def pause(self) -> None:
        """The planner is not stepped this cycle (hold, stop, release): the next step restarts
        its clock, and restarts it here if X_d is far from the vehicle."""
        self._planner_t = None

    def clear_hold(self) -> None:
        self.hold = None

    # --- engage and build ------------------------------------------------------------------

    def engage(self, now: float) -> bool:
        """Take over: the planner is built from the vehicle's position at the next `step` (the
        first cycle with inputs good enough to fly), after a turn to face the route
        (`_face_route`); False if there is nothing to fly."""
        self.facing = None
        self.update_frame()
        state = self.vehicle_state()
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
        self.planner = None
        self._start_due = True
        self._may_face, self._from_ground = self._from_ground, False
        return True

    def note_on_ground(self) -> None:
        """The vehicle is disarmed: the next take-over starts a flight (it may turn to face
        the route; a take-over in mid-flight, a re-engage or a service started or restarted
        with the vehicle armed, keeps the heading the vehicle has)."""
        self._from_ground = True

    def _face_route(self, state: VehicleState, ranges_m: FloatArray, now: float) -> bool:
        """At the first take-over of a flight (`note_on_ground`): begin a turn in place
        towards the first base point still to fly when the heading is off its bearing by more
        than `control.face_route_deg` and no obstacle reading is within FACE_CLEAR_D_MIN *
        D_min; True if it began."""
        pts = self.route_source_points
        assert pts is not None
        here = state.position_enu[:2]
        ahead = pts[self.next_point :]
        gaps = np.hypot(*(ahead - here).T) if len(ahead) else np.zeros(0)
        ahead = ahead[gaps >= MIN_BASE_POINT_SPACING_M]
        if not len(ahead):
            return False
        bearing = math.atan2(*(ahead[0] - here)[::-1])
        off = abs(wrap_pi(bearing - state.yaw_rad))
        if off <= math.radians(self.cfg.control.face_route_deg):
            return False
        ranges = ranges_m[self.sensors.obstacle_index]
        seen = ranges[np.isfinite(ranges) & (ranges > 0.0)]
        if len(seen) and float(seen.min()) < FACE_CLEAR_D_MIN * self.params.d_min_m:
            log.info(
                "heading %.0f deg off the route, obstacle %.1f m away: no turn to face it",
                math.degrees(off),
                float(seen.min()),
            )
            return False
        self.planner = None
        self.facing = Facing(state.position_enu + self.shift, bearing, now)
        self.hold = HoldPoint(self.facing.position_enu, bearing)
        self._say(f"turning {math.degrees(off):.0f} deg to face the route", Severity.INFO)
        return True

    def _faced(self, state: VehicleState, now: float) -> bool:
        """While turning to face the route: keep the hold's yaw on the bearing; True (and
        the turn over) once the heading is within FACE_DONE_RAD of it or FACE_TIMEOUT_S
        has passed."""
        f = self.facing
        assert f is not None
        off = abs(wrap_pi(f.bearing_rad - state.yaw_rad))
        if off > FACE_DONE_RAD and now - f.since < FACE_TIMEOUT_S:
            # a hold restarted meanwhile (a position jump) keeps turning from where it is
            if self.hold is None or self.hold.yaw_rad != f.bearing_rad:
                self.hold = HoldPoint(state.position_enu + self.shift, f.bearing_rad)
            return False
        if off > FACE_DONE_RAD:
            self._say(
                f"turn to the route not done in {FACE_TIMEOUT_S:.0f} s "
                f"({math.degrees(off):.0f} deg off): starting from this heading",
                Severity.WARNING,
            )
        self.facing = None
        self.hold = None
        return True

    def _to_planner(self, state: VehicleState) -> VehicleState:
        if not self._shifted:
            return state
        return VehicleState(
            state.position_enu - self.shift, state.roll_rad, state.pitch_rad, state.yaw_rad
        )

    def _from_planner(self, result: StepResult) -> StepResult:
        if not self._shifted:
            return result
        sp = result.setpoint
        moved = replace(sp, position_enu=sp.position_enu + self.shift)
        return StepResult(moved, result.diagnostics)

    def _start_planner(self, state: VehicleState) -> None:
        """A new planner from `state` (in the planner's frame, see `position_jumped`)."""
        pts = self.route_source_points
        assert pts is not None
        here = state.position_enu[:2]
        remaining = pts[self.next_point :]
        while len(remaining) and np.hypot(*(remaining[0] - here)) < MIN_BASE_POINT_SPACING_M:
            remaining = remaining[1:]
            self.next_point += 1
        if len(remaining) == 0:
            self.planner = None
            self._say("route complete: holding", Severity.INFO)
            self.hold = HoldPoint(state.position_enu + self.shift, state.yaw_rad)
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
        self._built_params = self.params
        self._rebuild_due = False
        self.last_result = None
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
        self.building = True
        task = asyncio.get_running_loop().create_task(asyncio.to_thread(build))
        task.add_done_callback(lambda t: self._build_done(gen, t))
        self._build_task = task

    def _build_done(self, gen: int, task: asyncio.Task[tuple[PlannerLike, Route]]) -> None:
        if gen != self._build_gen or task.cancelled():
            return
        self.building = False
        exc = task.exception()
        if exc is not None:
            self._route_failed(exc)
            return
        self._planner_built(gen, *task.result())

    def _planner_built(self, gen: int, planner: PlannerLike, route: Route) -> None:
        if gen != self._build_gen:
            return
        self.planner = planner
        self.route_error = ""
        if self.params != self._built_params:  # changed while it was being built
            if height_only(self._built_params, self.params):
                planner.set_desired_height(self.params.h_d_m)
            else:
                self._rebuild_due = True
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
        x0, y0 = (round(float(v), 2) + 0.0 for v in route.base_points[0][:2])  # no "-0.00"
        log.info(
            "planner started at E %.2f m, N %.2f m with %d base points",
            x0,
            y0,
            len(route.base_points) - 1,
        )

    def _route_failed(self, exc: BaseException) -> None:
        """The route or planner could not be built: hold where the vehicle is and say why
        (never end the process with the vehicle in GUIDED/OFFBOARD)."""
        self.planner = None
        self.building = False
        self.planner_failed = True
        self.route_error = str(exc)
        self.counters["route_build_failed"] += 1
        log.error("cannot fly the route: %s; holding", exc)
        self._say(f"cannot fly route: {exc}: holding", Severity.CRITICAL)

    # --- the step --------------------------------------------------------------------------

    def step(self, now: float) -> StepResult | None:
        """One planner step at service time `now`; None when the caller must hold (no
        state, route complete, being built, not flyable, or the planner failed)."""
        # the ranges with the attitude of their own time (`pairing.py`): the planner turns
        # them into points with the state's attitude
        pairing = self.tel.paired_ranges(now, self.sensor_max_age_s)
        estimate = self.vehicle_state(pairing.attitude)
        self.step_state = estimate
        if estimate is None:
            return None
        state = self._to_planner(estimate)
        if self._start_due:
            self._start_due = False
            if self._may_face and self._face_route(state, pairing.ranges_m, now):
                return None  # the caller holds, turning
            self._start_planner(state)
        elif self.facing is not None:
            if not self._faced(state, now):
                return None  # the caller holds: at the turn's position, yaw on the bearing
            self._start_planner(state)
        if self._rebuild_due and self.planner is not None:
            log.info("planner parameters changed: restarting the planner here")
            self._start_planner(state)
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
        try:
            result = self.planner.step(state, pairing.ranges_m, dt)
            if not finite_setpoint(result.setpoint):
                raise FloatingPointError(f"non-finite setpoint {result.setpoint}")
            self.planner_failed = False
        except Exception:  # a planner bug must not crash the service: hold instead
            self.planner_failed = True
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

    def position_jumped(self, jump_enu: FloatArray) -> None:
        """The position estimate jumped for good (estimator reset). The planner keeps its
        own frame, continuous through the jump (as ArduPilot's position controller shifts
        its targets on an EKF reset): positions given to it are the estimate minus the
        jumps so far, its setpoints are sent plus them. A plan, the obstacles it remembers
        and the route stay where they were in the world; a hold restarts where the vehicle
        is now."""
        self.shift = self.shift + jump_enu
        self.hold = None
        log.warning(
            "position estimate jumped %s m: the planner's frame moves with it",
            np.round(jump_enu, 2),
        )
        self._say("position jump: plan kept", Severity.WARNING)

    def hold_setpoint(self) -> Setpoint | None:
        """Where to hold: the vehicle's position when the hold began (service frame)."""
        if self.hold is None:
            state = self.vehicle_state()
            if state is None:
                pos = self.tel.position
                if pos is None or self.frame is None:
                    return None
                e, n, u = self.frame.to_enu(GeoPoint(pos.lat_deg, pos.lon_deg, pos.alt_amsl_m))
                yaw = 0.0 if self.last_setpoint is None else self.last_setpoint.yaw_rad
                self.hold = HoldPoint(np.array([e, n, u]), yaw)
            else:
                self.hold = HoldPoint(state.position_enu.copy(), state.yaw_rad)
        h = self.hold
        return Setpoint(h.position_enu, np.zeros(3), wrap_pi(h.yaw_rad), 0.0)

    def remaining_points(self, position_xy: FloatArray) -> bool:
        """True when a base point is at least MIN_BASE_POINT_SPACING_M from position_xy."""
        pts = self.route_source_points
        if pts is None or not len(pts):
            return False
        gaps = np.hypot(*(pts - position_xy).T)
        return float(np.max(gaps)) >= MIN_BASE_POINT_SPACING_M


__all__ = [
    "MIN_BASE_POINT_SPACING_M",
    "Facing",
    "HoldPoint",
    "PlannerFactory",
    "PlannerHost",
    "PlannerLike",
    "RetuneRefusedError",
    "default_planner_factory",
    "finite_setpoint",
    "height_only",
]
