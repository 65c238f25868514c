"""Routing by source (`companion.service.connection`): before and after the lock, waiters,
receipt stamps from the injected clock, and a handler bug that must not stop the receive path."""

from __future__ import annotations

from typing import Any

import pytest

from companion.service.codec import MavCodec, mavlink2
from companion.service.connection import waiting_hint
from tests.service_peer import connected, settle

pytestmark = pytest.mark.timeout(30)


def heartbeat() -> Any:
    return mavlink2.MAVLink_heartbeat_message(
        mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0, 3
    )


def attitude(t_ms: int = 1) -> Any:
    return mavlink2.MAVLink_attitude_message(t_ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


async def test_before_the_lock_only_heartbeats_are_offered_and_the_rest_counted() -> None:
    conn, peer = await connected(lock=False, clock=lambda: 12.5)
    offered: list[tuple[str, float]] = []
    passed: list[str] = []
    conn.on_unlocked = lambda m, t: offered.append((m.get_type(), t))
    conn.on_message = lambda m, t: passed.append(m.get_type())
    peer.send(heartbeat())
    peer.send(attitude())
    await settle()
    assert offered == [("HEARTBEAT", 12.5)]  # stamped with the injected clock
    assert passed == [] and conn.counters["before_lock"] == 2


async def test_after_the_lock_other_systems_and_components_are_dropped_and_counted() -> None:
    conn, peer = await connected()
    passed: list[tuple[int, int]] = []
    others: list[int] = []
    conn.on_message = lambda m, t: passed.append((m.get_srcSystem(), m.get_srcComponent()))
    conn.on_other = lambda m, t: others.append(m.get_srcSystem())
    peer.send(attitude())
    stranger = MavCodec(2, 1)
    peer.link.send(stranger.encode(heartbeat()))
    gimbal = MavCodec(1, 154)
    peer.link.send(gimbal.encode(attitude()))
    await settle()
    assert passed == [(1, 1)]
    assert others == [2]  # another system's heartbeat is shown (a second autopilot?)
    assert conn.counters["other_system"] == 1 and conn.counters["other_component"] == 1
    assert conn.counters["accepted"] == 1


async def test_a_waiter_sees_its_message_before_the_general_handler() -> None:
    conn, peer = await connected()
    order: list[str] = []
    conn.on_message = lambda m, t: order.append("handler")
    fut = conn.expect("ATTITUDE", lambda m: int(m.time_boot_ms) == 7)
    fut.add_done_callback(lambda f: order.append("waiter"))
    peer.send(attitude(6))
    peer.send(attitude(7))
    await settle()
    assert fut.done() and int(fut.result().time_boot_ms) == 7
    # the waiter's future was resolved first (its callback runs on the next loop turn)
    assert order[:2] == ["handler", "handler"] and order[-1] == "waiter"


async def test_forget_cancels_a_waiter() -> None:
    conn, peer = await connected()
    fut = conn.expect("ATTITUDE")
    conn.forget(fut)
    peer.send(attitude())
    await settle()
    assert fut.cancelled()


async def test_a_handler_bug_is_counted_and_the_next_message_still_handled() -> None:
    conn, peer = await connected()
    seen: list[int] = []

    def handler(m: Any, t: float) -> None:
        if int(m.time_boot_ms) == 1:
            raise RuntimeError("bug")
        seen.append(int(m.time_boot_ms))

    conn.on_message = handler
    peer.send(attitude(1))
    peer.send(attitude(2))
    await settle()
    assert seen == [2] and conn.counters["handler_errors"] == 1


async def test_send_goes_through_the_codec_to_the_peer() -> None:
    conn, peer = await connected()
    conn.send(heartbeat())
    await settle()
    (hb,) = peer.of_type("HEARTBEAT")
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 191)


def test_waiting_hint_names_who_speaks_first() -> None:
    assert "autopilot must send here first" in waiting_hint("udpin:0.0.0.0:14550")
    assert "sending heartbeats" in waiting_hint("udpout:10.0.0.1:14550")
