"""Byte streams into the service's receive path: fuzzed with hypothesis, counted.

Every datagram goes through what a received UDP datagram goes through (size check, codec in
robust mode, routing by source, telemetry validation). For each: no exception escapes, a
non-empty datagram moves at least one codec/link counter (nothing vanishes silently), the
input cache only ever holds finite in-range values, and the only things the receive path
ever sends are TIMESYNC answers and PARAM_VALUE answers to parameter requests (it commands
nothing, and no planner value changes). With signing on, not one fuzzed frame
is accepted.

Counts: the three tests feed 64 000 + 25 600 + 12 800 = 102 400 inputs (asserted). The long
run (`pytest -m long`, tests/test_reliability_long.py) calls the same checks with ten times
the examples: 1 024 000 inputs. RELIABILITY_FUZZ_SCALE=N scales the default tests too.
"""

from __future__ import annotations

import logging
import os
import random

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from companion.service.codec import MavCodec, mavlink2
from companion.service.counters import ProblemReporter
from companion.service.link import MemoryLink
from tests.reliability_inputs import ReceivePath, frame_strategy, mutations

PER_EXAMPLE = 256
SCALE = int(os.environ.get("RELIABILITY_FUZZ_SCALE", "1"))
KEY = bytes(range(32))


def fuzz_settings(examples: int) -> settings:
    return settings(
        max_examples=examples,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
        database=None,
        derandomize=True,  # the same inputs on every run: a CI failure can be reproduced
    )


frames_and_seed = st.tuples(st.lists(frame_strategy(), min_size=1, max_size=6), st.integers())


def run_datagrams(path: ReceivePath, examples: int) -> None:
    @fuzz_settings(examples)
    @given(frames_and_seed)
    def fuzz(case: tuple[list[bytes], int]) -> None:
        frames, seed = case
        for d in mutations(frames, random.Random(seed), PER_EXAMPLE):
            path.feed(d)
        path.check_cache()

    fuzz()


def test_fuzzed_datagrams_are_counted_and_command_nothing(
    caplog: pytest.LogCaptureFixture,
) -> None:
    path = check_datagrams(SCALE)
    # the problems are reported: one warning per problem counter (every 10 s in service)
    with caplog.at_level(logging.WARNING, logger="companion.service"):
        ProblemReporter().report(path.svc.counter_values())
    logged = caplog.text
    for name in ("codec.garbage", "codec.bad_crc", "codec.truncated", "link.oversized_dropped"):
        assert name in logged


def check_datagrams(scale: int) -> ReceivePath:
    path = ReceivePath()
    examples = 250 * scale
    run_datagrams(path, examples)
    fed = path.fed
    assert fed.inputs >= examples * PER_EXAMPLE >= 64_000
    assert fed.nonempty_uncounted == 0
    c = path.svc.counter_values()
    for name in ("garbage", "bad_crc", "truncated", "unknown_msgid", "bad_frame"):
        assert c[f"codec.{name}"] > 0, name
    assert c["link.oversized_dropped"] > 0
    assert c.get("conn.other_system", 0) + c.get("conn.other_component", 0) > 0
    assert c.get("conn.handler_errors", 0) == 0
    assert c["codec.parser_errors"] == 0
    # answers to TIMESYNC requests and to parameter requests (PARAM_VALUE), nothing else
    assert path.sent_types() <= {"TIMESYNC", "PARAM_VALUE"}
    assert path.svc.host.tuning == path.cfg.planner  # no fuzzed PARAM_SET changed a value
    return path


def test_fuzzed_byte_stream_in_arbitrary_chunks() -> None:
    """TCP and serial: no datagram boundaries; a frame can be split across reads."""
    check_stream(SCALE)


def check_stream(scale: int) -> int:
    path = ReceivePath()
    link = MemoryLink("stream", datagram=False)
    path.svc.conn.link = link  # the codec keeps its state between chunks
    examples = 100 * scale
    count = 0

    @fuzz_settings(examples)
    @given(frames_and_seed)
    def fuzz(case: tuple[list[bytes], int]) -> None:
        nonlocal count
        frames, seed = case
        rng = random.Random(seed)
        data = b"".join(mutations(frames, rng, PER_EXAMPLE))
        cuts = sorted(rng.sample(range(len(data) + 1), min(PER_EXAMPLE - 1, len(data) + 1)))
        for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True):
            path.svc.conn._on_bytes(data[a:b], None)
            count += 1
        path.check_cache()

    fuzz()
    assert count >= 25_600 * scale * 0.95  # a few short examples have fewer cut points
    c = path.svc.counter_values()
    assert c["codec.garbage"] > 0 and c["codec.frames"] > 0
    assert c.get("conn.handler_errors", 0) == 0 and c["codec.parser_errors"] == 0
    assert path.sent_types() <= {"TIMESYNC"}
    # and the stream still works afterwards: a good frame after the noise gets through
    frames = path.svc.codec.counters.frames
    good = MavCodec(1, 1).encode(mavlink2.MAVLink_heartbeat_message(2, 3, 1, 5, 4, 3))
    path.svc.conn._on_bytes(b"\x00" * 300 + good * 3, None)
    assert path.svc.codec.counters.frames > frames
    return count


def test_fuzzed_frames_never_accepted_with_signing_on() -> None:
    check_signed(SCALE)


def check_signed(scale: int) -> int:
    path = ReceivePath(signing_key=KEY)
    frames_before = path.svc.codec.counters.frames  # the signed heartbeat that locked it
    examples = 50 * scale
    run_datagrams(path, examples)
    assert path.fed.inputs >= 12_800 * scale
    assert path.fed.nonempty_uncounted == 0
    c = path.svc.counter_values()
    assert path.svc.codec.counters.frames == frames_before  # not one fuzzed frame accepted
    assert c["codec.unsigned_rejected"] > 0
    assert path.sent_types() == set()  # no TIMESYNC answers either: nothing got in
    return path.fed.inputs
