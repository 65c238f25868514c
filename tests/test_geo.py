"""The one geodesy (`companion.geo`) against pymap3d, its oracle: to within a few ulps."""

from __future__ import annotations

import math
import random

import pymap3d
import pytest

from companion.config import latlon_points_xy
from companion.geo import GeoPoint, LocalFrame, ecef_to_geodetic, geodetic_to_ecef, latlon_to_enu_xy


def _metres(a: GeoPoint, b: GeoPoint) -> float:
    """Distance between two nearby geodetic points, m (small-angle, ample for mm checks)."""
    north = math.radians(a.lat_deg - b.lat_deg) * 6_378_137.0
    east = math.radians(a.lon_deg - b.lon_deg) * 6_378_137.0 * math.cos(math.radians(a.lat_deg))
    return math.sqrt(north**2 + east**2 + (a.alt_m - b.alt_m) ** 2)


def _random_origin(rnd: random.Random) -> GeoPoint:
    return GeoPoint(rnd.uniform(-85, 85), rnd.uniform(-180, 180), rnd.uniform(-400, 4000))


def _within_ulps(a: tuple[float, ...], b: tuple[float, ...], ulps: int = 4) -> bool:
    """Each pair equal to within a few units in the last place. companion.geo does pymap3d's
    operations with `math`; pymap3d does them with numpy, whose vectorised sin and cos differ
    from libm's by an ulp on some CPUs (seen on AMD EPYC: 64 of 900 points, at most
    3e-14 degrees, 3 nm), so bit for bit holds on some machines and not on others."""
    return all(
        abs(x - y) <= ulps * math.ulp(max(abs(x), abs(y))) for x, y in zip(a, b, strict=True)
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_local_frame_equals_pymap3d_within_ulps_within_50_km(seed: int) -> None:
    rnd = random.Random(seed)
    for _ in range(300):
        o = _random_origin(rnd)
        frame = LocalFrame(o)
        enu = (rnd.uniform(-50e3, 50e3), rnd.uniform(-50e3, 50e3), rnd.uniform(-500, 500))
        got = frame.to_geodetic(*enu)
        lat, lon, alt = pymap3d.enu2geodetic(*enu, o.lat_deg, o.lon_deg, o.alt_m)
        want = GeoPoint(float(lat), float(lon), float(alt))
        assert _within_ulps(
            (got.lat_deg, got.lon_deg, got.alt_m), (want.lat_deg, want.lon_deg, want.alt_m)
        )
        e, n, u = pymap3d.geodetic2enu(
            want.lat_deg, want.lon_deg, want.alt_m, o.lat_deg, o.lon_deg, o.alt_m
        )
        back = frame.to_enu(got)
        # ENU differences of ECEF coordinates of about 6.4e6 m: an ulp there is 1e-9 m.
        assert max(abs(x - float(y)) for x, y in zip(back, (e, n, u), strict=True)) < 1e-8
        assert max(abs(x - y) for x, y in zip(back, enu, strict=True)) < 1e-3
        assert _metres(got, frame.to_geodetic(*back)) < 1e-3


def test_ecef_equals_pymap3d_and_round_trips_at_poles_equator_and_antimeridian() -> None:
    for lat, lon, alt in [(90.0, 0.0, 10.0), (-90.0, 0.0, 0.0), (0.0, 180.0, 5.0), (0.0, 0.0, 0.0)]:
        xyz = geodetic_to_ecef(lat, lon, alt)
        assert xyz == tuple(float(v) for v in pymap3d.geodetic2ecef(lat, lon, alt))
        la, lo, al = ecef_to_geodetic(*xyz)
        assert la == pytest.approx(lat, abs=1e-9)
        assert al == pytest.approx(alt, abs=1e-4)
        if abs(lat) < 90.0:
            assert math.cos(math.radians(lo - lon)) == pytest.approx(1.0, abs=1e-12)


def test_frames_compare_by_origin_and_hash() -> None:
    a, b = LocalFrame(GeoPoint(47.4, 8.5, 488.0)), LocalFrame(GeoPoint(47.4, 8.5, 488.0))
    assert a == b and hash(a) == hash(b)
    assert a != LocalFrame(GeoPoint(47.4, 8.5, 489.0))
    with pytest.raises(ValueError, match="finite"):
        LocalFrame(GeoPoint(math.nan, 8.5, 0.0))


def test_latlon_points_are_the_tangent_plane_at_the_first_point() -> None:
    """The config's route checks use the same geodesy as the flight (no sphere any more)."""
    rnd = random.Random(3)
    for _ in range(50):
        o = _random_origin(rnd)
        o = GeoPoint(o.lat_deg, o.lon_deg, 0.0)
        frame = LocalFrame(o)
        pts = [(o.lat_deg, o.lon_deg)] + [
            (o.lat_deg + rnd.uniform(-0.3, 0.3), o.lon_deg + rnd.uniform(-0.3, 0.3))
            for _ in range(5)
        ]
        pts = [(max(-90.0, min(90.0, a)), (b + 180.0) % 360.0 - 180.0) for a, b in pts]
        xy = latlon_points_xy(pts)
        assert xy == latlon_to_enu_xy(pts)
        assert xy[0] == (0.0, 0.0)
        for (lat, lon), (x, y) in zip(pts, xy, strict=True):
            e, n, _ = frame.to_enu(GeoPoint(lat, lon, 0.0))
            assert (x, y) == (e, n)


def test_latlon_points_keep_metre_scale_distances() -> None:
    """About 1 m of latitude and of longitude at 47 deg N, to a millimetre (the route's
    spacing check, MIN_ROUTE_SPACING_M, sees real metres)."""
    lat0, lon0 = 47.397742, 8.545594
    dlat = 1.0 / 111_200.0
    dlon = 1.0 / (111_320.0 * math.cos(math.radians(lat0)))
    xy = latlon_points_xy([(lat0, lon0), (lat0 + dlat, lon0), (lat0 + dlat, lon0 + dlon)])
    assert xy[1][0] == pytest.approx(0.0, abs=1e-6)
    assert xy[1][1] == pytest.approx(1.0, abs=0.01)
    assert xy[2][0] == pytest.approx(1.0, abs=0.01)
    assert latlon_to_enu_xy([]) == []
