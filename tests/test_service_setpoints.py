"""ENU setpoints -> SET_POSITION_TARGET_GLOBAL_INT, frames 5 and 6."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.geo import GeoPoint, LocalFrame
from companion.service.setpoints import (
    TYPE_MASK,
    TYPE_MASK_NO_ACCELERATION,
    SetpointFrame,
    position_target,
)

FRAME = LocalFrame(GeoPoint(47.4, 8.5, 500.0))


def test_type_mask_uses_position_velocity_acceleration_yaw() -> None:
    assert TYPE_MASK & 0b111 == 0  # position used
    assert TYPE_MASK & 0b111000 == 0  # velocity used
    assert TYPE_MASK & 0b111000000 == 0  # acceleration used
    assert TYPE_MASK & 512 == 0  # no force
    assert TYPE_MASK & 1024 == 0 and TYPE_MASK & 2048 == 2048  # yaw used, yaw rate ignored
    assert TYPE_MASK_NO_ACCELERATION == TYPE_MASK | 0b111000000


def _target(acceleration: np.ndarray | None) -> object:
    return position_target(
        np.zeros(3),
        np.array([1.0, 0.0, 0.0]),
        0.0,
        acceleration,
        frame=FRAME,
        mav_frame=SetpointFrame.GLOBAL,
        home_alt_amsl_m=500.0,
        time_boot_ms=0,
        target_system=1,
        target_component=1,
    )


def test_acceleration_goes_out_in_ned_or_is_masked() -> None:
    msg = _target(np.array([0.3, -0.2, 0.5]))  # east, north, up
    assert msg.type_mask == TYPE_MASK
    assert (msg.afx, msg.afy, msg.afz) == pytest.approx((-0.2, 0.3, -0.5))
    msg = _target(None)
    assert msg.type_mask == TYPE_MASK_NO_ACCELERATION
    assert (msg.afx, msg.afy, msg.afz) == (0.0, 0.0, 0.0)


@settings(max_examples=100, deadline=None)
@given(
    st.floats(-500, 500), st.floats(-500, 500), st.floats(-50, 200), st.floats(-math.pi, math.pi)
)
def test_round_trip_through_the_message(e: float, n: float, u: float, yaw: float) -> None:
    v = np.array([1.0, -2.0, 0.5])
    for mav_frame in SetpointFrame:
        msg = position_target(
            np.array([e, n, u]),
            v,
            yaw,
            frame=FRAME,
            mav_frame=mav_frame,
            home_alt_amsl_m=502.0,  # the autopilot's home moved 2 m up since we anchored
            time_boot_ms=1234,
            target_system=1,
            target_component=1,
        )
        assert msg.coordinate_frame == int(mav_frame)
        alt = msg.alt if mav_frame is SetpointFrame.GLOBAL else msg.alt + 502.0
        back = FRAME.to_enu(GeoPoint(msg.lat_int * 1e-7, msg.lon_int * 1e-7, alt))
        np.testing.assert_allclose(back, [e, n, u], atol=0.02)
        assert (msg.vx, msg.vy, msg.vz) == pytest.approx((-2.0, 1.0, -0.5))  # NED
        yaw_back = math.pi / 2 - msg.yaw
        assert math.cos(yaw_back - yaw) == pytest.approx(1.0, abs=1e-6)
