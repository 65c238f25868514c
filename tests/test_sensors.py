"""Sensor table, orientation conventions and eqs (1)-(2)."""

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from companion.planner.rotations import r_g
from companion.planner.sensors import (
    MAV_SENSOR_ORIENTATION_DEG,
    Group,
    Role,
    SensorSpec,
    SensorTable,
    boresight_from_mav_orientation,
    boresight_from_quaternion_frd,
    boresight_from_rpy_frd,
    mav_orientation_for_boresight,
    quaternion_from_boresight_frd,
    range_points_world,
)


def test_yaw_90_points_right_as_ardupilot_and_px4_read_it() -> None:
    """MAV_SENSOR_ROTATION_YAW_90: body FRD (0, 1, 0), the vehicle's right."""
    u = boresight_from_mav_orientation(mavlink.MAV_SENSOR_ROTATION_YAW_90)
    np.testing.assert_allclose(u, [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(
        boresight_from_mav_orientation(mavlink.MAV_SENSOR_ROTATION_YAW_270), [0, -1, 0], atol=1e-12
    )
    np.testing.assert_allclose(
        boresight_from_mav_orientation(mavlink.MAV_SENSOR_ROTATION_PITCH_270), [0, 0, 1], atol=1e-12
    )
    np.testing.assert_allclose(
        boresight_from_mav_orientation(mavlink.MAV_SENSOR_ROTATION_PITCH_90), [0, 0, -1], atol=1e-12
    )
    s = math.sqrt(0.5)
    np.testing.assert_allclose(
        boresight_from_mav_orientation(mavlink.MAV_SENSOR_ROTATION_PITCH_315), [s, 0, s], atol=1e-12
    )


def test_world_direction_of_a_right_sensor() -> None:
    """A YAW_90 sensor on a vehicle heading north (ENU yaw pi/2) looks east."""
    spec = SensorSpec.from_frd(
        1, Role.OBSTACLE, Group.RIGHT, boresight_from_mav_orientation(2), 0.1, 10
    )
    p = range_points_world(
        np.zeros(3), r_g(0, 0, math.pi / 2), spec.boresight_flu[None, :], np.array([5.0])
    )
    np.testing.assert_allclose(p[0], [5, 0, 0], atol=1e-12)


def test_orientation_table_matches_pymavlink_names() -> None:
    """Our table of roll/pitch/yaw per enum value agrees with the names pymavlink carries."""
    enum = mavlink.enums["MAV_SENSOR_ORIENTATION"]
    for value, (roll, pitch, yaw) in MAV_SENSOR_ORIENTATION_DEG.items():
        name = enum[value].name.removeprefix("MAV_SENSOR_ROTATION_")
        parts = dict.fromkeys(("ROLL", "PITCH", "YAW"), 0.0)
        if name != "NONE":
            tokens = name.split("_")
            for axis, angle in zip(tokens[::2], tokens[1::2], strict=True):
                parts[axis] = float(angle)
        if value == 38:  # ROLL_90_PITCH_68_YAW_293: the enum rounds 68.8 and 293.3
            continue
        assert (roll, pitch, yaw) == (parts["ROLL"], parts["PITCH"], parts["YAW"]), name


def test_rpy_and_quaternion_agree_with_the_enum() -> None:
    for value, (roll, pitch, yaw) in MAV_SENSOR_ORIENTATION_DEG.items():
        u = boresight_from_rpy_frd(*(math.radians(a) for a in (roll, pitch, yaw)))
        np.testing.assert_allclose(u, boresight_from_mav_orientation(value), atol=1e-12)
        q = quaternion_from_boresight_frd(u)
        np.testing.assert_allclose(boresight_from_quaternion_frd(q), u, atol=1e-9)


def test_custom_orientation_round_trip() -> None:
    back_down = boresight_from_rpy_frd(0, math.radians(315), math.pi)
    assert mav_orientation_for_boresight(back_down) == mavlink.MAV_SENSOR_ROTATION_CUSTOM
    assert mav_orientation_for_boresight(boresight_from_mav_orientation(39)) == 39


def _table() -> SensorTable:
    fwd = boresight_from_mav_orientation(39)
    back = boresight_from_rpy_frd(0, math.radians(315), math.pi)
    return SensorTable(
        [
            SensorSpec.from_frd(0, Role.OBSTACLE, Group.FORWARD, [1, 0, 0], 0.2, 10),
            SensorSpec.from_frd(1, Role.SURFACE, Group.SURFACE_FORWARD, fwd, 0.2, 10),
            SensorSpec.from_frd(2, Role.SURFACE, Group.SURFACE_BACK, back, 0.2, 10),
        ]
    )


def test_nothing_detected_readings() -> None:
    """0, below min, at/over max and NaN all mean "nothing detected"."""
    t = _table()
    valid = t.valid(np.array([0.0, 0.1, 10.0]))
    assert not valid.any()
    assert t.valid(np.array([np.nan, 9.99, 0.2])).tolist() == [False, True, True]


def test_table_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="duplicate sensor ids"):
        SensorTable([*list(_table().specs), _table().specs[0]])
    with pytest.raises(ValueError, match="'back' surface sensor"):
        SensorTable(list(_table().specs[:2]))
    with pytest.raises(ValueError, match="min_range_m < max_range_m"):
        SensorSpec.from_frd(5, Role.OBSTACLE, Group.LEFT, [0, -1, 0], 5, 1)
    with pytest.raises(ValueError, match="group L, F or R"):
        SensorSpec.from_frd(5, Role.OBSTACLE, Group.SURFACE_LEFT, [0, -1, 0], 0.1, 1)
    with pytest.raises(ValueError, match="CUSTOM needs a quaternion"):
        boresight_from_mav_orientation(100)
