"""Links and the codec: connection strings, serial over a pty, in-memory pairs, parsing."""

from __future__ import annotations

import asyncio
import os
import tty

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.service.codec import MavCodec, mavlink2
from companion.service.link import (
    LinkSpec,
    SerialLink,
    UdpInLink,
    UdpOutLink,
    memory_pair,
    open_link,
    parse_connection,
)

pytestmark = pytest.mark.timeout(20)


@pytest.mark.parametrize(
    ("text", "spec"),
    [
        ("udpin:0.0.0.0:14550", LinkSpec("udpin", host="0.0.0.0", port=14550)),
        ("udp:127.0.0.1:14540", LinkSpec("udpin", host="127.0.0.1", port=14540)),
        ("udpout:192.168.1.5:14580", LinkSpec("udpout", host="192.168.1.5", port=14580)),
        ("tcp:localhost:5760", LinkSpec("tcp", host="localhost", port=5760)),
        ("/dev/ttyAMA0:921600", LinkSpec("serial", device="/dev/ttyAMA0", baud=921600)),
        ("/dev/ttyUSB0,57600", LinkSpec("serial", device="/dev/ttyUSB0", baud=57600)),
        ("serial:/dev/ttyACM0:57600", LinkSpec("serial", device="/dev/ttyACM0", baud=57600)),
    ],
)
def test_parse_connection(text: str, spec: LinkSpec) -> None:
    assert parse_connection(text) == spec
    assert parse_connection(str(spec)) == spec


@pytest.mark.parametrize(
    "text",
    ["", "udpin:14550", "udpout:host:0", "tcp:host:x", "udpin:h:70000", "/dev/ttyS0:12345", "x"],
)
def test_parse_connection_rejects(text: str) -> None:
    with pytest.raises(ValueError):
        parse_connection(text)


def test_open_link_kinds() -> None:
    assert isinstance(open_link("udpin:127.0.0.1:0"), UdpInLink)
    assert isinstance(open_link("udpout:127.0.0.1:9"), UdpOutLink)
    assert isinstance(open_link("/dev/null:57600"), SerialLink)


async def test_memory_pair_delivers_and_cut_drops() -> None:
    a, b = memory_pair()
    got: list[bytes] = []
    await a.open(lambda d, p: None)
    await b.open(lambda d, p: got.append(d))
    a.send(b"hello")
    await asyncio.sleep(0)
    assert got == [b"hello"]
    b.up = False
    a.send(b"lost")
    await asyncio.sleep(0)
    assert got == [b"hello"] and a.stats.send_dropped == 1


async def test_udp_in_replies_to_last_sender_until_pinned() -> None:
    server = UdpInLink("127.0.0.1", 0)
    got: list[bytes] = []
    await server.open(lambda d, p: got.append(d))
    server.send(b"nobody yet")
    assert server.stats.send_no_peer == 1 and server.stats.send_dropped == 0
    host, port = server.local_address
    client = UdpOutLink(host, port)
    back: list[bytes] = []
    await client.open(lambda d, p: back.append(d))
    client.send(b"ping")
    for _ in range(100):
        if got:
            break
        await asyncio.sleep(0.01)
    server.send(b"pong")
    for _ in range(100):
        if back:
            break
        await asyncio.sleep(0.01)
    assert got == [b"ping"] and back == [b"pong"]
    await client.close()
    await server.close()


async def test_serial_link_over_a_pty_round_trip() -> None:
    master, slave = os.openpty()
    tty.setraw(master)
    name = os.ttyname(slave)
    link = SerialLink(name, 57600)
    got: list[bytes] = []
    await link.open(lambda d, p: got.append(d))
    codec = MavCodec(1, 1)
    frame = codec.encode(mavlink2.MAVLink_heartbeat_message(2, 3, 0, 0, 3, 3))
    os.write(master, frame)
    for _ in range(200):
        if sum(map(len, got)) >= len(frame):
            break
        await asyncio.sleep(0.005)
    assert b"".join(got) == frame
    link.send(b"\x01\x02\x03")
    await asyncio.sleep(0.02)
    assert os.read(master, 16) == b"\x01\x02\x03"
    await link.close()
    os.close(master)
    os.close(slave)


def _frames() -> list[bytes]:
    c = MavCodec(1, 1)
    return [
        c.encode(mavlink2.MAVLink_heartbeat_message(2, 3, 0, 0, 3, 3)),
        c.encode(mavlink2.MAVLink_attitude_message(1, 0.1, 0.2, 0.3, 0, 0, 0)),
        bytes(mavlink2.MAVLink_heartbeat_message(2, 3, 0, 0, 3, 3).pack(c.mav, True)),  # v1
    ]


def test_codec_decodes_mavlink1_and_2_and_counts_bad_frames() -> None:
    frames = _frames()
    rx = MavCodec(1, 191)
    assert len(rx.decode(b"".join(frames))) == 3
    bad = bytearray(frames[1])
    bad[12] ^= 0x55  # payload byte: CRC fails
    assert rx.decode(bytes(bad)) == [] and rx.counters.bad_crc == 1
    unknown = bytearray(frames[0])
    unknown[7:10] = bytes([0x39, 0x30, 0x00])  # msg id 12345: not in the dialect
    assert rx.decode(bytes(unknown)) == []
    assert rx.counters.bad_crc + rx.counters.unknown_msgid == 2
    assert rx.decode(frames[1][:-3]) == [] and rx.counters.truncated == 1
    assert len(rx.decode(frames[0])) == 1  # the truncated one did not poison the next


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=300), max_size=8), st.booleans())
def test_codec_never_raises_and_recovers(chunks: list[bytes], datagram: bool) -> None:
    rx = MavCodec(1, 191)
    good = _frames()[1]
    for chunk in chunks:
        for m in rx.decode(chunk, datagram):
            assert m.get_type() != "BAD_DATA"
    rx.decode(b"", datagram)
    # after any garbage, a datagram with a good frame decodes (stream: a few frames later)
    got = []
    for _ in range(1 if datagram else 300):
        got += rx.decode(good, datagram)
        if got:
            break
    assert got and got[0].get_type() == "ATTITUDE"


def test_signing_checks_signature_before_recording_the_stream_time() -> None:
    key = bytes(range(32))
    tx, rx = MavCodec(1, 1), MavCodec(1, 191)
    tx.enable_signing(key, timestamp=1000)
    rx.enable_signing(key, timestamp=1)
    forger = MavCodec(1, 1)
    forger.enable_signing(bytes(32), timestamp=10**15)  # wrong key, far-future timestamp
    hb = mavlink2.MAVLink_heartbeat_message(2, 3, 0, 0, 3, 3)
    assert rx.decode(forger.encode(hb)) == [] and rx.counters.bad_signature == 1
    assert len(rx.decode(tx.encode(hb))) == 1  # the real sender is not locked out
    frame = tx.encode(hb)
    assert len(rx.decode(frame)) == 1
    assert rx.decode(frame) == [] and rx.counters.bad_signature == 2  # replay
    assert rx.decode(MavCodec(1, 1).encode(hb)) == [] and rx.counters.unsigned_rejected == 1


@pytest.mark.parametrize(
    ("text", "pymavlink"),
    [
        ("udp://:14540", "udpin:0.0.0.0:14540"),
        ("udp://127.0.0.1:14540", "udpin:127.0.0.1:14540"),
        ("udpin://0.0.0.0:14540", "udpin:0.0.0.0:14540"),
        ("udpout://192.168.1.5:14580", "udpout:192.168.1.5:14580"),
        ("tcp://localhost:5760", "tcp:localhost:5760"),
        ("tcpout://localhost:5760", "tcp:localhost:5760"),
        ("serial:///dev/ttyACM0:57600", "serial:/dev/ttyACM0:57600"),
    ],
)
def test_parse_connection_mavsdk_urls(text: str, pymavlink: str) -> None:
    """MAVSDK's URL forms are read as the pymavlink form the service opens."""
    assert str(parse_connection(text)) == pymavlink
    assert parse_connection(text) == parse_connection(pymavlink)


@pytest.mark.parametrize(
    ("text", "hint"),
    [
        ("tcpin://:5760", "tcp:HOST:PORT"),
        ("serial_flowcontrol:///dev/ttyACM0:57600", "serial:DEVICE:BAUD"),
        ("udpout://:14550", "needs a host"),
        ("http://host:80", "udpin:HOST:PORT"),
    ],
)
def test_parse_connection_refuses_urls_with_the_pymavlink_form(text: str, hint: str) -> None:
    with pytest.raises(ValueError, match=hint):
        parse_connection(text)


async def test_mavsdk_url_opens_like_pymavlink_form() -> None:
    """`run` opens what `check-config` accepts: the URL form binds and receives."""
    import socket

    link = open_link("udp://127.0.0.1:0")
    got: list[bytes] = []
    await link.open(lambda d, p: got.append(d))
    try:
        assert isinstance(link, UdpInLink)
        host, port = link.local_address
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(b"ping", (host, port))
        for _ in range(200):
            if got:
                break
            await asyncio.sleep(0.01)
        assert got == [b"ping"]
    finally:
        await link.close()


def test_waiting_hint_says_which_side_must_speak_first() -> None:
    """The service's "waiting for autopilot heartbeat" line (tests/test_reliability_safety)
    says whether the autopilot must send first or the companion is sending."""
    from companion.service.connection import waiting_hint

    assert "must send here first" in waiting_hint("udpin:127.0.0.1:14540")
    assert "sending heartbeats" in waiting_hint("udpout:127.0.0.1:14550")
