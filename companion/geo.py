"""Geodetic <-> local ENU, anchored at a home/origin position (WGS-84): the one geodesy.

The planner works in a local tangent plane: x east, y north, z up, metres, with the origin at
the home position's latitude, longitude and altitude. The service (every cycle), the config's
route checks and the simulator all convert here.

Plain float arithmetic, with pymap3d's formulas in pymap3d's order of operations
(geodetic2ecef, the ENU <-> ECEF rotation, You (2000)'s closed-form ecef2geodetic), so the
results equal pymap3d's bit for bit (the tests keep pymap3d as their oracle) without its
per-call array set-up (about 100 us a call, 19 times this). The origin's ECEF position and
trigonometry are computed once per frame. Latitude, longitude: degrees; altitude: metres above
the WGS-84 ellipsoid, the same reference as the origin's (AMSL in, AMSL out when the origin is
AMSL: the frame only differences them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

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


@dataclass(frozen=True, slots=True)
class GeoPoint:
    """A WGS-84 position: degrees and metres above mean sea level."""

    lat_deg: float
    lon_deg: float
    alt_m: float

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.lat_deg, self.lon_deg, self.alt_m)):
            raise ValueError(f"geodetic position must be finite, got {self}")
        if not (-90.0 <= self.lat_deg <= 90.0 and -180.0 <= self.lon_deg <= 180.0):
            raise ValueError(f"latitude/longitude out of range: {self}")


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


@dataclass(frozen=True, slots=True)
class LocalFrame:
    """Local ENU tangent plane at `origin` (x east, y north, z up, metres).

    Equal frames are frames of equal origins; the origin's ECEF position and trigonometry
    are computed once, at construction.
    """

    origin: GeoPoint
    _ecef: tuple[float, float, float] = field(init=False, repr=False, compare=False)
    _trig: tuple[float, float, float, float] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        o = self.origin
        object.__setattr__(self, "_ecef", geodetic_to_ecef(o.lat_deg, o.lon_deg, o.alt_m))
        lat, lon = math.radians(o.lat_deg), math.radians(o.lon_deg)
        object.__setattr__(
            self, "_trig", (math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon))
        )

    def to_enu(self, point: GeoPoint) -> tuple[float, float, float]:
        """(east, north, up) in metres of a geodetic point."""
        x, y, z = geodetic_to_ecef(point.lat_deg, point.lon_deg, point.alt_m)
        ox, oy, oz = self._ecef
        u, v, w = x - ox, y - oy, z - oz
        sf, cf, sl, cl = self._trig
        t = cl * u + sl * v
        return -sl * u + cl * v, -sf * t + cf * w, cf * t + sf * w

    def to_geodetic(self, east_m: float, north_m: float, up_m: float) -> GeoPoint:
        """Geodetic point of local (east, north, up) metres."""
        sf, cf, sl, cl = self._trig
        t = cf * up_m - sf * north_m
        w = sf * up_m + cf * north_m
        u = cl * t - sl * east_m
        v = sl * t + cl * east_m
        ox, oy, oz = self._ecef
        return GeoPoint(*ecef_to_geodetic(ox + u, oy + v, oz + w))


def latlon_to_enu_xy(
    points: list[tuple[float, float]], origin: GeoPoint | None = None
) -> list[tuple[float, float]]:
    """(lat, lon) degrees -> (east, north) metres in the tangent plane at `origin` (default:
    the first point, at altitude 0), the points taken at the origin's altitude."""
    if not points:
        return []
    o = origin if origin is not None else GeoPoint(points[0][0], points[0][1], 0.0)
    frame = LocalFrame(o)
    out = []
    for lat, lon in points:
        e, n, _ = frame.to_enu(GeoPoint(lat, lon, o.alt_m))
        out.append((e, n))
    return out


__all__ = [
    "WGS84_A",
    "WGS84_B",
    "GeoPoint",
    "LocalFrame",
    "ecef_to_geodetic",
    "geodetic_to_ecef",
    "latlon_to_enu_xy",
]
