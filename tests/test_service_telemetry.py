"""The input cache: validation, units, sensor mapping, ordering, reboots, jumps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.service.codec import mavlink2
from companion.service.telemetry import Telemetry
from tests.service_fakes import HOME, make_config


def tel() -> Telemetry:
    return Telemetry(make_config().sensor_table())


def att(tb: int, roll: float = 0.0) -> object:
    return mavlink2.MAVLink_attitude_message(tb, roll, 0.1, 0.2, 0.0, 0.0, 0.0)


def pos(tb: int, north_m: float = 0.0, alt: float = HOME[2] + 5) -> object:
    lat = HOME[0] + math.degrees(north_m / 6_378_137.0)
    return mavlink2.MAVLink_global_position_int_message(
        tb, round(lat * 1e7), round(HOME[1] * 1e7), round(alt * 1000), 5000, 100, -50, 20, 0
    )


def dist(tb: int, sid: int, cm: int, orientation: int = 0, q: list[float] | None = None) -> object:
    return mavlink2.MAVLink_distance_sensor_message(
        tb, 10, 1000, cm, 0, sid, orientation, 0, 0.0, 0.0, q or [0, 0, 0, 0]
    )


def test_attitude_nan_inf_and_range_rejected_and_counted() -> None:
    t = tel()
    assert t.update(att(10), 1.0) == "ATTITUDE"
    assert t.update(att(20, math.nan), 2.0) is None
    assert t.update(att(30, math.inf), 3.0) is None
    assert t.update(att(40, 4.0), 4.0) is None  # |roll| > pi
    assert t.counters["rejected_attitude_nonfinite"] == 2
    assert t.counters["rejected_attitude_range"] == 1
    assert t.attitude is not None and t.attitude.t_rx == 1.0  # the old value stays and ages


def test_position_units_and_no_fix() -> None:
    t = tel()
    assert t.update(pos(10), 0.5) == "GLOBAL_POSITION_INT"
    p = t.position
    assert p is not None
    assert p.alt_amsl_m == pytest.approx(HOME[2] + 5) and p.relative_alt_m == 5.0
    assert p.velocity_ned_mps == (1.0, -0.5, 0.2)
    zero = mavlink2.MAVLink_global_position_int_message(20, 0, 0, 0, 0, 0, 0, 0, 0)
    assert t.update(zero, 0.6) is None and t.counters["rejected_position_range"] == 1


def test_out_of_order_duplicates_and_reboot() -> None:
    t = tel()
    for i in range(3):  # the first stamps of two kinds agree on the autopilot's clock
        t.update(att(5000 + 50 * i), 1.0 + 0.05 * i)
        t.update(pos(5000 + 50 * i), 1.0 + 0.05 * i)
    assert t.update(att(5090), 1.15) is None and t.counters["out_of_order"] == 1
    assert t.update(att(5100), 1.2) is None and t.counters["duplicate"] == 1
    # 5 s back: one message is no proof of a reboot (it could be forged)
    assert t.update(att(100), 1.3) is None and t.counters["time_boot_suspect"] == 1
    assert t.reboots == 0 and t.position is not None
    # a new boot clock that several messages of two types agree on: a reboot
    for i in range(3):
        t.update(att(150 + 50 * i), 1.35 + 0.05 * i)
        t.update(pos(150 + 50 * i), 1.35 + 0.05 * i)
    assert t.reboots == 1 and t.counters["time_boot_backwards"] == 1
    assert t.position is not None and t.position.time_boot_ms >= 150  # the new clock's


def test_position_jump_rejected_then_accepted_if_it_persists() -> None:
    t = Telemetry(
        make_config().sensor_table(),
        max_speed_mps=20.0,
        jump_accept_s=0.5,
        max_accepted_jump_m=150.0,
    )
    t.update(pos(1000, 0.0), 1.0)
    assert t.update(pos(1100, 0.5), 1.1) is not None  # 5 m/s: fine
    assert t.update(pos(1200, 100.0), 1.2) is None  # 1000 m/s: glitch
    assert t.counters["rejected_position_jump"] == 1
    assert t.update(pos(1500, 100.0), 1.5) is None
    assert t.update(pos(1800, 100.0), 1.8) is not None  # persisted 0.6 s: accept
    assert t.counters["position_jump_accepted"] == 1


def test_distance_sensor_mapping_units_and_nothing_detected() -> None:
    t = tel()
    now = 2.0
    assert t.update(dist(1, 0, 250), now)
    r = t.range_vector(now, 0.5)
    assert r[0] == 2.5 and math.isnan(r[1]) and math.isnan(r[2])  # missing = NaN
    for cm, name, want in ((0, "range_none", 0.0), (65535, "range_none", 0.0),
                           (5, "range_below_min", 0.1),  # too close to measure: at the min
                           (1000, "range_at_max", 0.0), (1500, "range_at_max", 0.0)):  # fmt: skip
        t.update(dist(0, 0, cm), now)
        assert t.range_vector(now, 0.5)[0] == want  # fresh "nothing" (0.0) or the minimum
        assert t.counters[name] >= 1
    assert math.isnan(t.range_vector(now + 0.6, 0.5)[0])  # stale = NaN
    assert t.stale_sensors(now, 0.5) == [1, 2]


def test_distance_sensor_orientation_checked() -> None:
    t = tel()
    assert t.update(dist(0, 1, 300, orientation=39), 1.0)  # PITCH_315 as configured
    assert not t.update(dist(0, 1, 300, orientation=25), 1.0)  # PITCH_270: mismatch
    assert t.counters["rejected_sensor_orientation_mismatch"] == 1
    assert not t.update(dist(0, 0, 300, orientation=77), 1.0)
    assert t.counters["rejected_sensor_orientation_unknown"] == 1
    assert not t.update(dist(0, 42, 300), 1.0)
    assert t.counters["rejected_sensor_unknown_id"] == 1
    # sensor 2 is tilted back-down: CUSTOM with a quaternion, or unverifiable without one
    spec = t.sensors.specs[2]
    from companion.planner.sensors import quaternion_from_boresight_frd

    q = quaternion_from_boresight_frd(spec.boresight_frd).tolist()
    assert t.update(dist(0, 2, 300, orientation=100, q=q), 1.0)
    assert t.update(dist(0, 2, 300, orientation=100), 1.0)
    assert t.counters["sensor_orientation_unverified"] == 1
    np.testing.assert_allclose(t.range_vector(1.0, 0.5), [math.nan, 3.0, 3.0])


def test_one_id_with_several_wrong_orientations_is_said_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """PX4 passes on the rangefinders fed to it over one link as one sensor, each reading
    with its own orientation: the configured one is used, the others refused, and the
    sharing is said once. One wrong orientation alone (another device on that id, as SIH's
    downward rangefinder) is only a mismatch."""
    t = tel()
    for k in range(5):
        assert not t.update(dist(1 + k, 0, 300, orientation=25), 1.0)  # sensor 0 is NONE
    assert t.counters["sensor_id_shared"] == 0 and "shares this id" not in caplog.text
    for k, orientation in enumerate([39, 0, 6, 39, 0, 2, 39]):
        ok = t.update(dist(10 + k, 1, 300 + k, orientation=orientation), 1.0)
        assert bool(ok) == (orientation == 39)  # sensor 1 is PITCH_315
    assert t.counters["sensor_id_shared"] == 1
    assert caplog.text.count("shares this id") == 1 and "id 1 " in caplog.text


def test_custom_orientation_checked_per_quaternion_every_time() -> None:
    """The check of a CUSTOM orientation is remembered per (sensor, quaternion): the same
    quaternion keeps its verdict, another one is judged afresh, whichever came first."""
    from companion.planner.sensors import quaternion_from_boresight_frd

    t = tel()
    good = quaternion_from_boresight_frd(t.sensors.specs[2].boresight_frd).tolist()
    wrong = quaternion_from_boresight_frd(t.sensors.specs[1].boresight_frd).tolist()
    for k in range(3):
        stamp = 1 + 2 * k
        assert t.update(dist(stamp, 2, 300, orientation=100, q=good), 1.0)
        assert not t.update(dist(stamp + 1, 2, 300, orientation=100, q=wrong), 1.0)
    assert t.counters["rejected_sensor_orientation_mismatch"] == 3
    # the wrong quaternion is wrong for sensor 2 only: it is sensor 1's own
    assert t.update(dist(7, 1, 300, orientation=100, q=wrong), 1.0)
    # a sender varying its quaternion stays bounded
    for k in range(1100):
        q = [1.0, 0.0, 0.0, k * 1e-9]
        t.update(dist(10 + k, 2, 300, orientation=100, q=q), 1.0)
    assert len(t._custom_ok) <= 1025
