"""The service clocks (`companion.service.clock`): the manual clock tests use, the sim clock."""

from __future__ import annotations

import asyncio

import pytest

from companion.service.clock import Clock, ManualClock, MonotonicClock, SimClock


async def test_manual_sleep_returns_only_when_advanced_past_its_end() -> None:
    clock = ManualClock(10.0)
    woke: list[float] = []

    async def sleeper() -> None:
        await clock.sleep(1.0)
        woke.append(clock.now())

    task = asyncio.create_task(sleeper())
    for _ in range(5):
        await asyncio.sleep(0)
    assert woke == []
    clock.advance(0.6)
    for _ in range(5):
        await asyncio.sleep(0)
    assert woke == []
    clock.advance(0.6)
    await asyncio.wait_for(task, 5.0)
    assert woke == [pytest.approx(11.2)]


async def test_a_zero_sleep_still_yields() -> None:
    clock = ManualClock()
    ran: list[int] = []

    async def other() -> None:
        ran.append(1)

    task = asyncio.create_task(other())
    await clock.sleep(0.0)
    assert ran == [1]
    await task


def test_clocks_never_go_backwards() -> None:
    sim = SimClock(5.0)
    sim.set(4.0)
    assert sim.now() == 5.0
    sim.set(6.5)
    assert sim.now() == 6.5
    manual = ManualClock()
    with pytest.raises(ValueError, match="cannot go back"):
        manual.advance(-1.0)


def test_every_clock_meets_the_protocol() -> None:
    clocks: list[Clock] = [MonotonicClock(), SimClock(), ManualClock()]
    a = [c.now() for c in clocks]
    b = [c.now() for c in clocks]
    assert all(y >= x for x, y in zip(a, b, strict=True))


def test_only_the_clock_module_reads_the_computers_time() -> None:
    """The service's time comes from an injected Clock: no other module of companion.service
    calls time.monotonic/time/perf_counter (or imports them by name)."""
    import ast
    from pathlib import Path

    import companion.service

    readers = {"monotonic", "monotonic_ns", "time", "time_ns", "perf_counter", "perf_counter_ns"}
    offenders = []
    for path in sorted(Path(companion.service.__file__).parent.glob("*.py")):
        if path.name == "clock.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id == "time"
                and node.attr in readers
            ):
                offenders.append(f"{path.name}:{node.lineno} time.{node.attr}")
            if isinstance(node, ast.ImportFrom) and node.module == "time":
                offenders.append(f"{path.name}:{node.lineno} from time import ...")
    assert offenders == []
