"""One MAVLink conversation with one autopilot: a Link, the codec and message routing.

Bytes from the link are decoded at once, in the event loop's callback, and every message is
stamped with the service clock at that moment (its receipt time). Until the autopilot is
known, HEARTBEATs are offered to `on_unlocked` so the service can pick it; after `lock()`,
only messages from the autopilot's (system id, component id) are passed on, everything else
is dropped and counted (TIMESYNC requests are answered before the lock too: a lockstep
simulator waits for them before it sends its first heartbeat). Waiters registered with
`expect` (command acks, mission items) see each accepted message before the general handler.
Requests to our own component (`on_request`: the parameter protocol) come from anyone, a
ground station most often, and are offered before that filtering.
"""

from __future__ import annotations

import asyncio
import logging
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

from companion.service.codec import MavCodec, MAVLinkMessage
from companion.service.link import Link, Peer
from companion.service.telemetry import LOG_AT_COUNTS

log = logging.getLogger(__name__)


def waiting_hint(link_name: str) -> str:
    """What a service that hears no autopilot on link_name is waiting for: a link both ends
    expect the other to open first is the usual first-run puzzle."""
    if link_name.startswith("udpin:"):
        return "listening; the autopilot must send here first"
    return "sending heartbeats; no reply yet"


"""Wall seconds without a heartbeat from any autopilot before saying, once, what we wait for."""

Handler = Callable[[MAVLinkMessage, float], None]
Predicate = Callable[[MAVLinkMessage], bool]


@dataclass(eq=False, slots=True)
class _Waiter:
    types: frozenset[str]
    predicate: Predicate
    future: asyncio.Future[MAVLinkMessage]


class Connection:
    """Link + codec + filtering by source + waiters. `clock()` stamps receipts."""

    def __init__(self, link: Link, codec: MavCodec, clock: Callable[[], float]) -> None:
        self.link = link
        self.codec = codec
        self.clock = clock
        self.target_system: int | None = None
        self.target_component: int | None = None
        self.on_message: Handler | None = None
        self.on_unlocked: Handler | None = None
        self.on_other: Handler | None = None
        """HEARTBEATs of other systems after the lock (to notice a second autopilot)."""
        self.on_request: Callable[[MAVLinkMessage], bool] | None = None
        """Offered every message first, from any source (a ground station's PARAM_* requests
        to our component); True when it took the message."""
        self.counters: Counter[str] = Counter()
        self._waiters: list[_Waiter] = []
        self._peer: Peer = None

    async def open(self) -> None:
        await self.link.open(self._on_bytes)

    async def close(self) -> None:
        for w in self._waiters:
            if not w.future.done():
                w.future.cancel()
        self._waiters.clear()
        await self.link.close()

    def lock(self, system_id: int, component_id: int) -> None:
        """From now on accept only this autopilot's messages."""
        self.target_system, self.target_component = system_id, component_id

    # -- receive ----------------------------------------------------------------------------

    def _on_bytes(self, data: bytes, peer: Peer) -> None:
        t_rx = self.clock()
        for msg in self.codec.decode(data, self.link.datagram):
            try:
                self._route(msg, t_rx, peer)
            except Exception:  # a handler bug must not kill the receive path
                self.counters["handler_errors"] += 1
                log.exception("error handling %s", msg.get_type())

    def _route(self, msg: MAVLinkMessage, t_rx: float, peer: Peer) -> None:
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        if self.on_request is not None and self.on_request(msg):
            return
        if self.target_system is None:
            mtype = msg.get_type()
            if mtype == "HEARTBEAT" and self.on_unlocked is not None:
                self.on_unlocked(msg, t_rx)
            elif mtype == "TIMESYNC" and self.on_message is not None:
                # answered before an autopilot is known: a lockstep simulator waits for it
                self.on_message(msg, t_rx)
                return
            if self.target_system is None:
                self.counters["before_lock"] += 1
                return
        if src_sys != self.target_system:
            self._ignored("other_system", msg)
            if self.on_other is not None and msg.get_type() == "HEARTBEAT":
                self.on_other(msg, t_rx)
            return
        if src_comp != self.target_component:
            self._ignored("other_component", msg)
            return
        if peer is not None and peer != self._peer and msg.get_type() == "HEARTBEAT":
            # Only the autopilot's own heartbeat says where it is: other messages in its name
            # may come from elsewhere (sensors sent to the companion directly).
            self._peer = peer
            self.link.pin_peer(peer)
        self.counters["accepted"] += 1
        if self._waiters:
            mtype = msg.get_type()
            for w in list(self._waiters):
                if mtype in w.types and not w.future.done() and w.predicate(msg):
                    w.future.set_result(msg)
                    self._waiters.remove(w)
        if self.on_message is not None:
            self.on_message(msg, t_rx)

    def _ignored(self, name: str, msg: MAVLinkMessage) -> None:
        n = self.counters[name] + 1
        self.counters[name] = n
        if n in LOG_AT_COUNTS:
            # once as a warning; a steady stream (a router echoing a sensor bridge's own
            # messages back) is then only counted, at debug
            log.log(
                logging.WARNING if n == 1 else logging.DEBUG,
                "conn.%s: %d so far (ignored %s from %d/%d; the autopilot is %s/%s)",
                name,
                n,
                msg.get_type(),
                msg.get_srcSystem(),
                msg.get_srcComponent(),
                self.target_system,
                self.target_component,
            )

    # -- send / wait ------------------------------------------------------------------------

    def send(self, msg: MAVLinkMessage) -> None:
        self.link.send(self.codec.encode(msg))

    def expect(
        self, types: str | frozenset[str], predicate: Predicate = lambda m: True
    ) -> asyncio.Future[MAVLinkMessage]:
        """A future for the next accepted message of `types` matching `predicate`.

        Register before sending the request (a reply can arrive before `await`); call
        `forget` when giving up.
        """
        tset = frozenset([types]) if isinstance(types, str) else types
        fut: asyncio.Future[MAVLinkMessage] = asyncio.get_running_loop().create_future()
        self._waiters.append(_Waiter(tset, predicate, fut))
        return fut

    def forget(self, fut: asyncio.Future[MAVLinkMessage]) -> None:
        self._waiters = [w for w in self._waiters if w.future is not fut]
        if not fut.done():
            fut.cancel()
