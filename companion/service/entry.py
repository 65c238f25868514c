"""The process entry: `companion run --config FILE` (logging, signals, exit status)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import sys
from collections.abc import Mapping
from pathlib import Path

from companion.config import ConfigError, load_config
from companion.service.link import open_link
from companion.service.service import Service


def configure_logging(level: str, environ: Mapping[str, str] | None = None) -> None:
    """Log to stderr at `level`; no time stamps under journald (it adds its own)."""
    import os

    env = os.environ if environ is None else environ
    fmt = "%(levelname)s %(name)s: %(message)s"
    if "JOURNAL_STREAM" not in env:
        fmt = "%(asctime)s " + fmt
    logging.basicConfig(level=level.upper(), format=fmt, stream=sys.stderr, force=True)


async def run_with_signals(service: Service) -> int:
    """`service.run()` with SIGTERM/SIGINT as `service.stop()`."""
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, service.stop)
    return await service.run()


def main(config_path: Path, connection: str | None = None, log_level: str | None = None) -> int:
    """`companion run --config FILE`: exit 0 on SIGTERM/SIGINT, 2 on a bad config, 3 when the
    link's port cannot be had (in use), 1 on another error.

    connection, log_level: the command line's `--connection` and `--log-level`.
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
    return asyncio.run(run_with_signals(service))


__all__ = ["configure_logging", "main", "run_with_signals"]
