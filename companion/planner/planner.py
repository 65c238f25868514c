"""`Planner.step`: one cycle of the spatial planner (steps 1-3 of section 3 of the paper).

Every cycle:
1. Range readings become world points, eqs (1)-(2).
2. Terrain following: aim point X_z, eq. (3), and desired pitch phi_d, eq. (4).
3. Steepness phi_i* and thresholds, eqs (6)-(7); steep points enter the obstacle memory.
4. If the path ahead comes within D_min + margin/2 of a remembered point, the horizontal
   path is reshaped (`avoidance.plan_detour`); if no reshaped path keeps D_min the planner
   reports BLOCKED and stops short of the obstacle, then backs out along the distance it has
   covered and tries the other way (`retreat`); failing that, or after a third retreat,
   straight legs over a grid of the memory (`gridpath`). The search spends at most
   SEARCH_BUDGET_UNITS work units a cycle and resumes next cycle (docs/avoidance.md).
5. The reference speed (`speed`) is limited by curvature (lateral acceleration), by the
   distance to the first point that would come closer than D_min, and by the distance to the
   end of the path, and ramps at accel_max; X_d advances along the path at that 3-D speed,
   eq. (5).
Deterministic: same inputs, same outputs. No clocks or I/O; dt_s comes from the caller.

Cost per cycle (a Raspberry Pi runs this at 20-50 Hz): the flown path's dense samples are
built once per path, the look-ahead (its samples, their clearance from the remembered
points) once per cycle and shared by the conflict check and the speed limit; the rest is
scalar arithmetic and a few small array operations on the sensor readings.
"""

from __future__ import annotations

import bisect
import copy
import math
from collections import deque
from collections.abc import Generator
from dataclasses import dataclass
from typing import NamedTuple, TypeVar

import numpy as np

from companion.planner import speed
from companion.planner.avoidance import (
    AvoidanceRequest,
    Detour,
    SearchFrame,
    detour_search,
    min_distance,
    min_distance_within,
    min_distance_within_updated,
    passed_beside,
)
from companion.planner.decision import chord_steepness_rows, decide_rows, steepness, thresholds
from companion.planner.frames import wrap_pi
from companion.planner.freespace import FreeFans
from companion.planner.gridpath import GridPlan, grid_search
from companion.planner.ground import (
    GroundPoints,
    carry_to_heading,
    fit_floor_z,
    floor_z,
    offsets_from_fit,
)
from companion.planner.memory import ObstacleMemory
from companion.planner.params import ArcMethod, PlannerParams
from companion.planner.path import Path
from companion.planner.retreat import RetreatPlan, backwards_track, retreat_search
from companion.planner.rotations import r_g
from companion.planner.route import Route
from companion.planner.sensors import (
    SURFACE_FOR_GROUP,
    Group,
    SensorTable,
    range_points_world,
    sector_fan_flu,
)
from companion.planner.sight import (
    describe_sweep,
    forward_depression_rad,
    layout_speed_limit_mps,
    sweep_amplitude_rad,
    wall_flag_distance_m,
)
from companion.planner.terrain import (
    advance_exact,
    advance_paper,
    aim_point_xyz,
    desired_pitch_xyz,
)
from companion.planner.types import (
    BoolArray,
    Decision,
    Diagnostics,
    FloatArray,
    PathMode,
    Setpoint,
    Side,
    StepResult,
    VehicleState,
)

_T = TypeVar("_T")
_TRACK_SPACING_M = 0.5
_TRACK_MAX_POINTS = 400
ACCEL_FEEDFORWARD_MAX_MPS2 = 2.0
"""Cap on the norm of the setpoint's acceleration feed-forward (m/s^2). X_d's own
acceleration stays far below it (speed ramps at accel_max, turns at lat_accel_max, climbs
follow the relief: 0.5 m/s^2 at the 99th percentile over the project's scenarios); what it
clips is the one-cycle jump of a velocity that a re-planned path turns at once."""
SEARCH_BUDGET_UNITS = 32
"""Work units (candidate corrections tried, `avoidance.detour_search`) a cycle may spend on
a re-plan. At rest, a search that needs more resumes next cycle where it stopped (while X_d,
the path's mode and sides are unchanged; it finishes on the points it started with); moving,
it counts as failed (blocked: the vehicle stops and searches again at rest). Enough for every
correction accepted while moving in the project's scenarios and in the random-world sweep
(at most 27 units seen), so that the bound changes no decision made on the move; what it
spreads over cycles are the searches at rest and the dead-end retreat (up to 9 full
searches, 50-150 ms in one cycle before)."""
SEARCH_BUDGET_UNITS_AT_REST = 8
"""The same bound for a search from X_d at rest: nothing waits on it but the vehicle's
stop, which it lengthens by a few cycles, and it resumes where it stopped, so a quarter of
the moving budget keeps those cycles (the slowest there were: 32 units cost 9-21 ms) within
a few milliseconds and the loop's period."""
_CLEARANCE_EXTRA_M = 10.0
"""The look-ahead clearances are measured this much beyond the look-ahead at once, metres,
sliced while the path does not change and brought up to date as the memory changes
(`Planner._clearance`): X_d covers this much before they are measured afresh. Longer makes
that rarer (at 2.5 m it was about 1% of the cycles on the move), for a few more samples
in each update."""
_NO_POINTS = np.empty((0, 3))
_NO_INFLATION = np.empty(0)
_NO_POINTS.setflags(write=False)
_NO_INFLATION.setflags(write=False)


class _SteepColumns(NamedTuple):
    """Per steep point of a cycle (`Planner._steep_points`), each (k,): its inflation,
    metres; the slope it comes from, radians (NaN: none measured); its reach on a long
    chord, metres, and the height it comes down to, world z metres (NaN: no reach); in
    the order of `ObstacleMemory.add`'s arguments."""

    inflation: FloatArray
    slope: FloatArray
    reach: FloatArray
    reach_z: FloatArray


_NO_COLUMNS = _SteepColumns(_NO_INFLATION, _NO_INFLATION, _NO_INFLATION, _NO_INFLATION)
_REACH_FREE_SHORT_M = 0.1
"""A ray bounds a remembered point's reach with its free part only up to this much short of
its range (range noise), metres (`Planner._bound_reach`)."""
_REACH_HEIGHT_TOLERANCE_M = 0.3
"""A ray's part up to this much above a point's reach height bounds its reach, metres: the
vehicle's height wanders about flight height, and above it a flank's footprint is smaller
by this over tan(theta) at most."""
_CARVE_SHORT_M = 0.5
"""A ray clears remembered points only up to this much short of its range, metres."""
_CARVE_TOLERANCE_M = 0.25
"""How close to a ray a remembered point must lie to be cleared by it, metres (one cell)."""
_CARVE_SUPPORT_M = 0.5
"""A point with a neighbour this close that stays is on a surface: not carved, metres."""
_ESCAPE_TOLERANCE_M = 0.05
"""A sample of an escape (a correction accepted inside the re-plan band) conflicts again only
if it has come this much closer to the memory than when the correction was accepted, m."""
_BLOCKED_AGAIN_M = 0.5
"""Left without a new path, the blocked state is said again only once X_d has moved this
far from where it was left, metres."""
_SECTOR_ARC_SPACING_M = 0.5
"""Spacing of the points a sector reading's arc enters the memory with, metres."""
# Sector readings kept as evidence of free space (`FreeFans`): the poses, and how far apart
# (metres moved or radians turned); 32 poses 0.5 m apart are the last 16 m flown.
_FREE_POSES = 32
_FREE_POSE_MOVE_M = 0.5
_FREE_POSE_TURN_RAD = math.radians(10.0)
# Boxed in at rest by sector arcs (`Planner._start_scan`): how long each heading of the
# turn is held (s), how many turns one place gets, and how near counts as the same place (m).
_SCAN_HOLD_S = 0.5
_SCANS_PER_PLACE = 2
_SCAN_PLACE_M = 1.0
_YAW_RATE_AT_REST_RAD_S = 0.8
_YAW_ALIGNED_RAD = 0.1
SWEEP_YAW_RATE_MAX_RAD_S = 0.75
"""The yaw sweep's rate at most (`Planner._swept_yaw`), rad/s (43 deg/s): within the yaw rate
PX4 allows an automatic heading (MPC_YAWRAUTO_MAX, 60 deg/s by default in the PX4 SITL
tested). At v_d 1 m/s the paper layout's swing peaks at 0.62."""
_GROUND_HOLD_RANGE = 4.0
_RETRY_BLOCKED_CYCLES = 20
# Retreats after which a block at rest searches the grid before the covered track: a retreat
# finds a correction that the memory allows, and a memory that grows at each new try can
# send the vehicle back and forth between two blocks for as long as it flies.
_RETREATS_BEFORE_GRID = 3
_MIN_CHORD_M = 0.5
"""Shortest chord, horizontally or vertically, whose slope counts (`chord_steepness`): over
shorter ones a few centimetres of range noise would read as a steep slope."""
_LOCAL_CHORD_M = 2.5
"""Longest horizontal chord whose slope is taken as the slope at its upper end, and the
farthest a flank is taken to reach below a remembered point (`Planner._steep_points`)."""
_SLOPE_SHARE_M = _LOCAL_CHORD_M
"""A long chord's reach is taken at most at the steepest slope a short chord measured within
this of its point horizontally, metres (`ObstacleMemory.slope_share_m`): as far as a short
chord's slope is taken as the slope at its upper end."""
_LEVEL_EPS = 1e-6
"""A sensor whose boresight's up component (body frame) is at most this is not tilted up."""
_GROUND_FIT_RADIUS_M = 3.0
"""Ground points within this horizontal radius of the middle of X_d(k-1) -> X_z shape the
aim (`ground`), metres."""
_GROUND_LIFT_MAX_M = 0.5
"""The most the ground's shape may move eq. (3)'s aim point up or down, metres."""
_GROUND_CONFIRM_M = 0.2
"""A surface hit enters the ground store only if its sensor's previous range is this near
to its own, metres (`Planner._remember_ground`)."""
_SURFACE_AHEAD_M = 0.5
"""X_d steers at the height H_d from the ground points this far ahead along its path's
heading (`Planner._surface_pitch`), metres."""
_SURFACE_SNAP_M = 0.2
"""... at the ground point nearest there, when one lies this near; else eq. (4) steers, no
lower than that height, metres."""
_REST_CLIMB_FRACTION = 0.5
"""At rest X_d's height moves toward H_d from the ground under it at up to this fraction of
the vertical speed the path allows (v_d sin(phi_max)) (`Planner._climb_at_rest`)."""
_REST_DEADBAND_M = 0.03
"""... when X_d is more than this off that height, metres; and on until within
_REST_SETTLED_M."""
_REST_SETTLED_M = 1e-3
_SLOPE_AHEAD_MARGIN_RAD = 1e-3
"""Where no ground point lies ahead, the fitted slope under X_d takes over from eq. (4) on
a descent only when it descends more steeply by this much, radians: over level ground the
fit's rounding (1e-11) must not move a level flight."""


@dataclass(frozen=True, slots=True)
class _PathSamples:
    """The flown path's dense samples as the per-cycle checks read them, built once per
    path: arc lengths s (n,) (also as a list, for bisect) and points (n, 2); v_curve_sq
    (n,), the squared speed at which each sample's curvature reaches lat_accel_max; and
    the "curve samples", where that speed is below about v_d (the only ones that can lower
    the reference speed; on straight stretches there are none): their indices (sorted),
    arc lengths and v_curve_sq."""

    s: FloatArray
    s_list: list[float]
    points: FloatArray
    curves: list[int]
    curve_s: FloatArray
    curve_v_sq: FloatArray

    @classmethod
    def of(cls, path: Path, lat_accel_max_mps2: float, v_d_mps: float) -> _PathSamples:
        poly = path.polyline()
        kappa = np.abs(poly.curvature)
        with np.errstate(divide="ignore"):
            v_curve = np.sqrt(lat_accel_max_mps2 / np.maximum(kappa, 1e-9))
        # A sample whose v_curve >= v_d cannot limit the speed (which never exceeds v_d);
        # 1 % over, so that the rounding of v_curve**2 cannot matter.
        curves = np.flatnonzero(v_curve < 1.01 * v_d_mps)
        v_sq = v_curve**2
        return cls(
            poly.s, poly.s.tolist(), poly.points, curves.tolist(), poly.s[curves], v_sq[curves]
        )

    def window(self, s_from: float, length_m: float) -> slice:
        """The samples with s_from <= s <= s_from + length_m (s is sorted)."""
        lo = bisect.bisect_left(self.s_list, s_from)
        return slice(lo, bisect.bisect_right(self.s_list, s_from + length_m))

    def curves_in(self, window: slice) -> slice:
        """The curve samples inside a window of samples, as a slice of curve_s/curve_v_sq."""
        lo = bisect.bisect_left(self.curves, window.start)
        return slice(lo, bisect.bisect_left(self.curves, window.stop))


class _LookAhead(NamedTuple):
    """The path from X_d to lookahead this cycle: the samples' arc lengths and points, the
    curve samples among them (their arc lengths and v_curve_sq, see `_PathSamples`), and
    the samples' clearance: the distance to the nearest remembered point, exact below the
    planner's clearance cutoff, larger or inf above; None when the memory is empty."""

    s: FloatArray
    points: FloatArray
    curve_s: FloatArray
    curve_v_sq: FloatArray
    clearance: FloatArray | None
    conflict: bool
    """Some sample's clearance is below the re-plan trigger, D_min + margin / 2."""


class _ClearanceCache(NamedTuple):
    """Clearances of the path samples start:stop (`Planner._clearance`), measured against
    the memory at `version`."""

    version: int
    samples: _PathSamples
    start: int
    stop: int
    values: FloatArray
    close: list[int]
    """The samples (indices into the path's samples, ascending) closer than the re-plan
    trigger."""
    box: tuple[float, float, float, float] | None
    """The samples' bounding box (x_lo, y_lo, x_hi, y_hi), metres, once an update needed
    it."""


@dataclass(frozen=True, slots=True)
class _Resolved:
    """How a re-plan search ended: a correction from here, a retreat, a way over the grid,
    or none of them (blocked)."""

    detour: Detour | None = None
    retreat: RetreatPlan | None = None
    grid: GridPlan | None = None


class Planner:
    """The spatial planner. Construct once per flight; call `step` every sampling period.

    params: tuning. sensors: the sensor table; `step` takes ranges in its order.
    route: the original route through the base points. start_position_enu: X_d at start
    (x, y must be the route's first base point; z is the starting height), metres ENU.
    """

    def __init__(
        self,
        params: PlannerParams,
        sensors: SensorTable,
        route: Route,
        start_position_enu: FloatArray,
    ) -> None:
        start = np.asarray(start_position_enu, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(start)):
            raise ValueError(f"start position must be finite, got {start}")
        gap = float(np.hypot(*(start[:2] - route.base_points[0])))
        if gap > 1.0:
            raise ValueError(
                f"start position is {gap:.1f} m from the first base point; "
                "prepend the vehicle position to the route"
            )
        self.params = params
        self.sensors = sensors
        self.route = route
        self._obstacle_groups = sensors.obstacle_groups
        self._thresholds = thresholds(self._obstacle_groups, params)
        self._threshold_list: list[float] = self._thresholds.tolist()
        # Threshold of every row of the table: eq. (7) for obstacle sensors; for surface
        # sensors phi_max fore and aft (the climb) and eq. (7)'s side value left and right.
        row_threshold = np.full(len(sensors), params.phi_max_rad)
        row_threshold[sensors.obstacle_index] = self._thresholds
        for group in (Group.SURFACE_LEFT, Group.SURFACE_RIGHT):
            if group in sensors.surface_index:
                row_threshold[sensors.surface_index[group]] = params.side_threshold_rad
        self._row_threshold = row_threshold
        self._row_threshold_list: list[float] = row_threshold.tolist()
        self._obstacle_rows: list[int] = sensors.obstacle_index.tolist()
        self._surface_items = tuple(sensors.surface_index.items())
        # Row of the sensor table -> its position among the obstacle sensors.
        self._obstacle_position = {int(r): k for k, r in enumerate(sensors.obstacle_index)}
        # Obstacle sensors mounted tilted up (body frame): their points lie above flight
        # height by design, where a long chord's reach down is taken (`_steep_points`).
        self._tilted_up: list[bool] = [
            r in self._obstacle_position and float(sensors.boresights_flu[r, 2]) > _LEVEL_EPS
            for r in range(len(sensors))
        ]
        # The rows of `_ground_points` when every surface sensor reads (the usual case).
        all_surface = sensors.surface_index
        self._ground_rows_all = np.array(
            [
                all_surface.get(SURFACE_FOR_GROUP[g], all_surface[Group.SURFACE_FORWARD])
                for g in self._obstacle_groups
            ],
            dtype=np.intp,
        )
        self._memory = ObstacleMemory(
            params.memory_cell_m,
            params.memory_radius_m,
            params.memory_max_points,
            _SLOPE_SHARE_M,
            _MIN_CHORD_M,
        )
        self._path: Path = route
        self._samples: _PathSamples | None = None
        self._look: _LookAhead | None = None
        self._clearance_cache: _ClearanceCache | None = None
        # Clearances only matter below the re-plan trigger (D_min + margin / 2) and, for the
        # stopping limit, 0.05 m beyond it; anything farther need not be measured exactly.
        self._clearance_cutoff_m = params.d_min_m + 0.5 * params.clearance_margin_m + 0.1
        self._segment, self._t = 0, 0.0
        self._s = 0.0
        self._z = float(start[2])
        self._xd_prev = np.array([*route.base_points[0], start[2]])
        self._v = 0.0
        self._velocity_prev = np.zeros(3)
        self._yaw = route.start_heading_rad
        self._h_d = params.h_d_m
        self._cycle = 0
        self._mode = PathMode.ROUTE
        self._side = Side.NONE
        self._avoid_side = Side.NONE
        self._after_retreat: tuple[PathMode, Side, float] | None = None
        self._detour_end_s = 0.0
        self._blocked = False
        self._stops: list[float] = []
        self._track: deque[tuple[float, float]] = deque(maxlen=_TRACK_MAX_POINTS)
        self._track.append((float(start[0]), float(start[1])))
        self._last_ground: dict[Group, list[float]] = {}  # [x, y, z] world ENU, metres
        self._ground_store = GroundPoints()
        self._surface_range: dict[int, float] = {}  # each surface sensor's last range, m
        self._sight_key: tuple[float, float] | None = None  # (H_d, phi_max) of _flag_m
        self._failed_attempt: tuple[int, int, int, bool] | None = None
        self._failed_cycle = 0
        self._search_units = 0
        self._search: tuple[tuple[object, ...], Generator[bool, None, _Resolved]] | None = None
        self._flag_m = 0.0  # how far ahead the layout flags a wall (`sight`), metres
        self._v_cruise = params.v_d_mps  # v_d, or the layout's limit without the lead
        self._v_layout = params.v_d_mps  # that limit with this cycle's lead
        self._ahead_m = 0.0  # the vehicle ahead of X_d along the path, metres
        self._held_by_leash = False  # X_d waits for a vehicle a leash from it
        # Obstacle sensors that read a sector (`SensorSpec.fov_rad`), and the rows of this
        # cycle's steep points (`_steep_points`), for `_sector_arcs`.
        self._sector_rows = np.flatnonzero(sensors.fov_rad > 0.0)
        self._arc_fans: dict[tuple[int, int], FloatArray] = {}  # (row, n): body FLU fan
        self._scan: list[float] = []  # yaw offsets still to turn to at rest, radians
        # The heading's swing across the layout's gaps while moving (`_swept_yaw`): its
        # amplitude (radians, 0: none) and phase (radians).
        period = params.yaw_sweep_period_m
        self._sweep_amplitude = sweep_amplitude_rad(sensors) if period > 0.0 else 0.0
        self._sweep_phase = 0.0
        # How far off the path the swing takes the forward surface sensor's ground hits,
        # per metre of H_d over level ground (`_surface_pitch`): 0 without a swing.
        depression = forward_depression_rad(sensors)
        self._swing_offset_per_h_d = (
            math.sin(self._sweep_amplitude) / math.tan(depression) if depression > 0.0 else 0.0
        )
        self._climb = 0.0  # X_d's vertical speed at rest (`_climb_at_rest`), m/s
        self._settling = False  # ... and whether it is on its way to H_d there
        self._scan_held_s = 0.0
        self._scan_place: tuple[int, int] | None = None
        self._scans_here = 0
        self._free_fans = (
            FreeFans(
                len(self._sector_rows),
                poses=_FREE_POSES,
                move_m=_FREE_POSE_MOVE_M,
                turn_rad=_FREE_POSE_TURN_RAD,
                tolerance_m=_CARVE_TOLERANCE_M,
            )
            if self._sector_rows.size
            else None
        )
        self._steep_rows = np.zeros(0, dtype=np.intp)
        # An accepted correction's stretch inside the re-plan band: arc lengths on the path
        # and the clearances it was accepted with (`_escape_exempt`); None if it has none.
        self._escape: tuple[FloatArray, FloatArray] | None = None
        # The clearance (m) below which the band's speed cap stops X_d (`_lower_band_floor`).
        self._band_floor = params.d_min_m
        # Flying straight legs over the grid (`gridpath`): a conflict is met by the grid.
        self._grid_way = False
        self._retreats = 0  # retreats since the start or the last way over the grid
        # X_d where the blocked state was left without a new path (`_set_blocked`).
        self._unblocked_xy: FloatArray | None = None

    def __deepcopy__(self, memo: dict[int, object]) -> Planner:
        """A copy of the planner; a re-plan search still going on (a generator, which cannot
        be copied) starts afresh in the copy."""
        twin = Planner.__new__(Planner)
        memo[id(self)] = twin
        for name, value in self.__dict__.items():
            setattr(twin, name, None if name == "_search" else copy.deepcopy(value, memo))
        return twin

    @property
    def _xd_prev(self) -> FloatArray:
        """X_d of the last cycle, (3,) metres world ENU; also kept as plain floats
        (`_xd_prev_xyz`) for the per-cycle scalar paths, set together by the setter."""
        return self._xd_prev_enu

    @_xd_prev.setter
    def _xd_prev(self, value: FloatArray) -> None:
        self._xd_prev_enu = value
        x, y, z = value.tolist()
        self._xd_prev_xyz = (x, y, z)

    # --- public controls -------------------------------------------------------------------
    @property
    def desired_height_m(self) -> float:
        return self._h_d

    def set_desired_height(self, h_d_m: float) -> None:
        """Change H_d in flight. The climb to it is limited by phi_max, so it is a ramp."""
        if not (math.isfinite(h_d_m) and h_d_m > 0.0):
            raise ValueError(f"H_d must be a positive number, got {h_d_m}")
        self._h_d = float(h_d_m)

    def replace_route(self, points_xy: FloatArray, arrival_heading_rad: float | None) -> None:
        """Fly a new route from the current reference point, leaving along its current
        tangent (no jump in heading or speed)."""
        pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        here = self._xd_prev[:2]
        if len(pts) and float(np.hypot(*(pts[0] - here))) < 1e-3:
            pts = pts[1:]
        route = Route(np.vstack([here, pts]), self._path_heading(), arrival_heading_rad)
        self.route = route
        self._set_path(route, PathMode.ROUTE, Side.NONE)
        self._detour_end_s = 0.0
        self._retreats = 0
        self._blocked = False
        self._unblocked_xy = None

    @property
    def path(self) -> Path:
        """The horizontal path currently flown (the route or a corrected one)."""
        return self._path

    @property
    def memory_points_xy(self) -> FloatArray:
        return self._memory.points_xy().copy()

    # --- the cycle -------------------------------------------------------------------------
    def _acceleration(self, velocity: FloatArray, dt_s: float) -> FloatArray:
        """X_d's acceleration over this cycle (m/s^2, ENU): the change of its velocity, its
        norm capped at ACCEL_FEEDFORWARD_MAX_MPS2 (a re-planned path turns the velocity at
        once, which no vehicle follows within a cycle)."""
        a = (velocity - self._velocity_prev) / dt_s
        self._velocity_prev = velocity
        n = math.sqrt(float(a.dot(a)))
        if n > ACCEL_FEEDFORWARD_MAX_MPS2:
            a *= ACCEL_FEEDFORWARD_MAX_MPS2 / n
        return a

    def step(self, state: VehicleState, ranges_m: FloatArray, dt_s: float) -> StepResult:
        """One planner cycle. ranges_m: (n,) metres in sensor-table order; 0, NaN, below min
        or at/over max mean "nothing detected". dt_s: sampling period, seconds."""
        if not (math.isfinite(dt_s) and dt_s > 0.0):
            raise ValueError(f"dt_s must be a positive number, got {dt_s}")
        ranges = np.asarray(ranges_m, dtype=np.float64).reshape(-1)
        if len(ranges) != len(self.sensors):
            raise ValueError(f"expected {len(self.sensors)} ranges, got {len(ranges)}")
        params = self.params
        self._cycle += 1
        self._search_units = 0
        events: list[str] = []
        if self._cycle == 1 and self._sweep_amplitude > 0.0:
            gap = math.degrees(2.0 * self._sweep_amplitude)
            sweep = describe_sweep(self._sweep_amplitude, params.yaw_sweep_period_m)
            events.append(f"sensor layout leaves a {gap:.0f} deg gap ahead: {sweep}")

        # Eqs (1)-(2): world points of every reading.
        rot = r_g(state.roll_rad, state.pitch_rad, state.yaw_rad)
        valid = self.sensors.valid(ranges)
        valid_list: list[bool] = valid.tolist()
        points = range_points_world(state.position_enu, rot, self.sensors.boresights_flu, ranges)
        pts: list[list[float]] = points.tolist()
        surface = {g: i for g, i in self._surface_items if valid_list[i]}

        # Eqs (3)-(4): desired pitch from the fore and aft ground points.
        x_h1 = self._ground_point(Group.SURFACE_FORWARD, pts, surface, state)
        x_h2 = self._ground_point(Group.SURFACE_BACK, pts, surface, state)
        surface_valid = x_h1 is not None and x_h2 is not None
        if x_h1 is not None and x_h2 is None and params.shape_terrain:
            x_h2 = self._ground_behind(x_h1)
        x_z: tuple[float, float, float] | None = None
        if x_h1 is not None and x_h2 is not None:
            try:
                (x1, y1, z1), (x2, y2, z2) = x_h1, x_h2
                x_z = aim_point_xyz(x1, y1, z1, x2, y2, z2, state.yaw_rad, self._h_d)
            except ValueError:
                surface_valid = False

        # Eqs (6)-(7): steepness of each obstacle reading against its group's ground point,
        # raised to the steepest chord measured this cycle (`chord_steepness`); steep
        # points, surface readings included, enter the obstacle memory.
        obs = self.sensors.obstacle_index
        detected = valid[obs]
        ground = self._ground_points(points, surface, state)
        phi_star = steepness(points.take(obs, axis=0), ground, detected)
        steep_xyz, steep_columns = self._steep_points(
            points, pts, valid, valid_list, detected, ground, phi_star
        )
        if self._sector_rows.size and len(steep_xyz):
            steep_xyz, steep_columns = self._sector_arcs(
                state.position_enu, rot, ranges, valid, steep_xyz, steep_columns
            )
        phi_d = 0.0  # no ground in view: hold the height
        if x_z is not None:
            if params.shape_terrain:
                self._remember_ground(pts, ranges, surface, len(steep_xyz) > 0)
                phi_d = self._surface_pitch(x_z, state, params.phi_max_rad)
            else:
                phi_d = desired_pitch_xyz(*x_z, *self._xd_prev_xyz, params.phi_max_rad)
        decision = decide_rows(phi_star.tolist(), self._threshold_list)
        self._carve(state, rot, ranges, valid)
        if len(steep_xyz):
            self._memory.add(steep_xyz, self._cycle, *steep_columns)
        self._bound_reach(state, rot, ranges, valid)
        self._memory.forget_far(state.position_enu[:2])
        ranges_list: list[float] = ranges.tolist()
        nearest = min(
            [ranges_list[r] for r in self._obstacle_rows if valid_list[r]], default=math.inf
        )
        min_range = nearest if nearest < math.inf else 0.0

        # Horizontal correction when the path ahead conflicts with remembered points.
        self._look = None  # the memory has changed: measure the look-ahead afresh
        was_blocked = self._blocked
        replanned = self._update_path(state, ranges, valid, events)
        if was_blocked and not self._blocked and not replanned:
            self._unblocked_xy = self._xd_prev[:2].copy()
        if self._blocked:
            decision = Decision.BLOCKED

        # Reference speed and eq. (5); the stop allows for the vehicle ahead of X_d.
        heading = self._path_heading()
        self._ahead_m = self._vehicle_ahead_m(state.position_enu, heading)
        self._update_layout_limit(dt_s, events)
        v_target = self._speed_target()
        lag = self._vehicle_lag_m(state.position_enu)
        v_leash = speed.leash_limit(lag, params.leash_m, v_target, params.accel_max_mps2)
        self._announce_leash(lag, v_leash == 0.0 < v_target, events)
        v_target = v_leash
        yaw_error = wrap_pi(heading - self._yaw)
        if abs(yaw_error) > _YAW_ALIGNED_RAD and self._v <= speed.STOPPED_MPS:
            v_target = 0.0  # turn on the spot before leaving a stop in a new direction
        if self._search is not None and self._v <= speed.STOPPED_MPS:
            v_target = 0.0  # at rest, a search still going on finishes from here
        if self._scan:
            v_target = 0.0  # turning on the spot to read the sectors from other headings
        self._v = speed.ramp(self._v, v_target, params.accel_max_mps2, dt_s)
        step_m = speed.step_to_next_stop(self._v * dt_s, self._s, self._stops, phi_d)
        if params.arc_method is ArcMethod.EXACT:
            self._s, self._z = advance_exact(self._path, self._s, self._z, step_m, phi_d)
            self._segment, self._t = self._path.locate(self._s)
        elif step_m > 0.0:
            seg, t, z, _ = advance_paper(
                self._path, self._segment, self._t, self._z, step_m, phi_d, params.paper_delta
            )
            self._segment, self._t, self._z = seg, t, z
            self._s = self._path.arc_length_at(seg, t)
        climb_mps = self._climb_at_rest(self._v <= speed.STOPPED_MPS, dt_s)
        self._z += climb_mps * dt_s
        x, y = self._path.segments[self._segment].point(self._t)
        x_d = np.array([x, y, self._z])

        heading = self._path_heading()
        if self._v > speed.STOPPED_MPS:
            self._yaw = self._swept_yaw(heading, step_m, dt_s)
            self._scan.clear()  # (no list made each cycle)
        else:
            self._sweep_phase = 0.0  # the next swing starts on the heading
            aim = heading + self._scan[0] if self._scan else heading
            turn = _YAW_RATE_AT_REST_RAD_S * dt_s
            self._yaw = wrap_pi(self._yaw + min(max(wrap_pi(aim - self._yaw), -turn), turn))
            if self._scan and abs(wrap_pi(aim - self._yaw)) < 1e-9:
                self._scan_held_s += dt_s
                if self._scan_held_s >= _SCAN_HOLD_S:
                    self._scan.pop(0)
                    self._scan_held_s = 0.0
        cos_phi = math.cos(phi_d)
        velocity = np.array(
            [
                self._v * (math.cos(heading) * cos_phi),
                self._v * (math.sin(heading) * cos_phi),
                self._v * math.sin(phi_d) + climb_mps,
            ]
        )
        acceleration = self._acceleration(velocity, dt_s)
        self._record_track(x, y)
        self._xd_prev = x_d

        if self._mode is not PathMode.ROUTE and self._s >= self._detour_end_s:
            if self._after_retreat is not None:
                # Backed out: now the correction on the other side.
                self._mode, self._side, self._detour_end_s = self._after_retreat
                self._after_retreat = None
            else:
                events.append("obstacle passed, back on route")
                self._mode, self._side = PathMode.ROUTE, Side.NONE
                self._grid_way = False
                self._avoid_side = Side.NONE
        finished = (
            self._path.length - self._s <= params.goal_tolerance_m
            and self._v <= speed.STOPPED_MPS
            and self._path_ends_at_goal()
            and lag <= 0.5 * params.leash_m
            and abs(wrap_pi(heading - self._yaw)) < 1e-9  # turned back from a swing
        )
        x_d.setflags(write=False)
        setpoint = Setpoint(x_d, velocity, self._yaw, phi_d, acceleration)
        diagnostics = Diagnostics(
            decision=decision,
            mode=self._mode,
            side=self._side,
            phi_star_rad=phi_star,
            threshold_rad=self._thresholds,
            phi_d_rad=phi_d,
            segment=self._segment,
            parameter=self._t,
            speed_ref_mps=self._v if climb_mps == 0.0 else float(np.linalg.norm(velocity)),
            min_range_m=min_range,
            surface_valid=surface_valid,
            replanned=replanned,
            finished=finished,
            events=tuple(events),
            search_units=self._search_units,
            searching=self._search is not None,
        )
        return StepResult(setpoint, diagnostics)

    # --- helpers ----------------------------------------------------------------------------
    def _ground_point(
        self, group: Group, pts: list[list[float]], surface: dict[Group, int], state: VehicleState
    ) -> list[float] | None:
        """X_h of a surface sensor this cycle, or the last one it measured while that is
        still on its side of the vehicle (ahead for h1, behind for h2) and within
        _GROUND_HOLD_RANGE H_d: ground does not move, and a tilted vehicle looks past it
        for a while (a nose-down pitch lifts the backward sensor above its range).
        [x, y, z], world ENU metres (pts: this cycle's range points as plain floats)."""
        idx = surface.get(group)
        if idx is not None:
            point = pts[idx]
            self._last_ground[group] = point
            return point
        held = self._last_ground.get(group)
        if held is None:
            return None
        x, y = state.position_enu[:2].tolist()
        rel_x, rel_y = held[0] - x, held[1] - y
        along = rel_x * math.cos(state.yaw_rad) + rel_y * math.sin(state.yaw_rad)
        ahead = group is Group.SURFACE_FORWARD
        if (along > 0.0) == ahead and math.hypot(rel_x, rel_y) <= _GROUND_HOLD_RANGE * self._h_d:
            return held
        return None

    def _ground_behind(self, x_h1: list[float]) -> list[float]:
        """A stand-in for X_h2 when the backward sensor has no point (it looks past the
        ground while the vehicle pitches nose-down, or its reading could not be paired with
        an attitude): the place H_d behind X_h1 along the path's heading, on the slope the
        ground store fits there, level without a fit. Eq. (4) then steers H_d above the
        ground the forward sensor measures, instead of X_d holding its height for want of
        a second point (a jolt in phi_d mid-descent). [x, y, z], world ENU metres."""
        x1, y1, z1 = x_h1
        heading = self._path_heading()
        c, s = math.cos(heading), math.sin(heading)
        fit = self._ground_store.fit(x1, y1, _GROUND_FIT_RADIUS_M)
        gx, gy = fit.gradient(x1, y1) if fit is not None else (0.0, 0.0)
        back = self._h_d
        return [x1 - back * c, y1 - back * s, z1 - back * (gx * c + gy * s)]

    def _remember_ground(
        self, pts: list[list[float]], ranges: FloatArray, surface: dict[Group, int], steep: bool
    ) -> None:
        """This cycle's surface hits that are not too steep to climb into the ground store,
        each only when its sensor's previous range agrees within _GROUND_CONFIRM_M: the
        store's floor is a maximum over its points (`_surface_pitch`), and one spurious
        short range (a point in the air) would hold X_d up for as long as it is kept."""
        skip = set(self._steep_rows.tolist()) if steep else set()
        for i in surface.values():
            r = float(ranges[i])
            prev = self._surface_range.get(i)
            self._surface_range[i] = r
            if i in skip or prev is None or abs(r - prev) > _GROUND_CONFIRM_M:
                continue
            x, y, z = pts[i]
            self._ground_store.add(i, x, y, z)

    def _shaped_aim(
        self, x_z: tuple[float, float, float], state: VehicleState
    ) -> tuple[float, float, float]:
        """Eq. (3)'s aim point raised for the slope across the heading and for the lag over
        curved relief (`ground.offsets_from_fit`), and its height carried over to X_d's
        heading line, when the ground store fits a surface. (x, y, z) world ENU, metres."""
        zx, zy, zz = x_z
        xd, yd, _ = self._xd_prev_xyz
        # About the middle of the stretch eq. (4) steers over: X_d (k-1) to the aim.
        cx = 0.5 * (zx + xd)
        cy = 0.5 * (zy + yd)
        fit = self._ground_store.fit(cx, cy, _GROUND_FIT_RADIUS_M)
        if fit is None:
            return x_z
        lead = math.hypot(zx - xd, zy - yd)
        side, bend = offsets_from_fit(
            fit, zx, zy, state.yaw_rad, self._h_d, lead, reach_m=_GROUND_FIT_RADIUS_M
        )
        # The aim lies on the body's heading, 3-4 m ahead on a descent: on a curved path
        # that is off X_d's heading, and on a side slope the ground there is not the
        # path's. Carried over to the heading line with the fitted slope, as
        # `_surface_pitch` does for a stored point.
        _, shift = carry_to_heading(*fit.gradient(zx, zy), zx, zy, xd, yd, self._path_heading())
        lift = min(max(side + bend + shift, -_GROUND_LIFT_MAX_M), _GROUND_LIFT_MAX_M)
        return zx, zy, zz + lift

    def _surface_pitch(
        self, x_z: tuple[float, float, float], state: VehicleState, phi_max_rad: float
    ) -> float:
        """phi_d (radians, within phi_max) from the ground store: H is the shortest distance
        to the surface, and the stored ground points say where H_d is (`ground.floor_z`:
        the lowest height at H_d from every point).

        - Where a ground point lies within _SURFACE_SNAP_M (plus, while the heading swings,
          how far off the path the swing takes the forward sensor's hits) of the place
          _SURFACE_AHEAD_M ahead of X_d on its heading (and ahead of X_d along it), X_d
          steers at H_d from the points there (at that point's own place, where its
          sphere is exact; between points their envelope dips by H_d - sqrt(H_d^2 - r^2)),
          and no lower than H_d off the plane of the fit's
          slope through that point (the points lie in a few lines along the track, and on
          a side slope the place where H_d's sphere touches the ground lies between them:
          there the fit's slope says more), carried over from the point to X_d's heading
          with the fit's slope. Eq. (4) steers at an aim about 2 H_d ahead: a
          first-order lag that cuts a mesa's rim or a crest on the way down and rounds a
          flank's foot.
        - Else eq. (4) on the aim shaped by the fit (`_shaped_aim`); on a descent, H_d off
          the slope fitted under X_d, _SURFACE_AHEAD_M ahead, instead, whether it descends
          more steeply (a level body's forward sensor, a multicopter's, meets a descent
          nearly as steep as its tilt only past the foot, and eq. (4) then steers along
          the chord over the foot, up to 1 m above H_d: docs/paper.md) or less steeply
          (over a crest on the way down the slope steepens, and the height H_d off it with
          it, faster than eq. (4)'s lag towards an aim 3-4 m ahead follows: X_d went
          0.14 m low), never climbing for it.
        Either is kept no lower than H_d from the points _SURFACE_AHEAD_M ahead, and from
        the surface fitted under X_d about there (`ground.fit_floor_z`: the ground between
        the sensors' lines)."""
        xd, yd, zd = self._xd_prev_xyz
        heading = self._path_heading()
        cos_h, sin_h = math.cos(heading), math.sin(heading)
        qx = xd + _SURFACE_AHEAD_M * cos_h
        qy = yd + _SURFACE_AHEAD_M * sin_h
        store = self._ground_store
        # Every point within H_d of q, or of a point within _SURFACE_SNAP_M of q.
        # (Swinging, the forward sensor's hits lie up to its swing's offset off the line.)
        snap = _SURFACE_SNAP_M + self._h_d * self._swing_offset_per_h_d
        points, r2q = store.near(qx, qy, self._h_d + snap)
        floor_q = floor_z(points[:, 2], r2q, self._h_d)
        k = int(r2q.argmin()) if len(r2q) else -1
        px, py, pz = points[k].tolist() if k >= 0 else (qx, qy, math.nan)
        run = math.hypot(px - xd, py - yd)
        # (ahead of X_d along the heading: a swing's hit can lie off the line beside X_d)
        ahead = (px - xd) * cos_h + (py - yd) * sin_h
        if k >= 0 and r2q[k] <= snap * snap and min(run, ahead) >= 0.5 * _SURFACE_AHEAD_M:
            dx = points[:, 0] - px
            dy = points[:, 1] - py
            target = floor_z(points[:, 2], dx * dx + dy * dy, self._h_d)
            fit = store.fit(0.5 * (px + xd), 0.5 * (py + yd), _GROUND_FIT_RADIUS_M)
            if fit is not None:
                gx, gy = fit.gradient(px, py)
                lift = self._h_d * (math.sqrt(1.0 + gx * gx + gy * gy) - 1.0)
                target = max(target, pz + self._h_d + min(lift, _GROUND_LIFT_MAX_M))
                # The point lies up to _SURFACE_SNAP_M off X_d's heading (on a curve, the
                # forward sensor's hits lie on the tangent, outside the path): carry the
                # height over to the heading with the fitted slope, and steer over the run
                # along it. On a side slope the height at the point is not the path's.
                along, shift = carry_to_heading(gx, gy, px, py, xd, yd, heading)
                target += min(max(shift, -_GROUND_LIFT_MAX_M), _GROUND_LIFT_MAX_M)
                run = along
            phi_d = min(max(math.atan2(target - zd, run), -phi_max_rad), phi_max_rad)
            under = store.fit(xd, yd, _GROUND_FIT_RADIUS_M)
        else:
            phi_d = desired_pitch_xyz(
                *self._shaped_aim(x_z, state), *self._xd_prev_xyz, phi_max_rad
            )
            under = store.fit(xd, yd, _GROUND_FIT_RADIUS_M)
            if under is not None and phi_d < 0.0:
                gx, gy = under.gradient(qx, qy)
                target = under.height(qx, qy) + self._h_d * math.sqrt(1.0 + gx * gx + gy * gy)
                along_fit = math.atan2(target - zd, _SURFACE_AHEAD_M)
                if along_fit < phi_d - _SLOPE_AHEAD_MARGIN_RAD:
                    phi_d = max(along_fit, -phi_max_rad)
                elif along_fit > phi_d:
                    phi_d = min(along_fit, 0.0)
        # ... and H_d from the surface fitted under X_d about there: the ground between
        # the sensors' lines (`ground.fit_floor_z`).
        if under is not None:
            floor_q = max(floor_q, fit_floor_z(under, qx, qy, self._h_d))
        if floor_q > -math.inf:
            phi_d = max(phi_d, min(math.atan2(floor_q - zd, _SURFACE_AHEAD_M), phi_max_rad))
        return phi_d

    def _climb_at_rest(self, at_rest: bool, dt_s: float) -> float:
        """X_d's vertical speed this cycle on top of eq. (5)'s, m/s (up positive).

        Eq. (5) moves X_d only along its path, so a stop keeps the height X_d had, and its
        offset from H_d, for as long as the vehicle stands (a stop on the way into a hollow
        held X_d 0.11 m high for 20 s: random world 492, ring-8), and an H_d changed at rest
        is not taken up. At rest (with `shape_terrain`) X_d moves by `_rest_height_error`
        at up to _REST_CLIMB_FRACTION v_d sin(phi_max), speeding up and slowing down at
        accel_max so that it stops there. It starts only when X_d is more than
        _REST_DEADBAND_M off (sensor noise does not move a vehicle at rest), and goes on
        until within _REST_SETTLED_M. Once X_d moves again, this speed ramps down to zero at
        accel_max (eq. (5) steers from there)."""
        params = self.params
        want = 0.0
        error = self._rest_height_error() if at_rest and params.shape_terrain else 0.0
        if abs(error) > _REST_DEADBAND_M:
            self._settling = True
        elif abs(error) < _REST_SETTLED_M:
            self._settling = False
        if self._settling:
            top = _REST_CLIMB_FRACTION * params.v_d_mps * math.sin(params.phi_max_rad)
            brake = speed.stepped_braking_speed(abs(error), params.accel_max_mps2, dt_s)
            want = math.copysign(min(top, brake, abs(error) / dt_s), error)
        dv = params.accel_max_mps2 * dt_s
        self._climb = min(max(want, self._climb - dv), self._climb + dv)
        return self._climb

    def _rest_height_error(self) -> float:
        """How far X_d (of the last cycle) lies below the height H_d from the ground under
        it, metres (negative: above): `ground.floor_z` of the stored points within H_d, no
        lower than `ground.fit_floor_z` of the surface fitted there. 0 where no stored point
        lies within H_d or no surface is fitted, and no lower than 0 while a remembered
        obstacle point lies within D_min + margin of X_d horizontally: the store leaves steep
        points out, so its floor beside or on top of a solid can lie below the solid's
        surface (random world 487, ring-8, came down 4 cm over a steep solid to 1.91 m from
        it)."""
        xd, yd, zd = self._xd_prev_xyz
        store = self._ground_store
        fit = store.fit(xd, yd, _GROUND_FIT_RADIUS_M)
        points, r2 = store.near(xd, yd, self._h_d)
        if fit is None or len(r2) == 0:
            return 0.0
        floor = max(floor_z(points[:, 2], r2, self._h_d), fit_floor_z(fit, xd, yd, self._h_d))
        error: float = floor - zd
        keep_m = self.params.d_min_m + self.params.clearance_margin_m
        if error < 0.0 and len(self._memory.near(self._xd_prev[:2], keep_m)):
            return 0.0
        return error

    def _ground_points(
        self, points: FloatArray, surface: dict[Group, int], state: VehicleState
    ) -> FloatArray:
        """X_hj paired with each obstacle sensor (eq. 6); when the group's surface reading is
        missing, the forward one, else the point H_d below the vehicle."""
        if len(surface) == len(self.sensors.surface_index):
            every: FloatArray = points.take(self._ground_rows_all, axis=0)
            return every
        rows = [surface.get(SURFACE_FOR_GROUP[group], -1) for group in self._obstacle_groups]
        out: FloatArray = points.take(rows, axis=0)
        missing = [k for k, idx in enumerate(rows) if idx < 0]
        if missing:
            fallback_idx = surface.get(Group.SURFACE_FORWARD)
            if fallback_idx is not None:
                out[missing] = points[fallback_idx]
            else:
                out[missing] = state.position_enu - np.array([0.0, 0.0, self._h_d])
        return out

    def _steep_points(
        self,
        points: FloatArray,
        pts: list[list[float]],
        valid: BoolArray,
        valid_list: list[bool],
        detected: BoolArray,
        ground: FloatArray,
        phi_star: FloatArray,
    ) -> tuple[FloatArray, _SteepColumns]:
        """The points measured this cycle that are too steep to climb, (k, 3), and per
        point (`_SteepColumns`, each (k,)): the inflation, metres; the slope theta it comes
        from, radians (NaN where no short chord measured it); the reach on a long chord,
        metres, and the height it comes down to (world z, metres). phi_star (eq. 6, per
        obstacle sensor) is raised in place to the steepest chord through each obstacle
        reading.

        Inflation: the solid below a steep point X_i slopes towards the vehicle at about
        theta, its steepest chord (a lower bound on the true slope, so the estimate errs
        wide). Two things follow from theta:
        - keeping D_min from an inclined flank takes D_min / sin(theta) horizontally, so
          that a point's inflated disc is D_min away where the flank is (the margin on top
          is kept whole: the memory's measure is never the optimistic one). Only for a
          short chord (<= _LOCAL_CHORD_M), which says something about the surface at X_i;
        - the vehicle passes at the height of the ground near X_i, z_g (the lower of the
          chord's other end and the group's ground point), plus H_d, where the flank reaches
          (z_i - z_g - H_d) / tan(theta) nearer than X_i: the surface crosses that height
          somewhere between X_i and the chord's other end, and the chord's line says where.
          Never past the other end. On a long chord the reach is a guess (a wall seen by
          a beam tilted up reads the same as a flank), taken only for sensors mounted
          tilted up, whose points lie above flight height by design and whose flank below
          no level sensor may see, and no farther than _LOCAL_CHORD_M (the most a short
          chord can reach). A level sensor's point is above flight height only by the
          vehicle's attitude, and its reading is the solid at flight height. That reach is
          kept apart from the inflation (as the reach, down to z_g + H_d), and the memory
          bounds it by evidence over time (`ObstacleMemory`): taken from a second cycle's
          reading there; at most at the steepest slope measured within _SLOPE_SHARE_M,
          or chord to the other remembered points there (a pillar's face measured steep
          by the forward beams, a wall met at other heights); at most as far as the rays
          that passed it at flight height allow (`_bound_reach`). So a wall or a pillar
          is not widened, and a flank keeps what it may reach.
        Short chord (h <= _LOCAL_CHORD_M): e = max(0, D_min / sin(theta) - D_min) + min(h,
        max(0, z_i - z_g - H_d) / tan(theta)), no reach; long chord, sensor tilted up: e =
        0, reach min(_LOCAL_CHORD_M, max(0, z_i - z_g - H_d) / tan(theta)); else e = 0 and
        no reach (as seen).
        The lower part of a flank is measured, not only extrapolated: the surface sensors
        hit it as the vehicle comes near, and their steep points enter the memory too.
        """
        params = self.params
        sensors = self.sensors
        # Plain floats up to the steep test (the usual cycle has nothing steep): the same
        # numbers as the array form (max of two floats, the same comparisons).
        rows = [r for r, ok in enumerate(valid_list) if ok]
        cloud_points = [pts[r] for r in rows]
        for g, p in self._last_ground.items():
            if (i := sensors.surface_index.get(g)) is None or not valid_list[i]:
                cloud_points.append(p)
        phi_pair, partners = chord_steepness_rows(cloud_points, _MIN_CHORD_M)
        phi_row = [0.0] * len(sensors)
        for r, phi in zip(rows, phi_pair, strict=False):
            phi_row[r] = phi
        obs = self._obstacle_rows
        chord_obs = [phi_row[r] for r in obs]
        star = phi_star.tolist()
        # Both are 0 where nothing was detected (`steepness`, and phi_row's zeros).
        raised = list(map(max, star, chord_obs))
        for r, phi in zip(obs, raised, strict=True):
            phi_row[r] = phi
        threshold = self._row_threshold_list
        steep_rows = [r for r in rows if phi_row[r] > threshold[r]]
        phi_star[:] = raised
        if not steep_rows:  # the usual cycle: nothing to remember
            return _NO_POINTS, _NO_COLUMNS
        # Where eq. (6)'s own chord is the steeper one, its other end is the ground point.
        eq6 = [ok and a >= b for ok, a, b in zip(detected.tolist(), star, chord_obs, strict=True)]
        # The rest per steep row in plain Python (there are a few): the chord's other end
        # and the group's ground height (inf for a surface row), then the inflation.
        cloud_rows = {r: j for j, r in enumerate(rows)}
        ground_points = ground.tolist()
        xyz = points.take(steep_rows, axis=0)
        lows: list[list[float]] = []
        for r in steep_rows:
            k = self._obstacle_position.get(r)
            if k is not None and eq6[k]:
                lows.append(ground_points[k])
            else:
                j = partners[cloud_rows[r]]
                lows.append(cloud_points[j] if j >= 0 else [math.nan] * 3)
        steep_points = [pts[r] for r in steep_rows]
        # np.hypot, not math.hypot: the two can differ in the last bit.
        chords: list[float] = np.hypot(
            [p[0] - q[0] for p, q in zip(steep_points, lows, strict=True)],
            [p[1] - q[1] for p, q in zip(steep_points, lows, strict=True)],
        ).tolist()
        n = len(steep_rows)
        inflation, slope = [0.0] * n, [math.nan] * n
        reach, reach_z = [0.0] * n, [math.nan] * n
        d_min = params.d_min_m
        for j, (r, p, q, h) in enumerate(zip(steep_rows, steep_points, lows, chords, strict=True)):
            if math.isnan(h):  # no chord's other end: as seen
                continue
            theta = phi_row[r]
            k = self._obstacle_position.get(r)
            z_g = q[2] if k is None else min(q[2], ground_points[k][2])
            rise = max(p[2] - z_g - self._h_d, 0.0)
            if h <= _LOCAL_CHORD_M:
                slope[j] = theta
                foot = min(h, rise / math.tan(theta))
                inflation[j] = max(d_min / math.sin(theta) - d_min, 0.0) + foot
            elif self._tilted_up[r]:
                reach[j] = min(_LOCAL_CHORD_M, rise / math.tan(theta))
                reach_z[j] = z_g + self._h_d
        self._steep_rows = np.asarray(steep_rows, dtype=np.intp)
        columns = _SteepColumns(
            np.array(inflation), np.array(slope), np.array(reach), np.array(reach_z)
        )
        return xyz, columns

    def _sector_arcs(
        self,
        position_enu: FloatArray,
        rot: FloatArray,
        ranges: FloatArray,
        valid: BoolArray,
        xyz: FloatArray,
        columns: _SteepColumns,
    ) -> tuple[FloatArray, _SteepColumns]:
        """A steep reading of a sensor with a field of view (a proximity sector) says that
        the nearest object in the sector is at that range, not where on the arc: the whole
        arc across the sector, points _SECTOR_ARC_SPACING_M apart, enters the memory with
        the boresight point's inflation, slope and reach (`_SteepColumns`). (k, 3) points
        and their columns, the arcs added."""
        rows = self._steep_rows
        fov = self.sensors.fov_rad[rows]
        sector = fov > 0.0
        if not np.count_nonzero(sector):
            return xyz, columns
        arcs: list[FloatArray] = []
        which = sector.nonzero()[0]
        for k in which:
            i = int(rows[k])
            r = float(ranges[i])
            n = max(2, math.ceil(float(fov[k]) * r / _SECTOR_ARC_SPACING_M) + 1)
            fan = self._arc_fans.get((i, n))
            if fan is None:  # (at most a few dozen per sector: n grows with the range)
                fan = sector_fan_flu(self.sensors.boresights_flu[i], float(fov[k]), n)
                self._arc_fans[(i, n)] = fan
            arcs.append(position_enu + r * (fan @ rot.T))
        if self._free_fans is not None:
            # Where a fan from another pose saw part of an arc free, the object is on the
            # rest of it (all of it seen free: the readings disagree, and it all stays).
            seen = self._free_fans.seen_free(np.vstack(arcs))
            ends = np.cumsum([len(a) for a in arcs])[:-1]
            for j, part in enumerate(np.split(seen, ends)):
                if part.any() and not part.all():
                    arcs[j] = arcs[j][~part]
        extra_xyz = [xyz]
        extra: list[list[FloatArray]] = [[c] for c in columns]
        for k, arc in zip(which, arcs, strict=True):
            extra_xyz.append(arc)
            for parts, c in zip(extra, columns, strict=True):
                parts.append(np.full(len(arc), c[k]))
        return np.vstack(extra_xyz), _SteepColumns(*(np.concatenate(p) for p in extra))

    def _path_heading(self) -> float:
        return self._path.segments[self._segment].heading(self._t)

    def _swept_yaw(self, heading: float, step_m: float, dt_s: float) -> float:
        """The yaw while moving (radians, ENU): the path's heading, swung across the widest
        bearing gap between the obstacle sensors ahead by a sine of X_d's travel (amplitude
        `sight.sweep_amplitude_rad`, one swing each way per `yaw_sweep_period_m` of travel,
        step_m this cycle's), its rate at most SWEEP_YAW_RATE_MAX_RAD_S (a faster X_d swings
        over more travel): the rays at the gap's edges cross every bearing of it, so a pole
        or a wall's end standing in the gap is seen as far off as one on a ray. The heading
        itself when the layout has no gap or the sweep is off."""
        amplitude = self._sweep_amplitude
        if amplitude == 0.0:
            return heading
        advance = 2.0 * math.pi * step_m / self.params.yaw_sweep_period_m
        advance = min(advance, SWEEP_YAW_RATE_MAX_RAD_S * dt_s / amplitude)
        self._sweep_phase = (self._sweep_phase + advance) % (2.0 * math.pi)
        return wrap_pi(heading + amplitude * math.sin(self._sweep_phase))

    def _path_ends_at_goal(self) -> bool:
        return float(np.hypot(*(self._path.end - self.route.base_points[-1]))) < 1e-3

    def _set_path(self, path: Path, mode: PathMode, side: Side) -> None:
        self._path = path
        self._samples = None
        self._look = None
        self._s = 0.0
        self._segment, self._t = 0, 0.0
        self._mode, self._side = mode, side
        self._stops = []
        self._after_retreat = None
        self._search = None
        self._escape = None
        self._grid_way = False
        self._scan = []

    def _record_track(self, x: float, y: float) -> None:
        """Append X_d to the covered track every _TRACK_SPACING_M; going back over the
        track (backing out) unwinds it instead, so that the track never doubles back on
        itself and a later retreat along it has no cusp."""
        last = self._track[-1]
        if math.hypot(x - last[0], y - last[1]) < _TRACK_SPACING_M:
            return
        if len(self._track) >= 2:
            prev = self._track[-2]
            if math.hypot(x - prev[0], y - prev[1]) < _TRACK_SPACING_M:
                self._track.pop()
                return
        self._track.append((x, y))

    def _look_ahead(self) -> _LookAhead:
        """The path from X_d to lookahead with its clearances: measured once per cycle (it
        serves the conflict check and the stopping limit), again only if the path changes."""
        if self._look is None:
            params = self.params
            if self._samples is None:
                self._samples = _PathSamples.of(
                    self._path, params.lat_accel_max_mps2, params.v_d_mps
                )
            samples = self._samples
            ahead = samples.window(self._s, params.lookahead_m)
            points = samples.points[ahead]
            curves = samples.curves_in(ahead)
            clearance, conflict = None, False
            if len(self._memory):
                clearance, close = self._clearance(samples, ahead)
                first = bisect.bisect_left(close, ahead.start)
                conflict = first < len(close) and close[first] < ahead.stop
            self._look = _LookAhead(
                samples.s[ahead],
                points,
                samples.curve_s[curves],
                samples.curve_v_sq[curves],
                clearance,
                conflict,
            )
        return self._look

    def _clearance(self, samples: _PathSamples, ahead: slice) -> tuple[FloatArray, list[int]]:
        """The look-ahead samples' clearance from the remembered points (`_LookAhead`).

        Measured _CLEARANCE_EXTRA_M beyond the look-ahead at once and kept while the path
        stays the same: X_d moves a few centimetres a cycle, so most cycles slice what an
        earlier one measured. When the memory changes (`ObstacleMemory.version`), the kept
        values are brought up to date from its change log: only the points added or
        removed since are measured, and the samples whose nearest point was removed
        against every point (`min_distance_within_updated`). Below the cutoff the numbers
        are those of measuring the window alone against the memory as it is (the nearest
        point is among the points considered either way); above it both are >= the cutoff,
        which every reader treats alike. Also the samples closer than the re-plan trigger
        (`_ClearanceCache`)."""
        memory = self._memory
        cached = self._clearance_cache
        changes = None
        if (
            cached is not None
            and cached.version != memory.version
            and cached.samples is samples
            and cached.start <= ahead.start
            and ahead.stop <= cached.stop
        ):
            changes = memory.changes_since(cached.version)
        cutoff = self._clearance_cutoff_m
        if cached is not None and changes is not None:
            points = samples.points[cached.start : cached.stop]
            box = cached.box
            if box is None:
                lo, hi = points.min(axis=0).tolist(), points.max(axis=0).tolist()
                box = (lo[0], lo[1], hi[0], hi[1])
            values, stale = min_distance_within_updated(
                points, cached.values, cutoff, box, changes.removed, changes.added
            )
            if len(stale):  # (a few samples: all points, no box to cut them down)
                values[stale] = min_distance(points[stale], *memory.slot_points())
            if values is cached.values:
                cached = cached._replace(version=memory.version, box=box)
            else:
                cached = self._keep_clearance(memory.version, samples, cached.start, values, box)
            self._clearance_cache = cached
        elif (
            cached is None
            or cached.version != memory.version
            or cached.samples is not samples
            or ahead.start < cached.start
            or ahead.stop > cached.stop
        ):
            reach = samples.window(self._s, self.params.lookahead_m + _CLEARANCE_EXTRA_M)
            values = min_distance_within(
                samples.points[reach], memory.points_xy(), cutoff, memory.inflation_m()
            )
            cached = self._keep_clearance(memory.version, samples, reach.start, values, None)
            self._clearance_cache = cached
        window = cached.values[ahead.start - cached.start : ahead.stop - cached.start]
        return window, cached.close

    def _keep_clearance(
        self,
        version: int,
        samples: _PathSamples,
        start: int,
        values: FloatArray,
        box: tuple[float, float, float, float] | None,
    ) -> _ClearanceCache:
        """The cache entry of the clearances `values` of the samples from `start` on, at
        memory `version`."""
        params = self.params
        trigger = params.d_min_m + 0.5 * params.clearance_margin_m
        close = [i + start for i in (values < trigger).nonzero()[0].tolist()]
        return _ClearanceCache(version, samples, start, start + len(values), values, close, box)

    def _update_path(
        self, state: VehicleState, ranges: FloatArray, valid: BoolArray, events: list[str]
    ) -> bool:
        """Re-plan if the path ahead conflicts with the memory. Returns True if re-planned."""
        params = self.params
        here = self._xd_prev[:2]
        radius = params.lookahead_m + 2.0 * params.d_min_m + 10.0
        if len(self._memory) == 0:
            self._blocked = False
            self._search = None
            return False
        look = self._look_ahead()
        if len(look.s) == 0 or look.clearance is None:  # (None only with no memory)
            if len(self._memory.near(here, radius)) == 0:
                self._blocked = False
            self._search = None
            return False
        # The samples are within lookahead of here, so every remembered point closer to one
        # than the trigger distance is within `radius` of here: no need to filter first.
        trigger = params.d_min_m + 0.5 * params.clearance_margin_m
        conflict_samples = look.clearance < trigger if look.conflict else None
        if conflict_samples is not None and self._escape is not None and not self._blocked:
            conflict_samples &= ~self._escape_exempt(look.s, look.clearance)
        if self._band_pinned(look):
            # Held at rest by the band's speed limit (points seen since the path was taken
            # are nearer than its floor): look for a way out from here, as when blocked.
            conflict_samples = look.clearance < trigger
        if conflict_samples is None or not conflict_samples.any():
            self._blocked = False
            self._search = None
            return False
        if self._mode is PathMode.RETREAT and not self._blocked:
            return False  # backing out along the covered track: it is known to be free
        if self._blocked and self._v > speed.STOPPED_MPS:
            # Stopping for a conflict that no correction from the moving X_d could clear: the
            # search starts again once at rest. (While it stops, X_d moves every cycle, and
            # a search from each new point would start afresh and spend a whole budget.)
            self._search = None
            return False
        if (
            not self._blocked
            and self._v <= speed.STOPPED_MPS
            and abs(wrap_pi(self._path_heading() - self._yaw)) > _YAW_ALIGNED_RAD
        ):
            # Turning on the spot onto a new path: the vehicle does not move, and what the
            # turning sensors add (a proximity sector's arc sweeps with them) would flip the
            # choice to the other side and back. The path is checked once aligned.
            return False
        nearby, nearby_inflation = self._memory.near_with_inflation(here, radius)
        # Points that the conflicting part of the path comes too close to.
        bad = look.points[conflict_samples]
        d_to_bad = np.sqrt(((nearby[:, None, :] - bad[None, :, :]) ** 2).sum(axis=2)).min(axis=1)
        conflict_xy = nearby[d_to_bad - nearby_inflation < trigger]
        free_left, free_right = self._free_range(ranges, valid)
        at_rest = self._v <= speed.STOPPED_MPS
        if not at_rest:
            start_clear = float(min_distance(here[None, :], nearby, nearby_inflation)[0])
            if start_clear < params.d_min_m - _ESCAPE_TOLERANCE_M:
                # Inside D_min (as the memory has it) and moving: a correction from here
                # would start where it is and keep that floor, and the next cycle's new
                # points lower it again (creeping along a flank). Stop; from rest the
                # search may lead out.
                self._search = None
                self._set_blocked(events)
                return False
        # A search that failed is not repeated while nothing it depends on has changed: no
        # new or dropped memory cell, the reference point within a cell of where it was, the
        # same state of motion (a blocked cycle is the costly one; bounded, it is retried
        # at least every _RETRY_BLOCKED_CYCLES cycles).
        attempt = (
            self._memory.generation,
            round(float(here[0]) / self.params.memory_cell_m),
            round(float(here[1]) / self.params.memory_cell_m),
            at_rest,
        )
        if (
            self._blocked
            and attempt == self._failed_attempt
            and self._cycle - self._failed_cycle < _RETRY_BLOCKED_CYCLES
        ):
            return False
        # The search resumes where it stopped last cycle while nothing it depends on has
        # changed (at rest, the reference point does not move); else it starts afresh. At
        # rest it also goes on over changes of the memory: it finishes on the points it
        # started with (a vehicle at rest sees its surroundings change a little every few
        # cycles, and a search restarted each time would never finish), and the path it gives
        # is checked against the memory as it is then, as every path is each cycle, before
        # X_d moves on it.
        key = (
            None if at_rest else self._memory.generation,
            float(here[0]),
            float(here[1]),
            at_rest,
            self._mode,
            self._side,
            self._avoid_side,
        )
        if self._search is None or self._search[0] != key:
            request = AvoidanceRequest(
                start_xy=here.copy(),
                start_dir=None if at_rest else self._path.segments[self._segment].tangent(self._t),
                conflict_xy=conflict_xy,
                obstacles_xy=nearby,
                committed_side=self._side,
                free_left_m=free_left,
                free_right_m=free_right,
                avoid_side=self._avoid_side,
                obstacles_inflation=nearby_inflation,
            )
            self._search = (key, self._resolve(request, at_rest))
        budget = SEARCH_BUDGET_UNITS_AT_REST if at_rest else SEARCH_BUDGET_UNITS
        resolved = self._advance_search(self._search[1], budget, events)
        if resolved is None and at_rest:
            return False  # the search goes on next cycle, from this same rest point
        self._search = None
        if resolved is None:
            # Moving, X_d changes every cycle and the search would start afresh: one that
            # does not fit in a cycle counts as failed (blocked: stop, then search at rest).
            self._set_blocked(events)
            self._failed_attempt, self._failed_cycle = attempt, self._cycle
            return False
        if resolved.detour is not None:
            self._accept(resolved.detour, events, stop_first=at_rest)
            return True
        if resolved.retreat is not None:
            self._start_retreat(resolved.retreat, events)
            return True
        if resolved.grid is not None:
            self._take_grid_way(resolved.grid, events)
            return True
        self._failed_attempt, self._failed_cycle = attempt, self._cycle
        if at_rest and self._free_fans is not None and not self._scan:
            self._start_scan(events)
        return False

    def _start_scan(self, events: list[str]) -> None:
        """Boxed in at rest with proximity sectors: turn on the spot half a sector each way
        and back (a quarter the second time at the same place), holding each heading
        _SCAN_HOLD_S. The sectors then read from headings that split their arcs
        differently, and what each sees free trims the others' arcs (`FreeFans`,
        carving), so the next search sees less of the arcs' phantom part."""
        x, y = self._xd_prev[:2].tolist()
        place = (round(x / _SCAN_PLACE_M), round(y / _SCAN_PLACE_M))
        if place != self._scan_place:
            self._scan_place, self._scans_here = place, 0
        if self._scans_here >= _SCANS_PER_PLACE:
            return
        half = 0.5 * float(self.sensors.fov_rad[self._sector_rows].max())
        offset = half / (2**self._scans_here)
        self._scans_here += 1
        self._scan, self._scan_held_s = [offset, -offset, 0.0], 0.0
        events.append(
            f"boxed in by proximity sector arcs: turning {math.degrees(offset):.0f} degrees "
            "each way to narrow them"
        )

    def _resolve(
        self, request: AvoidanceRequest, at_rest: bool
    ) -> Generator[bool, None, _Resolved]:
        """The re-plan search in work units (yields False per unit): a correction from here;
        failing that (yields True once: blocked) and at rest, a retreat along the covered
        track to where a correction on the other side exists; failing that too, straight
        legs over a grid of the memory (`gridpath`). After _RETREATS_BEFORE_GRID retreats the
        grid comes before the retreat. On legs taken because nothing else was found, only
        the grid again."""
        if self._grid_way:
            # On a way over the grid, a conflict is met the same way: stop, search the grid.
            yield True
            if not at_rest:
                return _Resolved()
            way = yield from _units(grid_search(self.route, request, self.params))
            return _Resolved(grid=way)
        frame = (
            SearchFrame.of(self.route, request, self.params) if len(request.conflict_xy) else None
        )
        detour = yield from _units(detour_search(self.route, request, self.params, frame))
        if detour is not None:
            return _Resolved(detour=detour)
        yield True
        if not at_rest:
            return _Resolved()
        if self._retreats >= _RETREATS_BEFORE_GRID:
            grid = yield from _units(grid_search(self.route, request, self.params))
            if grid is not None:
                return _Resolved(grid=grid)
        track = backwards_track(self._xd_prev[:2], self._track)
        plan = yield from _units(
            retreat_search(
                self.route, request, self.params, track, _TRACK_SPACING_M, self._side, frame
            )
        )
        if plan is not None:
            return _Resolved(retreat=plan)
        grid = yield from _units(grid_search(self.route, request, self.params))
        return _Resolved(grid=grid)

    def _advance_search(
        self, search: Generator[bool, None, _Resolved], budget: int, events: list[str]
    ) -> _Resolved | None:
        """Run the search for at most `budget` units this cycle; its outcome, or None if it
        is not done. Reaching the blocked mark stops the vehicle (and says so once)."""
        while self._search_units < budget:
            try:
                blocked_mark = next(search)
            except StopIteration as done:
                resolved: _Resolved = done.value
                return resolved
            if blocked_mark:
                self._set_blocked(events)
            else:
                self._search_units += 1
        return None

    def _set_blocked(self, events: list[str]) -> None:
        """Enter the blocked state; say so once per stop. A conflict that vanishes for a
        cycle (a point carved at rest, then seen again) must not repeat the event: after the
        blocked state was left without a new path, it is said again only once X_d has moved
        _BLOCKED_AGAIN_M from where it was left."""
        if not self._blocked:
            left = self._unblocked_xy
            if left is None or math.hypot(*(self._xd_prev[:2] - left)) >= _BLOCKED_AGAIN_M:
                events.append("blocked: no path keeps D_min, stopping")
        self._blocked = True

    def _accept(self, detour: Detour, events: list[str], stop_first: bool) -> None:
        if detour.side is not self._side or self._mode is PathMode.ROUTE:
            events.append(f"avoiding obstacle on the {detour.side.value} ({detour.mode.value})")
        if self._blocked:
            events.append("resumed")
        self._blocked = False
        self._unblocked_xy = None
        self._say_passed_beside(detour.path, self._xd_prev[:2], detour.rejoin_s, events)
        self._set_path(detour.path, detour.mode, detour.side)
        self._lower_band_floor()
        if stop_first:
            self._stops = [0.0]
        self._detour_end_s = detour.path.length - (self.route.length - detour.rejoin_s)
        self._escape = self._escape_stretch()

    def _band_pinned(self, look: _LookAhead) -> bool:
        """X_d at rest, not blocked, on a path the band's speed limit gives no speed at all
        (`speed.band_limit`): nothing else would make it move or search again."""
        if (
            self._blocked
            or self._v > speed.STOPPED_MPS
            or self._mode is PathMode.RETREAT
            or look.clearance is None
            or len(look.s) == 0
        ):
            return False
        return self._band_cap(float(look.clearance[0])) == 0.0

    def _band_cap(self, clearance_m: float) -> float:
        """`speed.band_limit` for X_d at clearance_m (m) from the memory, with this path's floor."""
        params = self.params
        replan = params.d_min_m + 0.5 * params.clearance_margin_m
        return speed.band_limit(
            clearance_m, self._band_floor, replan, params.accel_max_mps2, params.reaction_time_s
        )

    def _lower_band_floor(self) -> None:
        """A new path taken at rest inside D_min (as the memory has it) leads out from
        there: the band's speed cap (`speed.band_limit`) counts from its start, not from
        D_min, or X_d could not move. A path taken on the move keeps the floor it had, so
        that re-planning as new points come in cannot lower it step by step."""
        if self._v > speed.STOPPED_MPS:
            return
        look = self._look_ahead()
        if look.clearance is not None and len(look.s):
            start = float(look.clearance[0]) - _ESCAPE_TOLERANCE_M
            self._band_floor = min(self.params.d_min_m, start)

    def _say_passed_beside(
        self, path: Path, start_xy: FloatArray, rejoin_s: float, events: list[str]
    ) -> None:
        """Say which base points a new path leaves out (out of its reach), and by how much."""
        for k, miss in passed_beside(self.route, path, start_xy, rejoin_s):
            events.append(f"base point {k + 1} out of reach: passing it {miss:.1f} m to the side")

    def _escape_stretch(self) -> tuple[FloatArray, FloatArray] | None:
        """The new path's look-ahead with the clearances it was accepted with (arc lengths,
        clearances), up to its last sample inside the re-plan band; None when it starts
        outside the band.

        A correction that starts inside the band leads out of it (`avoidance.ESCAPE_SLOPE`),
        and from inside D_min it need keep only D_min after (`avoidance.keeps_clear`), so it
        may come back into the band farther on; the speed schedule flies it (places no
        closer than here are free). The conflict check must agree, or it finds the same
        stretch in conflict every cycle and re-plans each time (the vehicle crawls out,
        re-planning 20 times a second), or, moving inside D_min, stops, and from rest takes
        the same path again (blocked and resumed every other cycle)."""
        look = self._look_ahead()
        trigger = self.params.d_min_m + 0.5 * self.params.clearance_margin_m
        if look.clearance is None or len(look.s) == 0 or look.clearance[0] >= trigger:
            return None
        inside = (look.clearance < trigger).nonzero()[0]
        end = int(inside[-1]) + 1
        return look.s[:end].copy(), look.clearance[:end].copy()

    def _escape_exempt(self, look_s: FloatArray, clearance: FloatArray) -> BoolArray:
        """Look-ahead samples on the accepted escape stretch that are no closer to the memory
        than when it was accepted (less _ESCAPE_TOLERANCE_M): not a conflict. A point seen
        since, that comes closer, makes the sample a conflict again."""
        assert self._escape is not None
        esc_s, esc_clear = self._escape
        on = look_s <= esc_s[-1]
        planned = np.interp(look_s, esc_s, esc_clear)
        exempt: BoolArray = on & (clearance >= planned - _ESCAPE_TOLERANCE_M)
        return exempt

    def _take_grid_way(self, plan: GridPlan, events: list[str]) -> None:
        """Fly the straight legs over the grid to a base point, stopping at every corner."""
        legs = len(plan.stops)
        why = (
            f"backed out {self._retreats} times"
            if self._retreats >= _RETREATS_BEFORE_GRID
            else "no correction or retreat"
        )
        events.append(
            f"{why}: {legs} straight leg{'s' if legs > 1 else ''} "
            f"round the obstacles to base point {plan.base_index + 1}, stopping at each corner"
        )
        after_retreats = self._retreats >= _RETREATS_BEFORE_GRID
        self._retreats = 0
        self._say_passed_beside(plan.path, self._xd_prev[:2], plan.rejoin_s, events)
        self._blocked = False
        self._unblocked_xy = None
        self._set_path(plan.path, PathMode.AROUND, Side.NONE)
        self._lower_band_floor()
        # Taken for a vehicle going back and forth, a conflict on the legs is met as on any
        # path (a correction first); taken because nothing else was found, by the grid again.
        self._grid_way = not after_retreats
        self._stops = [0.0, *plan.stops]
        self._detour_end_s = plan.legs_length_m
        self._escape = self._escape_stretch()

    def _start_retreat(self, plan: RetreatPlan, events: list[str]) -> None:
        """Back out along the covered track, stop, turn, and take the correction found."""
        detour = plan.detour
        turn_xy = detour.path.segments[0].control[0]
        self._say_passed_beside(detour.path, turn_xy, detour.rejoin_s, events)
        self._set_path(plan.path, PathMode.RETREAT, detour.side)
        self._stops = [0.0, *plan.turns_m, plan.back_length_m]
        self._avoid_side = plan.failed_side
        self._detour_end_s = plan.back_length_m
        rejoin_on_path = (
            plan.back_length_m + detour.path.length - (self.route.length - detour.rejoin_s)
        )
        self._after_retreat = (detour.mode, detour.side, rejoin_on_path)
        self._retreats += 1
        events.append(f"dead end: backing out {plan.back_m:.0f} m, then {detour.side.value}")
        self._blocked = False
        self._unblocked_xy = None

    def _carve(
        self, state: VehicleState, rot: FloatArray, ranges: FloatArray, valid: BoolArray
    ) -> None:
        """Free-space carving (`ObstacleMemory.carve`): remembered points that this cycle's
        rays see through are dropped (a phantom from a reading paired with the wrong attitude
        would otherwise block for ever). A ray counts up to _CARVE_SHORT_M short of what it
        measured, or of its max range when it saw nothing; readings of 0, NaN or below min
        range say nothing and carve nothing. A beam carves only with X_d at rest (a phantom
        stops the vehicle): in motion a ray sweeping past a solid's rim would pass just
        beside points that are real (grazing) and carve them. A sector (a reading with a
        field of view) carves in motion too: it read the nearest object anywhere across
        it, so a point in it nearer than its reading contradicts it (and the arcs that
        sector readings leave are wider than the object)."""
        moving = self._v > speed.STOPPED_MPS
        if moving and not self._sector_rows.size:
            return
        sensors = self.sensors
        r = np.asarray(ranges, dtype=np.float64)
        nothing = np.isfinite(r) & (r >= sensors.max_range_m)
        reach = np.where(valid, r, np.where(nothing, sensors.max_range_m, 0.0))
        free = reach - _CARVE_SHORT_M
        use = (valid | nothing) & (free > 0.0)
        sector = sensors.fov_rad > 0.0
        cone = use & sector
        if np.count_nonzero(cone):
            # A sector reading is the nearest object anywhere across the sector: nothing is
            # nearer in all of it, so its whole width is free up to the reading.
            fan_args = (
                state.position_enu,
                rot[:, 2],
                sensors.boresights_flu.compress(cone, axis=0) @ rot.T,
                0.5 * sensors.fov_rad[cone],
                free[cone],
            )
            if self._free_fans is not None:
                self._free_fans.add(*fan_args, state.yaw_rad)
        if not np.count_nonzero(use) or len(self._memory) == 0:
            return
        beam = use & ~sector
        if np.count_nonzero(beam) and not moving:
            dirs = sensors.boresights_flu.compress(beam, axis=0) @ rot.T
            self._memory.carve(
                state.position_enu, dirs, free[beam], _CARVE_TOLERANCE_M, _CARVE_SUPPORT_M
            )
        if np.count_nonzero(cone) and len(self._memory):
            # That carves across the sector's width (a reading's arc, entered from farther
            # away, is over-wide once seen from nearer).
            self._memory.carve_sectors(*fan_args, _CARVE_TOLERANCE_M, _CARVE_SUPPORT_M)

    def _bound_reach(
        self, state: VehicleState, rot: FloatArray, ranges: FloatArray, valid: BoolArray
    ) -> None:
        """Bound the remembered points' reach on long chords by this cycle's rays
        (`ObstacleMemory.bound_reach`): each ray, obstacle or surface, saw nothing up to
        _REACH_FREE_SHORT_M short of what it measured (range noise), or up to its max range
        when it detected nothing (0, inf, or at or over max: the service passes "out of
        range" on as 0); NaN says nothing. Unlike carving, a reading of 0 counts: a wrong
        one can only take a reach away, back to the point as seen. In motion too: a ray
        passing beside a point is the evidence here (it drops nothing)."""
        if not self._memory.has_reach():
            return  # (most cycles: nothing to bound)
        sensors = self.sensors
        r = np.asarray(ranges, dtype=np.float64)
        nothing = ~valid & ((r == 0.0) | (r >= sensors.max_range_m))
        free = np.where(valid, r - _REACH_FREE_SHORT_M, np.where(nothing, sensors.max_range_m, 0.0))
        use = (valid | nothing) & (free > 0.0)
        if not np.count_nonzero(use):
            return
        dirs = sensors.boresights_flu.compress(use, axis=0) @ rot.T
        self._memory.bound_reach(state.position_enu, dirs, free[use], _REACH_HEIGHT_TOLERANCE_M)

    def _vehicle_ahead_m(self, position_enu: FloatArray, heading: float) -> float:
        """How far the vehicle is ahead of last cycle's X_d along the path's heading there
        (heading, radians: `_path_heading`), metres (0 when behind or level); horizontal."""
        x, y = position_enu[:2].tolist()  # plain floats: the same numbers, fewer calls
        xd, yd, _ = self._xd_prev_xyz
        ahead = (x - xd) * math.cos(heading) + (y - yd) * math.sin(heading)
        return ahead if math.isfinite(ahead) and ahead > 0.0 else 0.0

    def _vehicle_lag_m(self, position_enu: FloatArray) -> float:
        """How far the vehicle is from last cycle's X_d, the setpoint it is flying to:
        3-D, metres."""
        x, y, z = position_enu.tolist()
        xd, yd, zd = self._xd_prev_xyz
        return math.sqrt((x - xd) ** 2 + (y - yd) ** 2 + (z - zd) ** 2)

    def _announce_leash(self, lag_m: float, stopped: bool, events: list[str]) -> None:
        """Say once when the leash stops X_d to wait for the vehicle (stopped), and once when
        the vehicle has closed to half the leash again (lag_m, metres)."""
        leash = self.params.leash_m
        if not self._held_by_leash and stopped:
            self._held_by_leash = True
            events.append(
                f"vehicle {lag_m:.1f} m from the setpoint (leash {leash:g} m): "
                "waiting for it to follow"
            )
        elif self._held_by_leash and lag_m <= 0.5 * leash:
            self._held_by_leash = False
            events.append("vehicle following again")

    def _free_range(self, ranges: FloatArray, valid: BoolArray) -> tuple[float, float]:
        """Sum of free range seen by the left and by the right obstacle sensors, metres."""
        left = right = 0.0
        for k, i in enumerate(self.sensors.obstacle_index):
            r = float(ranges[i]) if valid[i] else float(self.sensors.max_range_m[i])
            if self._obstacle_groups[k] is Group.LEFT:
                left += r
            elif self._obstacle_groups[k] is Group.RIGHT:
                right += r
        return left, right

    def _update_layout_limit(self, dt_s: float, events: list[str]) -> None:
        """The speed from which a wall first flagged as steep can still be stopped for,
        reaction allowance included (`sight`): the flag distance is recomputed when H_d or
        phi_max changes (and the limit announced when it binds), the limit every cycle with that
        cycle's period (a live service measures a different one every cycle) and the
        vehicle's measured lead on X_d."""
        params = self.params
        trigger = params.d_min_m + 0.5 * params.clearance_margin_m
        a, t = params.accel_max_mps2, params.reaction_time_s
        key = (self._h_d, params.phi_max_rad)
        announce = key != self._sight_key
        if announce:
            self._sight_key = key
            self._flag_m = wall_flag_distance_m(self.sensors, self._h_d, params.phi_max_rad)
        v_max = layout_speed_limit_mps(self._flag_m, trigger, a, dt_s, t)
        self._v_cruise = min(params.v_d_mps, v_max)
        if announce and self._v_cruise < params.v_d_mps:
            events.append(
                f"sensor layout flags a wall as steep only {self._flag_m:.1f} m ahead: "
                f"speed limited to {self._v_cruise:.2f} m/s (v_d {params.v_d_mps:g})"
            )
        v_now = layout_speed_limit_mps(self._flag_m, trigger, a, dt_s, t, self._ahead_m)
        self._v_layout = min(params.v_d_mps, v_now)

    def _speed_target(self) -> float:
        """Reference speed allowed here (`speed`): v_d (or the layout's limit), lowered
        before the path's end and the next stop, ahead of tight curves (lateral
        acceleration) and before places closer than the re-plan distance."""
        params = self.params
        a = params.accel_max_mps2
        s_here = self._s
        v = min(self._v_layout, speed.braking_speed(self._path.length - s_here, a))
        stop = speed.next_stop(self._stops, s_here)
        if stop is not None:
            v = min(v, speed.braking_speed(stop - s_here, a))
        look = self._look_ahead()
        if len(look.s) == 0:
            return v
        v = min(v, speed.curve_limit(look.curve_s, look.curve_v_sq, s_here, a))
        if look.clearance is not None and look.conflict:  # (else `clearance_limit` is inf)
            # A search still going on (`SEARCH_BUDGET_UNITS`) stops the vehicle as a blocked
            # one does, until it has its answer.
            v = min(
                v,
                speed.clearance_limit(
                    look.s,
                    look.clearance,
                    s_here,
                    a,
                    params.d_min_m + 0.5 * params.clearance_margin_m,
                    stop_at_band=self._blocked or self._search is not None,
                    reaction_s=params.reaction_time_s,
                    allowance_m=self._ahead_m,
                    rest_margin_m=speed.rest_margin_m(self._v_cruise, params.reaction_time_s),
                ),
            )
        if look.clearance is not None and len(look.s) and self._mode is not PathMode.RETREAT:
            here = float(look.clearance[0])
            replan = params.d_min_m + 0.5 * params.clearance_margin_m
            if here >= replan:
                self._band_floor = params.d_min_m
            v = min(v, self._band_cap(here))
        return max(v, 0.0)


def _units(search: Generator[None, None, _T]) -> Generator[bool, None, _T]:
    """A search's work units as `Planner._resolve` counts them (False: one unit)."""
    while True:
        try:
            next(search)
        except StopIteration as done:
            result: _T = done.value
            return result
        yield False
