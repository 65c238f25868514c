"""COMMAND_LONG with its COMMAND_ACK: retries, timeouts and typed errors.

Errors::

    CommandError            a command did not succeed; .command (MAV_CMD), .name
    +-- CommandDeniedError       the autopilot answered with a result other than ACCEPTED;
    |                       .result (MAV_RESULT) and .result_name
    +-- CommandTimeoutError      no final ack after all attempts; .attempts

An ack counts when it names the command and, if it names a target, names us. IN_PROGRESS
acks extend the wait without resending. Retries increment `confirmation`, as MAVLink asks.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Sequence

from companion.service.codec import MAVLinkMessage, mavlink2
from companion.service.connection import Connection

MAV_RESULT_ACCEPTED: int = mavlink2.MAV_RESULT_ACCEPTED
MAV_RESULT_IN_PROGRESS: int = mavlink2.MAV_RESULT_IN_PROGRESS

MAV_CMD_NAV_TAKEOFF: int = mavlink2.MAV_CMD_NAV_TAKEOFF
MAV_CMD_DO_SET_MODE: int = mavlink2.MAV_CMD_DO_SET_MODE
MAV_CMD_COMPONENT_ARM_DISARM: int = mavlink2.MAV_CMD_COMPONENT_ARM_DISARM
MAV_CMD_SET_MESSAGE_INTERVAL: int = mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL
MAV_CMD_REQUEST_MESSAGE: int = mavlink2.MAV_CMD_REQUEST_MESSAGE


def command_name(command: int) -> str:
    entry = mavlink2.enums["MAV_CMD"].get(command)
    return entry.name if entry is not None else f"MAV_CMD({command})"


def result_name(result: int) -> str:
    entry = mavlink2.enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else f"MAV_RESULT({result})"


class CommandError(Exception):
    """A command that did not succeed."""

    def __init__(self, command: int, message: str) -> None:
        self.command = command
        self.name = command_name(command)
        super().__init__(f"{self.name}: {message}")


class CommandDeniedError(CommandError):
    def __init__(self, command: int, result: int) -> None:
        self.result = result
        self.result_name = result_name(result)
        super().__init__(command, self.result_name)


class CommandTimeoutError(CommandError):
    def __init__(self, command: int, attempts: int, timeout_s: float) -> None:
        self.attempts = attempts
        super().__init__(command, f"no ack after {attempts} attempt(s) of {timeout_s:g} s")


class CommandClient:
    """Sends COMMAND_LONG to the locked autopilot and awaits the ack."""

    def __init__(self, conn: Connection, timeout_s: float = 1.0, retries: int = 3) -> None:
        self.conn = conn
        self.timeout_s = timeout_s
        self.retries = retries
        self._locks: dict[int, asyncio.Lock] = {}

    def _matches(self, command: int, ack: MAVLinkMessage) -> bool:
        if int(ack.command) != command:
            return False
        ts, tc = int(getattr(ack, "target_system", 0)), int(getattr(ack, "target_component", 0))
        ours = self.conn.codec
        return (ts in (0, ours.system_id)) and (tc in (0, ours.component_id))

    async def long(
        self,
        command: int,
        params: Sequence[float] = (),
        *,
        timeout_s: float | None = None,
        retries: int | None = None,
    ) -> int:
        """Send `command` with up to 7 params (missing ones 0); returns MAV_RESULT_ACCEPTED.

        Raises CommandDeniedError or CommandTimeoutError.
        """
        if self.conn.target_system is None or self.conn.target_component is None:
            raise CommandError(command, "no autopilot yet")
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        timeout = self.timeout_s if timeout_s is None else timeout_s
        attempts = 1 + (self.retries if retries is None else retries)
        lock = self._locks.setdefault(command, asyncio.Lock())
        async with lock:  # one outstanding command per id: acks carry no sequence number
            for attempt in range(attempts):
                msg = mavlink2.MAVLink_command_long_message(
                    self.conn.target_system,
                    self.conn.target_component,
                    command,
                    min(attempt, 255),
                    *p,
                )
                result = await self._exchange(msg, command, timeout)
                if result is None:
                    continue
                if result != MAV_RESULT_ACCEPTED:
                    raise CommandDeniedError(command, result)
                return result
        raise CommandTimeoutError(command, attempts, timeout)

    async def _exchange(self, msg: MAVLinkMessage, command: int, timeout: float) -> int | None:
        """Send once; the final result, or None on timeout. IN_PROGRESS waits on."""
        sent = False
        while True:
            fut = self.conn.expect("COMMAND_ACK", lambda m: self._matches(command, m))
            try:
                if not sent:
                    self.conn.send(msg)
                    sent = True
                # asyncio.timeout, not wait_for: on Python 3.11 wait_for returns the result
                # when the ack and a cancel of this task (auto start aborted by a mode change)
                # land in the same loop turn, and the cancel is lost.
                async with asyncio.timeout(timeout):
                    ack = await fut
            except TimeoutError:
                return None
            finally:
                self.conn.forget(fut)
            result = int(ack.result)
            if result != MAV_RESULT_IN_PROGRESS:
                return result

    # -- the commands the service uses ------------------------------------------------------

    async def set_message_interval(self, msg_id: int, rate_hz: float) -> int:
        interval_us = -1.0 if rate_hz <= 0 else 1e6 / rate_hz
        return await self.long(MAV_CMD_SET_MESSAGE_INTERVAL, (msg_id, interval_us))

    async def request_message(self, msg_id: int) -> int:
        return await self.long(MAV_CMD_REQUEST_MESSAGE, (msg_id,))

    async def arm(self, arm: bool = True) -> int:
        return await self.long(MAV_CMD_COMPONENT_ARM_DISARM, (1.0 if arm else 0.0,))

    async def set_mode(self, params: tuple[float, float, float]) -> int:
        return await self.long(MAV_CMD_DO_SET_MODE, params)

    async def takeoff(self, altitude_m: float) -> int:
        """NAV_TAKEOFF: ArduPilot reads param7 relative to home, PX4 as AMSL (caller decides)."""
        return await self.long(
            MAV_CMD_NAV_TAKEOFF, (0.0, 0.0, 0.0, math.nan, math.nan, math.nan, altitude_m)
        )
