"""World configuration: the feature schema read from scenario YAML (pydantic models).

Frame: local ENU (x east, y north, z up), metres; angles in degrees as written in YAML.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, model_validator

__all__ = [
    "XY",
    "BoxConfig",
    "CylinderConfig",
    "FeatureConfig",
    "GaussianHillConfig",
    "HeightmapConfig",
    "MesaConfig",
    "PlaneConfig",
    "WorldConfig",
]

XY = tuple[float, float]

_CFG = ConfigDict(extra="forbid", allow_inf_nan=False)


class GaussianHillConfig(BaseModel):
    """Additive hill h * exp(-r^2 / 2 sigma^2); sigma_xy_m + yaw_deg make it elliptic."""

    model_config = _CFG
    type: Literal["gaussian_hill"] = "gaussian_hill"
    name: str = Field("gaussian_hill", min_length=1)
    obstacle: bool = False
    center: XY
    height_m: float
    sigma_m: PositiveFloat | None = None
    sigma_xy_m: tuple[PositiveFloat, PositiveFloat] | None = None
    yaw_deg: float = 0.0
    """Rotation of the sigma_xy axes, degrees CCW from +x."""

    @model_validator(mode="after")
    def _one_sigma(self) -> GaussianHillConfig:
        if (self.sigma_m is None) == (self.sigma_xy_m is None):
            raise ValueError("gaussian_hill needs exactly one of sigma_m or sigma_xy_m")
        return self


class MesaConfig(BaseModel):
    """Steep hill: flat top disc of radius_m at ground_z + height_m, sides at side_slope_deg."""

    model_config = _CFG
    type: Literal["mesa"] = "mesa"
    name: str = Field("mesa", min_length=1)
    obstacle: bool = True
    center: XY
    radius_m: PositiveFloat
    height_m: PositiveFloat
    side_slope_deg: float = Field(80.0, gt=0.0, le=90.0)


class CylinderConfig(BaseModel):
    """Vertical cylinder standing on ground_z."""

    model_config = _CFG
    type: Literal["cylinder"] = "cylinder"
    name: str = Field("cylinder", min_length=1)
    obstacle: bool = True
    center: XY
    radius_m: PositiveFloat
    height_m: PositiveFloat


class BoxConfig(BaseModel):
    """Box standing on ground_z: size_m = (length along its x, width along its y, height)."""

    model_config = _CFG
    type: Literal["box"] = "box"
    name: str = Field("box", min_length=1)
    obstacle: bool = True
    center: XY
    size_m: tuple[PositiveFloat, PositiveFloat, PositiveFloat]
    yaw_deg: float = 0.0
    """Rotation of the box about z, degrees CCW from +x."""


class PlaneConfig(BaseModel):
    """Additive inclined plane, 0 at `point`, rising at slope_deg towards direction_deg."""

    model_config = _CFG
    type: Literal["plane"] = "plane"
    name: str = Field("plane", min_length=1)
    obstacle: bool = False
    slope_deg: float = Field(ge=0.0, lt=90.0)
    direction_deg: float = 0.0
    """Direction of steepest ascent, degrees CCW from +x."""
    point: XY = (0.0, 0.0)


class HeightmapConfig(BaseModel):
    """Additive grid of heights from a .npy file (rows = y, cols = x), bilinear, 0 outside."""

    model_config = _CFG
    type: Literal["heightmap"] = "heightmap"
    name: str = Field("heightmap", min_length=1)
    obstacle: bool = False
    file: str = Field(min_length=1)
    """Path to the .npy file; relative paths are relative to the loader's base_dir."""
    resolution_m: PositiveFloat
    origin: XY = (0.0, 0.0)
    """World (x, y) of element [0, 0]."""


FeatureConfig = Annotated[
    GaussianHillConfig | MesaConfig | CylinderConfig | BoxConfig | PlaneConfig | HeightmapConfig,
    Field(discriminator="type"),
]


class WorldConfig(BaseModel):
    model_config = _CFG
    ground_z_m: float = 0.0
    features: list[FeatureConfig] = Field(default_factory=list)
