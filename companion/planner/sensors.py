"""The range-sensor table and eqs (1)-(2): from a range reading to a world point.

Each sensor's orientation is kept as its boresight unit vector in the body frame. It can be
given, as in MAVLink DISTANCE_SENSOR, by a MAV_SENSOR_ORIENTATION value, by roll/pitch/yaw
angles in the same convention (the rotation, in body FRD, that takes "forward" onto the
boresight: Rz(yaw) Ry(pitch) Rx(roll)), or by a quaternion (w, x, y, z) in body FRD as in
MAV_SENSOR_ROTATION_CUSTOM. So MAV_SENSOR_ROTATION_YAW_90 points right and PITCH_270 down,
as ArduPilot and PX4 read them.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from companion.planner.frames import frd_to_flu, quaternion_to_matrix
from companion.planner.rotations import euler_zyx
from companion.planner.types import BoolArray, FloatArray

MAV_SENSOR_ROTATION_CUSTOM = 100

# MAV_SENSOR_ORIENTATION value -> (roll, pitch, yaw) in degrees, as the enum names them.
MAV_SENSOR_ORIENTATION_DEG: dict[int, tuple[float, float, float]] = {
    0: (0, 0, 0),
    1: (0, 0, 45),
    2: (0, 0, 90),
    3: (0, 0, 135),
    4: (0, 0, 180),
    5: (0, 0, 225),
    6: (0, 0, 270),
    7: (0, 0, 315),
    8: (180, 0, 0),
    9: (180, 0, 45),
    10: (180, 0, 90),
    11: (180, 0, 135),
    12: (0, 180, 0),
    13: (180, 0, 225),
    14: (180, 0, 270),
    15: (180, 0, 315),
    16: (90, 0, 0),
    17: (90, 0, 45),
    18: (90, 0, 90),
    19: (90, 0, 135),
    20: (270, 0, 0),
    21: (270, 0, 45),
    22: (270, 0, 90),
    23: (270, 0, 135),
    24: (0, 90, 0),
    25: (0, 270, 0),
    26: (0, 180, 90),
    27: (0, 180, 270),
    28: (90, 90, 0),
    29: (180, 90, 0),
    30: (270, 90, 0),
    31: (90, 180, 0),
    32: (270, 180, 0),
    33: (90, 270, 0),
    34: (180, 270, 0),
    35: (270, 270, 0),
    36: (90, 180, 90),
    37: (90, 0, 270),
    38: (90, 68.8, 293.3),
    39: (0, 315, 0),
    40: (90, 315, 0),
}


class Role(enum.StrEnum):
    OBSTACLE = "obstacle"
    SURFACE = "surface"


class Group(enum.StrEnum):
    """Obstacle groups L/F/R of eq. (6) and surface positions h1..h4 of eq. (2)."""

    LEFT = "L"
    FORWARD = "F"
    RIGHT = "R"
    SURFACE_FORWARD = "forward"
    SURFACE_BACK = "back"
    SURFACE_LEFT = "left"
    SURFACE_RIGHT = "right"


OBSTACLE_GROUPS = (Group.LEFT, Group.FORWARD, Group.RIGHT)
SURFACE_GROUPS = (
    Group.SURFACE_FORWARD,
    Group.SURFACE_BACK,
    Group.SURFACE_LEFT,
    Group.SURFACE_RIGHT,
)
# Eq. (6) pairing as docs/paper.md reads it: L with the left point, F forward, R right.
SURFACE_FOR_GROUP = {
    Group.LEFT: Group.SURFACE_LEFT,
    Group.FORWARD: Group.SURFACE_FORWARD,
    Group.RIGHT: Group.SURFACE_RIGHT,
}


def boresight_from_rpy_frd(roll_rad: float, pitch_rad: float, yaw_rad: float) -> FloatArray:
    """Boresight unit vector in body FRD for a MAVLink-style rotation of "forward"."""
    return euler_zyx(roll_rad, pitch_rad, yaw_rad)[:, 0].copy()


def boresight_from_mav_orientation(orientation: int) -> FloatArray:
    """Boresight unit vector in body FRD for a MAV_SENSOR_ORIENTATION value.

    Raises ValueError for ROTATION_CUSTOM (use the quaternion) or an unknown value.
    """
    if orientation == MAV_SENSOR_ROTATION_CUSTOM:
        raise ValueError("MAV_SENSOR_ROTATION_CUSTOM needs a quaternion")
    try:
        roll, pitch, yaw = MAV_SENSOR_ORIENTATION_DEG[orientation]
    except KeyError:
        raise ValueError(f"unknown MAV_SENSOR_ORIENTATION value {orientation}") from None
    return boresight_from_rpy_frd(math.radians(roll), math.radians(pitch), math.radians(yaw))


def boresight_from_quaternion_frd(q_wxyz: Sequence[float] | FloatArray) -> FloatArray:
    """Boresight unit vector in body FRD: the quaternion applied to "forward"."""
    return quaternion_to_matrix(np.asarray(q_wxyz, dtype=np.float64))[:, 0].copy()


def quaternion_from_boresight_frd(boresight_frd: FloatArray) -> FloatArray:
    """A quaternion (w, x, y, z) that turns body forward onto the boresight (no roll about it).

    Used to fill DISTANCE_SENSOR.quaternion for MAV_SENSOR_ROTATION_CUSTOM.
    """
    u = np.asarray(boresight_frd, dtype=np.float64)
    u = u / np.linalg.norm(u)
    fwd = np.array([1.0, 0.0, 0.0])
    axis = np.cross(fwd, u)
    s = float(np.linalg.norm(axis))
    c = float(np.dot(fwd, u))
    if s < 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0]) if c > 0 else np.array([0.0, 0.0, 0.0, 1.0])
    angle = math.atan2(s, c)
    axis = axis / s
    half = angle / 2.0
    return np.array([math.cos(half), *(math.sin(half) * axis)])


def mav_orientation_for_boresight(boresight_frd: FloatArray, tol: float = 1e-6) -> int:
    """The MAV_SENSOR_ORIENTATION value whose boresight matches, else ROTATION_CUSTOM (100)."""
    u = np.asarray(boresight_frd, dtype=np.float64)
    for value in sorted(MAV_SENSOR_ORIENTATION_DEG):
        if np.allclose(boresight_from_mav_orientation(value), u, atol=tol):
            return value
    return MAV_SENSOR_ROTATION_CUSTOM


@dataclass(frozen=True, slots=True)
class SensorSpec:
    """One range sensor.

    sensor_id: the DISTANCE_SENSOR id it reports as. boresight_flu: unit vector in body FLU.
    min_range_m / max_range_m: readings of 0, below min or at/over max mean "nothing detected"
    (Condition 1 of the paper and the MAVLink convention).
    fov_rad: width of the sector the reading covers, radians, spread about the body's up
    axis (yaw) round the boresight; 0 for a narrow beam. A proximity sector (ArduPilot
    reports the nearest object within 45 degrees) reads the nearest object anywhere in it:
    the planner takes such a reading as "something at this range within the sector"
    (`sector_fan_flu`).
    """

    sensor_id: int
    role: Role
    group: Group
    boresight_flu: FloatArray
    min_range_m: float
    max_range_m: float
    name: str = ""
    fov_rad: float = 0.0

    def __post_init__(self) -> None:
        u = np.asarray(self.boresight_flu, dtype=np.float64).reshape(3)
        norm = float(np.linalg.norm(u))
        if not math.isfinite(norm) or norm < 1e-9:
            raise ValueError(f"sensor {self.sensor_id}: boresight must be non-zero, got {u}")
        u = u / norm
        u.setflags(write=False)
        object.__setattr__(self, "boresight_flu", u)
        if self.role is Role.OBSTACLE and self.group not in OBSTACLE_GROUPS:
            raise ValueError(f"sensor {self.sensor_id}: obstacle sensors need group L, F or R")
        if self.role is Role.SURFACE and self.group not in SURFACE_GROUPS:
            raise ValueError(
                f"sensor {self.sensor_id}: surface sensors need group forward/back/left/right"
            )
        if not (0.0 <= self.min_range_m < self.max_range_m and math.isfinite(self.max_range_m)):
            raise ValueError(
                f"sensor {self.sensor_id}: need 0 <= min_range_m < max_range_m, got "
                f"{self.min_range_m}, {self.max_range_m}"
            )
        if not (math.isfinite(self.fov_rad) and 0.0 <= self.fov_rad < math.pi):
            raise ValueError(
                f"sensor {self.sensor_id}: fov must be within [0, 180) degrees, got "
                f"{math.degrees(self.fov_rad)}"
            )

    @property
    def boresight_frd(self) -> FloatArray:
        return frd_to_flu(self.boresight_flu)  # the flip is its own inverse

    @classmethod
    def from_frd(
        cls,
        sensor_id: int,
        role: Role | str,
        group: Group | str,
        boresight_frd: FloatArray,
        min_range_m: float,
        max_range_m: float,
        name: str = "",
        fov_rad: float = 0.0,
    ) -> SensorSpec:
        return cls(
            sensor_id,
            Role(role),
            Group(group),
            frd_to_flu(boresight_frd),
            float(min_range_m),
            float(max_range_m),
            name,
            float(fov_rad),
        )


class SensorTable:
    """The ordered set of sensors; readings are arrays aligned with `specs`.

    Obstacle sensors are the vector D, surface sensors the vector H of the paper. The table
    must hold a forward and a back surface sensor (eq. 3); left/right are needed for the side
    groups of eq. (6) and fall back to the forward one if missing.
    """

    def __init__(self, specs: Sequence[SensorSpec]) -> None:
        if not specs:
            raise ValueError("sensor table is empty")
        ids = [s.sensor_id for s in specs]
        dup = {i for i in ids if ids.count(i) > 1}
        if dup:
            raise ValueError(f"duplicate sensor ids {sorted(dup)}")
        self.specs: tuple[SensorSpec, ...] = tuple(specs)
        self.boresights_flu = np.array([s.boresight_flu for s in specs])
        self.min_range_m = np.array([s.min_range_m for s in specs])
        # "> 0 and >= min" as one comparison: >= the larger of min and the smallest float > 0.
        self._detect_from_m = np.maximum(self.min_range_m, np.nextafter(0.0, 1.0))
        self.max_range_m = np.array([s.max_range_m for s in specs])
        self.fov_rad = np.array([s.fov_rad for s in specs])
        self.obstacle_index = np.array(
            [i for i, s in enumerate(specs) if s.role is Role.OBSTACLE], dtype=np.intp
        )
        self.obstacle_groups = tuple(specs[i].group for i in self.obstacle_index)
        surface: dict[Group, int] = {}
        for i, s in enumerate(specs):
            if s.role is Role.SURFACE:
                if s.group in surface:
                    raise ValueError(f"two surface sensors in group {s.group.value}")
                surface[s.group] = i
        for needed in (Group.SURFACE_FORWARD, Group.SURFACE_BACK):
            if needed not in surface:
                raise ValueError(f"sensor table needs a '{needed.value}' surface sensor (eq. 3)")
        self.surface_index = surface
        self.index_of_id = {s.sensor_id: i for i, s in enumerate(specs)}

    def __len__(self) -> int:
        return len(self.specs)

    def valid(self, ranges_m: FloatArray) -> BoolArray:
        """Boolean mask of readings that detect something: finite, > 0, >= min and < max.
        (NaN fails every comparison and inf the one with the finite max: no isfinite needed.)"""
        r = np.asarray(ranges_m, dtype=np.float64)
        detects: BoolArray = (r >= self._detect_from_m) & (r < self.max_range_m)
        return detects


def sector_fan_flu(boresight_flu: FloatArray, fov_rad: float, n: int) -> FloatArray:
    """n unit directions (n, 3), body FLU, spread evenly across a sector of fov_rad about the
    body's up axis, centred on the boresight (the boresight itself when fov_rad is 0 or n
    is 1). A sector reading r says: the nearest object in the sector is r away along one of
    these, and nothing is nearer along any of them."""
    u = np.asarray(boresight_flu, dtype=np.float64).reshape(3)
    if fov_rad <= 0.0 or n <= 1:
        return u[None, :].copy()
    a = np.linspace(-0.5 * fov_rad, 0.5 * fov_rad, n)
    c, s = np.cos(a), np.sin(a)
    return np.column_stack([c * u[0] - s * u[1], s * u[0] + c * u[1], np.full(n, u[2])])


def range_points_world(
    position_enu: FloatArray,
    r_world_body: FloatArray,
    boresights_flu: FloatArray,
    ranges_m: FloatArray,
) -> FloatArray:
    """Eqs (1)-(2): X_i = X + R_G R_MR [0, 0, d_i]^T for every sensor, world ENU, metres.

    R_MR [0, 0, 1] is the sensor's boresight (body FLU), so this is X + R_G (u_i d_i).
    boresights_flu: (n, 3); ranges_m: (n,). Returns (n, 3); invalid readings give
    meaningless points and must be masked by the caller.
    """
    r = np.where(np.isfinite(ranges_m), ranges_m, 0.0)
    dirs_world = boresights_flu @ r_world_body.T
    return np.asarray(position_enu, dtype=np.float64) + dirs_world * r[:, None]
