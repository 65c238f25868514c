"""Generators of bad MAVLink input for the reliability suite, and a service to feed it to.

`frame_strategy()` (hypothesis) builds a real frame of any message of the dialect, with any
field values (NaN, inf, extremes), as MAVLink 2 or MAVLink 1, from the autopilot or from
another system. `mutations(frames, rng, n)` turns a few frames into `n` datagrams: as they
are, truncated, a byte flipped, the CRC broken, the message id made unknown, several frames
and garbage run together, random bytes, empty and oversized datagrams.

`ReceivePath` is a Service whose UDP link is not opened: `feed(datagram)` calls the link's
datagram callback directly (size check, then codec, routing, telemetry: everything a
received datagram goes through), so 10^5 inputs take seconds, not a socket round trip each.
Everything the service sends in reply is recorded.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

from hypothesis import strategies as st

from companion.config import ServiceConfig
from companion.service import Service
from companion.service.codec import CodecCounters, MavCodec, mavlink2
from companion.service.link import MAX_DATAGRAM_BYTES, UdpInLink
from companion.service.notify import SystemdNotifier
from tests.service_fakes import FakePlanner, make_config

AUTOPILOT = (1, 1)
PEER = ("127.0.0.1", 14555)

MESSAGE_CLASSES = sorted(mavlink2.mavlink_map.values(), key=lambda c: c.id)
INTERESTING = [
    mavlink2.MAVLink_heartbeat_message,
    mavlink2.MAVLink_attitude_message,
    mavlink2.MAVLink_global_position_int_message,
    mavlink2.MAVLink_home_position_message,
    mavlink2.MAVLink_distance_sensor_message,
    mavlink2.MAVLink_timesync_message,
    mavlink2.MAVLink_command_ack_message,
    mavlink2.MAVLink_command_long_message,
    mavlink2.MAVLink_mission_count_message,
    mavlink2.MAVLink_mission_item_int_message,
    mavlink2.MAVLink_statustext_message,
    mavlink2.MAVLink_set_position_target_global_int_message,
]
"""What the service reads (and what it would act on if it took commands), drawn more often."""

_INT_RANGES = {
    "uint8_t": (0, 2**8 - 1),
    "int8_t": (-(2**7), 2**7 - 1),
    "uint16_t": (0, 2**16 - 1),
    "int16_t": (-(2**15), 2**15 - 1),
    "uint32_t": (0, 2**32 - 1),
    "int32_t": (-(2**31), 2**31 - 1),
    "uint64_t": (0, 2**64 - 1),
    "int64_t": (-(2**63), 2**63 - 1),
}


def _scalar(ftype: str) -> st.SearchStrategy[Any]:
    if ftype == "float":
        return st.floats(width=32)
    if ftype == "double":
        return st.floats()
    lo, hi = _INT_RANGES[ftype.replace("_mavlink_version", "")]
    edges = st.sampled_from(sorted({lo, hi, 0, min(hi, 1), min(hi, 65535)}))
    return st.one_of(edges, st.integers(lo, hi))


def _field(ftype: str, length: int) -> st.SearchStrategy[Any]:
    if ftype == "char":
        return st.binary(max_size=max(length, 1))
    if length:
        return st.lists(_scalar(ftype), min_size=length, max_size=length)
    return _scalar(ftype)


@st.composite
def message_strategy(draw: Callable[..., Any]) -> Any:
    """Any message of the dialect with any field values."""
    cls = draw(st.one_of(st.sampled_from(INTERESTING), st.sampled_from(MESSAGE_CLASSES)))
    args = [
        draw(_field(ftype, length))
        for ftype, length in zip(cls.fieldtypes, cls.array_lengths, strict=True)
    ]
    return cls(*args)


@st.composite
def frame_strategy(draw: Callable[..., Any]) -> bytes:
    """One packed frame: MAVLink 2 or 1, from the autopilot or another system."""
    msg = draw(message_strategy())
    src = draw(st.one_of(st.just(AUTOPILOT), st.tuples(st.integers(0, 255), st.integers(0, 255))))
    mav = mavlink2.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    mav.seq = draw(st.integers(0, 255))
    v1 = msg.id < 256 and draw(st.booleans())
    try:
        return bytes(msg.pack(mav, force_mavlink1=v1))
    except Exception:  # a value pymavlink cannot pack (e.g. a too long string): raw bytes
        return bytes(draw(st.binary(min_size=1, max_size=64)))


def _crc_broken(frame: bytes) -> bytes:
    b = bytearray(frame)
    if len(b) >= 2:
        b[-1] ^= 0x5A
        b[-2] ^= 0xA5
    return bytes(b)


def _unknown_id(frame: bytes, rng: random.Random) -> bytes:
    b = bytearray(frame)
    if b and b[0] == mavlink2.PROTOCOL_MARKER_V2 and len(b) >= 10:
        unknown = rng.choice([i for i in range(10_000, 16_000_000, 99_991)])
        b[7:10] = unknown.to_bytes(3, "little")
    elif len(b) >= 6:
        b[5] = rng.choice([i for i in range(256) if i not in mavlink2.mavlink_map])
    return bytes(b)


def mutations(frames: list[bytes], rng: random.Random, n: int) -> list[bytes]:
    """`n` datagrams made from `frames` (see the module docstring)."""
    out: list[bytes] = []
    for i in range(n):
        f = frames[i % len(frames)]
        op = rng.randrange(12)
        if op == 0:
            d = f
        elif op == 1 and len(f) > 1:
            d = f[: rng.randrange(1, len(f))]  # truncated
        elif op == 2 and f:
            b = bytearray(f)
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
            d = bytes(b)
        elif op == 3:
            d = _crc_broken(f)
        elif op == 4:
            d = _unknown_id(f, rng)
        elif op == 5:  # several frames, mixed versions, garbage between
            parts = [frames[rng.randrange(len(frames))] for _ in range(rng.randrange(2, 6))]
            d = b"".join(p + rng.randbytes(rng.randrange(3)) for p in parts)
        elif op == 6:
            d = rng.randbytes(rng.randrange(0, 300))
        elif op == 7:  # garbage, then a frame cut in the middle
            d = rng.randbytes(rng.randrange(1, 20)) + f[: max(1, len(f) // 2)]
        elif op == 8:
            d = f + f  # duplicated in one datagram
        elif op == 9:  # a frame start with a length longer than what follows
            d = bytes([rng.choice([0xFD, 0xFE]), 255]) + rng.randbytes(rng.randrange(30))
        elif op == 10:
            d = b"" if rng.random() < 0.5 else bytes([rng.choice([0xFD, 0xFE])])
        else:  # oversized, or just large
            big = rng.random() < 0.1
            size = rng.randrange(MAX_DATAGRAM_BYTES + 1, 4 * MAX_DATAGRAM_BYTES) if big else 2000
            d = (f * (size // max(len(f), 1) + 1))[:size]
        out.append(d)
    return out


CODEC_FIELDS = tuple(f.name for f in fields(CodecCounters))


@dataclass
class Fed:
    inputs: int = 0
    nonempty_uncounted: int = 0


class ReceivePath:
    """A Service locked onto autopilot (1, 1) whose datagrams are fed by hand."""

    def __init__(self, cfg: ServiceConfig | None = None, signing_key: bytes | None = None):
        # locks on its first heartbeat (no listening for other autopilots)
        self.cfg = cfg or make_config(autopilot={"auto_id_listen_s": 0.0})
        self.link = UdpInLink("127.0.0.1", 0)
        self.svc = Service(
            self.cfg,
            self.link,
            planner_factory=lambda *a: FakePlanner(*a),
            notifier=SystemdNotifier({}),
        )
        self.sent: list[bytes] = []
        self.link.send = self.sent.append  # type: ignore[method-assign]
        self.link._receiver = self.svc.conn._on_bytes
        if signing_key is not None:
            self.svc.codec.enable_signing(signing_key, timestamp=1)
        self.autopilot = MavCodec(*AUTOPILOT)
        if signing_key is not None:
            self.autopilot.enable_signing(signing_key, timestamp=10**9)
        self.fed = Fed()
        # lock onto the autopilot with a good heartbeat
        self.feed(self.autopilot.encode(mavlink2.MAVLink_heartbeat_message(2, 3, 1, 5, 4, 3)))
        assert self.svc.status().target_system == AUTOPILOT[0], "did not lock onto the autopilot"

    def problem_total(self) -> int:
        c = self.svc.codec.counters
        return sum(getattr(c, k) for k in CODEC_FIELDS) + self.link.stats.oversized_dropped

    def feed(self, datagram: bytes) -> None:
        before = self.problem_total()
        self.link._on_datagram(datagram, PEER)
        self.fed.inputs += 1
        if datagram and self.problem_total() == before:
            self.fed.nonempty_uncounted += 1

    def sent_types(self) -> set[str]:
        dec = MavCodec(255, 0)
        return {m.get_type() for data in self.sent for m in dec.decode(data)}

    def check_cache(self) -> None:
        """Whatever got in, the input cache holds only finite, in-range values."""
        tel = self.svc.tel
        a = tel.attitude
        if a is not None:
            assert all(math.isfinite(v) for v in (a.roll_rad, a.pitch_rad, a.yaw_rad))
            assert abs(a.roll_rad) <= math.pi + 1e-3 and abs(a.pitch_rad) <= math.pi / 2 + 1e-3
        for p in (tel.position, tel.home):
            if p is not None:
                assert math.isfinite(p.lat_deg) and -90 <= p.lat_deg <= 90
                assert math.isfinite(p.lon_deg) and -180 <= p.lon_deg <= 180
                assert math.isfinite(p.alt_amsl_m) and -1000 <= p.alt_amsl_m <= 50_000
        for spec, r in zip(tel.sensors.specs, tel.ranges, strict=True):
            if r is not None:
                assert math.isfinite(r.distance_m) and 0.0 <= r.distance_m < spec.max_range_m
