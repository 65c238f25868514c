"""The companion service: MAVLink I/O around the planner, for ArduPilot and PX4.

Construct and run it from Python with an injected link (and, in tests, an injected clock)::

    from companion.config import load_config
    from companion.service import Service, open_link

    cfg = load_config(Path("config/sitl-copter.yaml"))
    service = Service(cfg, open_link(cfg.link.spec))
    exit_code = await service.run()          # until service.stop() or a fatal error
    service.status()                          # a frozen snapshot: health, owner, hold, ...

`main(config_path)` does all of that (logging, signals, systemd notification) for
`companion run`. The parts, one job each, are drawn in docs/architecture.md.
"""

from __future__ import annotations

from companion.service.clock import Clock, ManualClock, MonotonicClock, SimClock
from companion.service.entry import main
from companion.service.flightlog import FlightLog, read_flight_log
from companion.service.link import Link, MemoryLink, UdpInLink, UdpOutLink, memory_pair, open_link
from companion.service.notify import SystemdNotifier
from companion.service.service import Service, ServiceCounters
from companion.service.status import PlannerState, SensorFreshness, ServiceStatus

__all__ = [
    "Clock",
    "FlightLog",
    "Link",
    "ManualClock",
    "MemoryLink",
    "MonotonicClock",
    "PlannerState",
    "SensorFreshness",
    "Service",
    "ServiceCounters",
    "ServiceStatus",
    "SimClock",
    "SystemdNotifier",
    "UdpInLink",
    "UdpOutLink",
    "main",
    "memory_pair",
    "open_link",
    "read_flight_log",
]
