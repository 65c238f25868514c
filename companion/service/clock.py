"""Service clocks: the computer's monotonic clock, or the simulator's time.

In "sim" mode the simulator drives time: each lockstep tick sends TIMESYNC(tc1=0, ts1=sim
time in ns); the service sets its clock to that time, runs a cycle if one is due, and answers.
Receipt stamps in sim mode are the latest tick's time, so ages are over-estimated by at most
one tick (conservative for the staleness checks).
"""

from __future__ import annotations

import time


class MonotonicClock:
    def now(self) -> float:
        return time.monotonic()


class SimClock:
    """Time set from outside (seconds); never goes backwards."""

    def __init__(self, start_s: float = 0.0) -> None:
        self._t = start_s

    def now(self) -> float:
        return self._t

    def set(self, t_s: float) -> None:
        if t_s > self._t:
            self._t = t_s
