"""Planner parameters: the paper's H_d, D_min, phi_max, v_d and the project's additions."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass


class ArcMethod(enum.StrEnum):
    """How X_d is advanced along the segment, eq. (5)."""

    EXACT = "exact"
    """Exact inverse of the arc length (Gauss-Legendre table + Newton with bisection)."""
    PAPER = "paper"
    """The paper's fixed-increment search over delta (reference implementation)."""


@dataclass(frozen=True, slots=True)
class PlannerParams:
    """Tuning of the planner. Lengths in metres, angles in radians, speeds in m/s.

    h_d_m, d_min_m, phi_max_rad, v_d_mps: H_d, D_min, phi_max and v_d of the paper.
    min_turn_radius_m: curvature bound of every reshaped path.
    lat_accel_max_mps2: the reference speed is lowered where v^2 * curvature would exceed it.
    accel_max_mps2: how fast the reference speed ramps up and down (also the stopping budget).
    clearance_margin_m: extra distance kept from detected obstacle points when planning, so
        that the true clearance stays >= D_min between sensor rays.
    lookahead_m: how far along the path obstacle conflicts are checked.
    memory_radius_m / memory_max_points / memory_cell_m: obstacle memory bounds.
    arc_method / paper_delta: eq. (5) stepping method and the paper's increment.
    goal_tolerance_m: distance of X_d to the last base point that counts as arrived.
    reaction_time_s: seconds the stop before an obstacle allows for the vehicle to go on at
        its speed (readings that arrive late, an autopilot's position controller trailing and
        then overshooting a decelerating setpoint): X_d brakes v * reaction_time_s earlier,
        and further by how far the vehicle is measured ahead of X_d along the path. 0: the
        paper's ideal stop exactly at the trigger.
    leash_m: how far (3-D) the vehicle may be from X_d: X_d slows from half of it and waits
        at it, so that a vehicle that does not follow (stuck, landed, held back by wind,
        a slow climb) is never sent a setpoint far ahead (an autopilot flies the straight
        line to it, cutting a correction's curve) and a route is never called done with the
        vehicle elsewhere.
    shape_terrain: raise eq. (3)'s aim point for the ground's slope across the heading and
        its curvature along it, from a fit of the recent surface hits (`ground`); False: the
        paper's eqs (3)-(4) alone.
    yaw_sweep_period_m: while moving, the heading swings across the widest bearing gap
        between the obstacle sensors ahead (`sight.sweep_amplitude_rad`: half the gap either
        way, a sine over this much travel of X_d, metres), so that the rays cross every
        bearing ahead: a pole or a wall's end standing in a gap is otherwise seen only when
        it is already close. 0: the heading follows the path (the paper); nothing changes
        with a layout that has no gap (a proximity ring).
    """

    h_d_m: float = 2.0
    d_min_m: float = 2.0
    phi_max_rad: float = 0.6
    v_d_mps: float = 1.0
    min_turn_radius_m: float = 2.0
    lat_accel_max_mps2: float = 0.5
    accel_max_mps2: float = 0.5
    clearance_margin_m: float = 0.6
    lookahead_m: float = 25.0
    memory_radius_m: float = 40.0
    memory_max_points: int = 4096
    memory_cell_m: float = 0.25
    arc_method: ArcMethod = ArcMethod.EXACT
    paper_delta: float = 1e-4
    goal_tolerance_m: float = 0.05
    reaction_time_s: float = 0.4
    leash_m: float = 2.0
    shape_terrain: bool = True
    yaw_sweep_period_m: float = 4.0

    def __post_init__(self) -> None:
        positive = (
            "h_d_m",
            "d_min_m",
            "phi_max_rad",
            "v_d_mps",
            "min_turn_radius_m",
            "lat_accel_max_mps2",
            "accel_max_mps2",
            "lookahead_m",
            "memory_radius_m",
            "memory_cell_m",
            "paper_delta",
            "goal_tolerance_m",
            "leash_m",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        if not self.phi_max_rad < math.pi / 2:
            raise ValueError(f"phi_max_rad must be < pi/2, got {self.phi_max_rad}")
        if not (math.isfinite(self.clearance_margin_m) and self.clearance_margin_m >= 0.0):
            raise ValueError(f"clearance_margin_m must be >= 0, got {self.clearance_margin_m}")
        if not (math.isfinite(self.reaction_time_s) and 0.0 <= self.reaction_time_s <= 5.0):
            value = self.reaction_time_s
            raise ValueError(f"reaction_time_s must be within [0, 5] s, got {value!r}")
        if not (math.isfinite(self.yaw_sweep_period_m) and self.yaw_sweep_period_m >= 0.0):
            value = self.yaw_sweep_period_m
            raise ValueError(f"yaw_sweep_period_m must be >= 0 (0: off), got {value!r}")
        if self.memory_max_points < 16:
            raise ValueError(f"memory_max_points must be >= 16, got {self.memory_max_points}")
        object.__setattr__(self, "arc_method", ArcMethod(self.arc_method))

    @property
    def side_threshold_rad(self) -> float:
        """Eq. (7) for the side groups: min(arctan(H_d / D_min), phi_max)."""
        return min(math.atan2(self.h_d_m, self.d_min_m), self.phi_max_rad)
