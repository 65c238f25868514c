"""Problem counters in the log: a steady harmless stream is said once, then only counted."""

from __future__ import annotations

import logging

import pytest

from companion.service.counters import ProblemReporter


@pytest.mark.parametrize("steady", ["conn.other_component", "codec.unknown_msgid"])
def test_steady_streams_warned_once_then_debug(
    steady: str, caplog: pytest.LogCaptureFixture
) -> None:
    rep = ProblemReporter()
    caplog.set_level(logging.DEBUG, logger="companion.service")
    for total in (5, 60, 120):
        rep.report({steady: total, "link.send_dropped": total // 5})
    other = [r for r in caplog.records if r.getMessage().startswith(steady)]
    drops = [r for r in caplog.records if r.getMessage().startswith("link.send_dropped")]
    assert [r.levelno for r in other] == [logging.WARNING, logging.DEBUG, logging.DEBUG]
    assert other[1].getMessage() == f"{steady}: +55 (total 60)"
    # a real problem keeps warning every time it grows
    assert [r.levelno for r in drops] == [logging.WARNING] * 3


def test_no_growth_no_line(caplog: pytest.LogCaptureFixture) -> None:
    rep = ProblemReporter()
    caplog.set_level(logging.DEBUG, logger="companion.service")
    rep.report({"conn.other_component": 0, "link.send_no_peer": 3, "service.cycles": 9})
    rep.report({"conn.other_component": 0, "link.send_no_peer": 4, "service.cycles": 19})
    assert caplog.records == []
