"""WGS-84 geodetic <-> local ENU in plain float arithmetic, for the per-cycle conversions.

Same frame and same accuracy as `companion.geo.LocalFrame` (pymap3d) — exact ellipsoid,
not a flat-earth approximation — without numpy scalars per call: the origin's ECEF position
and rotation are computed once; ECEF -> geodetic uses Bowring's formula refined by two fixed
iterations (sub-micrometre on and near the ellipsoid). East, north, up: metres; latitude and
longitude: degrees; altitude: metres above the ellipsoid reference used for the origin.
"""

from __future__ import annotations

import math

from companion.geo import GeoPoint, LocalFrame

WGS84_A = 6378137.0
"""Semi-major axis, m."""
WGS84_F = 1.0 / 298.257223563
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
"""First eccentricity squared."""
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)
"""Second eccentricity squared."""


def geodetic_to_ecef(lat_deg: float, lon_deg: float, alt_m: float) -> tuple[float, float, float]:
    """ECEF x, y, z (m) of a geodetic point (deg, deg, m above the ellipsoid)."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    sl, cl = math.sin(lat), math.cos(lat)
    n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * sl * sl)
    r = (n + alt_m) * cl
    return r * math.cos(lon), r * math.sin(lon), (n * (1.0 - WGS84_E2) + alt_m) * sl


def ecef_to_geodetic(x: float, y: float, z: float) -> tuple[float, float, float]:
    """Geodetic (deg, deg, m) of an ECEF point (m): Bowring's start, two refinements."""
    p = math.hypot(x, y)
    lon = math.atan2(y, x)
    if p < 1e-9:  # on the axis
        lat = math.copysign(math.pi / 2.0, z)
        return math.degrees(lat), math.degrees(lon), abs(z) - WGS84_B
    beta = math.atan2(z, p * (1.0 - WGS84_F))
    for _ in range(3):
        sb, cb = math.sin(beta), math.cos(beta)
        lat = math.atan2(z + WGS84_EP2 * WGS84_B * sb**3, p - WGS84_E2 * WGS84_A * cb**3)
        beta = math.atan2((1.0 - WGS84_F) * math.sin(lat), math.cos(lat))
    sl, cl = math.sin(lat), math.cos(lat)
    n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * sl * sl)
    # altitude along the normal; the better-conditioned form for the latitude at hand
    alt = p / cl - n if abs(cl) > 0.5 else z / sl - n * (1.0 - WGS84_E2)
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
        dx, dy, dz = x - ox, y - oy, z - oz
        sf, cf, sl, cl = self._r
        t = cl * dx + sl * dy
        return -sl * dx + cl * dy, -sf * t + cf * dz, cf * t + sf * dz

    def to_geodetic(self, east_m: float, north_m: float, up_m: float) -> GeoPoint:
        """Geodetic point of local (east, north, up) metres."""
        sf, cf, sl, cl = self._r
        t = -sf * north_m + cf * up_m
        ox, oy, oz = self._o
        x = ox + cl * t - sl * east_m
        y = oy + sl * t + cl * east_m
        z = oz + cf * north_m + sf * up_m
        return GeoPoint(*ecef_to_geodetic(x, y, z))
