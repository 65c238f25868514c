"""The MAVLink 2 codec: pymavlink's generated `MAVLink` object, bytes in and messages out.

`MavCodec.decode(chunk)` feeds `parse_buffer` in robust mode and returns only good messages;
everything else is counted, never raised: bad prefixes (garbage bytes), CRC failures, length
errors, unknown message ids, signature rejections, and frames cut off at the end of a UDP
datagram. For datagram links the parser state is reset after every datagram so a truncated
frame cannot swallow the next datagram's messages. Any unexpected exception from the parser
is counted and the parser reset.

Whole MAVLink 2 frames skip the parser: a datagram that is exactly one (nearly all of them),
and each whole frame of a datagram that holds several (a lockstep simulator's period) up to
the first that is not whole. An unsigned frame of a known message with a good checksum goes
through `_decode_unsigned` (what pymavlink's `decode` does, its per-type work done once per
type: about half the cost), any other straight to pymavlink's `decode`, with the verdicts
the parser would give; what follows the last whole frame goes to the parser.

Signing: with a key, outgoing frames are signed and incoming frames must carry a valid
signature with a timestamp newer than the last one seen on their stream (replays fail).
pymavlink's own check records a stream's timestamp *before* checking the signature, so one
forged frame with a large timestamp would lock out the real sender; `_Codec` checks the
signature first.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import operator
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

log = logging.getLogger(__name__)

MAVLinkMessage = Any
"""pymavlink messages are untyped; fields are read by name."""

_SIGNATURE_TS = 6_000 * 1_000
"""pymavlink's allowance for a new stream: one minute behind our timestamp."""


class _Codec(mavlink2.MAVLink):  # type: ignore[misc]
    def check_signature(self, msgbuf: bytearray, srcSystem: int, srcComponent: int) -> bool:
        key = self.signing.secret_key
        assert key is not None
        if not hmac.compare_digest(
            hashlib.sha256(key + bytes(msgbuf[:-6])).digest()[:6], bytes(msgbuf[-6:])
        ):
            return False
        link_id = msgbuf[-13]
        tlow, thigh = self.mav_sign_unpacker.unpack(msgbuf[-12:-6])
        timestamp = int(tlow) + (int(thigh) << 32)
        stream_key = (link_id, srcSystem, srcComponent)
        last = self.signing.stream_timestamps.get(stream_key)
        if last is not None:
            if timestamp <= last:
                return False  # replayed or reordered
        elif timestamp + _SIGNATURE_TS < self.signing.timestamp:
            return False  # a "new" stream far in the past
        self.signing.stream_timestamps[stream_key] = timestamp
        self.signing.timestamp = max(self.signing.timestamp, timestamp)
        return True


@dataclass(slots=True)
class CodecCounters:
    frames: int = 0
    """Good frames decoded."""
    garbage: int = 0
    """Runs of bytes that were not a frame start."""
    bad_crc: int = 0
    bad_frame: int = 0
    """Length, header or payload errors."""
    bad_signature: int = 0
    """Signed frames whose signature or timestamp failed (forged, wrong key, replayed)."""
    unsigned_rejected: int = 0
    """Frames without a signature while signing is required."""
    unknown_msgid: int = 0
    truncated: int = 0
    """Partial frames left at the end of a datagram."""
    parser_errors: int = 0
    """Unexpected exceptions from the parser (it is reset)."""


class MavCodec:
    """Encode and decode MAVLink 2 frames for one source (system id, component id)."""

    def __init__(self, system_id: int = 1, component_id: int = 191) -> None:
        self.mav = _Codec(None, srcSystem=system_id, srcComponent=component_id)
        self.mav.robust_parsing = True
        self.counters = CodecCounters()
        self._allow_unsigned: frozenset[int] = frozenset()

    # -- identity & signing -----------------------------------------------------------------

    @property
    def system_id(self) -> int:
        return int(self.mav.srcSystem)

    @property
    def component_id(self) -> int:
        return int(self.mav.srcComponent)

    def set_source(self, system_id: int, component_id: int) -> None:
        self.mav.srcSystem = system_id
        self.mav.srcComponent = component_id

    def enable_signing(
        self,
        key: bytes,
        *,
        link_id: int = 0,
        timestamp: int = 0,
        allow_unsigned_msgids: Iterable[int] = (),
    ) -> None:
        """Sign outgoing frames and require valid signatures on incoming ones."""
        if len(key) != 32:
            raise ValueError(f"signing key must be 32 bytes, got {len(key)}")
        s = self.mav.signing
        s.secret_key = key
        s.link_id = link_id
        s.timestamp = max(int(timestamp), 1)
        s.sign_outgoing = True
        self._allow_unsigned = frozenset(allow_unsigned_msgids)
        s.allow_unsigned_callback = self._allow_unsigned_cb

    def _allow_unsigned_cb(self, _mav: object, msg_id: int) -> bool:
        return msg_id in self._allow_unsigned

    @property
    def signing_enabled(self) -> bool:
        return self.mav.signing.secret_key is not None

    @property
    def signing_timestamp(self) -> int:
        return int(self.mav.signing.timestamp)

    def advance_signing_clock(self, timestamp: int) -> None:
        """Move the outgoing timestamp forward to at least `timestamp` (never back)."""
        s = self.mav.signing
        s.timestamp = max(int(s.timestamp), int(timestamp))

    # -- encode / decode --------------------------------------------------------------------

    def encode(self, msg: MAVLinkMessage) -> bytes:
        """Pack (and sign) one message with our source ids and the next sequence number."""
        buf: bytes = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf

    def decode(self, data: bytes, datagram: bool = True) -> list[MAVLinkMessage]:
        """Good messages in `data`; everything else is counted in `counters`."""
        mav = self.mav
        c = self.counters
        msgs: list[MAVLinkMessage] = []
        good = 0
        """How many of `msgs`, from the start, are good messages of the codec's decoder."""
        try:
            end = 0
            rest = True
            """Bytes are left for the parser."""
            if mav.buf_index == len(mav.buf):  # the parser holds nothing from before
                end = _frame_end(data, 0)
                if (
                    end == len(data)
                    and end
                    and not data[2]
                    and mav.signing.secret_key is None
                    and type(data) is bytes
                ):
                    # the usual datagram, one whole unsigned MAVLink 2 frame: straight to
                    # the codec's decoder, as pymavlink's parser would hand it over
                    m = _decode_unsigned(data)
                    if m is not None:  # a good frame of a known message
                        mav.have_prefix_error = False
                        mav.total_bytes_received += end
                        mav.total_packets_received += 1
                        c.frames += 1
                        return [m]
            if end:
                # whole MAVLink 2 frames, one after the other: each as the parser would hand
                # it to pymavlink's `decode` (good unsigned ones to the codec's decoder),
                # whatever follows the last whole one to the parser
                start, size = 0, len(data)
                unsigned = mav.signing.secret_key is None and type(data) is bytes
                while end:
                    frame = data if end - start == size else data[start:end]
                    m = _decode_unsigned(frame) if unsigned and not frame[2] else None
                    if m is None:
                        m = self._decode_frame(frame)
                    else:
                        mav.have_prefix_error = False
                        mav.total_bytes_received += end - start
                        mav.total_packets_received += 1
                        if good == len(msgs):
                            good += 1
                    msgs.append(m)
                    start = end
                    end = _frame_end(data, start)
                rest = start < size
                data = data[start:]
            if rest:
                # `parse_buffer`, without its last call on an empty buffer (which cannot
                # give a message)
                m = mav.parse_char(data)
                while m is not None:
                    msgs.append(m)
                    m = mav.parse_char(b"") if mav.buf_len() > 0 else None
        except Exception as exc:
            self.counters.parser_errors += 1
            log.debug("parser error: %r", exc)
            self._reset()
            return []
        out = msgs[:good]
        c.frames += good
        for m in msgs[good:] if good else msgs:
            mtype = m.get_type()
            if mtype == "BAD_DATA":
                reason = str(getattr(m, "reason", ""))
                if reason == "Bad prefix":
                    c.garbage += 1
                elif "CRC" in reason:
                    c.bad_crc += 1
                elif reason == "Invalid signature":
                    if m.get_msgbuf()[0] == mavlink2.PROTOCOL_MARKER_V2 and (
                        m.get_msgbuf()[2] & mavlink2.MAVLINK_IFLAG_SIGNED
                    ):
                        c.bad_signature += 1
                    else:
                        c.unsigned_rejected += 1
                else:
                    c.bad_frame += 1
            elif mtype.startswith("UNKNOWN_"):
                c.unknown_msgid += 1
            else:
                c.frames += 1
                out.append(m)
        if datagram and mav.buf_len() > 0:
            c.truncated += 1
            self._reset()
        return out

    def _decode_frame(self, data: bytes) -> MAVLinkMessage:
        """One whole MAVLink 2 frame (`_one_v2_frame`) through pymavlink's `decode`, with
        what its parser does around that call in robust mode: a frame that fails to decode
        becomes BAD_DATA with the decoder's reason, and the parser's totals count it."""
        mav = self.mav
        buf = bytearray(data)
        try:
            m = mav.decode(buf)
        except mavlink2.MAVError as exc:
            m = mavlink2.MAVLink_bad_data(buf, exc.message)
            mav.total_receive_errors += 1
        mav.have_prefix_error = False
        mav.total_bytes_received += len(data)
        mav.total_packets_received += 1
        return m

    def _reset(self) -> None:
        m = self.mav
        m.buf = bytearray()
        m.buf_index = 0
        m.expected_length = mavlink2.HEADER_LEN_V1 + 2
        m.have_prefix_error = False


_V2_FRAME_OVERHEAD: int = mavlink2.HEADER_LEN_V2 + 2
"""Bytes of a MAVLink 2 frame around its payload: header and checksum (no signature)."""


_MARKER_V2: int = mavlink2.PROTOCOL_MARKER_V2
_NOT_SIGNED: int = ~mavlink2.MAVLINK_IFLAG_SIGNED
_SIGNATURE_LEN: int = mavlink2.MAVLINK_SIGNATURE_BLOCK_LEN


def _frame_end(data: bytes, start: int) -> int:
    """Where the whole MAVLink 2 frame that starts at `start` of `data` ends, by its header
    (the start marker, no incompatibility flag other than "signed", and the length its
    header gives: payload, header, checksum, signature if signed); 0 when there is none.
    Its contents are the decoder's to judge."""
    if len(data) - start < _V2_FRAME_OVERHEAD or data[start] != _MARKER_V2:
        return 0
    flags = data[start + 2]
    if flags & _NOT_SIGNED:
        return 0
    end: int = start + data[start + 1] + _V2_FRAME_OVERHEAD
    if flags:
        end += _SIGNATURE_LEN
    return end if end <= len(data) else 0


def _one_v2_frame(data: bytes) -> bool:
    """`data` is exactly one MAVLink 2 frame by its header (`_frame_end`)."""
    return bool(data) and _frame_end(data, 0) == len(data)


@dataclass(frozen=True, slots=True)
class _Plan:
    """How pymavlink's `MAVLink.decode` turns one message type's payload into its fields,
    worked out once: `pick` takes each field's first unpacked value, in field order; the
    array fields are then (field index, unpacked index, length), a list of that many
    values; the text fields have their trailing NULs stripped."""

    msgtype: Any
    crc_extra: bytes
    size: int
    unpack: Callable[[bytes], tuple[Any, ...]]
    pick: Callable[[tuple[Any, ...]], Any]
    arrays: tuple[tuple[int, int, int], ...]
    texts: tuple[int, ...]


def _plan(msg_id: int) -> _Plan | None:
    msgtype = mavlink2.mavlink_map.get(msg_id)
    if msgtype is None:
        return None
    unpacker = msgtype.unpacker
    probe = unpacker.unpack(bytes(unpacker.size))  # the value types do not depend on content
    lengths, orders = msgtype.lengths, msgtype.orders
    picks: list[tuple[int, int]] = []
    if sum(lengths) == len(lengths):  # no arrays
        picks = [(orders[i], 0) for i in range(len(probe))]
    else:
        for order in orders:
            n, tip = lengths[order], sum(lengths[:order])
            picks.append((tip, 0 if n == 1 or isinstance(probe[tip], bytes) else n))
    tips = [tip for tip, _ in picks]
    # itemgetter of one index gives the value itself: one field is a slice of one
    pick = (
        operator.itemgetter(*tips)
        if len(tips) > 1
        else operator.itemgetter(slice(tips[0], tips[0] + 1))
    )
    return _Plan(
        msgtype,
        bytes([msgtype.crc_extra]),
        unpacker.size,
        unpacker.unpack,
        pick,
        tuple((i, tip, n) for i, (tip, n) in enumerate(picks) if n),
        tuple(i for i, (tip, n) in enumerate(picks) if n == 0 and isinstance(probe[tip], bytes)),
    )


_PLANS: dict[int, _Plan | None] = {}
_CRC: Callable[[bytes, int], int] | None = getattr(mavlink2, "mcrf4xx", None)


def _decode_unsigned(data: bytes) -> MAVLinkMessage | None:
    """One whole unsigned MAVLink 2 frame of a known message with a good checksum, decoded
    exactly as pymavlink's `MAVLink.decode` does (the same message, fields, header and
    buffers; `tests/test_service_codec.py` holds it to that); None for anything else, which
    is then pymavlink's to judge. Its per-type work (field order, arrays, text) is done once
    per type, and the checksum is pymavlink's own (fastcrc)."""
    crc_fn = _CRC
    if crc_fn is None or mavlink2.MAVLINK_IGNORE_CRC:
        return None
    msg_id = data[7] | data[8] << 8 | data[9] << 16
    try:
        plan = _PLANS[msg_id]
    except KeyError:
        plan = _PLANS[msg_id] = _plan(msg_id)
    if plan is None:
        return None
    crc = data[-2] | data[-1] << 8
    if crc_fn(data[1:-2] + plan.crc_extra, 0xFFFF) != crc:
        return None
    payload = data[10:-2]
    size = plan.size
    if len(payload) < size:
        payload += bytes(size - len(payload))  # zero-trimmed by the sender
    elif len(payload) > size:
        payload = payload[:size]
    t = plan.unpack(payload)
    fields: list[Any] = list(plan.pick(t))
    for i, tip, n in plan.arrays:
        fields[i] = list(t[tip : tip + n])
    for i in plan.texts:
        fields[i] = fields[i].rstrip(b"\x00")
    try:
        m = plan.msgtype(*fields)
    except Exception:
        return None  # pymavlink's decode gives its verdict
    msgbuf = bytearray(data)
    m._signed = False
    m._msgbuf = msgbuf
    m._payload = msgbuf[6:-2]
    m._crc = crc
    m._header = mavlink2.MAVLink_header(msg_id, 0, data[3], data[1], data[4], data[5], data[6])
    return m


def new_message_factory() -> Any:
    """A pymavlink `MAVLink` object for building messages (`.heartbeat_encode(...)`, ...)."""
    return mavlink2.MAVLink(None)


__all__ = ["CodecCounters", "MAVLinkMessage", "MavCodec", "mavlink2", "new_message_factory"]
