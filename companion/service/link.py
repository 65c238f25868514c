"""Byte transports under the MAVLink codec: UDP in/out, TCP, serial, and an in-memory pair.

A `Link` moves raw bytes and knows nothing about MAVLink. It calls its receiver in the event
loop with every chunk as it arrives (a UDP datagram, or whatever a stream read returned), and
`send` never blocks and never raises for I/O trouble: a failed or refused send is dropped and
counted in `stats`, because a control loop must not stall on a socket. Memory stays bounded:
oversized datagrams and sends beyond the write-buffer limit are dropped and counted.

Connection strings follow pymavlink's forms:

    udpin:HOST:PORT     listen (also `udp:`); replies go to the autopilot's address
    udpout:HOST:PORT    send to HOST:PORT, receive its replies
    tcp:HOST:PORT       connect (reconnects with back-off)
    serial:DEVICE:BAUD  or DEVICE:BAUD or DEVICE,BAUD (DEVICE starting with /dev/)

Serial needs no pyserial: the device is opened non-blocking, set raw with termios and watched
with the event loop's `add_reader`/`add_writer`.
"""

from __future__ import annotations

import abc
import asyncio
import contextlib
import dataclasses
import logging
import os
import socket
import termios
import tty
from collections.abc import Callable
from dataclasses import dataclass

from companion.connection import LinkSpec, parse_connection

log = logging.getLogger(__name__)

Peer = tuple[str, int] | None
Receiver = Callable[[bytes, Peer], None]
"""Called with (chunk, peer address or None) for every chunk received."""

MAX_DATAGRAM_BYTES = 16 * 1024
"""A MAVLink frame is at most 280 bytes; larger datagrams are dropped and counted."""
MAX_WRITE_BUFFER_BYTES = 64 * 1024
"""Sends are dropped (and counted) while this much is already waiting in the kernel/transport."""
READ_CHUNK_BYTES = 4096


@dataclass(slots=True)
class LinkStats:
    chunks_in: int = 0
    bytes_in: int = 0
    chunks_out: int = 0
    bytes_out: int = 0
    send_dropped: int = 0
    """Sends dropped: link down or write buffer full."""
    send_no_peer: int = 0
    """Sends before anyone has spoken to a listening link (normal until the autopilot's
    first packet: not a problem, the service says it is waiting)."""
    oversized_dropped: int = 0
    errors: int = 0
    """Transport errors reported by the OS (ICMP unreachable, EIO, ...)."""
    reconnects: int = 0
    kernel_dropped: int = 0
    """UDP datagrams the kernel dropped because the socket's receive buffer was full (the
    service reads too slowly), from /proc/net/udp on Linux; updated by `refresh()`."""

    def as_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)


class Link(abc.ABC):
    """A bidirectional byte transport. `datagram` links deliver self-contained chunks."""

    datagram: bool = False

    def __init__(self, name: str) -> None:
        self.name = name
        self.stats = LinkStats()
        self._receiver: Receiver | None = None

    @abc.abstractmethod
    async def open(self, receiver: Receiver) -> None:
        """Start receiving; `receiver` is called in the event loop for every chunk."""

    @abc.abstractmethod
    def send(self, data: bytes) -> None:
        """Queue `data` for sending. Never blocks, never raises for I/O errors."""

    @abc.abstractmethod
    async def close(self) -> None:
        """Stop receiving and release the transport. Safe to call twice."""

    def pin_peer(self, peer: Peer) -> None:  # noqa: B027 - optional hook, no-op by default
        """Tell a listening link where the autopilot is (replies go only there)."""

    def refresh_stats(self) -> LinkStats:
        """Update the statistics the OS keeps (kernel drops); returns `stats`."""
        return self.stats

    def _deliver(self, data: bytes, peer: Peer) -> None:
        self.stats.chunks_in += 1
        self.stats.bytes_in += len(data)
        if self._receiver is not None:
            self._receiver(data, peer)


def open_link(spec: LinkSpec | str) -> Link:
    """The Link for a connection string or spec (not yet opened)."""
    if isinstance(spec, str):
        spec = parse_connection(spec)
    if spec.kind == "udpin":
        return UdpInLink(spec.host, spec.port)
    if spec.kind == "udpout":
        return UdpOutLink(spec.host, spec.port)
    if spec.kind == "tcp":
        return TcpLink(spec.host, spec.port)
    return SerialLink(spec.device, spec.baud)


# --- UDP -----------------------------------------------------------------------------------


MAX_DATAGRAMS_PER_WAKE = 64
"""Datagrams read per readiness event at most (then other tasks run, and the loop comes
back): a burst of telemetry costs one event-loop wake-up, not one per datagram."""


def udp_kernel_drops(fd: int) -> int | None:
    """Datagrams the kernel dropped on this UDP socket (Linux /proc/net/udp*), else None."""
    try:
        inode = str(os.fstat(fd).st_ino)
    except OSError:
        return None
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            with open(table) as f:
                for line in f:
                    cols = line.split()
                    if len(cols) > 12 and cols[9] == inode:
                        return int(cols[12])
        except (OSError, ValueError):
            continue
    return None


class _UdpLink(Link):
    """A non-blocking UDP socket watched with the loop's `add_reader`: on each readiness
    event every datagram already queued is read (up to MAX_DATAGRAMS_PER_WAKE), so a burst
    of telemetry is one wake-up of the event loop. Sends go straight to the socket; one the
    kernel cannot take at once (buffer full) is dropped and counted."""

    datagram = True

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self._sock: socket.socket | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._connected_peer: tuple[str, int] | None = None
        """The one peer of a connected socket (it receives from nobody else)."""

    async def _open_socket(
        self, receiver: Receiver, host: str, port: int, *, connect: bool
    ) -> None:
        """Resolve host:port, bind (listen) or connect (send to it), start reading."""
        loop = asyncio.get_running_loop()
        infos = await loop.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        if not infos:
            raise OSError(f"cannot resolve {host}")
        family, kind, proto, _, addr = infos[0]
        sock = socket.socket(family, kind, proto)
        try:
            sock.setblocking(False)
            if connect:
                sock.connect(addr)
                peer = sock.getpeername()
                self._connected_peer = (str(peer[0]), int(peer[1]))
            else:
                sock.bind(addr)
        except OSError:
            sock.close()
            raise
        self._receiver, self._sock, self._loop = receiver, sock, loop
        loop.add_reader(sock.fileno(), self._readable)

    def _readable(self) -> None:
        sock = self._sock
        if sock is None:
            return
        connected = self._connected_peer
        for _ in range(MAX_DATAGRAMS_PER_WAKE):
            try:
                if connected is not None:
                    # no source address to build per datagram: a connected socket's is known
                    data, peer = sock.recv(MAX_DATAGRAM_BYTES + 1), connected
                else:
                    data, addr = sock.recvfrom(MAX_DATAGRAM_BYTES + 1)
                    peer = (addr[0], addr[1])
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # ICMP port unreachable from a connected peer, ...
                self.stats.errors += 1
                log.debug("%s: %s", self.name, exc)
                continue
            self._on_datagram(data, peer)
            if self._sock is None:  # closed by what the datagram caused
                return

    def _on_datagram(self, data: bytes, peer: tuple[str, int]) -> None:
        if len(data) > MAX_DATAGRAM_BYTES:
            self.stats.oversized_dropped += 1
            return
        self._deliver(data, peer)

    def _sendto(self, data: bytes, addr: tuple[str, int] | None) -> None:
        sock = self._sock
        if sock is None:
            self.stats.send_dropped += 1
            return
        try:
            if addr is None:
                sock.send(data)
            else:
                sock.sendto(data, addr)
        except (BlockingIOError, InterruptedError):  # the kernel's buffer is full
            self.stats.send_dropped += 1
            return
        except OSError as exc:  # e.g. network unreachable: count, never stop the loop
            self.stats.errors += 1
            log.debug("%s: send failed: %s", self.name, exc)
            return
        self.stats.chunks_out += 1
        self.stats.bytes_out += len(data)

    def refresh_stats(self) -> LinkStats:
        if self._sock is not None:
            drops = udp_kernel_drops(self._sock.fileno())
            if drops is not None:
                self.stats.kernel_dropped = drops
        return self.stats

    @property
    def is_open(self) -> bool:
        """True between `open` and `close`."""
        return self._sock is not None

    @property
    def local_address(self) -> tuple[str, int]:
        """The bound (host, port); useful with port 0."""
        assert self._sock is not None, "link not open"
        host, port = self._sock.getsockname()[:2]
        return str(host), int(port)

    async def close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            if self._loop is not None and not self._loop.is_closed():
                self._loop.remove_reader(sock.fileno())
            sock.close()


class UdpInLink(_UdpLink):
    """Listen on HOST:PORT. Replies go to the pinned autopilot address, else the last sender."""

    def __init__(self, host: str, port: int) -> None:
        super().__init__(f"udpin:{host}:{port}")
        self.host, self.port = host, port
        self._last_peer: Peer = None
        self._pinned: Peer = None

    async def open(self, receiver: Receiver) -> None:
        await self._open_socket(receiver, self.host, self.port, connect=False)

    def _on_datagram(self, data: bytes, peer: tuple[str, int]) -> None:
        if self._pinned is None:
            self._last_peer = peer
        super()._on_datagram(data, peer)

    def pin_peer(self, peer: Peer) -> None:
        if peer is not None and peer != self._pinned:
            log.info("%s: autopilot at %s:%d", self.name, peer[0], peer[1])
            self._pinned = peer

    @property
    def peer(self) -> Peer:
        return self._pinned or self._last_peer

    def send(self, data: bytes) -> None:
        peer = self.peer
        if peer is None:
            self.stats.send_no_peer += 1
            return
        self._sendto(data, peer)


class UdpOutLink(_UdpLink):
    """Send to HOST:PORT from an ephemeral port and receive its replies."""

    def __init__(self, host: str, port: int) -> None:
        super().__init__(f"udpout:{host}:{port}")
        self.host, self.port = host, port

    async def open(self, receiver: Receiver) -> None:
        await self._open_socket(receiver, self.host, self.port, connect=True)

    def send(self, data: bytes) -> None:
        self._sendto(data, None)


# --- TCP -----------------------------------------------------------------------------------


class TcpLink(Link):
    """Connect to HOST:PORT; reconnect with back-off (0.5 s doubling to 5 s) when it drops."""

    def __init__(self, host: str, port: int) -> None:
        super().__init__(f"tcp:{host}:{port}")
        self.host, self.port = host, port
        self._writer: asyncio.StreamWriter | None = None
        self._task: asyncio.Task[None] | None = None
        self.connected = asyncio.Event()

    async def open(self, receiver: Receiver) -> None:
        self._receiver = receiver
        self._task = asyncio.create_task(self._run(), name=self.name)

    async def _run(self) -> None:
        backoff = 0.5
        while True:
            try:
                reader, writer = await asyncio.open_connection(self.host, self.port)
            except OSError as exc:
                self.stats.errors += 1
                log.warning("%s: connect failed: %s; retrying in %.1f s", self.name, exc, backoff)
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2.0, 5.0)
                continue
            backoff = 0.5
            self._writer = writer
            self.connected.set()
            log.info("%s: connected", self.name)
            try:
                while data := await reader.read(READ_CHUNK_BYTES):
                    self._deliver(data, None)
            except OSError as exc:
                self.stats.errors += 1
                log.warning("%s: %s", self.name, exc)
            finally:
                self.connected.clear()
                self._writer = None
                writer.close()
            self.stats.reconnects += 1
            log.warning("%s: connection closed; reconnecting", self.name)

    def send(self, data: bytes) -> None:
        w = self._writer
        if (
            w is None
            or w.is_closing()
            or w.transport.get_write_buffer_size() > (MAX_WRITE_BUFFER_BYTES)
        ):
            self.stats.send_dropped += 1
            return
        w.write(data)
        self.stats.chunks_out += 1
        self.stats.bytes_out += len(data)

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        if self._writer is not None:
            self._writer.close()
            self._writer = None


# --- serial --------------------------------------------------------------------------------


def configure_serial_fd(fd: int, baud: int) -> None:
    """Raw 8N1, no flow control, at `baud`, on an open tty file descriptor."""
    speed = getattr(termios, f"B{baud}", None)
    if speed is None:
        raise ValueError(f"unsupported baud rate {baud}")
    tty.setraw(fd)
    attrs = termios.tcgetattr(fd)
    attrs[2] |= termios.CLOCAL | termios.CREAD  # cflag: ignore modem lines, enable receiver
    attrs[2] &= ~getattr(termios, "CRTSCTS", 0)
    attrs[4] = attrs[5] = speed
    termios.tcsetattr(fd, termios.TCSANOW, attrs)


class SerialLink(Link):
    """A serial device (or pty) on the event loop; reopens it when it goes away (USB unplug)."""

    def __init__(self, device: str, baud: int) -> None:
        super().__init__(f"serial:{device}:{baud}")
        self.device, self.baud = device, baud
        self._fd: int | None = None
        self._out = bytearray()
        self._reopen: asyncio.Task[None] | None = None
        self._closed = False

    async def open(self, receiver: Receiver) -> None:
        self._receiver = receiver
        self._closed = False
        self._open_fd()

    def _open_fd(self) -> None:
        fd = os.open(self.device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            configure_serial_fd(fd, self.baud)
        except (termios.error, ValueError):
            os.close(fd)
            raise
        self._fd = fd
        asyncio.get_running_loop().add_reader(fd, self._on_readable)

    def _on_readable(self) -> None:
        assert self._fd is not None
        try:
            data = os.read(self._fd, READ_CHUNK_BYTES)
        except BlockingIOError:
            return
        except OSError as exc:
            self._fail(exc)
            return
        if data:
            self._deliver(data, None)

    def _fail(self, exc: OSError) -> None:
        self.stats.errors += 1
        log.warning("%s: %s; reopening", self.name, exc)
        self._drop_fd()
        if not self._closed and self._reopen is None:
            self._reopen = asyncio.get_running_loop().create_task(self._reopen_loop())

    async def _reopen_loop(self) -> None:
        try:
            while not self._closed and self._fd is None:
                await asyncio.sleep(1.0)
                try:
                    self._open_fd()
                    self.stats.reconnects += 1
                except OSError as exc:
                    log.debug("%s: reopen failed: %s", self.name, exc)
        finally:
            self._reopen = None

    def _drop_fd(self) -> None:
        if self._fd is None:
            return
        loop = asyncio.get_running_loop()
        loop.remove_reader(self._fd)
        loop.remove_writer(self._fd)
        with contextlib.suppress(OSError):
            os.close(self._fd)
        self._fd = None
        self._out.clear()

    def send(self, data: bytes) -> None:
        if self._fd is None or len(self._out) + len(data) > MAX_WRITE_BUFFER_BYTES:
            self.stats.send_dropped += 1
            return
        self.stats.chunks_out += 1
        self.stats.bytes_out += len(data)
        if self._out:
            self._out += data
            return
        try:
            n = os.write(self._fd, data)
        except BlockingIOError:
            n = 0
        except OSError as exc:
            self._fail(exc)
            return
        if n < len(data):
            self._out += data[n:]
            asyncio.get_running_loop().add_writer(self._fd, self._on_writable)

    def _on_writable(self) -> None:
        assert self._fd is not None
        try:
            n = os.write(self._fd, self._out)
        except BlockingIOError:
            return
        except OSError as exc:
            self._fail(exc)
            return
        del self._out[:n]
        if not self._out:
            asyncio.get_running_loop().remove_writer(self._fd)

    async def close(self) -> None:
        self._closed = True
        if self._reopen is not None:
            self._reopen.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._reopen
        self._drop_fd()


# --- in memory -----------------------------------------------------------------------------


class MemoryLink(Link):
    """One end of an in-memory pair (see `memory_pair`); can record what it sent.

    Delivery is scheduled with `call_soon`, as a socket would, so a reply never re-enters the
    sender's stack. `inject` delivers raw bytes to this end as if received; `up = False`
    simulates a cut link (sends in both directions are dropped).
    """

    def __init__(self, name: str = "memory", datagram: bool = True, record: bool = False) -> None:
        super().__init__(name)
        self.datagram = datagram
        self.record = record
        self.sent: list[bytes] = []
        self.up = True
        self.other: MemoryLink | None = None

    async def open(self, receiver: Receiver) -> None:
        self._receiver = receiver

    def send(self, data: bytes) -> None:
        if self.record:
            self.sent.append(bytes(data))
        other = self.other
        if not self.up or other is None or not other.up or other._receiver is None:
            self.stats.send_dropped += 1
            return
        self.stats.chunks_out += 1
        self.stats.bytes_out += len(data)
        asyncio.get_running_loop().call_soon(other._deliver, bytes(data), None)

    def inject(self, data: bytes) -> None:
        """Deliver `data` to this end's receiver now."""
        self._deliver(bytes(data), None)

    async def close(self) -> None:
        self._receiver = None


def memory_pair(datagram: bool = True) -> tuple[MemoryLink, MemoryLink]:
    """Two connected in-memory links: what one sends, the other receives."""
    a = MemoryLink("memory-a", datagram)
    b = MemoryLink("memory-b", datagram)
    a.other, b.other = b, a
    return a, b


__all__ = [
    "MAX_DATAGRAM_BYTES",
    "Link",
    "LinkSpec",
    "LinkStats",
    "MemoryLink",
    "SerialLink",
    "TcpLink",
    "UdpInLink",
    "UdpOutLink",
    "memory_pair",
    "open_link",
    "parse_connection",
]
