"""Scenario files: the world, the route, the vehicle, its sensors and the planner tuning.

A scenario is one YAML file (see docs/scenarios.md). It is validated on load: a wrong key,
type or range is refused with the key path, what was expected and what was found.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from companion.planner.params import PlannerParams
from companion.planner.route import Route
from companion.planner.sensors import SensorTable
from companion.sim.vehicle import VehicleModelConfig
from companion.sim.world import World, WorldConfig
from companion.tuning import (
    Finite,
    PlannerConfig,
    RouteConfig,
    SensorConfig,
    include_sensors_file,
    sensor_table,
)

Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]


class ScenarioError(ValueError):
    """A scenario file that cannot be used; the message names the key and the problem."""


class Expectation(BaseModel):
    """`expect:` section: the outcome the scenario is meant to show, asserted by the tests.

    Any key left out is not checked. Lengths metres, angles radians, speeds m/s.
    passes: obstacle feature name -> "left" / "right" (side the vehicle passes it on).
    unchanged_over: feature names over which the horizontal path must stay on the route
    (max lateral deviation below max_lateral_deviation_over_m).
    max_replans: at most this many re-plans (cycles that took a new path) in the flight.
    known_issue: set when the scenario reproduces a defect not fixed yet: the expectations
    are what must hold once it is; tests/test_scenarios.py reports the scenario's
    expectations and D_min as expected failures with this text (XPASS the day they hold).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    reached_goal: bool | None = None
    min_clearance_m: Finite | None = None
    max_abs_pitch_rad: Finite | None = None
    """Bound on |phi_d| (eq. 4, the paper's Fig. 7c) and on the vehicle's own pitch."""
    max_height_error_m: Finite | None = None
    max_speed_error_mps: Finite | None = None
    final_heading_deg: Finite | None = None
    passes: dict[str, str] = Field(default_factory=dict)
    unchanged_over: list[str] = Field(default_factory=list)
    max_lateral_deviation_over_m: Finite = 0.05
    min_decisions: dict[str, int] = Field(default_factory=dict)
    collisions: int | None = 0
    max_replans: int | None = Field(default=None, ge=0)
    known_issue: str | None = None


class Scenario(BaseModel):
    """A whole scenario file. Frame: local ENU metres; time seconds."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    name: str
    description: str = ""
    duration_s: Positive = 300.0
    dt_s: Annotated[float, Field(gt=0, le=1.0)] = 0.05
    start_position: tuple[Finite, Finite, Finite] | None = None
    world: WorldConfig = Field(default_factory=WorldConfig)
    route: RouteConfig
    vehicle: VehicleModelConfig = Field(default_factory=VehicleModelConfig)
    sensors: Annotated[list[SensorConfig], Field(min_length=2)]
    """The sensor table; in the file either a list or the name of a YAML file holding one."""
    planner: PlannerConfig = Field(default_factory=PlannerConfig)
    expect: Expectation = Field(default_factory=Expectation)
    mavlink: dict[str, Any] | None = None
    """Options of the MAVLink simulator (companion/sim/mavlink), validated there."""

    def params(self) -> PlannerParams:
        return self.planner.to_params()

    def sensor_table(self) -> SensorTable:
        return sensor_table(self.sensors)

    def route_obj(self) -> Route:
        return self.route.to_route()

    def start(self, world: World) -> np.ndarray:
        """Start position (x, y, z): given, or the first base point at H_d above ground."""
        if self.start_position is not None:
            return np.array(self.start_position, dtype=np.float64)
        x, y = self.route.points[0]
        z = float(world.height(x, y)) + self.planner.h_d_m
        return np.array([x, y, z])


def format_validation_error(err: ValidationError, source: str) -> str:
    """One line per problem: `file: key.path: message (found: value)`."""
    lines = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"]) or "(top level)"
        found = e.get("input")
        shown = repr(found) if not isinstance(found, dict | list) else type(found).__name__
        lines.append(f"{source}: {loc}: {e['msg']} (found: {shown})")
    return "\n".join(lines)


def load_scenario(path: Path | str) -> Scenario:
    """Read and validate a scenario file; ScenarioError with every problem found."""
    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ScenarioError(f"{p}: cannot read: {exc.strerror or exc}") from exc
    except yaml.YAMLError as exc:
        raise ScenarioError(f"{p}: not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise ScenarioError(f"{p}: expected a mapping at the top level")
    try:
        include_sensors_file(data, p.parent)
    except ValueError as exc:
        raise ScenarioError(f"{p}: {exc}") from exc
    try:
        scenario = Scenario.model_validate(data)
        scenario.sensor_table()  # cross-field checks (duplicate ids, missing surface sensors)
        scenario.route_obj()
    except ValidationError as exc:
        raise ScenarioError(format_validation_error(exc, str(p))) from exc
    except ValueError as exc:
        raise ScenarioError(f"{p}: {exc}") from exc
    return scenario
