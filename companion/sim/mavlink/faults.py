"""Deterministic fault injection: sensor faults, link faults and scheduled events.

Randomness comes from one seed split into independent streams (sensors, outgoing link,
incoming link), so enabling one kind of fault does not change the draws of another, and the
same scenario with the same companion gives the same faults. Each reading and each message
consumes a fixed number of draws whatever the outcome.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from companion.planner.types import FloatArray
from companion.sim.mavlink.config import FaultsConfig, LinkFaultConfig, SensorFaultConfig, Window

T = TypeVar("T")


def in_windows(windows: Sequence[Window], t_s: float) -> bool:
    return any(start <= t_s < end for start, end in windows)


def fault_rngs(seed: int) -> tuple[np.random.Generator, ...]:
    """(sensors, outgoing, incoming) generators from one seed."""
    return tuple(np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))


class SensorFaults:
    """Noise, dropouts, stuck readings and spikes for the sensors of one table."""

    def __init__(
        self,
        configs: Sequence[SensorFaultConfig],
        sensor_ids: Sequence[int],
        min_m: FloatArray,
        max_m: FloatArray,
        rng: np.random.Generator,
    ) -> None:
        self.per_sensor = [
            [c for c in configs if c.sensor_id is None or c.sensor_id == sid] for sid in sensor_ids
        ]
        self.min_m = np.asarray(min_m, dtype=np.float64)
        self.max_m = np.asarray(max_m, dtype=np.float64)
        self.rng = rng
        self._stuck: list[float | None] = [None] * len(sensor_ids)
        self._any = any(self.per_sensor)

    def apply(self, t_s: float, ranges_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(faulty ranges, send mask) for true ranges (n,) at time t_s."""
        out = np.array(ranges_m, dtype=np.float64)
        send = np.ones(len(out), dtype=bool)
        if not self._any:
            return out, send  # no faults configured: nothing to draw or hold
        for i, configs in enumerate(self.per_sensor):
            stuck_now = any(in_windows(c.stuck_windows, t_s) for c in configs)
            if not stuck_now:
                self._stuck[i] = None
            for c in configs:
                if c.noise_std_m > 0:
                    noise = float(self.rng.normal(0.0, c.noise_std_m))
                    if np.isfinite(out[i]):
                        out[i] = max(out[i] + noise, 0.0)
                if c.spike_probability > 0:
                    u, v = self.rng.random(2)
                    lo, hi = c.spike_range_m or (self.min_m[i], self.max_m[i])
                    if u < c.spike_probability:
                        out[i] = lo + v * (hi - lo)
                if c.dropout_probability > 0 and self.rng.random() < c.dropout_probability:
                    send[i] = False
                if in_windows(c.dropout_windows, t_s):
                    send[i] = False
            if stuck_now:
                held = self._stuck[i]
                if held is None:
                    self._stuck[i] = float(out[i])
                else:
                    out[i] = held
        return out, send


@dataclass
class LinkStats:
    offered: int = 0
    dropped: int = 0
    duplicated: int = 0
    reordered: int = 0


class LinkFaults(Generic[T]):
    """Loss, duplication and reordering of one direction of the link, per message."""

    def __init__(self, config: LinkFaultConfig, rng: np.random.Generator) -> None:
        self.config = config
        self.rng = rng
        self.stats = LinkStats()
        self._held: list[T] = []
        self._active = (
            config.loss_probability > 0
            or config.duplicate_probability > 0
            or config.reorder_probability > 0
        )

    def filter(self, item: T, t_s: float | None = None) -> list[T]:
        """Items to deliver now, in order (none, this one, twice, or with a held one).

        t_s: simulated time, for the config's windows (None: inside)."""
        self.stats.offered += 1
        if not self._active:
            return [item]
        c = self.config
        lose, dup, reorder = self.rng.random(3)
        if c.windows and t_s is not None and not in_windows(c.windows, t_s):
            out, self._held = [*self._held, item], []
            return out
        if lose < c.loss_probability:
            self.stats.dropped += 1
            return []
        out = [item]
        if dup < c.duplicate_probability:
            self.stats.duplicated += 1
            out.append(item)
        if not self._held and reorder < c.reorder_probability:
            self.stats.reordered += 1
            self._held = out
            return []
        out, self._held = out + self._held, []
        return out

    def flush(self) -> list[T]:
        out, self._held = self._held, []
        return out


class FaultSchedule:
    """Timed events of a FaultsConfig: link cuts, reboots and pilot mode changes."""

    def __init__(self, config: FaultsConfig) -> None:
        self.config = config
        self._reboot_windows: list[Window] = [
            (r.at_s, r.at_s + r.duration_s) for r in config.reboots
        ]

    def link_up(self, t_s: float) -> bool:
        return not in_windows(self.config.link_cuts, t_s) and not in_windows(
            self._reboot_windows, t_s
        )

    def reboots_in(self, t0_s: float, t1_s: float) -> list[float]:
        """Reboot times in [t0, t1): the tick starting at t0 triggers them."""
        return [r.at_s for r in self.config.reboots if t0_s <= r.at_s < t1_s]

    def mode_changes_in(self, t0_s: float, t1_s: float) -> list[str | int]:
        """Pilot mode changes in [t0, t1)."""
        return [m.mode for m in self.config.mode_changes if t0_s <= m.at_s < t1_s]

    def position_offset(self, t_s: float) -> FloatArray:
        """How far (ENU metres) the position estimate is off the truth at t_s."""
        out = np.zeros(3)
        for j in self.config.position_jumps:
            if j.at_s <= t_s and (j.duration_s is None or t_s < j.at_s + j.duration_s):
                out += np.asarray(j.offset_m, dtype=np.float64)
        return out
