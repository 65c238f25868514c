"""Ranges paired with the attitude of their own time (`companion.service.pairing`).

The cycle test reproduces what stalled the copter on smooth-hill: a one-cycle pitch jump whose
ATTITUDE was paired with ranges measured level (the median filter's older readings), giving
the planner points that no sensor saw. Manual clock, no link, no sleeps.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.planner.frames import attitude_enu_to_ned
from companion.service.pairing import (
    MAX_ATTITUDE_RATE_RADPS,
    PAIR_TOLERANCE_M,
    PAIR_TOLERANCE_RAD,
    AttitudeHistory,
    off_pose,
    pair_ranges,
)
from tests.test_service_cycle import GUIDED, PERIOD_S, rig

LEVEL_CM = {0: 0, 1: 700, 2: 700}
PITCHED_CM = {0: 0, 1: 300, 2: 450}
"""What the sensors measure while the nose is up: other ranges than level."""


def test_a_pitch_jump_is_never_paired_with_ranges_measured_level() -> None:
    r = rig()  # range_median_samples: the default 3
    r.ap.custom_mode = GUIDED
    measured: list[tuple[float, dict[int, int]]] = []  # (pitch NED, ranges cm) per tick

    def tick(pitch: float, ranges_cm: dict[int, int]) -> None:
        r.ap.pitch, r.ap.ranges_cm = pitch, dict(ranges_cm)
        measured.append((pitch, dict(ranges_cm)))
        r.run(PERIOD_S)

    for _ in range(20):
        tick(0.0, LEVEL_CM)
    # the ideal tracker at take-over: atan2(vz, vh) with vh just above its threshold
    tick(1.133, PITCHED_CM)
    for _ in range(3):
        tick(0.0, LEVEL_CM)
    (planner,) = r.box.made
    assert len(planner.inputs) == 24
    ids = sorted(LEVEL_CM)
    for state, ranges, _dt in planner.inputs:
        _, pitch_ned, _ = attitude_enu_to_ned(state.roll_rad, state.pitch_rad, state.yaw_rad)
        for i, sid in enumerate(ids):
            if math.isnan(ranges[i]) or ranges[i] == 0.0:
                continue
            # this value, at this attitude, was measured by this sensor at some tick
            assert any(
                abs(p - pitch_ned) <= PAIR_TOLERANCE_RAD and cm[sid] * 0.01 == ranges[i]
                for p, cm in measured
            ), (pitch_ned, sid, ranges[i])
    # the jump was not trusted (22 rad/s), and the cycles after it dropped what did not pair
    assert r.host.tel.counters["attitude_rate_untrusted"] == 1
    assert r.host.tel.counters["cycle_attitude_untrusted"] == 1
    assert r.cycle.last_kind == "planner"  # flying on: no hold for a skipped reading


def test_steady_flight_uses_every_reading() -> None:
    r = rig()
    r.ap.custom_mode = GUIDED
    r.run(1.0)
    (planner,) = r.box.made
    for _, ranges, _ in planner.inputs:
        np.testing.assert_array_equal(ranges, [0.0, 7.0, 7.0])
    assert r.host.tel.counters["range_unpaired"] == 0


def _history(*samples: tuple[int, float]) -> AttitudeHistory:
    h = AttitudeHistory()
    for t, pitch in samples:
        h.add(t, 0.0, pitch, 0.0)
    return h


def test_attitude_at_a_stamp_exact_interpolated_nearest_or_none() -> None:
    h = _history((1000, 0.0), (1100, 0.2), (1400, 0.3))
    exact = h.at(1100)
    assert exact is not None and exact.pitch_rad == 0.2
    mid = h.at(1050)
    assert mid is not None and mid.pitch_rad == pytest.approx(0.1)
    # a 300 ms gap is not interpolated: the nearest within 60 ms, else none
    near = h.at(1150)
    assert near is not None and near.pitch_rad == 0.2
    assert h.at(1250) is None
    assert h.at(900) is None and h.at(1500) is None


def test_yaw_interpolates_across_pi() -> None:
    h = AttitudeHistory()
    h.add(1000, 0.0, 0.0, math.pi - 0.05)
    h.add(1020, 0.0, 0.0, -math.pi + 0.05)
    a = h.at(1010)
    assert a is not None and abs(abs(a.yaw_rad) - math.pi) < 1e-9


def test_the_rate_gate_distrusts_a_jump_and_trusts_again_when_time_allows_it() -> None:
    h = AttitudeHistory()
    assert h.add(1000, 0.0, 0.0, 0.0)
    assert not h.add(1050, 0.0, 1.133, 0.0)  # 22.7 rad/s
    assert h.add(1100, 0.0, 0.2, 0.0)  # against the last trusted: 2 rad/s
    # a real, lasting change: trusted once its rate from the last trusted is possible
    h2 = AttitudeHistory()
    h2.add(1000, 0.0, 0.0, 0.0)
    jump = 1.0
    first_ok = math.ceil(jump / MAX_ATTITUDE_RATE_RADPS * 1000 / 10) * 10
    trusted = [h2.add(1000 + dt, 0.0, jump, 0.0) for dt in range(10, 200, 10)]
    assert trusted.index(True) == first_ok // 10 - 1
    assert h.untrusted == 1


def test_pair_ranges_drops_readings_of_another_attitude_and_keeps_unmatched_ones() -> None:
    h = _history((1000, 0.0), (1050, 0.3), (1100, 0.31))
    ranges = np.array([5.0, 6.0, 7.0, math.nan])
    # sensor 0 measured at 1000 (pitch 0), 1 at 1100, 2 unstamped, 3 stale
    p = pair_ranges(h, ranges, [1000, 1100, 0, 1100], h.at(1100))
    assert p.attitude is not None and p.attitude.pitch_rad == 0.31
    assert math.isnan(p.ranges_m[0]) and p.ranges_m[1] == 6.0 and p.ranges_m[2] == 7.0
    assert p.unpaired == 1 and not p.untrusted
    # nothing stamped: the latest attitude, every reading
    p = pair_ranges(h, ranges, [0, 0, 0, 0], h.at(1100))
    assert p.attitude is None and p.unpaired == 0
    np.testing.assert_array_equal(p.ranges_m[:3], ranges[:3])


def test_a_small_attitude_gap_drops_a_far_reading_and_keeps_a_near_one() -> None:
    """0.03 rad is within PAIR_TOLERANCE_RAD, but at 6 m it moves the point 0.18 m, past
    PAIR_TOLERANCE_M; at 2 m (0.06 m) the reading is used, and "nothing" (0) is judged
    by the angle alone."""
    gap = 0.03
    assert gap < PAIR_TOLERANCE_RAD and 2.0 * gap < PAIR_TOLERANCE_M < 6.0 * gap
    h = _history((1000, 0.0), (1050, gap))
    ranges = np.array([6.0, 2.0, 0.0, 6.0])
    p = pair_ranges(h, ranges, [1000, 1000, 1000, 1050], h.at(1050))
    assert math.isnan(p.ranges_m[0]) and p.unpaired == 1
    np.testing.assert_array_equal(p.ranges_m[1:], ranges[1:])
    gaps = np.array([0.0, gap, gap, gap, 0.06, math.nan])
    np.testing.assert_array_equal(
        off_pose(gaps, np.array([6.0, 6.0, 2.0, math.inf, 1.0, 6.0])),
        [False, True, False, False, True, False],
    )


def test_an_untrusted_cycle_attitude_uses_no_range() -> None:
    h = _history((1000, 0.0), (1050, 1.2))
    p = pair_ranges(h, np.array([5.0, 6.0]), [1050, 1050], h.at(1050))
    assert p.untrusted and np.all(np.isnan(p.ranges_m))
