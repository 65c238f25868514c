"""The live status line: its words, the terminal writer, systemd's STATUS= with the same text."""

from __future__ import annotations

import asyncio
import io
import logging
import socket
from pathlib import Path

import pytest

from companion.service import Service
from companion.service.entry import TerminalStatus, terminal_status
from companion.service.link import memory_pair
from companion.service.notify import SystemdNotifier
from companion.service.status import status_line
from tests.service_fakes import FakeAutopilot, PlannerBox, make_config

pytestmark = pytest.mark.timeout(60)

GUIDED = 4


async def until(pred: object, timeout: float = 20.0) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not pred():  # type: ignore[operator]
        if loop.time() > deadline:
            raise TimeoutError("condition not met")
        await asyncio.sleep(0.01)


async def test_status_line_words_sink_and_systemd_status(tmp_path: Path) -> None:
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as server:
        server.bind(path)
        server.setblocking(False)
        a, b = memory_pair()
        notifier = SystemdNotifier({"NOTIFY_SOCKET": path})
        svc = Service(make_config(), a, planner_factory=PlannerBox(), notifier=notifier)
        lines: list[str] = []
        svc.status_sink = lines.append
        ap = FakeAutopilot(b, ranges_cm={0: 800, 1: 650, 2: 700})
        task = asyncio.create_task(svc.run())
        await ap.start()
        try:
            await until(lambda: svc.status().configured)
            ap.set_mode(GUIDED)
            await ap.wait_for(lambda: len(ap.setpoints()) >= 5)
            await until(lambda: any("engaged" in s for s in lines))  # housekeeping, ~1 s
            text = status_line(svc.status())
            assert text.startswith("mode GUIDED | engaged | ")
            assert "nearest 6.5 m" in text and "H_d " in text and "v " in text
            assert "decision -" not in text  # the planner has decided something
            datagrams = []
            while True:
                try:
                    datagrams.append(server.recv(4096).decode())
                except BlockingIOError:
                    break
            statuses = [d for d in datagrams if d.startswith("STATUS=mode ")]
            assert statuses, datagrams
            assert any(s[len("STATUS=") :] in lines for s in statuses)
        finally:
            svc.stop()
            assert await asyncio.wait_for(task, 10) == 0
            await ap.stop()


def test_status_line_before_an_autopilot() -> None:
    svc = Service(make_config(), memory_pair()[0], notifier=SystemdNotifier({}))
    assert status_line(svc.status()) == "waiting for autopilot heartbeat"


def test_terminal_status_rewrites_in_place_and_yields_to_log_lines() -> None:
    out = io.StringIO()
    st = TerminalStatus(out, width=20)
    st("mode GUIDED | engaged | flying")
    assert out.getvalue() == "\r\x1b[Kmode GUIDED | engag"  # cut to the width
    rec = logging.LogRecord("x", logging.INFO, "f", 1, "msg", None, None)
    assert st.filter(rec)
    assert out.getvalue().endswith("\r\x1b[K") and not st.showing
    st("again")
    st.close()
    assert out.getvalue().endswith("again\n")


def test_no_terminal_status_when_quiet_or_not_a_terminal() -> None:
    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    assert terminal_status(False, io.StringIO()) is None
    assert terminal_status(True, Tty()) is None
    assert isinstance(terminal_status(False, Tty()), TerminalStatus)
