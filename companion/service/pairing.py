"""Each range reading paired with the attitude of its own time.

A range becomes a world point through the attitude the vehicle had when the range was
measured (paper eqs. 1-2). ATTITUDE and DISTANCE_SENSOR arrive as separate streams, at their
own rates, and a range may be a median of older readings (`range_median_samples`), so the
latest ATTITUDE is not always the attitude of the ranges a cycle uses: paired naively, a
reading taken level and an attitude pitched 1.1 rad a tick later give a phantom steep point,
which the planner remembers.

Both messages carry `time_boot_ms` on the autopilot's clock (ArduPilot stamps both at send
time; PX4 stamps ATTITUDE at estimation and a DISTANCE_SENSOR it re-publishes at receipt; the
bundled simulator stamps both with the tick they describe). `AttitudeHistory` keeps the last
second of attitudes by stamp and answers `at(stamp)`:

- a sample with that stamp: that sample;
- between two samples at most MAX_INTERPOLATION_GAP_MS apart: linear interpolation (angles
  wrapped);
- otherwise the nearest sample within MATCH_TOLERANCE_MS; else None ("none matches").

The rate gate: a sample whose angles moved faster than MAX_ATTITUDE_RATE_RADPS from the last
trusted sample is not trusted (no airframe this service flies turns that fast; a glitch or a
kinematic model's jump does). An answer built from an untrusted sample is untrusted. Against
the last *trusted* sample, so one glitch does not also condemn the good sample after it, and a
real fast change is trusted again once the time since makes its rate possible.

`pair_ranges` applies this to one cycle (see its docstring for what happens when nothing
matches).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from companion.planner.frames import wrap_pi
from companion.planner.types import FloatArray

HISTORY_MS = 1000
"""Attitudes older than this behind the newest are forgotten (longer than any range age)."""
HISTORY_MAX = 256
"""At most this many attitudes kept (a bound whatever the stream's rate)."""
MAX_INTERPOLATION_GAP_MS = 120
"""Two samples further apart than this are not interpolated between."""
MATCH_TOLERANCE_MS = 60
"""Without a bracketing pair, the nearest sample within this of the stamp is its attitude."""
MAX_ATTITUDE_RATE_RADPS = 10.0
"""Faster than this (about 570 deg/s, on any Euler angle) a sample is not trusted."""
PAIR_TOLERANCE_RAD = 0.05
"""A reading whose own attitude differs more than this (any angle) from the cycle's is not
used in that cycle: its point would be off by about range * this."""
PAIR_TOLERANCE_M = 0.1
"""... nor one whose point that difference would move more than this, metres (range * angle
gap): at 6 m, 0.05 rad is 0.3 m, six times the noise of a good rangefinder, and a ground
point that high lifts the floor X_d keeps over it (`ground.floor_z`, the highest of the
points' needs) by as much."""


@dataclass(frozen=True, slots=True)
class AttitudeSample:
    """An attitude on the autopilot's clock: FRD body in NED, radians; `trusted`: passed
    the rate gate."""

    time_boot_ms: int
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    trusted: bool = True


def off_pose(
    gap_rad: FloatArray | float, range_m: FloatArray | float
) -> npt.NDArray[np.bool_] | bool:
    """Whether a reading of range_m (metres; 0, inf or NaN: "nothing", judged by the angle
    alone) taken gap_rad (`angle_gap_rad`) from the cycle's attitude is not to be used with
    it: past PAIR_TOLERANCE_RAD, or moving its point past PAIR_TOLERANCE_M."""
    gap = np.asarray(gap_rad, dtype=np.float64)
    r = np.asarray(range_m, dtype=np.float64)
    measured = np.isfinite(r) & (r > 0.0)
    moved = gap * np.where(measured, r, 0.0)
    out = (gap > PAIR_TOLERANCE_RAD) | (measured & (moved > PAIR_TOLERANCE_M))
    return bool(out) if out.ndim == 0 else out


def angle_gap_rad(a: AttitudeSample, b: AttitudeSample) -> float:
    """The largest of the three Euler angle differences, radians (wrapped)."""
    return max(
        abs(wrap_pi(a.roll_rad - b.roll_rad)),
        abs(a.pitch_rad - b.pitch_rad),
        abs(wrap_pi(a.yaw_rad - b.yaw_rad)),
    )


class AttitudeHistory:
    """The last HISTORY_MS of attitudes by `time_boot_ms` (increasing), each rate-gated."""

    def __init__(self) -> None:
        self._samples: deque[AttitudeSample] = deque(maxlen=HISTORY_MAX)
        self._last_trusted: AttitudeSample | None = None
        self.untrusted = 0
        """Samples the rate gate did not trust, so far."""

    def clear(self) -> None:
        self._samples.clear()
        self._last_trusted = None

    def add(self, time_boot_ms: int, roll_rad: float, pitch_rad: float, yaw_rad: float) -> bool:
        """Record an attitude (stamps must increase; the caller drops others); returns
        whether the rate gate trusts it."""
        s = AttitudeSample(time_boot_ms, roll_rad, pitch_rad, yaw_rad)
        ref = self._last_trusted
        trusted = True
        if ref is not None and time_boot_ms > ref.time_boot_ms:
            dt_s = (time_boot_ms - ref.time_boot_ms) * 1e-3
            trusted = angle_gap_rad(s, ref) <= MAX_ATTITUDE_RATE_RADPS * dt_s
        if trusted:
            self._last_trusted = s
        else:
            s = AttitudeSample(time_boot_ms, roll_rad, pitch_rad, yaw_rad, trusted=False)
            self.untrusted += 1
        samples = self._samples
        samples.append(s)
        while samples and samples[0].time_boot_ms < time_boot_ms - HISTORY_MS:
            samples.popleft()
        return trusted

    def at(self, time_boot_ms: int) -> AttitudeSample | None:
        """The attitude at `time_boot_ms` (see the module docstring), or None."""
        samples = self._samples
        if not samples:
            return None
        # newest first: the stamp asked for is nearly always among the last few
        after: AttitudeSample | None = None
        for s in reversed(samples):
            if s.time_boot_ms == time_boot_ms:
                return s
            if s.time_boot_ms < time_boot_ms:
                before = s
                break
            after = s
        else:
            before = None
        if before is not None and after is not None:
            gap = after.time_boot_ms - before.time_boot_ms
            if gap <= MAX_INTERPOLATION_GAP_MS:
                w = (time_boot_ms - before.time_boot_ms) / gap
                return AttitudeSample(
                    time_boot_ms,
                    wrap_pi(before.roll_rad + w * wrap_pi(after.roll_rad - before.roll_rad)),
                    before.pitch_rad + w * (after.pitch_rad - before.pitch_rad),
                    wrap_pi(before.yaw_rad + w * wrap_pi(after.yaw_rad - before.yaw_rad)),
                    trusted=before.trusted and after.trusted,
                )
        near = [s for s in (before, after) if s is not None]
        best = min(near, key=lambda s: abs(s.time_boot_ms - time_boot_ms))
        return best if abs(best.time_boot_ms - time_boot_ms) <= MATCH_TOLERANCE_MS else None


@dataclass(frozen=True, slots=True)
class Pairing:
    """One cycle's ranges and the attitude to turn them into points with.

    ranges_m: sensor-table order; NaN where a reading is missing, stale or not usable with
    `attitude` this cycle. attitude: the attitude at the ranges' time, or None when none
    matches (the caller uses its latest). unpaired: readings set to NaN here.
    untrusted: the cycle's attitude failed the rate gate (then every range is NaN)."""

    ranges_m: FloatArray
    attitude: AttitudeSample | None
    unpaired: int
    untrusted: bool


def pair_ranges(
    history: AttitudeHistory,
    ranges_m: FloatArray,
    stamps_ms: Sequence[int],
    latest: AttitudeSample | None,
) -> Pairing:
    """Pair one cycle's ranges with the attitude of their time.

    ranges_m: (n,) fresh ranges (NaN: missing or stale); stamps_ms: each reading's own
    `time_boot_ms` (0: not stamped). The cycle's time is the newest stamp among the fresh
    readings (the last burst), and its attitude the history's answer there. Then:

    - no stamped reading, or no attitude matches that time: the latest attitude (`latest`)
      is used, as nothing says it is wrong; its rate gate still applies;
    - the cycle's attitude is untrusted: no range is used this cycle (all NaN); the planner
      steps on what it remembers, and the next cycle pairs afresh;
    - a reading whose own time has an untrusted attitude, or one more than
      PAIR_TOLERANCE_RAD from the cycle's or whose point that moves more than
      PAIR_TOLERANCE_M (`off_pose`), is not used this cycle (NaN); a reading whose own
      time matches no attitude is used (nothing says its attitude differs).
    """
    r = np.array(ranges_m, dtype=np.float64)
    fresh = [i for i, v in enumerate(r.tolist()) if not math.isnan(v)]
    stamped = [stamps_ms[i] for i in fresh if stamps_ms[i] > 0]
    att = history.at(max(stamped)) if stamped else None
    if att is None:
        if latest is not None and not latest.trusted:
            r[:] = math.nan
            return Pairing(r, None, len(fresh), True)
        return Pairing(r, None, 0, False)
    if not att.trusted:
        r[:] = math.nan
        return Pairing(r, att, len(fresh), True)
    unpaired = 0
    cache: dict[int, AttitudeSample | None] = {}
    for i in fresh:
        stamp = stamps_ms[i]
        if stamp <= 0 or stamp == att.time_boot_ms:
            continue  # unstamped, or of the cycle's own time: paired with `att` itself
        if stamp not in cache:
            cache[stamp] = history.at(stamp)
        own = cache[stamp]
        if own is not None and (not own.trusted or off_pose(angle_gap_rad(own, att), r[i])):
            r[i] = math.nan
            unpaired += 1
    return Pairing(r, att, unpaired, False)


__all__ = [
    "MAX_ATTITUDE_RATE_RADPS",
    "PAIR_TOLERANCE_M",
    "PAIR_TOLERANCE_RAD",
    "AttitudeHistory",
    "AttitudeSample",
    "Pairing",
    "angle_gap_rad",
    "off_pose",
    "pair_ranges",
]
