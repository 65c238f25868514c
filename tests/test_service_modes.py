"""Mode decoding, ownership, failsafe verdicts, identity and status texts."""

from __future__ import annotations

import pytest

from companion.service.failsafe import Assessment, Failsafe, Limits, Verdict, assess
from companion.service.identity import Health, companion_system_id, heartbeat_message
from companion.service.modes import (
    AutopilotKind,
    Ownership,
    OwnState,
    VehicleMode,
    autopilot_kind,
    is_guided,
    mode_name,
    set_mode_params,
)
from companion.service.statustext import Severity, StatusTexts
from companion.service.telemetry import Telemetry
from tests.service_fakes import make_config

AP, PX4 = AutopilotKind.ARDUPILOT, AutopilotKind.PX4


def test_autopilot_kind_and_mode_names() -> None:
    assert autopilot_kind(3) is AP and autopilot_kind(12) is PX4 and autopilot_kind(8) is None
    assert mode_name(AP, 2, 1, 4) == "GUIDED" and mode_name(AP, 12, 1, 9) == "SURFACE"
    assert mode_name(PX4, 2, 1, 6 << 16) == "OFFBOARD"
    assert mode_name(PX4, 2, 1, (4 << 16) | (5 << 24)) == "AUTO.RTL"
    assert mode_name(AP, 2, 0, 4) == "BASE(0)"


def test_is_guided_needs_custom_mode_flag() -> None:
    assert is_guided(AP, 1, 4) and not is_guided(AP, 0, 4) and not is_guided(AP, 1, 5)
    assert is_guided(PX4, 1, 6 << 16) and not is_guided(PX4, 1, 4 << 16)


def test_set_mode_params() -> None:
    assert set_mode_params(AP, "guided") == (1.0, 4.0, 0.0)
    assert set_mode_params(PX4, "guided") == (1.0, 6.0, 0.0)
    assert set_mode_params(PX4, "land") == (1.0, 4.0, 6.0)
    assert set_mode_params(AP, "rtl") == (1.0, 6.0, 0.0)


def mode(guided: bool = True, armed: bool = True, high: bool = True) -> VehicleMode:
    return VehicleMode(guided, armed, high, "GUIDED" if guided else "LOITER")


def test_ownership_engage_release_reengage() -> None:
    o = Ownership(reengage=True)
    assert o.update(mode(high=False)) == ["waiting: too low to take over"]
    assert o.update(mode(high=False)) == []  # said once
    assert o.update(mode(), allow_engage=False) == [] and o.state is OwnState.WAITING
    assert o.update(mode()) == ["flying route"] and o.engaged
    assert o.update(mode(guided=False)) == ["LOITER: stopped commanding"]
    assert o.state is OwnState.RELEASED
    assert o.update(mode()) == ["re-engaged"]
    assert o.update(mode(armed=False)) == ["disarmed: stopped commanding"]
    o2 = Ownership(reengage=False)
    o2.update(mode())
    o2.update(mode(guided=False))
    assert o2.update(mode()) == [] and o2.state is OwnState.RELEASED


def test_failsafe_verdicts_and_hysteresis() -> None:
    from tests.test_service_telemetry import att, dist, pos

    t = Telemetry(make_config().sensor_table())
    limits = Limits(1.0, 0.5, 0.5, 0.5)
    assert assess(0.0, t, limits, [0, 1, 2]).reason == "autopilot heartbeat lost"
    from companion.service.codec import mavlink2

    t.update(mavlink2.MAVLink_heartbeat_message(2, 3, 1, 4, 4, 3), 0.0)
    assert assess(0.0, t, limits, [0, 1, 2]).reason == "no home position"
    t.update(
        mavlink2.MAVLink_home_position_message(
            473977420, 85455940, 488000, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0
        ),
        0.0,
    )
    t.update(pos(10), 0.0)
    assert assess(0.0, t, limits, [0, 1, 2]) == Assessment(Verdict.HOLD, "attitude stale")
    t.update(att(10), 0.0)
    for sid in (0, 1):
        t.update(dist(10, sid, 300, orientation=(0, 39)[sid]), 0.0)
    a = assess(0.1, t, limits, [0, 1, 2])
    assert a == Assessment(Verdict.HOLD, "sensor 2 (h2) stale")
    assert assess(0.1, t, limits, [0, 1]).verdict is Verdict.RUN  # 2 optional
    assert assess(0.6, t, limits, [0, 1]).reason == "position stale"

    f = Failsafe(resume_after_s=1.0)
    hold = Assessment(Verdict.HOLD, "x stale")
    ok = Assessment(Verdict.RUN)
    assert f.update(0.0, hold) == (hold, ["HOLD: x stale"])
    assert f.update(0.1, hold) == (hold, [])
    assert f.update(0.2, ok) == (hold, [])
    assert f.update(1.0, ok) == (hold, [])
    assert f.update(1.2, ok) == (ok, ["resumed after x stale"])


def test_identity() -> None:
    hb = heartbeat_message(Health.CRITICAL)
    assert (hb.type, hb.autopilot, hb.system_status) == (18, 8, 5)
    assert companion_system_id("auto", 3) == 3 and companion_system_id(42, 3) == 42
    assert companion_system_id("auto", None) == 1
    with pytest.raises(ValueError):
        companion_system_id("auto", 255)


def test_statustext_rate_limit_and_repeats() -> None:
    s = StatusTexts(max_per_s=2.0, burst=2, repeat_interval_s=5.0)
    for i in range(5):
        s.post(0.0, f"msg {i}", Severity.NOTICE)
    s.post(0.0, "msg 0")
    assert [t for _, t in s.drain(0.0)] == ["msg 0", "msg 1"]
    assert [t for _, t in s.drain(0.5)] == ["msg 2"]
    assert [t for _, t in s.drain(2.0)] == ["msg 3", "msg 4"]
    s.post(2.5, "msg 0")  # repeated within 5 s of sending
    assert s.drain(10.0) == [] and s.suppressed == 2
