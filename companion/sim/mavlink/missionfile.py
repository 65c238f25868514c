"""Mission files a ground station writes, read into the simulator's mission list.

Two formats:
- QGroundControl / Mission Planner waypoint files (`QGC WPL 110` on the first line, then one
  tab-separated item per line: seq, current, frame, command, param1..4, x (lat deg), y (lon
  deg), z, autocontinue). As Mission Planner writes them for ArduPilot, item 0 is home.
- QGroundControl `.plan` files (JSON, `fileType: "Plan"`): `mission.items` of type
  `SimpleItem` (command, frame, params[7], autoContinue); home is
  `mission.plannedHomePosition`, not an item. Complex items (surveys, corridor scans) are
  refused: QGroundControl expands them only when it uploads.

`load_mission` returns the items as the simulator stores them for the personality: with a
home item at seq 0 on ArduPilot (its value is replaced by the vehicle's home on download),
without one on PX4. Errors are `MissionFileError` with one line naming the file and the item.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.sim.mavlink.mission import MAX_ITEMS, MissionItem

WPL_HEADER = "QGC WPL 110"
GLOBAL_FRAMES = frozenset(
    {
        mavlink.MAV_FRAME_GLOBAL,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
        mavlink.MAV_FRAME_GLOBAL_INT,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT,
        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    }
)


class MissionFileError(ValueError):
    """A mission file that cannot be read; the message is one line."""


def _item(
    where: str,
    seq: int,
    frame: int,
    command: int,
    params: tuple[float, float, float, float],
    lat: float,
    lon: float,
    z: float,
    autocontinue: int,
) -> MissionItem:
    values = [*params, lat, lon, z]
    if any(not math.isfinite(v) for v in values[4:]) or any(math.isnan(v) for v in params):
        raise MissionFileError(f"{where}: a position is not a finite number")
    if frame in GLOBAL_FRAMES and not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        raise MissionFileError(f"{where}: latitude/longitude {lat}, {lon} out of range")
    x, y = (round(lat * 1e7), round(lon * 1e7)) if frame in GLOBAL_FRAMES else (0, 0)
    p1, p2, p3, p4 = params
    return MissionItem(seq, frame, command, 0, autocontinue, p1, p2, p3, p4, x, y, float(z))


def _home(lat: float = 0.0, lon: float = 0.0, z: float = 0.0) -> MissionItem:
    return MissionItem(
        0,
        mavlink.MAV_FRAME_GLOBAL,
        mavlink.MAV_CMD_NAV_WAYPOINT,
        0,
        1,
        0.0,
        0.0,
        0.0,
        0.0,
        round(lat * 1e7),
        round(lon * 1e7),
        z,
    )


def _read_wpl(path: Path, lines: list[str]) -> list[MissionItem]:
    items: list[MissionItem] = []
    for n, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        where = f"{path}, line {n}"
        cols = line.split()
        if len(cols) != 12:
            raise MissionFileError(f"{where}: expected 12 columns, found {len(cols)}")
        try:
            seq, _current, frame, command = (int(c) for c in cols[:4])
            p1, p2, p3, p4, lat, lon, z = (float(c) for c in cols[4:11])
            autocontinue = int(float(cols[11]))
        except ValueError:
            raise MissionFileError(f"{where}: not a number where one is expected") from None
        if seq != len(items):
            raise MissionFileError(f"{where}: item {seq} where item {len(items)} was expected")
        items.append(_item(where, seq, frame, command, (p1, p2, p3, p4), lat, lon, z, autocontinue))
    return items


def _read_plan(path: Path, text: str) -> tuple[list[MissionItem], MissionItem]:
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise MissionFileError(f"{path}: not JSON ({exc.msg}, line {exc.lineno})") from None
    if not isinstance(doc, dict) or doc.get("fileType") != "Plan":
        raise MissionFileError(f'{path}: not a QGroundControl plan (no "fileType": "Plan")')
    mission = doc.get("mission")
    if not isinstance(mission, dict) or not isinstance(mission.get("items"), list):
        raise MissionFileError(f"{path}: no mission.items list")
    home_pos = mission.get("plannedHomePosition") or [0.0, 0.0, 0.0]
    try:
        home = _home(*(float(v) for v in home_pos[:3]))
    except (TypeError, ValueError):
        raise MissionFileError(f"{path}: plannedHomePosition is not [lat, lon, alt]") from None
    items: list[MissionItem] = []
    for k, raw in enumerate(mission["items"]):
        where = f"{path}, mission item {k}"
        if not isinstance(raw, dict):
            raise MissionFileError(f"{where}: not an object")
        if raw.get("type") != "SimpleItem":
            raise MissionFileError(
                f"{where}: {raw.get('type')!r} items are expanded by QGroundControl only when "
                "it uploads; upload the plan from QGroundControl, or save it as a waypoint file"
            )
        params: Any = raw.get("params")
        try:
            command, frame = int(raw["command"]), int(raw["frame"])
            vals = [math.nan if p is None else float(p) for p in params]
        except (KeyError, TypeError, ValueError):
            raise MissionFileError(f"{where}: needs command, frame and params[7]") from None
        if len(vals) != 7:
            raise MissionFileError(f"{where}: params has {len(vals)} values, not 7")
        p4 = 0.0 if math.isnan(vals[3]) else vals[3]  # QGC writes null for "no yaw"
        auto = int(bool(raw.get("autoContinue", True)))
        p = (vals[0], vals[1], vals[2], p4)
        items.append(_item(where, len(items), frame, command, p, vals[4], vals[5], vals[6], auto))
    return items, home


def load_mission(path: Path, has_home_item: bool) -> list[MissionItem]:
    """The mission items of a `.plan` or waypoint file, seq 0 being home when
    `has_home_item` (ArduPilot) and the first real item otherwise (PX4)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise MissionFileError(f"cannot read mission file {path}: {exc}") from None
    lines = text.splitlines()
    if lines and lines[0].strip() == WPL_HEADER:
        items = _read_wpl(path, lines)
        if not has_home_item:
            items = items[1:]  # the file's item 0 is home
    elif text.lstrip().startswith("{"):
        plan_items, home = _read_plan(path, text)
        items = [home, *plan_items] if has_home_item else plan_items
    else:
        raise MissionFileError(
            f"{path}: neither a QGroundControl plan (JSON) nor a waypoint file "
            f"(first line {WPL_HEADER!r})"
        )
    if len(items) > MAX_ITEMS:
        raise MissionFileError(f"{path}: {len(items)} items, more than {MAX_ITEMS}")
    return [replace(it, seq=seq) for seq, it in enumerate(items)]
