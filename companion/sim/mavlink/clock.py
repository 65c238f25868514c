"""Wall-clock pacing of simulated time.

`Pacer` keeps simulated time at `speedup` times wall-clock time (speedup = inf: as fast as
possible, yielding to the event loop now and then so the socket is served). Falling more
than `MAX_LAG_S` behind (a slow machine, a debugger) re-anchors instead of bursting to catch
up. Lockstep (see sim.mavlink.server) is layered on top: it only ever waits longer.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable

MAX_LAG_S = 0.25
YIELD_EVERY = 20
"""Ticks between event-loop yields when running as fast as possible."""


class Pacer:
    def __init__(self, speedup: float, wall: Callable[[], float] = time.monotonic) -> None:
        if not speedup > 0:
            raise ValueError(f"speedup must be > 0, got {speedup}")
        self.speedup = speedup
        self.wall = wall
        self.lag_events = 0
        self._anchor: tuple[float, float] | None = None
        self._calls = 0

    def restart(self, sim_s: float) -> None:
        """Anchor sim_s to now (at the start of a run, after a pause)."""
        self._anchor = (self.wall(), sim_s)

    async def pace(self, sim_s: float) -> None:
        """Wait until wall-clock time catches up with sim_s."""
        self._calls += 1
        if math.isinf(self.speedup):
            if self._calls % YIELD_EVERY == 0:
                await asyncio.sleep(0)
            return
        if self._anchor is None:
            self.restart(sim_s)
        assert self._anchor is not None
        wall0, sim0 = self._anchor
        delay = wall0 + (sim_s - sim0) / self.speedup - self.wall()
        if delay > 0.0:
            await asyncio.sleep(delay)
        elif delay < -MAX_LAG_S:
            self.lag_events += 1
            self.restart(sim_s)
            await asyncio.sleep(0)
        elif self._calls % YIELD_EVERY == 0:
            await asyncio.sleep(0)
