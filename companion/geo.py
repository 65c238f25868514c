"""Geodetic <-> local ENU, anchored at a home/origin position (WGS-84, via pymap3d).

The planner works in a local tangent plane: x east, y north, z up, metres, with the origin at
the home position's latitude, longitude and altitude (AMSL). This is the one place where the
service and the simulator convert.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import pymap3d


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


@dataclass(frozen=True, slots=True)
class LocalFrame:
    """Local ENU tangent plane at `origin`."""

    origin: GeoPoint

    def to_enu(self, point: GeoPoint) -> tuple[float, float, float]:
        """(east, north, up) in metres of a geodetic point."""
        o = self.origin
        e, n, u = pymap3d.geodetic2enu(
            point.lat_deg, point.lon_deg, point.alt_m, o.lat_deg, o.lon_deg, o.alt_m
        )
        return float(e), float(n), float(u)

    def to_geodetic(self, east_m: float, north_m: float, up_m: float) -> GeoPoint:
        """Geodetic point of local (east, north, up) metres."""
        o = self.origin
        lat, lon, alt = pymap3d.enu2geodetic(east_m, north_m, up_m, o.lat_deg, o.lon_deg, o.alt_m)
        return GeoPoint(float(lat), float(lon), float(alt))
