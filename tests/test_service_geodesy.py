"""The service's per-cycle geodesy against pymap3d, and the telemetry clock's O(1) median."""

from __future__ import annotations

import math
import random

import pytest

from companion.geo import GeoPoint, LocalFrame
from companion.service.codec import mavlink2
from companion.service.geodesy import TangentPlane, ecef_to_geodetic, geodetic_to_ecef
from companion.service.telemetry import Telemetry
from tests.service_fakes import make_config


def _metres(a: GeoPoint, b: GeoPoint) -> float:
    """Distance between two nearby geodetic points, m (small-angle, ample for mm checks)."""
    north = math.radians(a.lat_deg - b.lat_deg) * 6_378_137.0
    east = math.radians(a.lon_deg - b.lon_deg) * 6_378_137.0 * math.cos(math.radians(a.lat_deg))
    return math.sqrt(north**2 + east**2 + (a.alt_m - b.alt_m) ** 2)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tangent_plane_equals_pymap3d_within_50_km(seed: int) -> None:
    rnd = random.Random(seed)
    for _ in range(300):
        origin = GeoPoint(rnd.uniform(-85, 85), rnd.uniform(-180, 180), rnd.uniform(-400, 4000))
        ref, fast = LocalFrame(origin), TangentPlane(origin)
        enu = (rnd.uniform(-50e3, 50e3), rnd.uniform(-50e3, 50e3), rnd.uniform(-500, 500))
        a, b = ref.to_geodetic(*enu), fast.to_geodetic(*enu)
        assert _metres(a, b) < 1e-3
        assert a == b  # the same operations as pymap3d: bit for bit (lockstep flights unchanged)
        back_ref, back_fast = ref.to_enu(a), fast.to_enu(a)
        assert back_ref == back_fast
        assert max(abs(x - y) for x, y in zip(back_fast, enu, strict=True)) < 1e-3


def test_ecef_round_trip_at_poles_equator_and_antimeridian() -> None:
    for lat, lon, alt in [(90.0, 0.0, 10.0), (-90.0, 0.0, 0.0), (0.0, 180.0, 5.0), (0.0, 0.0, 0.0)]:
        la, lo, al = ecef_to_geodetic(*geodetic_to_ecef(lat, lon, alt))
        assert la == pytest.approx(lat, abs=1e-9)
        assert al == pytest.approx(alt, abs=1e-4)
        if abs(lat) < 90.0:
            assert math.cos(math.radians(lo - lon)) == pytest.approx(1.0, abs=1e-12)


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
