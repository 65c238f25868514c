"""The process entry: `companion run --config FILE` (logging, signals, exit status)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import TextIO

from companion.config import ConfigError, load_config
from companion.service.link import open_link
from companion.service.params import persist_to
from companion.service.service import Service


def configure_logging(level: str, environ: Mapping[str, str] | None = None) -> None:
    """Log to stderr at `level`; no time stamps under journald (it adds its own)."""
    import os

    env = os.environ if environ is None else environ
    fmt = "%(levelname)s %(name)s: %(message)s"
    if "JOURNAL_STREAM" not in env:
        fmt = "%(asctime)s " + fmt
    logging.basicConfig(level=level.upper(), format=fmt, stream=sys.stderr, force=True)


class TerminalStatus(logging.Filter):
    """The status line on a terminal: one line rewritten in place (carriage return, erase
    to end of line), cut to the terminal's width; a log line first erases it, and the next
    status call draws it again below. Install with `attach()`; `close()` ends the line."""

    def __init__(self, stream: TextIO, width: int = 120) -> None:
        super().__init__()
        self.stream = stream
        self.width = width
        self.showing = False

    def __call__(self, text: str) -> None:
        self.stream.write("\r\x1b[K" + text[: max(10, self.width - 1)])
        self.stream.flush()
        self.showing = True

    def filter(self, record: logging.LogRecord) -> bool:
        if self.showing:
            self.stream.write("\r\x1b[K")
            self.showing = False
        return True

    def attach(self) -> None:
        for handler in logging.getLogger().handlers:
            handler.addFilter(self)

    def close(self) -> None:
        if self.showing:
            self.stream.write("\n")
            self.stream.flush()
            self.showing = False


def terminal_status(quiet: bool, stream: TextIO | None = None) -> TerminalStatus | None:
    """A `TerminalStatus` on stderr when it is a terminal and not `quiet`, else None."""
    import shutil

    out = sys.stderr if stream is None else stream
    if quiet or not out.isatty():
        return None
    return TerminalStatus(out, shutil.get_terminal_size((120, 24)).columns)


async def run_with_signals(service: Service) -> int:
    """`service.run()` with SIGTERM/SIGINT as `service.stop()`."""
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, service.stop)
    return await service.run()


def main(
    config_path: Path,
    connection: str | None = None,
    log_level: str | None = None,
    quiet: bool = False,
    persist_params: bool = False,
) -> int:
    """`companion run --config FILE`: exit 0 on SIGTERM/SIGINT, 2 on a bad config, 3 when the
    link's port cannot be had (in use), 1 on another error.

    connection, log_level: the command line's `--connection` and `--log-level`; quiet: no
    status line on a terminal (`--quiet`; there is none when stderr is not a terminal).
    persist_params: write parameter changes accepted in flight (PARAM_SET) back into the
    config file's `planner:` section (`--persist-params`).
    """
    try:
        cfg = load_config(Path(config_path), connection)
    except ConfigError as exc:
        print(f"{config_path}: invalid configuration", file=sys.stderr)
        for line in exc.errors:
            print(f"  {line}", file=sys.stderr)
        return 2
    configure_logging(log_level or cfg.logging.level)
    service = Service(cfg, open_link(cfg.link.spec))
    if persist_params:
        service.params.persist = persist_to(Path(config_path))
    status = terminal_status(quiet)
    if status is not None:
        status.attach()
        service.status_sink = status
    try:
        return asyncio.run(run_with_signals(service))
    finally:
        if status is not None:
            status.close()


__all__ = ["TerminalStatus", "configure_logging", "main", "run_with_signals", "terminal_status"]
