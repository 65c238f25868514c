"""Service clocks: one protocol, passed in; the only place the service reads the computer's time.

- `MonotonicClock`: production, the computer's monotonic clock (seconds).
- `SimClock`: `control.time_source: sim`. The simulator drives time: each lockstep tick sends
  TIMESYNC(tc1=0, ts1=sim time in ns); the service sets its clock to that time, runs a cycle if
  one is due, and answers. Receipt stamps in sim mode are the latest tick's time, so ages are
  over-estimated by at most one tick (conservative for the staleness checks).
- `ManualClock`: tests; time moves only when the test calls `advance`, and `sleep` returns
  when the test has advanced past its end, so no test waits on the wall clock.

`sleep(duration_s)` sleeps on the clock's own time (simulated time in sim mode). A module of
the service that needs "now" takes a `Clock`; none calls `time.monotonic()` itself.
"""

from __future__ import annotations

import asyncio
import time
from typing import Protocol


def unix_time_s() -> float:
    """Seconds since 1970 (UTC) by the computer's calendar clock: only for what must name the
    date, the MAVLink signing timestamp; everything that measures time takes a `Clock`."""
    return time.time()


class Clock(Protocol):
    """Seconds on a clock that never goes backwards; its origin is arbitrary."""

    def now(self) -> float: ...

    async def sleep(self, duration_s: float) -> None: ...


class MonotonicClock:
    """The computer's monotonic clock (production)."""

    def now(self) -> float:
        return time.monotonic()

    async def sleep(self, duration_s: float) -> None:
        await asyncio.sleep(max(duration_s, 0.0))


class SimClock:
    """Time set from outside (seconds, the simulator's lockstep ticks); never goes backwards.

    `sleep` returns at the first `set` that reaches its end: in lockstep, on a tick, while
    the simulator waits for the tick's answer (so what the sleeper does next lands in that
    tick, whatever the machine's load).
    """

    def __init__(self, start_s: float = 0.0) -> None:
        self._t = start_s
        self._moved: asyncio.Event | None = None

    def now(self) -> float:
        return self._t

    def set(self, t_s: float) -> None:
        if t_s > self._t:
            self._t = t_s
            if self._moved is not None:
                self._moved.set()

    async def sleep(self, duration_s: float) -> None:
        if self._moved is None:
            self._moved = asyncio.Event()
        end = self._t + duration_s
        if self._t >= end:
            await asyncio.sleep(0)  # a sleep is always a chance for others to run
        while self._t < end:
            self._moved.clear()
            await self._moved.wait()


class ManualClock(SimClock):
    """A clock a test moves by hand: `advance(dt_s)` or `set(t_s)`; sleepers wake when their
    end has been reached (after the test yields to the event loop), never on the wall clock."""

    def advance(self, dt_s: float) -> float:
        """Move time forward by dt_s >= 0; returns the new time."""
        if dt_s < 0:
            raise ValueError(f"a clock cannot go back: dt_s = {dt_s}")
        self.set(self._t + dt_s)
        return self._t


__all__ = ["Clock", "ManualClock", "MonotonicClock", "SimClock", "unix_time_s"]
