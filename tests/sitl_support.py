"""Helpers for the tests that fly the real ArduCopter SITL (`pytest -m sitl`).

Each SITL gets its own instance number (TCP ports 5762/5763 + 10 I) and UDP port, chosen
free at the time, so several test runs can share a machine.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sim.sitl import Sitl, find_sitl, free_udp_port

LAUNCHER = find_sitl()
SKIP_REASON = (
    "no ArduCopter SITL at ../shared/sitl/arducopter next to the repository "
    "(the sitl tests fly the real autopilot)"
)
needs_sitl = pytest.mark.skipif(LAUNCHER is None, reason=SKIP_REASON)

_instances = itertools.count(20 + (os.getpid() % 8) * 8)
_lock = threading.Lock()


def _tcp_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def next_instance() -> int:
    """A SITL instance number whose TCP ports are free now (20..99)."""
    with _lock:
        for _ in range(80):
            i = 20 + (next(_instances) - 20) % 80
            if all(_tcp_free(5760 + 10 * i + k) for k in range(4)):
                return i
    raise RuntimeError("no free SITL instance")


@contextlib.contextmanager
def running_sitl(
    tmp: Path,
    params: dict[str, float] | None = None,
    fast_ekf: bool = True,
    speedup: float = 1.0,
) -> Iterator[Sitl]:
    """A started SITL whose heartbeat has been seen; killed (process group) on exit."""
    if LAUNCHER is None:
        pytest.skip(SKIP_REASON)
    sitl = Sitl(
        LAUNCHER,
        next_instance(),
        free_udp_port(),
        speedup=speedup,
        fast_ekf=fast_ekf,
        params=params or {},
        workdir=tmp / "sitl",
    )
    try:
        sitl.start()
        sitl.wait_heartbeat(60.0)
        yield sitl
    finally:
        sitl.stop()


def gcs_connect(sitl: Sitl, timeout_s: float = 20.0) -> Any:
    """A ground station (system 255) on SITL's SERIAL1 TCP port, heartbeat seen."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            conn = mavutil.mavlink_connection(
                f"tcp:127.0.0.1:{sitl.gcs_port}",
                source_system=255,
                source_component=mavlink.MAV_COMP_ID_MISSIONPLANNER,
                autoreconnect=False,
            )
            break
        except OSError:
            if time.monotonic() >= deadline:
                raise
            time.sleep(0.2)
    conn.wait_heartbeat(timeout=timeout_s)
    return conn


def gcs_command(conn: Any, command: int, *params: float, timeout_s: float = 5.0) -> int:
    """COMMAND_LONG to the autopilot; the COMMAND_ACK result (-1 without one)."""
    p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
    conn.mav.command_long_send(1, 1, command, 0, *p)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        ack = conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.5)
        if ack is not None and ack.command == command:
            return int(ack.result)
    return -1
