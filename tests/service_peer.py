"""A scripted MAVLink peer over an in-memory link, for tests of one service module at a time
(commands, connection, mission) without the whole service."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

from companion.service.codec import MavCodec
from companion.service.connection import Connection
from companion.service.link import MemoryLink, memory_pair

Reply = Callable[[Any], list[Any]]


class Peer:
    """The autopilot's end: decodes what the companion sends, records it, and answers with
    `reply(msg)` (a list of messages, sent from system/component sysid/compid)."""

    def __init__(self, link: MemoryLink, sysid: int = 1, compid: int = 1) -> None:
        self.link = link
        self.codec = MavCodec(sysid, compid)
        self.received: list[Any] = []
        self.reply: Reply = lambda msg: []

    async def open(self) -> None:
        await self.link.open(self._on_bytes)

    def _on_bytes(self, data: bytes, peer: object) -> None:
        for msg in self.codec.decode(data, True):
            self.received.append(msg)
            for answer in self.reply(msg):
                self.send(answer)

    def send(self, msg: Any) -> None:
        self.link.send(self.codec.encode(msg))

    def of_type(self, mtype: str) -> list[Any]:
        return [m for m in self.received if m.get_type() == mtype]


async def connected(
    lock: bool = True, clock: Callable[[], float] = lambda: 0.0
) -> tuple[Connection, Peer]:
    """A companion Connection (system 1, component 191) and an autopilot Peer (1/1), open;
    locked onto the peer unless lock=False."""
    a, b = memory_pair()
    conn = Connection(a, MavCodec(1, 191), clock)
    peer = Peer(b)
    await conn.open()
    await peer.open()
    if lock:
        conn.lock(1, 1)
    return conn, peer


async def settle() -> None:
    """Let in-memory deliveries (scheduled with call_soon) run."""
    for _ in range(5):
        await asyncio.sleep(0)
