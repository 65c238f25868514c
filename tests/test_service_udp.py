"""The service over real sockets on 127.0.0.1 against a fake autopilot (pymavlink codec)."""

from __future__ import annotations

import asyncio
import contextlib
import socket
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.config import ServiceConfig
from companion.service import Service
from companion.service.codec import MavCodec, mavlink2
from companion.service.identity import Health
from companion.service.link import (
    MAX_DATAGRAM_BYTES,
    Link,
    Receiver,
    TcpLink,
    UdpInLink,
    UdpOutLink,
)
from companion.service.notify import SystemdNotifier
from tests.service_fakes import FakeAutopilot, PlannerBox, make_config

pytestmark = pytest.mark.timeout(20)

GUIDED = 4
LOITER = 5
KEY = bytes(range(32))


async def until(pred: Any, timeout: float = 5.0) -> None:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while not pred():
        if loop.time() > deadline:
            raise TimeoutError("condition not met")
        await asyncio.sleep(0.01)


@contextlib.asynccontextmanager
async def over_udp(
    cfg: ServiceConfig | None = None, **ap_kwargs: Any
) -> AsyncIterator[tuple[Service, FakeAutopilot, PlannerBox]]:
    link = UdpInLink("127.0.0.1", 0)
    box = PlannerBox()
    svc = Service(cfg or make_config(), link, planner_factory=box, notifier=SystemdNotifier({}))
    task = asyncio.create_task(svc.run())
    await until(lambda: link.is_open)
    host, port = link.local_address
    ap = FakeAutopilot(UdpOutLink(host, port), **ap_kwargs)
    await ap.start()
    try:
        yield svc, ap, box
    finally:
        svc.stop()
        assert await asyncio.wait_for(task, 5) == 0
        await ap.stop()


async def test_udp_detect_configure_engage_and_mode_change() -> None:
    async with over_udp() as (svc, ap, _):
        await until(lambda: svc.status().configured)
        assert svc.status().autopilot is not None and svc.status().autopilot.value == "ardupilot"
        acks_expected = {30, 33, 132, 242}
        assert {int(c.param1) for c in ap.commands if int(c.command) == 511} == acks_expected
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 10)
        assert svc.status().health is Health.ACTIVE
        ap.set_mode(LOITER)
        n = len(ap.setpoints())
        await asyncio.sleep(0.4)
        assert len(ap.setpoints()) <= n + 1  # stopped within one cycle
        assert svc.status().health is Health.STANDBY


async def test_udp_px4_detected_frame_5() -> None:
    async with over_udp(kind="px4") as (svc, ap, _):
        await until(lambda: svc.status().configured)
        ap.set_mode(6 << 16)  # OFFBOARD
        await ap.wait_for(lambda: len(ap.setpoints()) >= 3)
        assert ap.setpoints()[-1].msg.coordinate_frame == 5


async def test_udp_heartbeat_loss_and_recovery() -> None:
    async with over_udp() as (svc, ap, _):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 5)
        ap.heartbeat_enabled = ap.telemetry_enabled = False
        await until(lambda: svc.status().health is Health.EMERGENCY, 2.0)
        n = len(ap.setpoints())
        await asyncio.sleep(0.3)
        # nothing new is commanded: only the brake, the last target again at rest
        during = [s.msg for s in ap.setpoints()[n:]]
        assert all((m.vx, m.vy, m.vz) == (0.0, 0.0, 0.0) for m in during)
        assert len({(m.lat_int, m.lon_int, m.alt) for m in during}) <= 1
        ap.heartbeat_enabled = ap.telemetry_enabled = True
        await until(lambda: svc.status().health is Health.ACTIVE, 3.0)
        m = len(ap.setpoints())
        await ap.wait_for(lambda: len(ap.setpoints()) > m + 3, 3.0)


async def test_udp_garbage_oversized_and_foreign_datagrams() -> None:
    async with over_udp() as (svc, ap, _):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 3)
        host, port = svc.link.local_address  # type: ignore[attr-defined]
        rng = np.random.default_rng(7)
        spoof = MavCodec(1, 1)  # right ids, other socket: a spoofer on the network
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(bytes(MAX_DATAGRAM_BYTES + 1), (host, port))
            for i in range(300):
                s.sendto(rng.bytes(int(rng.integers(1, 400))), (host, port))
                if i % 50 == 0:  # let the service read: the kernel drops what overflows
                    await asyncio.sleep(0.01)
            s.sendto(b"\xfe\x09" + bytes(5), (host, port))  # truncated MAVLink 1
            s.sendto(
                spoof.encode(mavlink2.MAVLink_heartbeat_message(2, 3, 1, 9, 4, 3)), (host, port)
            )
        n = len(ap.setpoints())
        await ap.wait_for(lambda: len(ap.setpoints()) > n + 5)
        c = svc.counter_values()
        assert c["link.oversized_dropped"] == 1
        assert c["codec.garbage"] > 0
        assert svc.status().health is Health.ACTIVE
        # replies still go to the autopilot's address, not to the last sender
        assert svc.link.peer == ap.link.local_address  # type: ignore[attr-defined]


async def test_udp_signing_rejects_unsigned_and_replayed(tmp_path: Path) -> None:
    key_file = tmp_path / "key"
    key_file.write_text(KEY.hex())
    key_file.chmod(0o600)
    state = tmp_path / "signing.json"
    cfg = make_config(
        signing={"enabled": True, "key_file": str(key_file), "state_file": str(state)}
    )
    async with over_udp(cfg, signing_key=KEY) as (svc, ap, _):
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 3)
        assert all(r.msg.get_signed() for r in ap.setpoints())  # ours are signed
        host, port = svc.link.local_address  # type: ignore[attr-defined]
        unsigned = MavCodec(1, 1)
        loiter = unsigned.encode(mavlink2.MAVLink_heartbeat_message(2, 3, 129, LOITER, 4, 3))
        replay: list[bytes] = []
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for _ in range(20):
                s.sendto(loiter, (host, port))
            # a signed LOITER heartbeat, captured and replayed
            signed = ap.codec.encode(mavlink2.MAVLink_heartbeat_message(2, 3, 129, GUIDED, 4, 3))
            replay.append(signed)
        ap.link.send(signed)
        await asyncio.sleep(0.05)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for _ in range(5):
                s.sendto(replay[0], (host, port))
        await asyncio.sleep(0.2)
        c = svc.counter_values()
        assert c["codec.unsigned_rejected"] >= 20
        assert c["codec.bad_signature"] >= 5
        assert svc.status().owner == "engaged"  # the unsigned LOITER heartbeats changed nothing
    saved = state.read_text()
    assert '"timestamp"' in saved


async def test_udp_sim_time_lockstep() -> None:
    """The simulator's TIMESYNC ticks drive the cycles: 20 Hz in simulated time."""
    cfg = make_config(control={"time_source": "sim"})
    async with over_udp(cfg, answer_timesync=False) as (svc, ap, box):
        ap.telemetry_enabled = ap.heartbeat_enabled = False  # the lockstep below sends them
        answers: dict[int, float] = {}
        answered = asyncio.Event()

        def on_timesync(msg: Any) -> None:
            if int(msg.tc1) != 0:
                answers[int(msg.ts1)] = asyncio.get_running_loop().time()
                answered.set()

        ap._on_timesync = on_timesync  # type: ignore[attr-defined]
        t_ns = 0
        tick_ns = 10_000_000  # 100 Hz physics
        setpoints_at_answer: list[int] = []

        async def tick() -> None:
            nonlocal t_ns
            t_ns += tick_ns
            ap.heartbeat()
            ap.telemetry()
            answered.clear()
            ap.send(mavlink2.MAVLink_timesync_message(0, t_ns))
            while t_ns not in answers:
                await asyncio.wait_for(answered.wait(), 2.0)
                answered.clear()
            setpoints_at_answer.append(len(ap.setpoints()))

        while not svc.status().configured or svc.status().verdict.verdict.value != "run":
            await tick()  # configured, and the inputs good for resume_after_s
        ap.set_mode(GUIDED)
        start_cycles = svc.counters["cycles"]
        start_t = t_ns
        for _ in range(200):  # 2 s of simulated time
            await tick()
        cycles = svc.counters["cycles"] - start_cycles
        assert cycles == pytest.approx(40, abs=1)  # 20 Hz of simulated time
        # every setpoint of a cycle is on the wire before that tick's answer
        planner = box.made[0]
        assert sum(dt for _, _, dt in planner.inputs) == pytest.approx(
            (t_ns - start_t) * 1e-9, abs=0.15
        )
        assert all(dt == pytest.approx(0.05) for _, _, dt in planner.inputs[1:])
        assert svc.clock.now() == pytest.approx(t_ns * 1e-9)


async def test_timesync_answered_immediately_in_monotonic_mode() -> None:
    async with over_udp() as (svc, ap, _):
        await until(lambda: svc.status().configured)
        ap.send(mavlink2.MAVLink_timesync_message(0, 123456789))
        await ap.wait_for(
            lambda: any(
                int(r.msg.ts1) == 123456789 and int(r.msg.tc1) != 0 for r in ap.of_type("TIMESYNC")
            )
        )


class _ServerSide(Link):
    """The accepting end of a TCP connection as a Link, for the fake autopilot."""

    datagram = False

    def __init__(self) -> None:
        super().__init__("tcp-server")
        self.writer: asyncio.StreamWriter | None = None
        self.server: asyncio.Server | None = None
        self.port = 0

    async def open(self, receiver: Receiver) -> None:
        self._receiver = receiver

        async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            self.writer = writer
            while data := await reader.read(4096):
                self._deliver(data, None)

        self.server = await asyncio.start_server(handle, "127.0.0.1", 0)
        self.port = self.server.sockets[0].getsockname()[1]

    def send(self, data: bytes) -> None:
        if self.writer is not None:
            self.writer.write(data)

    async def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        if self.server is not None:
            self.server.close()


async def test_tcp_link_end_to_end() -> None:
    server = _ServerSide()
    ap = FakeAutopilot(server)
    await ap.start()
    link = TcpLink("127.0.0.1", server.port)
    box = PlannerBox()
    svc = Service(make_config(), link, planner_factory=box, notifier=SystemdNotifier({}))
    task = asyncio.create_task(svc.run())
    try:
        await until(lambda: svc.status().configured)
        ap.set_mode(GUIDED)
        await ap.wait_for(lambda: len(ap.setpoints()) >= 5)
    finally:
        svc.stop()
        assert await asyncio.wait_for(task, 5) == 0
        await ap.stop()
