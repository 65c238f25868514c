"""DISTANCE_SENSOR from the world: ray casting at the vehicle pose, filled as autopilots do.

Each sensor's body (FLU) boresight is rotated into the world with R_G of the vehicle
attitude (`companion.planner.rotations.r_g`) and cast from the vehicle position.

Filling, per autopilot family (see GCS_MAVLINK::send_distance_sensor and PX4's
DISTANCE_SENSOR stream):
- distances in cm; type LASER; covariance 0; no field of view.
- id: ArduPilot the configured sensor id (its rangefinder instance); PX4 its own index of the
  sensor (table order), which need not match the configured id.
- orientation: the MAV_SENSOR_ORIENTATION whose boresight matches, else ROTATION_CUSTOM (100)
  with the quaternion (body FRD) when `with_quaternion` (real re-reports leave it zero).
- nothing within range: ArduPilot's serial lidar drivers report max_distance + 1 m
  (e.g. BENEWAKE_OUT_OF_RANGE_ADD_CM); PX4 (SIH, after LightWare) reports UINT16_MAX / 100 m,
  i.e. ~65535 cm.
- metres -> cm as the autopilots do it: float32 metres * 100.0f, truncated (so 0.53 m
  gives 52 cm; PX4 re-publishing adds another such step, the "1 cm lower" seen on SITL).
- signal_quality 0 (unknown): ArduPilot's SITL backend and PX4's stream do not report one.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.planner.rotations import r_g
from companion.planner.sensors import (
    MAV_SENSOR_ROTATION_CUSTOM,
    SensorSpec,
    mav_orientation_for_boresight,
    quaternion_from_boresight_frd,
)
from companion.planner.types import FloatArray, VehicleState
from companion.sim.mavlink.codec import Codec
from companion.sim.mavlink.models import RangeWorld
from companion.sim.sensing import SensorFan

_DS = mavlink.MAVLink_distance_sensor_message
_DS_ID = mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR
UINT16_MAX = 65535
ARDUPILOT_OUT_OF_RANGE_ADD_CM = 100
_PX4_OUT_OF_RANGE_CM = min(int(np.float32(UINT16_MAX / 100.0) * np.float32(100.0)), UINT16_MAX)


@dataclass(frozen=True, slots=True)
class SensorWire:
    """The fixed fields of one sensor's DISTANCE_SENSOR."""

    mav_id: int
    orientation: int
    quaternion: tuple[float, float, float, float]
    min_cm: int
    max_cm: int


class Rangefinders:
    """The configured range sensors: measure against the world, encode as DISTANCE_SENSOR."""

    def __init__(
        self,
        specs: Sequence[SensorSpec],
        world: RangeWorld,
        family: Literal["ardupilot", "px4"],
        with_quaternion: bool = True,
    ) -> None:
        self.specs = tuple(specs)
        self.world = world
        self.family = family
        self.boresights_flu = np.array([s.boresight_flu for s in self.specs]).reshape(-1, 3)
        self.min_m = np.array([s.min_range_m for s in self.specs])
        self.max_m = np.array([s.max_range_m for s in self.specs])
        self.cast_range_m = self.max_m * 1.01  # beyond max is out of range anyway
        self.fan = SensorFan(self.boresights_flu, np.array([s.fov_rad for s in self.specs]))
        self.wire = tuple(self._wire(i, s, with_quaternion) for i, s in enumerate(self.specs))
        self._out_of_range_cm = np.array(
            [min(w.max_cm + ARDUPILOT_OUT_OF_RANGE_ADD_CM, UINT16_MAX) for w in self.wire],
            dtype=np.int64,
        )

    def _wire(self, index: int, spec: SensorSpec, with_quaternion: bool) -> SensorWire:
        orientation = mav_orientation_for_boresight(spec.boresight_frd)
        q = (0.0, 0.0, 0.0, 0.0)
        if orientation == MAV_SENSOR_ROTATION_CUSTOM and with_quaternion:
            q = tuple(float(v) for v in quaternion_from_boresight_frd(spec.boresight_frd))  # type: ignore[assignment]
        return SensorWire(
            mav_id=spec.sensor_id if self.family == "ardupilot" else index,
            orientation=orientation,
            quaternion=q,
            min_cm=min(round(spec.min_range_m * 100.0), UINT16_MAX),
            max_cm=min(round(spec.max_range_m * 100.0), UINT16_MAX),
        )

    def __len__(self) -> int:
        return len(self.specs)

    def measure(self, state: VehicleState) -> FloatArray:
        """True ranges (n,) in metres from the vehicle position; inf where nothing is hit."""
        if not self.specs:
            return np.zeros(0)
        rot = r_g(state.roll_rad, state.pitch_rad, state.yaw_rad)
        ranges = self.fan.ranges(self.world.raycast, state.position_enu, rot, self.cast_range_m)
        return np.asarray(ranges, dtype=np.float64).reshape(len(self.specs))

    def current_cm(self, index: int, range_m: float) -> int:
        """current_distance for a reading, with the family's out-of-range convention."""
        w = self.wire[index]
        in_range = np.isfinite(range_m) and range_m < self.max_m[index]
        if not in_range:
            if self.family == "ardupilot":
                return min(w.max_cm + ARDUPILOT_OUT_OF_RANGE_ADD_CM, UINT16_MAX)
            range_m = UINT16_MAX / 100.0
        # Both autopilots multiply a float metre value by 100.0f and truncate to uint16.
        return min(int(np.float32(max(range_m, 0.0)) * np.float32(100.0)), UINT16_MAX)

    def currents_cm(self, ranges_m: FloatArray) -> list[int]:
        """`current_cm` of every sensor at once, ranges_m (n,) metres."""
        r = np.asarray(ranges_m, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            in_range = np.isfinite(r) & (r < self.max_m)
        out_cm = self._out_of_range_cm if self.family == "ardupilot" else _PX4_OUT_OF_RANGE_CM
        # As current_cm: a float32 metre value times 100.0f, truncated (in range: >= 0).
        cm = np.maximum(np.where(in_range, r, 0.0), 0.0).astype(np.float32) * np.float32(100.0)
        cm_int = np.minimum(cm.astype(np.int64), UINT16_MAX)
        return np.where(in_range, cm_int, out_cm).tolist()  # type: ignore[no-any-return]

    def messages(
        self, mav: Any, ranges_m: FloatArray, time_boot_ms: int, send: Any = None
    ) -> list[Any]:
        """DISTANCE_SENSOR of every sensor (where send, a mask (n,), holds; all if None)."""
        cms = self.currents_cm(ranges_m)
        return [
            self._encode(mav, i, cm, time_boot_ms)
            for i, cm in enumerate(cms)
            if send is None or send[i]
        ]

    def frames(
        self, codec: Codec, ranges_m: FloatArray, time_boot_ms: int, send: Any = None
    ) -> list[bytes]:
        """`messages`, packed: the same bytes as `codec.encode` of each, in the same order,
        without building the message objects."""
        cms = self.currents_cm(ranges_m)
        pack = _DS.unpacker.pack
        frame = codec.frame
        out = []
        for i, cm in enumerate(cms):
            if send is None or send[i]:
                w = self.wire[i]
                q = w.quaternion
                payload = pack(
                    time_boot_ms, w.min_cm, w.max_cm, cm, mavlink.MAV_DISTANCE_SENSOR_LASER,
                    w.mav_id, w.orientation, 0, 0.0, 0.0, q[0], q[1], q[2], q[3], 0,
                )  # fmt: skip
                out.append(frame(_DS_ID, _DS.crc_extra, payload))
        return out

    def message(self, mav: Any, index: int, range_m: float, time_boot_ms: int) -> Any:
        return self._encode(mav, index, self.current_cm(index, range_m), time_boot_ms)

    def _encode(self, mav: Any, index: int, current_cm: int, time_boot_ms: int) -> Any:
        w = self.wire[index]
        return mav.distance_sensor_encode(
            time_boot_ms,
            w.min_cm,
            w.max_cm,
            current_cm,
            mavlink.MAV_DISTANCE_SENSOR_LASER,
            w.mav_id,
            w.orientation,
            0,
            0.0,
            0.0,
            list(w.quaternion),
            0,
        )
