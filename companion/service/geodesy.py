"""WGS-84 geodetic <-> local ENU in plain float arithmetic, for the per-cycle conversions.

The same frame and the same numbers as `companion.geo.LocalFrame` (pymap3d): the same
formulas (pymap3d's geodetic2ecef, enu2uvw/uvw2enu and You (2000)'s ecef2geodetic) in the
same order of operations, so the results agree bit for bit (a test checks this) and a
lockstep flight is unchanged, without pymap3d's per-call array set-up (about 100 us a call).
The origin's ECEF position and trigonometry are computed once. East, north, up: metres;
latitude, longitude: degrees; altitude: metres above the WGS-84 ellipsoid as for the origin.
"""

from __future__ import annotations

import math

import numpy as np

from companion.geo import GeoPoint, LocalFrame

WGS84_A = 6378137.0
"""Semi-major axis, m (pymap3d's value)."""
WGS84_B = 6356752.31424518
"""Semi-minor axis, m (pymap3d's value)."""
_E = math.sqrt(WGS84_A**2 - WGS84_B**2)
_E2 = _E**2
_HALF_PI = math.pi / 2
_LIM_PI2 = math.pi / 2 - float(np.finfo(np.float64).eps)


def _hypot(x: float, y: float) -> float:
    # C's hypot, as numpy's (Python's math.hypot can differ in the last bit)
    return float(np.hypot(x, y))


def geodetic_to_ecef(lat_deg: float, lon_deg: float, alt_m: float) -> tuple[float, float, float]:
    """ECEF x, y, z (m) of a geodetic point (deg, deg, m above the ellipsoid)."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    cl, sl = math.cos(lat), math.sin(lat)
    n = WGS84_A**2 / _hypot(WGS84_A * cl, WGS84_B * sl)
    return (
        (n + alt_m) * cl * math.cos(lon),
        (n + alt_m) * cl * math.sin(lon),
        (n * (WGS84_B / WGS84_A) ** 2 + alt_m) * sl,
    )


def ecef_to_geodetic(x: float, y: float, z: float) -> tuple[float, float, float]:
    """Geodetic (deg, deg, m) of an ECEF point (m): You (2000), no iterations."""
    r = math.sqrt(x**2 + y**2 + z**2)
    u = math.sqrt(0.5 * (r**2 - _E2) + 0.5 * _hypot(r**2 - _E2, 2 * _E * z))
    hxy = _hypot(x, y)
    hue = _hypot(u, _E)
    if abs(u) <= 1e-8 or abs(hxy) <= 1e-8:  # on the axis or at the centre
        beta = 0.0 if abs(z) <= 1e-8 else (_HALF_PI if z > 0 else -_HALF_PI)
    else:
        beta = math.atan(hue / u * z / hxy)
        beta += ((WGS84_B * u - WGS84_A * hue + _E2) * math.sin(beta)) / (
            WGS84_A * hue * 1 / math.cos(beta) - _E2 * math.cos(beta)
        )
    lat = math.atan(WGS84_A / WGS84_B * math.tan(beta))
    cos_beta = math.cos(beta)
    if beta >= _LIM_PI2:
        lat, cos_beta = _HALF_PI, 0.0
    elif beta <= -_LIM_PI2:
        lat, cos_beta = -_HALF_PI, 0.0
    lon = math.atan2(y, x)
    alt = _hypot(z - WGS84_B * math.sin(beta), hxy - WGS84_A * cos_beta)
    if x**2 / WGS84_A**2 + y**2 / WGS84_A**2 + z**2 / WGS84_B**2 < 1:
        alt = -alt
    return math.degrees(lat), math.degrees(lon), alt


class TangentPlane:
    """Local ENU tangent plane at `origin` (x east, y north, z up, metres), like
    `companion.geo.LocalFrame`, with the origin's trigonometry computed once."""

    __slots__ = ("_o", "_r", "origin")

    def __init__(self, origin: GeoPoint) -> None:
        self.origin = origin
        self._o = geodetic_to_ecef(origin.lat_deg, origin.lon_deg, origin.alt_m)
        lat, lon = math.radians(origin.lat_deg), math.radians(origin.lon_deg)
        self._r = (math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon))

    @classmethod
    def of(cls, frame: LocalFrame) -> TangentPlane:
        return cls(frame.origin)

    def to_enu(self, point: GeoPoint) -> tuple[float, float, float]:
        """(east, north, up) in metres of a geodetic point."""
        x, y, z = geodetic_to_ecef(point.lat_deg, point.lon_deg, point.alt_m)
        ox, oy, oz = self._o
        u, v, w = x - ox, y - oy, z - oz
        sf, cf, sl, cl = self._r
        t = cl * u + sl * v
        return -sl * u + cl * v, -sf * t + cf * w, cf * t + sf * w

    def to_geodetic(self, east_m: float, north_m: float, up_m: float) -> GeoPoint:
        """Geodetic point of local (east, north, up) metres."""
        sf, cf, sl, cl = self._r
        t = cf * up_m - sf * north_m
        w = sf * up_m + cf * north_m
        u = cl * t - sl * east_m
        v = sl * t + cl * east_m
        ox, oy, oz = self._o
        return GeoPoint(*ecef_to_geodetic(ox + u, oy + v, oz + w))
