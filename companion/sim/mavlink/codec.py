"""pymavlink's generated MAVLink object used purely as a codec (no mavutil, no polling).

`Codec.encode` packs a message built with the dialect's `*_encode` helpers into MAVLink 2
bytes (advancing the sequence number); `Codec.frame` packs a payload already laid out by the
message's own struct into the same bytes, without building the message object (the
simulator's DISTANCE_SENSOR bursts); `Codec.decode` turns received bytes into messages,
dropping what does not parse (counted in `bad_data`).
"""

from __future__ import annotations

import struct
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

_HEADER = struct.Struct("<BBBBBBBHB")
_CRC = struct.Struct("<H")
_MCRF4XX = getattr(mavlink, "mcrf4xx", None)
"""pymavlink's compiled X.25 checksum (fastcrc's CRC-16/MCRF4XX) where it has one."""


def _crc(data: bytes) -> int:
    """MAVLink's X.25 checksum of data, as pymavlink computes it."""
    if _MCRF4XX is not None:
        return int(_MCRF4XX(data, 0xFFFF))
    return int(mavlink.x25crc(data).crc)


class _Sink:
    """File-like object MAVLink.send writes one packed message into."""

    def __init__(self) -> None:
        self.data = b""

    def write(self, data: bytes) -> None:
        self.data = data


class Codec:
    def __init__(self, system_id: int, component_id: int) -> None:
        self._sink = _Sink()
        self.mav = mavlink.MAVLink(self._sink, srcSystem=system_id, srcComponent=component_id)
        self._rx = mavlink.MAVLink(None)
        self._rx.robust_parsing = True
        self.bad_data = 0

    def encode(self, msg: Any) -> bytes:
        self.mav.send(msg)
        return self._sink.data

    def frame(self, msg_id: int, crc_extra: int, payload: bytes) -> bytes:
        """The MAVLink 2 frame of one message from its packed payload (the message class's
        `unpacker.pack` of its fields), as `encode` would give it: trailing zero bytes cut,
        this codec's ids and sequence number (advanced), the X.25 checksum with crc_extra.
        Not for a signing link (the simulator never signs)."""
        mav = self.mav
        end = len(payload)
        while end > 1 and payload[end - 1] == 0:
            end -= 1
        body = payload[:end]
        header = _HEADER.pack(
            253, end, 0, 0, mav.seq, mav.srcSystem, mav.srcComponent, msg_id & 0xFFFF, msg_id >> 16
        )
        crc = _crc(header[1:] + body + bytes((crc_extra,)))
        data = header + body + _CRC.pack(crc)
        mav.seq = (mav.seq + 1) % 256
        mav.total_packets_sent += 1
        mav.total_bytes_sent += len(data)
        return data

    def decode(self, data: bytes) -> list[Any]:
        messages = self._rx.parse_buffer(data) or []
        good = [m for m in messages if m.get_type() != "BAD_DATA"]
        self.bad_data += len(messages) - len(good)
        return good

    def restart(self) -> None:
        """Sequence numbers start again at 0 (an autopilot reboot)."""
        self.mav.seq = 0
