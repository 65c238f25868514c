"""YAML sections shared by the service config and the simulator's scenarios.

Validated with pydantic: unknown keys, wrong types and out-of-range values are refused with
the key path, what was expected and what was found. Each model turns into the planner's
plain data (`PlannerParams`, `SensorSpec`, `Route`) with a `to_...` method.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from companion.planner.params import ArcMethod, PlannerParams
from companion.planner.route import Route
from companion.planner.sensors import (
    MAV_SENSOR_ORIENTATION_DEG,
    MAV_SENSOR_ROTATION_CUSTOM,
    Group,
    Role,
    SensorSpec,
    SensorTable,
    boresight_from_mav_orientation,
    boresight_from_quaternion_frd,
    boresight_from_rpy_frd,
)

Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
XY = tuple[Finite, Finite]


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class PlannerConfig(Strict):
    """`planner:` section. Lengths m, angles rad, speeds m/s (see PlannerParams)."""

    h_d_m: Positive = 2.0
    d_min_m: Positive = 2.0
    phi_max_rad: Annotated[float, Field(gt=0, lt=math.pi / 2)] = 0.6
    v_d_mps: Annotated[float, Field(gt=0, le=20)] = 1.0
    min_turn_radius_m: Positive = 2.0
    lat_accel_max_mps2: Positive = 0.5
    accel_max_mps2: Positive = 0.5
    clearance_margin_m: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 0.6
    lookahead_m: Positive = 25.0
    memory_radius_m: Positive = 40.0
    memory_max_points: Annotated[int, Field(ge=16, le=1_000_000)] = 4096
    memory_cell_m: Positive = 0.25
    arc_method: ArcMethod = ArcMethod.EXACT
    paper_delta: Annotated[float, Field(gt=0, lt=0.1)] = 1e-4
    goal_tolerance_m: Positive = 0.05
    reaction_time_s: Annotated[float, Field(ge=0, le=5, allow_inf_nan=False)] = 0.4
    leash_m: Positive = 2.0
    shape_terrain: bool = True
    yaw_sweep_period_m: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 4.0

    def to_params(self) -> PlannerParams:
        return PlannerParams(**self.model_dump())


_ORIENTATION_NAMES = {
    "NONE": 0,
    **{
        name: value
        for value, name in [
            (1, "YAW_45"),
            (2, "YAW_90"),
            (3, "YAW_135"),
            (4, "YAW_180"),
            (5, "YAW_225"),
            (6, "YAW_270"),
            (7, "YAW_315"),
            (8, "ROLL_180"),
            (12, "PITCH_180"),
            (24, "PITCH_90"),
            (25, "PITCH_270"),
            (39, "PITCH_315"),
        ]
    },
}


class SensorConfig(Strict):
    """One entry of `sensors:`. Give exactly one of orientation, rpy_deg, quaternion.

    orientation: MAV_SENSOR_ORIENTATION value (int) or name ("YAW_90", "PITCH_270", ...).
    rpy_deg: [roll, pitch, yaw] degrees, the rotation in body FRD that takes forward onto the
        boresight (MAVLink's convention). quaternion: [w, x, y, z] in body FRD.
    """

    id: Annotated[int, Field(ge=0, le=255)]
    role: Role
    group: Group
    orientation: int | str | None = None
    rpy_deg: tuple[Finite, Finite, Finite] | None = None
    quaternion: tuple[Finite, Finite, Finite, Finite] | None = None
    min_range_m: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 0.1
    max_range_m: Positive = 10.0
    name: str = ""
    fov_deg: Annotated[float, Field(ge=0, lt=180, allow_inf_nan=False)] = 0.0
    """Width of the sector one reading covers (a proximity sector: 45), degrees; 0: a beam."""

    @field_validator("orientation")
    @classmethod
    def _known_orientation(cls, v: int | str | None) -> int | str | None:
        if isinstance(v, str):
            key = v.upper().removeprefix("MAV_SENSOR_ROTATION_")
            if key not in _ORIENTATION_NAMES:
                raise ValueError(
                    f"unknown orientation name {v!r}; use a MAV_SENSOR_ORIENTATION value, "
                    f"one of {sorted(_ORIENTATION_NAMES)}, rpy_deg or quaternion"
                )
            return _ORIENTATION_NAMES[key]
        if v is not None and v not in MAV_SENSOR_ORIENTATION_DEG:
            hint = " (give the quaternion instead)" if v == MAV_SENSOR_ROTATION_CUSTOM else ""
            raise ValueError(f"unknown MAV_SENSOR_ORIENTATION value {v}{hint}")
        return v

    @model_validator(mode="after")
    def _one_orientation(self) -> SensorConfig:
        given = [x is not None for x in (self.orientation, self.rpy_deg, self.quaternion)]
        if sum(given) != 1:
            raise ValueError("give exactly one of orientation, rpy_deg, quaternion")
        if self.quaternion is not None and np.linalg.norm(self.quaternion) < 1e-6:
            raise ValueError("quaternion must be non-zero")
        if self.min_range_m >= self.max_range_m:
            raise ValueError(
                f"min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})"
            )
        if self.role is Role.OBSTACLE and self.group.value not in ("L", "F", "R"):
            raise ValueError("obstacle sensors need group L, F or R")
        if self.role is Role.SURFACE and self.group.value in ("L", "F", "R"):
            raise ValueError("surface sensors need group forward, back, left or right")
        return self

    def to_spec(self) -> SensorSpec:
        if self.orientation is not None:
            u = boresight_from_mav_orientation(int(self.orientation))
        elif self.rpy_deg is not None:
            u = boresight_from_rpy_frd(*(math.radians(a) for a in self.rpy_deg))
        else:
            assert self.quaternion is not None
            u = boresight_from_quaternion_frd(self.quaternion)
        return SensorSpec.from_frd(
            self.id,
            self.role,
            self.group,
            u,
            self.min_range_m,
            self.max_range_m,
            self.name,
            math.radians(self.fov_deg),
        )


def include_sensors_file(data: dict[str, Any], base_dir: Path) -> None:
    """`sensors: FILE` in a YAML document: replace the name by the list the file holds.

    The path is relative to base_dir (the directory of the document). ValueError names the
    file and the problem.
    """
    name = data.get("sensors")
    if not isinstance(name, str):
        return
    path = base_dir / name
    try:
        data["sensors"] = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ValueError(f"sensors: cannot read {path}: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise ValueError(f"sensors: {path} is not valid YAML: {exc}") from None


def sensor_table(sensors: list[SensorConfig]) -> SensorTable:
    """Build the planner's sensor table; ValueError names the problem (duplicate id, ...)."""
    return SensorTable([s.to_spec() for s in sensors])


class RouteConfig(Strict):
    """`route:` section: base points W (local ENU x, y metres) and headings (degrees, ENU)."""

    points: Annotated[list[XY], Field(min_length=2)]
    start_heading_deg: Finite | None = None
    arrival_heading_deg: Finite | None = None

    def to_route(self) -> Route:
        return Route(
            np.array(self.points, dtype=np.float64),
            None if self.start_heading_deg is None else math.radians(self.start_heading_deg),
            None if self.arrival_heading_deg is None else math.radians(self.arrival_heading_deg),
        )
