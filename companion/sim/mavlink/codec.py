"""pymavlink's generated MAVLink object used purely as a codec (no mavutil, no polling).

`Codec.encode` packs a message built with the dialect's `*_encode` helpers into MAVLink 2
bytes (advancing the sequence number); `Codec.decode` turns received bytes into messages,
dropping what does not parse (counted in `bad_data`).
"""

from __future__ import annotations

from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink


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

    def decode(self, data: bytes) -> list[Any]:
        messages = self._rx.parse_buffer(data) or []
        good = [m for m in messages if m.get_type() != "BAD_DATA"]
        self.bad_data += len(messages) - len(good)
        return good

    def restart(self) -> None:
        """Sequence numbers start again at 0 (an autopilot reboot)."""
        self.mav.seq = 0
