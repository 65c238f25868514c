"""COMMAND_LONG and its COMMAND_ACK (`companion.service.commands`) against a scripted peer."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from companion.service.codec import mavlink2
from companion.service.commands import (
    CommandClient,
    CommandDeniedError,
    CommandError,
    CommandTimeoutError,
    command_name,
    result_name,
)
from tests.service_peer import connected

mav = mavlink2
pytestmark = pytest.mark.timeout(30)

SHORT_S = 0.05
"""Timeout of the attempts that must go unanswered (never a timing assertion)."""


def ack(command: int, result: int, target: tuple[int, int] = (1, 191)) -> Any:
    return mav.MAVLink_command_ack_message(command, result, 0, 0, *target)


async def test_accepted_on_the_first_attempt() -> None:
    conn, peer = await connected()
    peer.reply = lambda m: [ack(int(m.command), mav.MAV_RESULT_ACCEPTED)]
    client = CommandClient(conn, timeout_s=5.0, retries=2)
    assert await client.arm(True) == mav.MAV_RESULT_ACCEPTED
    (sent,) = peer.of_type("COMMAND_LONG")
    assert int(sent.command) == mav.MAV_CMD_COMPONENT_ARM_DISARM
    assert sent.param1 == 1.0 and sent.confirmation == 0
    assert (sent.target_system, sent.target_component) == (1, 1)


async def test_a_refusal_raises_with_the_result_and_is_not_retried() -> None:
    conn, peer = await connected()
    peer.reply = lambda m: [ack(int(m.command), mav.MAV_RESULT_DENIED)]
    client = CommandClient(conn, timeout_s=5.0, retries=3)
    with pytest.raises(CommandDeniedError) as info:
        await client.set_mode((1.0, 4.0, 0.0))
    assert info.value.result == mav.MAV_RESULT_DENIED
    assert info.value.result_name == "MAV_RESULT_DENIED"
    assert info.value.command == mav.MAV_CMD_DO_SET_MODE
    assert "MAV_CMD_DO_SET_MODE" in str(info.value)
    assert len(peer.of_type("COMMAND_LONG")) == 1


async def test_a_lost_ack_is_retried_with_the_confirmation_counted() -> None:
    conn, peer = await connected()
    answered: list[int] = []

    def second_only(m: Any) -> list[Any]:
        if int(m.confirmation) == 0:
            return []
        answered.append(int(m.confirmation))
        return [ack(int(m.command), mav.MAV_RESULT_ACCEPTED)]

    peer.reply = second_only
    client = CommandClient(conn, timeout_s=SHORT_S, retries=3)
    await client.request_message(mav.MAVLINK_MSG_ID_HOME_POSITION)
    sent = peer.of_type("COMMAND_LONG")
    assert [int(m.confirmation) for m in sent] == [0, 1] and answered == [1]
    assert sent[0].param1 == mav.MAVLINK_MSG_ID_HOME_POSITION


async def test_no_answer_at_all_raises_a_timeout_after_every_attempt() -> None:
    conn, peer = await connected()
    client = CommandClient(conn, timeout_s=SHORT_S, retries=2)
    with pytest.raises(CommandTimeoutError) as info:
        await client.takeoff(10.0)
    assert info.value.attempts == 3
    sent = peer.of_type("COMMAND_LONG")
    assert len(sent) == 3 and sent[-1].param7 == 10.0


async def test_in_progress_waits_without_resending() -> None:
    conn, peer = await connected()
    loop = asyncio.get_running_loop()

    def progress_then_done(m: Any) -> list[Any]:
        # the final ack a little later, as an autopilot that works on it would send it
        loop.call_later(0.05, peer.send, ack(int(m.command), mav.MAV_RESULT_ACCEPTED))
        return [ack(int(m.command), mav.MAV_RESULT_IN_PROGRESS)]

    peer.reply = progress_then_done
    client = CommandClient(conn, timeout_s=5.0, retries=0)
    assert await client.set_message_interval(mav.MAVLINK_MSG_ID_ATTITUDE, 50.0) == 0
    (sent,) = peer.of_type("COMMAND_LONG")
    assert sent.param2 == pytest.approx(20_000.0)  # 50 Hz as an interval in microseconds


async def test_acks_for_another_command_or_another_companion_do_not_count() -> None:
    conn, peer = await connected()
    peer.reply = lambda m: [
        ack(mav.MAV_CMD_NAV_TAKEOFF, mav.MAV_RESULT_ACCEPTED),
        ack(int(m.command), mav.MAV_RESULT_ACCEPTED, target=(1, 42)),
    ]
    client = CommandClient(conn, timeout_s=SHORT_S, retries=1)
    with pytest.raises(CommandTimeoutError):
        await client.arm(False)


async def test_no_autopilot_yet_is_an_error_not_a_send() -> None:
    conn, peer = await connected(lock=False)
    with pytest.raises(CommandError, match="no autopilot yet"):
        await CommandClient(conn).arm(True)
    assert peer.received == []


def test_names_come_from_pymavlink() -> None:
    assert command_name(mav.MAV_CMD_NAV_TAKEOFF) == "MAV_CMD_NAV_TAKEOFF"
    assert command_name(65000) == "MAV_CMD(65000)"
    assert result_name(mav.MAV_RESULT_TEMPORARILY_REJECTED) == "MAV_RESULT_TEMPORARILY_REJECTED"


class _HeldConn:
    """A connection whose COMMAND_ACK future the test completes by hand."""

    target_system, target_component = 1, 1

    def __init__(self) -> None:
        self.futures: list[asyncio.Future[Any]] = []

    def expect(self, types: Any, pred: Any) -> asyncio.Future[Any]:
        fut: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self.futures.append(fut)
        return fut

    def send(self, msg: Any) -> None:
        pass

    def forget(self, fut: Any) -> None:
        pass


async def test_a_cancel_landing_with_the_ack_is_kept() -> None:
    """Auto start is cancelled (a ground station changed the mode) in the same loop turn as
    the arm command's ack arrives: the command ends cancelled, so no retry follows. (With
    asyncio.wait_for on Python 3.11 the ack's result came back and the cancel was lost.)"""
    conn = _HeldConn()
    client = CommandClient(conn, timeout_s=5.0, retries=2)  # type: ignore[arg-type]
    task = asyncio.create_task(client.arm(True))
    while not conn.futures:
        await asyncio.sleep(0)
    await asyncio.sleep(0)  # (the command now waits on its ack)
    conn.futures[0].set_result(
        ack(mav.MAV_CMD_COMPONENT_ARM_DISARM, mav.MAV_RESULT_TEMPORARILY_REJECTED)
    )
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
