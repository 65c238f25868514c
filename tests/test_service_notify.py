"""sd_notify datagrams and the signing key/state files."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from companion.service.notify import SystemdNotifier
from companion.service.signing import (
    RESUME_MARGIN_TICKS,
    SigningKeyError,
    SigningState,
    load_key,
    timestamp_now,
)


def test_notify_sends_datagrams_to_notify_socket(tmp_path: Path) -> None:
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as server:
        server.bind(path)
        n = SystemdNotifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "4000000"})
        assert n.enabled and n.watchdog_interval_s == 2.0
        assert n.ready("waiting")
        assert server.recv(100) == b"READY=1\nSTATUS=waiting"
        assert n.watchdog()
        assert server.recv(100) == b"WATCHDOG=1"


def test_notify_disabled_without_socket_and_other_pid() -> None:
    n = SystemdNotifier({})
    assert not n.enabled and not n.ready()
    n = SystemdNotifier(
        {"NOTIFY_SOCKET": "@x", "WATCHDOG_USEC": "1000", "WATCHDOG_PID": str(os.getpid() + 1)}
    )
    assert n.watchdog_interval_s is None


def test_key_file_hex_raw_and_bad(tmp_path: Path) -> None:
    f = tmp_path / "key"
    f.write_text(bytes(range(32)).hex() + "\n")
    assert load_key(f) == bytes(range(32))
    f.write_bytes(bytes(range(32)))
    assert load_key(f) == bytes(range(32))
    f.write_text("short")
    with pytest.raises(SigningKeyError, match="found 5 bytes"):
        load_key(f)
    with pytest.raises(SigningKeyError, match="cannot read"):
        load_key(tmp_path / "none")


def test_signing_timestamp_persists_and_never_goes_back(tmp_path: Path) -> None:
    state = SigningState(tmp_path / "s.json")
    assert state.load() == 0
    future = timestamp_now() + 10**9  # a clock that later goes back (no RTC)
    state.save(future)
    assert state.initial_timestamp() == future + RESUME_MARGIN_TICKS
    (tmp_path / "s.json").write_text("garbage")
    assert state.load() == 0
    assert SigningState(None).initial_timestamp(1420070400 + 1.0) == 100_000
