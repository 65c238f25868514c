"""The MAVLink mission protocol, server side (upload and download of MISSION_ITEM_INT).

Upload: MISSION_COUNT -> MISSION_REQUEST_INT(0) -> MISSION_ITEM_INT(0) -> ... -> MISSION_ACK.
A missing item is requested again after `RETRY_S`; after `MAX_RETRIES` the upload is
cancelled (MISSION_ACK MAV_MISSION_OPERATION_CANCELLED). An out-of-order item gets
MAV_MISSION_INVALID_SEQUENCE and the expected one is still awaited.
Download: MISSION_REQUEST_LIST -> MISSION_COUNT; MISSION_REQUEST_INT(i) (or the deprecated
MISSION_REQUEST) -> MISSION_ITEM_INT(i) (or MISSION_ITEM); the client ends with MISSION_ACK.
MISSION_CLEAR_ALL empties a list.

Mission types 0 (mission), 1 (fence) and 2 (rally) are stored; others are refused with
MAV_MISSION_UNSUPPORTED. On ArduPilot mission item 0 is home: the count includes it, a
download returns the current home there, an uploaded item 0 is stored but reported as home.
PX4 has no home item. Times are simulated seconds.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

RETRY_S = 1.5
MAX_RETRIES = 5
MAX_ITEMS = 700
MISSION_TYPES = (
    mavlink.MAV_MISSION_TYPE_MISSION,
    mavlink.MAV_MISSION_TYPE_FENCE,
    mavlink.MAV_MISSION_TYPE_RALLY,
)


@dataclass(frozen=True, slots=True)
class MissionItem:
    """One MISSION_ITEM_INT: x, y are lat/lon in degE7 for global frames, z metres."""

    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float
    mission_type: int = mavlink.MAV_MISSION_TYPE_MISSION

    @classmethod
    def from_message(cls, msg: Any) -> MissionItem:
        x, y = msg.x, msg.y
        if msg.get_type() == "MISSION_ITEM":  # float lat/lon in degrees for global frames
            x, y = round(x * 1e7), round(y * 1e7)
        return cls(
            int(msg.seq),
            int(msg.frame),
            int(msg.command),
            int(msg.current),
            int(msg.autocontinue),
            float(msg.param1),
            float(msg.param2),
            float(msg.param3),
            float(msg.param4),
            int(x),
            int(y),
            float(msg.z),
            int(getattr(msg, "mission_type", 0)),
        )


@dataclass
class _Upload:
    peer: tuple[int, int]
    mission_type: int
    count: int
    items: list[MissionItem]
    last_request_s: float
    retries: int = 0


class MissionServer:
    """Mission storage and the protocol state machine; `send` transmits a message."""

    def __init__(
        self,
        mav: Any,
        send: Callable[[Any], None],
        home_item: Callable[[], MissionItem] | None,
    ) -> None:
        self.mav = mav
        self.send = send
        self.home_item = home_item
        self._lists: dict[int, list[MissionItem]] = {t: [] for t in MISSION_TYPES}
        self._upload: _Upload | None = None

    def items(self, mission_type: int = mavlink.MAV_MISSION_TYPE_MISSION) -> list[MissionItem]:
        """The list as a download would return it (home first on ArduPilot missions)."""
        stored = list(self._lists[mission_type])
        if mission_type == mavlink.MAV_MISSION_TYPE_MISSION and self.home_item is not None:
            home = self.home_item()
            stored = [home, *stored[1:]] if stored else [home]
        return [replace(item, seq=i) for i, item in enumerate(stored)]

    def load(
        self, items: list[MissionItem], mission_type: int = mavlink.MAV_MISSION_TYPE_MISSION
    ) -> None:
        """Store a list as an upload would (e.g. from a mission file at start-up)."""
        if mission_type not in MISSION_TYPES:
            raise ValueError(f"mission type {mission_type} is not stored")
        self._lists[mission_type] = list(items)

    def cancel_transfers(self) -> None:
        self._upload = None

    def handle(self, msg: Any, now_s: float) -> None:
        kind = msg.get_type()
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        mission_type = int(getattr(msg, "mission_type", 0))
        if kind in ("MISSION_COUNT", "MISSION_REQUEST_LIST", "MISSION_CLEAR_ALL") and (
            mission_type not in MISSION_TYPES
        ):
            self._ack(peer, mavlink.MAV_MISSION_UNSUPPORTED, mission_type)
            return
        if kind == "MISSION_COUNT":
            self._start_upload(peer, int(msg.count), mission_type, now_s)
        elif kind in ("MISSION_ITEM_INT", "MISSION_ITEM"):
            self._item(peer, MissionItem.from_message(msg), now_s)
        elif kind == "MISSION_REQUEST_LIST":
            self.send(
                self.mav.mission_count_encode(*peer, len(self.items(mission_type)), mission_type)
            )
        elif kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            self._send_item(peer, int(msg.seq), mission_type, as_int=kind == "MISSION_REQUEST_INT")
        elif kind == "MISSION_CLEAR_ALL":
            types = (
                MISSION_TYPES if mission_type == mavlink.MAV_MISSION_TYPE_ALL else (mission_type,)
            )
            for t in types:
                self._lists[t] = []
            self._ack(peer, mavlink.MAV_MISSION_ACCEPTED, mission_type)

    def tick(self, now_s: float) -> None:
        """Re-request a missing upload item, or give up."""
        up = self._upload
        if up is None or now_s - up.last_request_s < RETRY_S:
            return
        if up.retries >= MAX_RETRIES:
            self._upload = None
            self._ack(up.peer, mavlink.MAV_MISSION_OPERATION_CANCELLED, up.mission_type)
            return
        up.retries += 1
        self._request(up, now_s)

    def _start_upload(
        self, peer: tuple[int, int], count: int, mission_type: int, now_s: float
    ) -> None:
        if count > MAX_ITEMS:
            self._ack(peer, mavlink.MAV_MISSION_NO_SPACE, mission_type)
            return
        if count == 0:
            self._lists[mission_type] = []
            self._upload = None
            self._ack(peer, mavlink.MAV_MISSION_ACCEPTED, mission_type)
            return
        self._upload = _Upload(peer, mission_type, count, [], now_s)
        self._request(self._upload, now_s)

    def _request(self, up: _Upload, now_s: float) -> None:
        up.last_request_s = now_s
        self.send(self.mav.mission_request_int_encode(*up.peer, len(up.items), up.mission_type))

    def _item(self, peer: tuple[int, int], item: MissionItem, now_s: float) -> None:
        up = self._upload
        if up is None or item.mission_type != up.mission_type:
            self._ack(peer, mavlink.MAV_MISSION_DENIED, item.mission_type)
            return
        expected = len(up.items)
        if item.seq == expected - 1:
            return  # a duplicate of the last item: the request for the next one is out
        if item.seq != expected:
            self._ack(peer, mavlink.MAV_MISSION_INVALID_SEQUENCE, up.mission_type)
            return
        up.items.append(item)
        up.retries = 0
        if len(up.items) < up.count:
            self._request(up, now_s)
            return
        self._lists[up.mission_type] = up.items
        self._upload = None
        self._ack(peer, mavlink.MAV_MISSION_ACCEPTED, up.mission_type)

    def _send_item(self, peer: tuple[int, int], seq: int, mission_type: int, as_int: bool) -> None:
        if mission_type not in MISSION_TYPES:
            self._ack(peer, mavlink.MAV_MISSION_UNSUPPORTED, mission_type)
            return
        items = self.items(mission_type)
        if not 0 <= seq < len(items):
            self._ack(peer, mavlink.MAV_MISSION_INVALID_SEQUENCE, mission_type)
            return
        it = items[seq]
        params = (it.param1, it.param2, it.param3, it.param4)
        if as_int:
            self.send(
                self.mav.mission_item_int_encode(
                    *peer,
                    seq,
                    it.frame,
                    it.command,
                    it.current,
                    it.autocontinue,
                    *params,
                    it.x,
                    it.y,
                    it.z,
                    mission_type,
                )
            )
        else:
            self.send(
                self.mav.mission_item_encode(
                    *peer,
                    seq,
                    it.frame,
                    it.command,
                    it.current,
                    it.autocontinue,
                    *params,
                    it.x * 1e-7,
                    it.y * 1e-7,
                    it.z,
                    mission_type,
                )
            )

    def _ack(self, peer: tuple[int, int], result: int, mission_type: int) -> None:
        self.send(self.mav.mission_ack_encode(*peer, result, mission_type))
