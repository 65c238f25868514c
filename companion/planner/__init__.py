"""The spatial planner of the paper as a pure library: plain data in, plain data out.

No I/O, clocks, logging setup or globals; same inputs give the same outputs.
"""

from companion.planner.bezier import CubicBezier
from companion.planner.params import ArcMethod, PlannerParams
from companion.planner.path import Path
from companion.planner.planner import SEARCH_BUDGET_UNITS, SEARCH_BUDGET_UNITS_AT_REST, Planner
from companion.planner.route import Route
from companion.planner.sensors import Group, Role, SensorSpec, SensorTable
from companion.planner.types import (
    Decision,
    Diagnostics,
    PathMode,
    Setpoint,
    Side,
    StepResult,
    VehicleState,
)

__all__ = [
    "SEARCH_BUDGET_UNITS",
    "SEARCH_BUDGET_UNITS_AT_REST",
    "ArcMethod",
    "CubicBezier",
    "Decision",
    "Diagnostics",
    "Group",
    "Path",
    "PathMode",
    "Planner",
    "PlannerParams",
    "Role",
    "Route",
    "SensorSpec",
    "SensorTable",
    "Setpoint",
    "Side",
    "StepResult",
    "VehicleState",
]
