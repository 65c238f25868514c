"""The telemetry clock's O(1) median (the geodesy's tests are in test_geo.py)."""

from __future__ import annotations

import random

import pytest

from companion.service.codec import mavlink2
from companion.service.telemetry import Telemetry
from tests.service_fakes import make_config


def _brute_expected(t: Telemetry, t_rx: float) -> float | None:
    """The definition: lower median over kinds of (last stamp + time since its receipt)."""
    rx = t._last_rx
    vals = sorted(s + (t_rx - rx[k]) * 1000.0 for k, s in t._last_boot_ms.items() if k in rx)
    return vals[(len(vals) - 1) // 2] if vals else None


def test_expected_stamp_kept_sorted_equals_the_sorted_definition() -> None:
    """Jittered, reordered, forged and rebooting streams: the incremental median is the median."""
    rnd = random.Random(7)
    t = Telemetry(make_config().sensor_table())
    sensor_ids = [s.sensor_id for s in t.sensors.specs]
    boot_ms, t_rx, checked = 5000, 100.0, 0
    for i in range(3000):
        t_rx += 0.004
        boot_ms += 4
        if i == 1500:
            boot_ms = 200  # a reboot
        stamp = boot_ms + rnd.choice([0, 0, 0, -30, 20, 900, -5000])
        kind = rnd.randrange(3)
        if kind == 0:
            msg = mavlink2.MAVLink_attitude_message(max(stamp, 0), 0.0, 0.1, 0.2, 0.0, 0.0, 0.0)
        else:
            sid = rnd.choice(sensor_ids)
            msg = mavlink2.MAVLink_distance_sensor_message(
                max(stamp, 0), 10, 1000, 500, 0, sid, 0, 0, 0.0, 0.0, [0, 0, 0, 0]
            )
        t.update(msg, t_rx)
        want = _brute_expected(t, t_rx + 0.001)
        got = t._expected_stamp(t_rx + 0.001)
        if want is None:
            assert got is None
        else:
            assert got == pytest.approx(want, abs=1e-6)
            checked += 1
    assert checked > 2000
    assert t.reboots >= 1
