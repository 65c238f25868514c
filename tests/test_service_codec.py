"""The codec's short way for a datagram that is one whole MAVLink 2 frame (and its own decoder
for an unsigned one) decodes exactly as pymavlink's parser does: the same messages (fields,
header, buffers), the same verdicts on bad frames, the same counters, with and without
signing, on made-up frames and on traffic captured from ArduCopter SITL."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import companion.service.codec as codec_mod
from companion.service.codec import MavCodec, mavlink2

KEY = bytes(range(32))


def _frames(tx: Any) -> list[bytes]:
    return [
        tx.heartbeat_encode(2, 3, 81, 4, 4, 3).pack(tx),
        tx.attitude_encode(1000, 0.01, -0.02, 1.5, 0.0, 0.0, 0.0).pack(tx),
        tx.global_position_int_encode(1000, 473977420, 85455940, 50000, 2000, 10, 0, 0, 9000).pack(
            tx
        ),
        tx.distance_sensor_encode(
            1000, 10, 1200, 350, 0, 3, 100, 0, 0.0, 0.0, [0.7, 0.0, 0.7, 0.0], 0
        ).pack(tx),
        tx.statustext_encode(4, b"hello").pack(tx),
        tx.timesync_encode(0, 123456789).pack(tx),
        tx.param_value_encode(b"WPNAV_SPEED", 500.0, 9, 1200, 7).pack(tx),  # text, trimmed
        tx.home_position_encode(
            -353632610, 1491652299, 584090, 0.0, 0.0, 0.0, [math.nan] * 4, 0.0, 0.0, 0.0, 7
        ).pack(tx),  # NaN fields, an extension
        tx.command_long_encode(1, 1, 511, 0, 33, 50000, 0, 0, 0, 0, 0).pack(tx),
        tx.distance_sensor_encode(1000, 10, 1200, 0, 0, 0, 0, 0).pack(tx),  # all zeros trimmed
    ]


def _longer(frame: bytes) -> bytes:
    """The unsigned MAVLink 2 `frame` with two more payload bytes than the dialect knows (a
    newer sender's extension fields), its checksum made good again."""
    payload = frame[10:-2] + b"\x01\x02"
    body = bytes([len(payload)]) + frame[2:10] + payload
    crc_extra = mavlink2.mavlink_map[frame[7] | frame[8] << 8 | frame[9] << 16].crc_extra
    crc = mavlink2.x25crc(body + bytes([crc_extra])).crc
    return b"\xfd" + body + bytes([crc & 0xFF, crc >> 8])


def _variants(frame: bytes) -> list[bytes]:
    """The frame, and what a link could bring instead of it."""
    out = [frame]
    out.append(frame[:-1] + bytes([frame[-1] ^ 0xFF]))  # checksum (or signature) wrong
    out.append(frame[:10] + bytes([frame[10] ^ 0x55]) + frame[11:])  # payload changed
    out.append(frame[:7] + b"\xff\xff\xff" + frame[10:])  # unknown message id
    out.append(frame[:2] + bytes([frame[2] | 0x02]) + frame[3:])  # unknown incompat flag
    out.append(frame[:1] + bytes([frame[1] + 1]) + frame[2:])  # length says one more
    out.append(frame[:-3])  # cut short
    out.append(frame + frame)  # two in one datagram
    out.append(b"\x00\x01" + frame)  # garbage first
    return out


def _decode_all(datagrams: list[bytes], short_way: bool, signed: bool) -> tuple[Any, ...]:
    codec = MavCodec(1, 191)
    if signed:
        codec.enable_signing(KEY, timestamp=1000)
    original = codec_mod._frame_end
    if not short_way:
        codec_mod._frame_end = lambda data, start: 0
    try:
        got = [[_whole(m) for m in codec.decode(d)] for d in datagrams]
    finally:
        codec_mod._frame_end = original
    mav = codec.mav
    totals = (mav.total_packets_received, mav.total_bytes_received, mav.total_receive_errors)
    return got, codec.counters, totals, codec.signing_timestamp if signed else None


@pytest.mark.parametrize("signed", [False, True])
def test_one_frame_datagrams_decode_as_the_parser_does(signed: bool) -> None:
    tx = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    if signed:
        tx.signing.secret_key = KEY
        tx.signing.link_id = 0
        tx.signing.timestamp = 5000
        tx.signing.sign_outgoing = True
    frames = _frames(tx)
    if not signed:
        frames.append(_longer(frames[1]))
    v1 = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    v1.WIRE_PROTOCOL_VERSION = "1.0"
    datagrams = [v for f in frames for v in _variants(f)]
    datagrams += [frames[1], frames[1]]  # the same signed frame twice: a replay
    datagrams += [b"", b"\xfd", b"garbage", v1.attitude_encode(5, 0, 0, 0, 0, 0, 0).pack(v1)]
    short = _decode_all(datagrams, short_way=True, signed=signed)
    parser = _decode_all(datagrams, short_way=False, signed=signed)
    assert short == parser
    got, counters, _, _ = short
    # the comparison covers every kind of verdict
    assert sum(len(g) for g in got) >= len(frames)  # signed: the copies are replays
    assert counters.bad_crc > 0 and counters.unknown_msgid > 0 and counters.truncated > 0
    assert counters.bad_frame > 0 and counters.garbage > 0
    if signed:
        assert counters.bad_signature > 0


def test_unsigned_frames_take_the_codec_s_own_decoder() -> None:
    """The comparison above is of the codec's decoder, not pymavlink's again: every good
    unsigned frame is its, everything else pymavlink's."""
    tx = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    frames = [*_frames(tx), _longer(_frames(tx)[1])]
    assert all(codec_mod._decode_unsigned(f) is not None for f in frames)
    longer = codec_mod._decode_unsigned(frames[-1])
    assert longer is not None and longer.get_type() == "ATTITUDE"
    assert longer.roll == pytest.approx(0.01)
    for bad in (
        frames[1][:-1] + bytes([frames[1][-1] ^ 0xFF]),
        frames[1][:7] + b"\xff\xff\xff" + frames[1][10:],
    ):
        assert codec_mod._decode_unsigned(bad) is None


def test_one_v2_frame_reads_the_header_only() -> None:
    tx = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    frame = tx.attitude_encode(1000, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0).pack(tx)
    one = codec_mod._one_v2_frame
    assert one(frame)
    assert not one(frame[:-1]) and not one(frame + b"\x00") and not one(b"\xfe" + frame[1:])
    assert not one(frame[:2] + b"\x02" + frame[3:])  # an incompatibility flag we do not know
    assert not one(frame[:2] + b"\x01" + frame[3:])  # "signed" without the signature
    assert one(frame[:2] + b"\x01" + frame[3:] + bytes(13))


CAPTURE = Path(__file__).parent / "data" / "arducopter_sitl_wired.hex"
"""Datagrams the service received from ArduCopter SITL in the wired-wall flight (sensors fed
to the autopilot, which re-publishes them; its router also forwards the bridge's own frames)."""


def _captured() -> list[bytes]:
    lines = CAPTURE.read_text(encoding="utf-8").splitlines()
    return [bytes.fromhex(line.split()[1]) for line in lines if line and not line.startswith("#")]


def _whole(msg: Any) -> str:
    """Everything a decoded message carries: fields, header, raw buffers, signing state (repr,
    so that NaN fields, as in ArduPilot's HOME_POSITION, compare equal)."""
    state = {k: (v.__dict__ if k == "_header" else v) for k, v in msg.__dict__.items()}
    return repr(sorted(state.items()))


def test_captured_arducopter_traffic_decodes_as_the_parser_does() -> None:
    datagrams = _captured()
    results = []
    for short_way in (True, False):
        codec = MavCodec(1, 191)
        original = codec_mod._frame_end
        if not short_way:
            codec_mod._frame_end = lambda data, start: 0
        try:
            msgs = [m for d in datagrams for m in codec.decode(d)]
        finally:
            codec_mod._frame_end = original
        results.append(([_whole(m) for m in msgs], codec.counters))
    assert results[0] == results[1]
    # the sample is what it says: every datagram one good frame, the autopilot's messages and
    # the bridge's forwarded ones, the inputs of a cycle and the auto start's conversation
    codec = MavCodec(1, 191)
    msgs = [m for d in datagrams for m in codec.decode(d)]
    assert len(msgs) == len(datagrams) >= 300
    assert all(codec_mod._one_v2_frame(d) for d in datagrams)
    kinds = {(m.get_type(), m.get_srcComponent()) for m in msgs}
    for kind in ("HEARTBEAT", "ATTITUDE", "GLOBAL_POSITION_INT", "DISTANCE_SENSOR"):
        assert (kind, 1) in kinds
    assert ("DISTANCE_SENSOR", 158) in kinds
    for kind in ("HOME_POSITION", "COMMAND_ACK", "STATUSTEXT", "TIMESYNC", "PARAM_VALUE"):
        assert any(k == kind for k, _ in kinds)


def test_several_frames_in_one_datagram_decode_as_the_parser_does() -> None:
    """A lockstep simulator sends a period's frames in one datagram: each whole frame takes
    the short way, whatever follows the last whole one the parser's, with the parser's
    messages, verdicts and counters."""
    tx = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    frames = _frames(tx)
    batch = b"".join(frames)
    bad = frames[1][:-1] + bytes([frames[1][-1] ^ 0xFF])
    v1 = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    v1.WIRE_PROTOCOL_VERSION = "1.0"
    datagrams = [
        batch,
        frames[0] + bad + frames[2],  # a bad checksum between good frames
        frames[3] + frames[4][:-3],  # the last one cut short
        batch + b"\x00\x01garbage",  # garbage after them
        frames[5] + frames[6][:2] + b"\x02" + frames[6][3:] + frames[7],  # an unknown flag
        frames[2] + frames[2][:7] + b"\xff\xff\xff" + frames[2][10:],  # an unknown id last
        frames[8] + v1.attitude_encode(5, 0, 0, 0, 0, 0, 0).pack(v1) + frames[9],  # v1 inside
        _longer(frames[1]) + frames[1],
    ]
    short = _decode_all(datagrams, short_way=True, signed=False)
    parser = _decode_all(datagrams, short_way=False, signed=False)
    assert short == parser
    got, counters, _, _ = short
    assert [m for m in got[0]] == [_whole(m) for m in MavCodec(1, 191).decode(batch)]
    assert len(got[0]) == len(frames)
    assert counters.bad_crc and counters.truncated and counters.garbage and counters.bad_frame
    assert counters.unknown_msgid


def test_every_message_type_decodes_as_pymavlink_does() -> None:
    """The codec's decoder gives pymavlink's message, or leaves the frame to pymavlink, for
    every message type of the dialect (random payloads)."""
    rng = np.random.default_rng(7)
    mav = mavlink2.MAVLink(None)
    decoded = 0
    for msg_id, msgtype in mavlink2.mavlink_map.items():
        payload = rng.integers(0, 256, msgtype.unpacker.size, dtype=np.uint8).tobytes()
        body = bytes([len(payload), 0, 0, 7, 1, 1]) + msg_id.to_bytes(3, "little") + payload
        crc = mavlink2.x25crc(body + bytes([msgtype.crc_extra])).crc
        frame = b"\xfd" + body + bytes([crc & 0xFF, crc >> 8])
        try:
            expected = _whole(mav.decode(bytearray(frame)))
        except mavlink2.MAVError:
            expected = None
        got = codec_mod._decode_unsigned(frame)
        assert (None if got is None else _whole(got)) == expected, msgtype.msgname
        decoded += got is not None
    assert decoded == len(mavlink2.mavlink_map)  # every type is the codec's own decoder's
