"""Bad message fields while the service is flying: each one rejected or made harmless,
counted, logged, and nothing unsafe commanded.

The service flies (GUIDED, a fake planner) against the fake autopilot over an in-memory link;
each case injects bad messages between the autopilot's good ones. Then: the service is still
running and commanding, the counter named in the case went up, a log line names it, every
setpoint sent is finite and near the vehicle, and the planner was never given a non-finite
state or a range outside [0, max). Values: NaN/inf in ATTITUDE, positions at and beyond the
int32 limits, distances 0, below min, above max and 65535, orientations not in the sensor
table, duplicated sensor ids, time_boot_ms going backwards a little (reordered) and a lot
(a forged reboot), far in the future, other system and component ids.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import AsyncIterator, Callable
from typing import Any

import numpy as np
import pytest

from companion.config import FailsafeConfig
from companion.service import Service, memory_pair
from companion.service.codec import MavCodec, mavlink2
from companion.service.identity import Health
from companion.service.notify import SystemdNotifier
from companion.service.telemetry import Telemetry
from tests.service_fakes import HOME, FakeAutopilot, FakePlanner, PlannerBox, enu_of, make_config

pytestmark = pytest.mark.timeout(30)

GUIDED = 4
LOITER = 5
M = mavlink2
INT32_MAX = 2**31 - 1


async def until(pred: Callable[[], bool], timeout: float = 5.0) -> None:
    deadline = asyncio.get_running_loop().time() + timeout
    while not pred():
        if asyncio.get_running_loop().time() > deadline:
            raise TimeoutError("condition not met")
        await asyncio.sleep(0.01)


@contextlib.asynccontextmanager
async def flying(**cfg: Any) -> AsyncIterator[tuple[Service, FakeAutopilot, PlannerBox]]:
    a, b = memory_pair()
    box = PlannerBox()
    svc = Service(make_config(**cfg), a, planner_factory=box, notifier=SystemdNotifier({}))
    ap = FakeAutopilot(b, ranges_cm={0: 800, 1: 700, 2: 700})  # no "nothing" readings
    ap._boot -= 30.0  # up for 30 s already: time_boot_ms can go back 10 s
    task = asyncio.create_task(svc.run())
    await ap.start()
    try:
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 5)
        yield svc, ap, box
        assert not task.done(), "the service stopped"
    finally:
        svc.stop()
        rc = await asyncio.wait_for(task, 5)
        await ap.stop()
        assert rc == 0


def att(tb: int, r: float = 0.0, p: float = 0.0, y: float = 0.0) -> Any:
    return M.MAVLink_attitude_message(tb, r, p, y, 0.0, 0.0, 0.0)


def gpi(tb: int, lat: int, lon: int, alt_mm: int, rel_mm: int = 5000) -> Any:
    return M.MAVLink_global_position_int_message(tb, lat, lon, alt_mm, rel_mm, 0, 0, 0, 0)


def dist(tb: int, sid: int, cm: int, orientation: int | None = None, q: Any = None) -> Any:
    orient = {0: 0, 1: 39, 2: 100}.get(sid, 0) if orientation is None else orientation
    return M.MAVLink_distance_sensor_message(
        tb, 10, 1000, cm, 0, sid, orient, 0, 0.0, 0.0, q or [0.0, 0.0, 0.0, 0.0]
    )


LAT, LON = round(HOME[0] * 1e7), round(HOME[1] * 1e7)
NAN, INF = math.nan, math.inf

# (case id, builder(ap, tb) -> messages, counter that must go up, text the log must show)
CASES: list[tuple[str, Callable[[FakeAutopilot, int], list[Any]], str, str]] = [
    ("attitude_nan", lambda ap, tb: [att(tb, r=NAN)], "input.rejected_attitude_nonfinite", ""),
    ("attitude_inf", lambda ap, tb: [att(tb, y=INF)], "input.rejected_attitude_nonfinite", ""),
    (
        "attitude_all_nan",
        lambda ap, tb: [att(tb, NAN, NAN, NAN)],
        "input.rejected_attitude_nonfinite",
        "",
    ),
    ("attitude_range", lambda ap, tb: [att(tb, p=3.0)], "input.rejected_attitude_range", ""),
    (
        "position_lat_out_of_range",
        lambda ap, tb: [gpi(tb, INT32_MAX, LON, 493_000)],
        "input.rejected_position_range",
        "",
    ),
    (
        "position_zero_zero",
        lambda ap, tb: [gpi(tb, 0, 0, 493_000)],
        "input.rejected_position_range",
        "",
    ),
    (
        "position_alt_extreme",
        lambda ap, tb: [gpi(tb, LAT, LON, -INT32_MAX - 1, INT32_MAX)],
        "input.rejected_position_range",
        "",
    ),
    (
        "home_zero",
        lambda ap, tb: [
            M.MAVLink_home_position_message(0, 0, 0, NAN, INF, NAN, [NAN] * 4, 0, 0, 0)
        ],
        "input.rejected_home_range",
        "",
    ),
    ("distance_0", lambda ap, tb: [dist(tb, 1, 0)], "input.range_none", "sensor 1: 0 cm"),
    (
        "distance_65535",
        lambda ap, tb: [dist(tb, 1, 65535)],
        "input.range_none",
        "sensor 1: 65535 cm",
    ),
    (
        "distance_below_min",
        lambda ap, tb: [dist(tb, 1, 5)],
        "input.range_below_min",
        "sensor 1: 5 cm",
    ),
    (
        "distance_above_max",
        lambda ap, tb: [dist(tb, 1, 5000)],
        "input.range_at_max",
        "sensor 1: 5000 cm",
    ),
    (
        "orientation_not_in_table",
        lambda ap, tb: [dist(tb, 1, 300, orientation=77)],
        "input.rejected_sensor_orientation_unknown",
        "orientation 77",
    ),
    (
        "orientation_mismatch",
        lambda ap, tb: [dist(tb, 1, 300, orientation=25)],
        "input.rejected_sensor_orientation_mismatch",
        "orientation 25",
    ),
    (
        "custom_orientation_nan_quaternion",
        lambda ap, tb: [dist(tb, 2, 300, q=[NAN, NAN, NAN, NAN])],
        "input.sensor_orientation_unverified",
        "",
    ),
    (
        "unknown_sensor_id",
        lambda ap, tb: [dist(tb, 42, 300)],
        "input.rejected_sensor_unknown_id",
        "id 42",
    ),
    (
        "duplicated_sensor_id",  # two sensors report as id 1 at the same instant
        lambda ap, tb: [dist(tb + 1, 1, 300), dist(tb + 1, 1, 250)],
        "input.duplicate",
        "",
    ),
    (
        "duplicated_id_other_orientation",  # a second sensor on id 1, pointing elsewhere
        lambda ap, tb: [dist(tb + 1, 1, 300, orientation=24)],
        "input.rejected_sensor_orientation_mismatch",
        "",
    ),
    (
        "time_boot_back_a_little",
        lambda ap, tb: [att(max(tb - 500, 1))],
        "input.out_of_order",
        "",
    ),
    (
        "time_boot_back_a_lot",  # a reboot? not while the old clock's messages go on
        lambda ap, tb: [att(max(tb - 10_000, 1)), gpi(max(tb - 10_000, 1), LAT, LON, 493_000)],
        "input.time_boot_suspect",
        "ATTITUDE back",
    ),
    (
        "time_boot_far_future",  # one forged stamp: dropped, does not poison the ordering
        lambda ap, tb: [att(0xFFFFFFF0)],
        "input.time_boot_suspect",
        "ATTITUDE ahead",
    ),
]


@pytest.mark.parametrize(
    ("build", "counter", "text"), [c[1:] for c in CASES], ids=[c[0] for c in CASES]
)
async def test_bad_field_counted_logged_and_harmless(
    build: Callable[[FakeAutopilot, int], list[Any]],
    counter: str,
    text: str,
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="companion")
    async with flying() as (svc, ap, box):
        before = svc.counter_values().get(counter, 0)
        n_sp = len(ap.setpoints())
        for _ in range(3):
            for msg in build(ap, ap.time_boot_ms()):
                ap.send(msg)
            await asyncio.sleep(0.05)
        await until(lambda: svc.counter_values().get(counter, 0) > before, 2.0)
        await ap.wait_for(lambda: len(ap.setpoints()) >= n_sp + 5, 5.0)  # still commanding
        assert svc.status().health in (Health.ACTIVE, Health.CRITICAL, Health.EMERGENCY)
        name = counter.split(".", 1)[1]
        assert f"{counter.split('.')[0]}.{name}" in caplog.text or name in caplog.text
        if text:
            assert text in caplog.text
        assert_nothing_unsafe(svc, ap, box)


def assert_nothing_unsafe(svc: Service, ap: FakeAutopilot, box: PlannerBox) -> None:
    for r in ap.setpoints():
        m = r.msg
        assert all(math.isfinite(v) for v in (m.alt, m.vx, m.vy, m.vz, m.yaw))
        east, north = enu_of(m)
        assert math.hypot(east, north) < 50.0  # near home, where the fake vehicle is
        assert -10.0 < m.alt < 60.0
    table = svc.sensors
    for planner in box.made:
        for state, ranges, dt in planner.inputs:
            assert np.all(np.isfinite(state.position_enu))
            assert all(math.isfinite(v) for v in (state.roll_rad, state.pitch_rad, state.yaw_rad))
            assert math.isfinite(dt) and dt >= 0
            ok = np.isnan(ranges) | ((ranges >= 0) & (ranges < table.max_range_m))
            assert ok.all(), ranges


async def test_other_system_and_component_ignored_logged_and_harmless(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="companion")
    async with flying() as (svc, ap, box):
        for src in ((7, 1), (1, 50), (255, 190)):
            other = MavCodec(*src)
            for msg in (
                M.MAVLink_heartbeat_message(2, 3, 129, LOITER, 4, 3),  # "switch to LOITER"
                att(ap.time_boot_ms(), r=1.0),
                dist(ap.time_boot_ms(), 0, 50),  # "an obstacle 0.5 m ahead"
                M.MAVLink_command_long_message(1, 191, 400, 0, 0, 0, 0, 0, 0, 0, 0),
            ):
                ap.link.send(other.encode(msg))
        n = len(ap.setpoints())
        await ap.wait_for(lambda: len(ap.setpoints()) >= n + 5)
        c = svc.counter_values()
        assert c["conn.other_system"] >= 8 and c["conn.other_component"] >= 4
        assert svc.status().owner == "engaged"  # the foreign LOITER heartbeats changed nothing
        assert "conn.other_system" in caplog.text and "from 7/1" in caplog.text
        assert "conn.other_component" in caplog.text and "from 1/50" in caplog.text
        assert svc.tel.attitude is not None and svc.tel.attitude.roll_rad == 0.0
        assert_nothing_unsafe(svc, ap, box)


class NanPlanner(FakePlanner):
    """A planner bug: a NaN setpoint after a few good ones."""

    def step(self, state: Any, ranges_m: Any, dt_s: float) -> Any:
        result = super().step(state, ranges_m, dt_s)
        if len(self.inputs) > 5:
            result.setpoint.position_enu[:] = math.nan
        return result


async def test_non_finite_planner_setpoint_never_sent_holds_instead(
    caplog: pytest.LogCaptureFixture,
) -> None:
    a, b = memory_pair()
    svc = Service(make_config(), a, planner_factory=NanPlanner, notifier=SystemdNotifier({}))
    ap = FakeAutopilot(b)
    task = asyncio.create_task(svc.run())
    await ap.start()
    try:
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await until(lambda: svc.counters["planner_errors"] >= 3)
        n = len(ap.setpoints())
        await ap.wait_for(lambda: len(ap.setpoints()) >= n + 3)  # hold setpoints go on
        assert svc.status().health is Health.CRITICAL
        assert not task.done()
        for r in ap.setpoints():
            assert math.isfinite(r.msg.lat_int) and math.isfinite(r.msg.alt)
        assert "planner step failed" in caplog.text
    finally:
        svc.stop()
        assert await asyncio.wait_for(task, 5) == 0
        await ap.stop()


# --- the telemetry rules behind the cases, without a loop ---------------------------------


def tel(**kw: Any) -> Telemetry:
    return Telemetry(make_config().sensor_table(), **kw)


def pos(tb: int, east_m: float, vel_east_cms: int = 0) -> Any:
    lon = HOME[1] + math.degrees(east_m / (6_371_000.0 * math.cos(math.radians(HOME[0]))))
    return M.MAVLink_global_position_int_message(
        tb, LAT, round(lon * 1e7), 493_000, 5000, 0, vel_east_cms, 0, 0
    )


def test_jump_judged_against_reported_velocity() -> None:
    t = tel(max_jump_m=2.0, jump_accept_s=1.0)
    assert t.update(pos(1000, 0.0, 500), 1.0)
    assert t.update(pos(1100, 0.5, 500), 1.1)  # 5 m/s as reported: fine
    assert not t.update(pos(1200, 4.0, 500), 1.2)  # 3 m further than the velocity says
    assert t.counters["rejected_position_jump"] == 1
    # rejected samples do not widen the allowance: still a jump 0.7 s later
    assert not t.update(pos(1900, 4.0 + 3.5, 500), 1.9)
    assert t.update(pos(2300, 4.0 + 5.5, 500), 2.3)  # persisted 1.1 s: accepted
    assert t.counters["position_jump_accepted"] == 1 and t.jumps_accepted == 1


def test_median_filter_removes_single_spikes_and_dropouts() -> None:
    t = tel(median_samples=3)
    readings = [300, 300, 40, 300, 300, 0, 300, 300, 250, 250, 250]
    seen = []
    for i, cm in enumerate(readings):
        t.update(dist(1000 + 20 * i, 1, cm), 1.0 + 0.02 * i)
        seen.append(t.ranges[0 + 1].distance_m)  # sensor id 1 is index 1
    assert 0.4 not in seen and 0.0 not in seen[2:]  # the spike and the dropout never show
    assert seen[-1] == 2.5  # a real change comes through one reading later
    assert t.counters["range_filtered"] >= 2


def test_spike_filter_passes_noise_and_steady_change_at_once() -> None:
    """With spike_m (the configured default), a reading within it of the median of the last
    3 passes as it is, with its own stamp (its attitude is that time's); a spike, a
    dropout to "nothing" and the first reading of a step are replaced by the median."""
    t = tel(median_samples=3, spike_m=FailsafeConfig().range_spike_m)
    readings = [300, 300, 40, 300, 310, 330, 0, 320, 250, 250, 251]
    seen, stamps = [], []
    for i, cm in enumerate(readings):
        t.update(dist(1000 + 20 * i, 1, cm), 1.0 + 0.02 * i)
        seen.append(t.ranges[1].distance_m)
        stamps.append(t.ranges[1].time_boot_ms)
    assert seen == pytest.approx([3.0, 3.0, 3.0, 3.0, 3.1, 3.3, 3.3, 3.2, 3.2, 2.5, 2.51])
    # passed readings carry their own stamp; a replaced one, the median's
    assert stamps[4:6] == [1080, 1100] and stamps[6] == 1100 and stamps[8] == 1140
    assert t.counters["range_filtered"] == 3
