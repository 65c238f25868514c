"""Security: signing (unsigned, wrongly signed, replayed: all rejected; signed: accepted),
the signing timestamp across restarts, other system ids, and where the service binds."""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import struct
import time
from pathlib import Path
from typing import Any

import pytest

from companion.service import Service, memory_pair
from companion.service.codec import MavCodec, mavlink2
from companion.service.link import UdpInLink, UdpOutLink
from companion.service.notify import SystemdNotifier
from companion.service.signing import SIGNING_EPOCH_UNIX_S, TICKS_PER_SECOND
from tests.reliability_inputs import AUTOPILOT, ReceivePath
from tests.service_fakes import FakeAutopilot, PlannerBox, make_config

pytestmark = pytest.mark.timeout(30)

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
M = mavlink2
N = 500


def telemetry_msgs(i: int) -> list[Any]:
    return [
        M.MAVLink_heartbeat_message(2, 3, 129, 5, 4, 3),
        M.MAVLink_attitude_message(1000 + i, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0),
        M.MAVLink_command_long_message(1, 191, 400, 0, 0, 0, 0, 0, 0, 0, 0),
    ]


def signing_ts(frame: bytes) -> int:
    """The 48-bit timestamp of a signed MAVLink 2 frame."""
    lo, hi = struct.unpack("<IH", frame[-12:-6])
    return lo + (hi << 32)


def test_signing_rejects_every_unsigned_forged_and_replayed_frame() -> None:
    path = ReceivePath(signing_key=KEY)
    c = path.svc.codec.counters
    frames0 = c.frames
    good, unsigned, v1, wrong, replays = [], [], [], [], []
    signer = path.autopilot  # the autopilot's codec, with the key
    plain = MavCodec(*AUTOPILOT)
    forger = MavCodec(*AUTOPILOT)
    forger.enable_signing(OTHER_KEY, timestamp=2**47)  # and a far-future timestamp
    enc1 = mavlink2.MAVLink(None, *AUTOPILOT)
    for i in range(N):
        for msg in telemetry_msgs(i):
            good.append(signer.encode(msg))
            unsigned.append(plain.encode(msg))
            v1.append(bytes(msg.pack(enc1, force_mavlink1=True)))
            wrong.append(forger.encode(msg))
    # interleave: forgeries and unsigned frames between the good ones
    for g, u, one, w in zip(good, unsigned, v1, wrong, strict=True):
        for d in (w, u, g, one):
            path.feed(d)
    replays = good[::3]  # captured and sent again later
    for d in replays:
        path.feed(d)
    old_stream = MavCodec(*AUTOPILOT)
    old_stream.enable_signing(KEY, link_id=7, timestamp=1)
    stale = [old_stream.encode(m) for m in telemetry_msgs(0)]  # a new link, long ago
    for d in stale:
        path.feed(d)

    assert c.frames - frames0 == len(good)  # 100 % of the signed frames accepted
    assert c.unsigned_rejected == len(unsigned) + len(v1)  # 100 % rejected
    assert c.bad_signature == len(wrong) + len(replays) + len(stale)  # 100 % rejected
    assert path.fed.nonempty_uncounted == 0
    # the forged far-future timestamps did not lock the real sender out
    assert path.svc.tel.attitude is not None and path.svc.tel.attitude.time_boot_ms == 999 + N
    assert path.sent_types() == set()


async def test_signing_timestamp_persists_across_restarts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A companion without a real-time clock: after a restart its clock is years behind,
    yet every frame it signs is newer than every frame it signed before."""
    key_file = tmp_path / "key"
    key_file.write_text(KEY.hex())
    key_file.chmod(0o600)
    state = tmp_path / "signing.json"
    cfg = make_config(
        signing={"enabled": True, "key_file": str(key_file), "state_file": str(state)}
    )

    async def run_once() -> tuple[list[int], FakeAutopilot]:
        a, b = memory_pair()
        svc = Service(cfg, a, planner_factory=PlannerBox(), notifier=SystemdNotifier({}))
        ap = FakeAutopilot(b, signing_key=KEY)
        ap.codec.mav.signing.stream_timestamps.update(seen)  # the autopilot remembers
        task = asyncio.create_task(svc.run())
        await ap.start()
        await ap.wait_for(lambda: len(ap.of_type("HEARTBEAT")) >= 2 and svc.status().configured)
        svc.stop()
        assert await asyncio.wait_for(task, 5) == 0
        await ap.stop()
        seen.update(ap.codec.mav.signing.stream_timestamps)
        stamps = [signing_ts(bytes(r.msg.get_msgbuf())) for r in ap.received]
        return stamps, ap

    seen: dict[Any, int] = {}
    first, _ = await run_once()
    assert first and state.exists()
    # the clock goes back to 2016 (no RTC, no network time yet)
    monkeypatch.setattr(time, "time", lambda: SIGNING_EPOCH_UNIX_S + 365 * 86400.0)
    second, ap2 = await run_once()
    assert second and min(second) > max(first)
    assert ap2.codec.counters.bad_signature == 0  # the autopilot took them all
    # without the state file the restart would have gone back in time: the check matters
    assert max(first) > 365 * 86400 * TICKS_PER_SECOND


def test_commands_from_other_systems_are_ignored() -> None:
    path = ReceivePath()
    sent0 = len(path.sent)
    for sys_id, comp in ((2, 1), (255, 190), (1, 250), (0, 0)):
        other = MavCodec(sys_id, comp)
        for msg in (
            M.MAVLink_command_long_message(1, 191, 400, 0, 0, 0, 0, 0, 0, 0, 0),  # disarm
            M.MAVLink_command_long_message(1, 191, 246, 0, 1, 0, 0, 0, 0, 0, 0),  # reboot us
            M.MAVLink_set_mode_message(1, 1, 5),
            M.MAVLink_set_position_target_global_int_message(
                0, 1, 191, 6, 0, 0, 0, 100.0, 0, 0, 0, 0, 0, 0, 0, 0
            ),
            M.MAVLink_timesync_message(0, 123),  # not even TIMESYNC answered
            M.MAVLink_heartbeat_message(2, 3, 129, 5, 4, 3),
        ):
            path.feed(other.encode(msg))
    c = path.svc.counter_values()
    assert c["conn.other_system"] + c["conn.other_component"] == 4 * 6
    assert len(path.sent) == sent0
    assert path.svc.tel.heartbeat is not None and path.svc.tel.heartbeat.custom_mode == 5


def _socket_inodes() -> set[str]:
    out = set()
    for fd in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):
            target = os.readlink(f"/proc/self/fd/{fd}")
            if target.startswith("socket:["):
                out.add(target[8:-1])
    return out


def _bound(inodes: set[str]) -> list[tuple[str, str, int, str]]:
    """(protocol, local host, local port, state) of our sockets with these inodes."""
    found = []
    for proto in ("udp", "udp6", "tcp", "tcp6"):
        with contextlib.suppress(OSError), open(f"/proc/net/{proto}") as f:
            for line in f.readlines()[1:]:
                cols = line.split()
                if cols[9] not in inodes:
                    continue
                host_hex, port_hex = cols[1].split(":")
                if len(host_hex) == 8:
                    host = socket.inet_ntop(socket.AF_INET, bytes.fromhex(host_hex)[::-1])
                else:
                    raw = bytes.fromhex(host_hex)
                    host = socket.inet_ntop(
                        socket.AF_INET6, b"".join(raw[i : i + 4][::-1] for i in range(0, 16, 4))
                    )
                found.append((proto, host, int(port_hex, 16), cols[3]))
    return found


@pytest.mark.skipif(not Path("/proc/net/udp").exists(), reason="needs Linux /proc")
async def test_binds_only_where_configured() -> None:
    before = _socket_inodes()
    svc = Service(
        make_config(link={"connection": "udpin:127.0.0.1:0"}),
        UdpInLink("127.0.0.1", 0),
        planner_factory=PlannerBox(),
        notifier=SystemdNotifier({}),
    )
    task = asyncio.create_task(svc.run())
    try:
        while not svc.link.is_open:  # type: ignore[attr-defined]
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.2)
        mine = _bound(_socket_inodes() - before)
        _, port = svc.link.local_address  # type: ignore[attr-defined]
        assert mine == [("udp", "127.0.0.1", port, "07")]  # one UDP socket, loopback only
    finally:
        svc.stop()
        assert await asyncio.wait_for(task, 5) == 0


async def test_udpout_hears_only_its_autopilot() -> None:
    """udpout connects its socket: the kernel drops datagrams from any other address."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as autopilot:
        autopilot.bind(("127.0.0.1", 0))
        ap_port = autopilot.getsockname()[1]
        link = UdpOutLink("127.0.0.1", ap_port)
        got: list[bytes] = []
        await link.open(lambda data, peer: got.append(data))
        try:
            port = link.local_address[1]
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as intruder:
                for _ in range(20):
                    intruder.sendto(b"\xfd" + bytes(20), ("127.0.0.1", port))
            autopilot.sendto(b"from the autopilot", ("127.0.0.1", port))
            for _ in range(100):
                if got:
                    break
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.05)
            assert got == [b"from the autopilot"]
            assert link.local_address[0] == "127.0.0.1"
        finally:
            await link.close()
