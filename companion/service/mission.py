"""Mission download (MISSION_REQUEST_LIST / MISSION_REQUEST_INT) and its route points.

ArduPilot's item 0 is the home position and is skipped; PX4's item 0 is a real item. Only
items with a position the route can use are kept: NAV_WAYPOINT and NAV_SPLINE_WAYPOINT in a
global frame. Take-off, land, RTL and DO_ items are skipped (and logged).

Errors::

    MissionError         the download failed; .seq names the item when there is one
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass

import numpy as np

from companion.geo import GeoPoint, LocalFrame
from companion.planner.types import FloatArray
from companion.service.codec import MAVLinkMessage, mavlink2
from companion.service.connection import Connection
from companion.service.modes import AutopilotKind
from companion.service.telemetry import valid_lat_lon

log = logging.getLogger(__name__)

MAV_MISSION_TYPE_MISSION: int = mavlink2.MAV_MISSION_TYPE_MISSION
MAV_MISSION_ACCEPTED: int = mavlink2.MAV_MISSION_ACCEPTED
MAV_CMD_NAV_WAYPOINT: int = mavlink2.MAV_CMD_NAV_WAYPOINT
MAV_CMD_NAV_SPLINE_WAYPOINT: int = mavlink2.MAV_CMD_NAV_SPLINE_WAYPOINT
GLOBAL_FRAMES = frozenset(
    {
        mavlink2.MAV_FRAME_GLOBAL,
        mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT,
        mavlink2.MAV_FRAME_GLOBAL_INT,
        mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        mavlink2.MAV_FRAME_GLOBAL_TERRAIN_ALT,
        mavlink2.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    }
)
MAX_ITEMS = 1000


class MissionError(Exception):
    def __init__(self, message: str, seq: int | None = None) -> None:
        self.seq = seq
        super().__init__(message if seq is None else f"item {seq}: {message}")


@dataclass(frozen=True, slots=True)
class MissionItem:
    """One mission item; lat/lon degrees, z as the item's frame says."""

    seq: int
    frame: int
    command: int
    lat_deg: float
    lon_deg: float
    z: float


async def download_mission(
    conn: Connection, timeout_s: float = 1.0, retries: int = 3
) -> list[MissionItem]:
    """All mission items of the locked autopilot, in order. Raises MissionError."""
    ts, tc = conn.target_system, conn.target_component
    if ts is None or tc is None:
        raise MissionError("no autopilot yet")

    async def ask(msg: MAVLinkMessage, types: frozenset[str], pred: object, what: str,
                  seq: int | None = None) -> MAVLinkMessage:  # fmt: skip
        for _ in range(1 + retries):
            fut = conn.expect(types, pred)  # type: ignore[arg-type]
            try:
                conn.send(msg)
                async with asyncio.timeout(timeout_s):  # (keeps a cancel: see commands.py)
                    return await fut
            except TimeoutError:
                continue
            finally:
                conn.forget(fut)
        raise MissionError(f"no {what} after {1 + retries} attempt(s)", seq)

    def is_type(m: MAVLinkMessage) -> bool:
        return int(getattr(m, "mission_type", 0)) == MAV_MISSION_TYPE_MISSION

    count_msg = await ask(
        mavlink2.MAVLink_mission_request_list_message(ts, tc, MAV_MISSION_TYPE_MISSION),
        frozenset({"MISSION_COUNT"}),
        is_type,
        "MISSION_COUNT",
    )
    count = int(count_msg.count)
    if count > MAX_ITEMS:
        raise MissionError(f"mission of {count} items is larger than {MAX_ITEMS}")
    items: list[MissionItem] = []
    for seq in range(count):
        item = await ask(
            mavlink2.MAVLink_mission_request_int_message(ts, tc, seq, MAV_MISSION_TYPE_MISSION),
            frozenset({"MISSION_ITEM_INT", "MISSION_ITEM"}),
            lambda m, s=seq: int(m.seq) == s and is_type(m),
            "MISSION_ITEM_INT",
            seq,
        )
        if item.get_type() == "MISSION_ITEM_INT":
            lat, lon = item.x * 1e-7, item.y * 1e-7
        else:
            lat, lon = float(item.x), float(item.y)
        items.append(MissionItem(seq, int(item.frame), int(item.command), lat, lon, float(item.z)))
    conn.send(mavlink2.MAVLink_mission_ack_message(ts, tc, MAV_MISSION_ACCEPTED))
    return items


def mission_waypoints(items: list[MissionItem], kind: AutopilotKind) -> list[tuple[float, float]]:
    """The (lat, lon) degrees of the items a route can use, in order, repeats removed."""
    pts: list[tuple[float, float]] = []
    for it in items:
        if kind is AutopilotKind.ARDUPILOT and it.seq == 0:
            continue  # home
        if it.command not in (MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_SPLINE_WAYPOINT):
            log.info("mission item %d: command %d skipped (not a waypoint)", it.seq, it.command)
            continue
        if it.frame not in GLOBAL_FRAMES or not valid_lat_lon(it.lat_deg, it.lon_deg):
            log.warning("mission item %d: no usable global position; skipped", it.seq)
            continue
        if pts and pts[-1] == (it.lat_deg, it.lon_deg):
            continue  # repeated point: the route needs distinct consecutive points
        pts.append((it.lat_deg, it.lon_deg))
    return pts


def latlon_to_xy(points: list[tuple[float, float]], frame: LocalFrame) -> FloatArray:
    """(lat, lon) degrees -> local ENU (x, y) metres in `frame`, shape (n, 2)."""
    alt = frame.origin.alt_m
    xy = [frame.to_enu(GeoPoint(lat, lon, alt))[:2] for lat, lon in points]
    return np.array(xy, dtype=np.float64).reshape(-1, 2)
