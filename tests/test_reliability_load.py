"""Load: a flood of 10x the normal message rate and beyond, over real UDP.

The normal rate is what the service asks for: 20 Hz of ATTITUDE, GLOBAL_POSITION_INT and
each DISTANCE_SENSOR (3 sensors here: 100 messages/s, plus heartbeat and home). A separate
process streams them at 10x (1000/s, one message per datagram) instead of the autopilot,
then far beyond what one core can parse. The control loop must not be starved by the reads
(at least half its rate on a loaded machine, never faster than asked, and any cycle it
misses counted as an overrun), traced memory must not grow, and what cannot be read is
dropped by the kernel and counted (`link.kernel_dropped`); what is read but stale is counted
too (`input.duplicate`, ...). No figure here depends on the machine being idle: the rates
themselves are measured in `bench/`.
"""

from __future__ import annotations

import asyncio
import contextlib
import subprocess
import sys
import time
import tracemalloc
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from companion.service import Service
from companion.service.link import UdpInLink, UdpOutLink
from companion.service.notify import SystemdNotifier
from tests.service_fakes import FakeAutopilot, PlannerBox, make_config

pytestmark = pytest.mark.timeout(60)

GUIDED = 4
NORMAL_RATE = 3 * 20 + 2 * 20  # ATTITUDE, GLOBAL_POSITION_INT and 3 sensors at 20 Hz
LOOP_HZ = 20.0


def assert_loop_not_starved(f: dict[str, float]) -> None:
    """The cycle timer kept its turn between the reads: never faster than asked, at least half
    the rate even on a loaded machine, and a rate short of 95 % shows in the counters (a
    missed cycle is never silent): an overrun, or a cycle that ran on its deadline because
    the inputs it waits for did not all arrive (the flood's drops)."""
    assert f["cycle_hz"] <= 1.05 * LOOP_HZ
    assert f["cycle_hz"] >= 0.5 * LOOP_HZ
    if f["cycle_hz"] < 0.95 * LOOP_HZ:
        assert f["overruns"] + f["cycles_by_timer"] > 0


ROOT = Path(__file__).resolve().parents[1]


async def until(pred: Any, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError("condition not met")
        await asyncio.sleep(0.01)


@contextlib.asynccontextmanager
async def flying() -> AsyncIterator[tuple[Service, FakeAutopilot, int]]:
    link = UdpInLink("127.0.0.1", 0)
    svc = Service(make_config(), link, planner_factory=PlannerBox(), notifier=SystemdNotifier({}))
    task = asyncio.create_task(svc.run())
    await until(lambda: link.is_open)
    host, port = link.local_address
    ap = FakeAutopilot(UdpOutLink(host, port))
    await ap.start()
    try:
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 10)
        yield svc, ap, port
    finally:
        svc.stop()
        assert await asyncio.wait_for(task, 5) == 0
        await ap.stop()


async def flood(
    svc: Service, ap: FakeAutopilot, port: int, rate: float, seconds: float
) -> dict[str, float]:
    """Stream at `rate` messages/s from another process; the loop's figures meanwhile."""
    ap.telemetry_enabled = False  # the flood replaces the autopilot's streams
    await asyncio.sleep(0.1)
    tracemalloc.start()
    try:
        mem0 = tracemalloc.get_traced_memory()[0]
        c0 = svc.counter_values()
        t0 = time.monotonic()
        proc = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "tests.reliability_flood",
            "127.0.0.1",
            str(port),
            str(rate),
            str(seconds),
            repr(ap._boot),
            cwd=ROOT,
            stdout=subprocess.PIPE,
        )
        out, _ = await proc.communicate()
        elapsed = time.monotonic() - t0
        cycles = svc.counter_values()["service.cycles"]
        # What the flood left in the socket is read after it ends: on a loaded machine the
        # service may still be draining it. Give it up to 3 s to account for every datagram.
        sent_now = int(out.decode().strip() or 0)
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            now = svc.counter_values()
            seen = (now["link.chunks_in"] - c0["link.chunks_in"]) + (
                now["link.kernel_dropped"] - c0["link.kernel_dropped"]
            )
            if seen >= sent_now:
                break
            await asyncio.sleep(0.05)
        c1 = svc.counter_values()
        c1["service.cycles"] = cycles
        mem1 = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
        ap.telemetry_enabled = True
    sent = int(out.decode().strip() or 0)
    d = {k: c1.get(k, 0) - c0.get(k, 0) for k in c1}
    return {
        "sent": sent,
        "sent_per_s": sent / seconds,
        "elapsed_s": elapsed,
        "cycle_hz": d["service.cycles"] / elapsed,
        "received": d["link.chunks_in"],
        "kernel_dropped": d["link.kernel_dropped"],
        "accepted": d["conn.accepted"],
        "stale_dropped": d.get("input.duplicate", 0) + d.get("input.out_of_order", 0),
        "overruns": d.get("service.cycle_overruns", 0),
        "cycles_by_timer": d.get("service.cycles_by_timer", 0),
        "hold_cycles": d.get("service.hold_cycles", 0),
        "memory_growth_bytes": mem1 - mem0,
    }


async def test_flood_10x_keeps_the_loop_rate() -> None:
    async with flying() as (svc, ap, port):
        f = await flood(svc, ap, port, rate=10 * NORMAL_RATE, seconds=3.0)
        print(f)
        # The flood process, like the service, shares a possibly loaded machine: what it
        # managed to send is the reference, not the rate it was asked for.
        assert f["sent"] > 0.25 * 10 * NORMAL_RATE * 3.0
        assert_loop_not_starved(f)
        assert f["received"] + f["kernel_dropped"] >= 0.99 * f["sent"]
        if f["kernel_dropped"] == 0 and f["sent_per_s"] >= 0.95 * 10 * NORMAL_RATE:
            assert f["hold_cycles"] == 0  # every message read: the data kept flowing
        # On a loaded machine the service may not read 1000 messages/s: the kernel drops
        # the rest (counted above) and a stale input may hold the vehicle for a cycle or
        # two; what must hold is the loop's turn and that nothing goes uncounted.
        assert f["stale_dropped"] > 0  # same-instant repeats: dropped and counted
        assert f["memory_growth_bytes"] < 1_000_000
        assert svc.status().owner == "engaged"


async def test_flood_beyond_capacity_is_dropped_and_counted() -> None:
    """Far more than one core can parse: the kernel drops the rest, counted, and the loop
    still keeps its rate (the event loop alternates reads with the cycle's timer)."""
    async with flying() as (svc, ap, port):
        f = await flood(svc, ap, port, rate=60_000, seconds=2.0)
        print(f)
        assert_loop_not_starved(f)
        assert f["memory_growth_bytes"] < 1_000_000
        assert f["received"] + f["kernel_dropped"] >= 0.99 * f["sent"]
        if f["received"] < 0.95 * f["sent"]:  # the service could not keep up...
            assert f["kernel_dropped"] > 0  # ...and the drops are counted
        assert svc.status().owner == "engaged"
