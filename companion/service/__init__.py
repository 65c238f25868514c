"""The companion service: MAVLink I/O around the planner, for ArduPilot and PX4.

Construct and run it from Python with an injected link::

    from companion.config import load_config
    from companion.service import Service, open_link

    cfg = load_config(Path("config/sitl-copter.yaml"))
    service = Service(cfg, open_link(cfg.link.connection))
    exit_code = await service.run()          # until service.stop() or a fatal error

`main(config_path)` does all of that (logging, signals, systemd notification) for
`companion run`. Submodules are imported lazily so that `companion.config` can use the link
parser without pulling in the whole service.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from companion.service.link import Link, MemoryLink, memory_pair, open_link
    from companion.service.service import Service, ServiceCounters

__all__ = ["Link", "MemoryLink", "Service", "ServiceCounters", "main", "memory_pair", "open_link"]

_LAZY = {
    "Link": "companion.service.link",
    "MemoryLink": "companion.service.link",
    "memory_pair": "companion.service.link",
    "open_link": "companion.service.link",
    "Service": "companion.service.service",
    "ServiceCounters": "companion.service.service",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'companion.service' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(module), name)


def main(config_path: Path, connection: str | None = None, log_level: str | None = None) -> int:
    """Run the service from a config file until SIGTERM/SIGINT; returns the exit code.

    connection and log_level replace the file's link.connection and logging.level.
    """
    from companion.service.service import main as _main

    return _main(config_path, connection, log_level)
