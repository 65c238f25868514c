"""The input-triggered cycle (real time): cycles follow the inputs, the rate stays bounded."""

from __future__ import annotations

import asyncio
import time

import pytest

from companion.service import Service
from companion.service.link import memory_pair
from companion.service.notify import SystemdNotifier
from tests.service_fakes import FakeAutopilot, PlannerBox, make_config

pytestmark = pytest.mark.timeout(60)


async def _run(autopilot_hz: float, seconds: float) -> tuple[int, int, int, float]:
    """(cycles, by input, by timer, wall seconds) of a service at 20 Hz fed at autopilot_hz."""
    a, b = memory_pair()
    svc = Service(make_config(), a, planner_factory=PlannerBox(), notifier=SystemdNotifier({}))
    ap = FakeAutopilot(b, rate_hz=autopilot_hz)
    task = asyncio.create_task(svc.run())
    await ap.start()
    try:
        deadline = time.monotonic() + 20.0
        while not svc.status().configured:
            assert time.monotonic() < deadline, "the service did not configure the autopilot"
            await asyncio.sleep(0.01)
        c0 = dict(svc.counters)
        t0 = time.monotonic()
        await asyncio.sleep(seconds)
        wall = time.monotonic() - t0
        c1 = dict(svc.counters)
    finally:
        svc.stop()
        assert await asyncio.wait_for(task, 10) == 0
        await ap.stop()

    def grew(k: str) -> int:
        return c1.get(k, 0) - c0.get(k, 0)

    return grew("cycles"), grew("cycles_by_input"), grew("cycles_by_timer"), wall


async def test_inputs_faster_than_the_loop_never_raise_its_rate() -> None:
    """Fed at 100 Hz, a 20 Hz loop stays at most 20 Hz (plus the one saved-up cycle), and
    its cycles are started by the inputs, not the timer."""
    cycles, by_input, by_timer, wall = await _run(100.0, 2.0)
    assert cycles <= 20.0 * wall + 2
    assert cycles > 0 and by_input > by_timer


async def test_inputs_slower_than_the_loop_leave_the_timer_as_deadline() -> None:
    """Fed at 5 Hz, the 20 Hz loop does not wait for inputs forever: the deadline
    (1.5 periods) runs it, so it never stops cycling."""
    cycles, by_input, by_timer, wall = await _run(5.0, 2.0)
    assert cycles <= 20.0 * wall + 2
    assert by_timer > by_input and cycles >= by_timer


async def test_a_sensor_gone_quiet_is_not_waited_for() -> None:
    """The burst a cycle waits for is that of the sensors that reported in the last two:
    once a sensor has gone quiet the others' bursts start the cycles again, not the
    deadline."""
    a, b = memory_pair()
    svc = Service(make_config(), a, planner_factory=PlannerBox(), notifier=SystemdNotifier({}))
    ap = FakeAutopilot(b, rate_hz=40.0)
    task = asyncio.create_task(svc.run())
    await ap.start()
    try:
        deadline = time.monotonic() + 20.0
        while not svc.status().configured:
            assert time.monotonic() < deadline, "the service did not configure the autopilot"
            await asyncio.sleep(0.01)
        ap.sensors_enabled = {0, 1}
        await asyncio.sleep(1.0)  # sensor 2 goes stale (0.5 s)
        c0 = dict(svc.counters)
        await asyncio.sleep(2.0)
        c1 = dict(svc.counters)
    finally:
        svc.stop()
        assert await asyncio.wait_for(task, 10) == 0
        await ap.stop()
    by_input = c1.get("cycles_by_input", 0) - c0.get("cycles_by_input", 0)
    by_timer = c1.get("cycles_by_timer", 0) - c0.get("cycles_by_timer", 0)
    assert by_input > by_timer
