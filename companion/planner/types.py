"""Plain data passed into and out of the planner.

Frames: world is local ENU (x east, y north, z up, metres); body is FLU (x forward, y left,
z up). Yaw is measured from +x (east) counter-clockwise; pitch is nose-up positive; roll is
right-wing-down positive. Conversions from MAVLink's NED/FRD live in `companion.planner.frames`.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.intp]


class Decision(enum.StrEnum):
    """Strategy chosen by eqs (6)-(7) for the current cycle."""

    VERTICAL = "vertical"
    """Nothing too steep: keep the horizontal path, terrain following climbs over."""
    HORIZONTAL = "horizontal"
    """Something steeper than its threshold: pass it in the horizontal plane."""
    BLOCKED = "blocked"
    """No horizontal path keeps D_min: slowing to a stop at a safe distance."""


class PathMode(enum.StrEnum):
    """What the horizontal path currently is."""

    ROUTE = "route"
    """Following the original route through the base points."""
    AROUND = "around"
    """Going around an obstacle that sits across the path."""
    SHIFT = "shift"
    """Shifted away from an obstacle beside the path."""
    RETREAT = "retreat"
    """Backing out of a dead end along the distance already covered."""


class Side(enum.StrEnum):
    NONE = "none"
    LEFT = "left"
    RIGHT = "right"


@dataclass(frozen=True, slots=True)
class VehicleState:
    """Vehicle pose in the planner frames.

    position_enu: (3,) metres, local ENU. Angles in radians (ENU/FLU convention above).
    """

    position_enu: FloatArray
    roll_rad: float
    pitch_rad: float
    yaw_rad: float

    def __post_init__(self) -> None:
        pos = np.array(self.position_enu, dtype=np.float64).reshape(3)
        x, y, z = pos.tolist()
        # Plain floats: this runs every cycle, and numpy's per-call cost was most of it.
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            raise ValueError(f"position_enu must be finite, got {pos}")
        for name, value in (
            ("roll_rad", self.roll_rad),
            ("pitch_rad", self.pitch_rad),
            ("yaw_rad", self.yaw_rad),
        ):
            if not math.isfinite(value):
                raise ValueError(f"{name} must be finite, got {value}")
        pos.setflags(write=False)
        object.__setattr__(self, "position_enu", pos)


@dataclass(frozen=True, slots=True)
class Setpoint:
    """What the vehicle is asked to do this cycle.

    position_enu: X_d, metres, local ENU. velocity_enu: feed-forward velocity of X_d, m/s.
    yaw_rad: heading of the horizontal path's tangent (ENU, from +x, CCW).
    pitch_rad: phi_d of eq. (4), the desired pitch of the climb, radians.
    acceleration_enu: feed-forward acceleration of X_d, m/s^2, local ENU (zeros: none).
    """

    position_enu: FloatArray
    velocity_enu: FloatArray
    yaw_rad: float
    pitch_rad: float
    acceleration_enu: FloatArray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True, slots=True)
class Diagnostics:
    """Why the planner produced its setpoint.

    phi_star_rad / threshold_rad: per obstacle sensor (table order), eqs (6)-(7).
    speed_ref_mps: reference speed after curvature and stopping limits; while X_d at rest
      moves to H_d (`Planner._climb_at_rest`), the speed of that climb.
    """

    decision: Decision
    mode: PathMode
    side: Side
    phi_star_rad: FloatArray
    threshold_rad: FloatArray
    phi_d_rad: float
    segment: int
    parameter: float
    speed_ref_mps: float
    min_range_m: float
    """Smallest valid obstacle range this cycle; 0 when nothing is detected (as in Fig. 7b)."""
    surface_valid: bool
    replanned: bool
    finished: bool
    events: tuple[str, ...] = field(default_factory=tuple)
    """Messages a pilot should know about, raised this cycle (side chosen, blocked, ...)."""
    search_units: int = 0
    """Work units the re-plan search spent this cycle (candidate corrections tried; at most
    the planner's per-cycle budget); 0 on a cycle that did not search."""
    searching: bool = False
    """A re-plan search used its budget and goes on next cycle (the vehicle stops meanwhile)."""


@dataclass(frozen=True, slots=True)
class StepResult:
    setpoint: Setpoint
    diagnostics: Diagnostics
