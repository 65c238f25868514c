"""Run a SimServer in a background thread with its own event loop.

For blocking clients in the same process -- pymavlink's `mavutil` in tests and scripts --
that would otherwise stall the simulator's event loop:

    with ThreadedSim(lambda: SimServer(...), until_s=60.0) as sim:
        conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{sim.port}")
        ...
    sim.server.truth  # after the block, the thread has stopped
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from collections.abc import Callable
from types import TracebackType

from companion.sim.mavlink.server import SimServer


class ThreadedSim:
    def __init__(
        self,
        make_server: Callable[[], SimServer],
        until_s: float = math.inf,
        start_timeout_s: float = 10.0,
    ) -> None:
        self._make_server = make_server
        self.until_s = until_s
        self.start_timeout_s = start_timeout_s
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._server: SimServer | None = None
        self._thread = threading.Thread(target=self._main, name="mavlink-sim", daemon=True)

    @property
    def server(self) -> SimServer:
        if self._server is None:
            raise RuntimeError("the simulator has not started")
        return self._server

    @property
    def port(self) -> int:
        return self.server.port

    def __enter__(self) -> ThreadedSim:
        self._thread.start()
        if not self._started.wait(self.start_timeout_s):
            raise TimeoutError("the simulator thread did not start")
        if self._error is not None:
            raise RuntimeError("the simulator failed to start") from self._error
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    def stop(self, timeout_s: float = 10.0) -> None:
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(stop.set)
        self._thread.join(timeout_s)
        if self._error is not None:
            raise RuntimeError("the simulator failed") from self._error

    def wait_until(self, t_s: float, timeout_s: float = 30.0) -> None:
        """Block until simulated time reaches t_s (TimeoutError after timeout_s wall)."""
        deadline = time.monotonic() + timeout_s
        while self.server.t_s < t_s - 1e-9:
            if not self._thread.is_alive():
                raise RuntimeError(f"the simulator stopped at t={self.server.t_s:.2f} s")
            if time.monotonic() > deadline:
                raise TimeoutError(f"simulated time is {self.server.t_s:.2f} s, not {t_s} s")
            time.sleep(0.002)

    def _main(self) -> None:
        try:
            asyncio.run(self._amain())
        except BaseException as exc:  # reported to the caller's thread
            self._error = exc
            self._started.set()

    async def _amain(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self._server = self._make_server()
        await self._server.start()
        self._started.set()
        run = self._server.start_background(self.until_s)
        stop = asyncio.ensure_future(self._stop.wait())
        try:
            await asyncio.wait({run, stop}, return_when=asyncio.FIRST_COMPLETED)
            if run.done() and run.exception() is not None:
                raise run.exception()  # type: ignore[misc]
        finally:
            stop.cancel()
            await self._server.close()
