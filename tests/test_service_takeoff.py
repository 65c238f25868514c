"""When auto start's take-off counts as done (`companion.service.supervisor.TakeoffWatch`)."""

from __future__ import annotations

from companion.service.supervisor import TAKEOFF_STILL_S, TakeoffWatch


def test_done_within_0_1_m_of_the_altitude_at_once() -> None:
    w = TakeoffWatch(9.0)
    assert not w.done(8.85, -0.3, 0.0)
    assert w.done(8.95, -0.2, 0.1)


def test_short_of_it_only_once_the_climb_has_stopped() -> None:
    """90 % of the altitude while still climbing is not done (handing over there started the
    route 0.9 m low on a 9 m take-off); an autopilot that stops 0.5 m short is not waited on
    until the timeout: done after TAKEOFF_STILL_S still."""
    w = TakeoffWatch(9.0)
    assert not w.done(8.2, -0.6, 0.0)  # above 90 %, climbing
    t = 1.0
    assert not w.done(8.5, -0.05, t)  # stopped 0.5 m short: the clock starts
    assert not w.done(8.5, 0.02, t + 0.5 * TAKEOFF_STILL_S)
    assert not w.done(8.5, -0.3, t + 0.9 * TAKEOFF_STILL_S)  # moving again: starts over
    assert not w.done(8.5, 0.0, t + 1.5 * TAKEOFF_STILL_S)
    assert w.done(8.5, 0.0, t + 2.5 * TAKEOFF_STILL_S)


def test_never_below_90_percent() -> None:
    w = TakeoffWatch(9.0)
    assert not any(w.done(7.9, 0.0, float(t)) for t in range(30))
