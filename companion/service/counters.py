"""Counters by dotted name, and which of them are problems worth a log line.

Names: `link.*` (bytes and chunks, drops), `codec.*` (parser), `conn.*` (routing by source),
`input.*` (telemetry validation), `signing.*` (with signing on), `statustext.*` and
`service.*` (the service's own: cycles, holds, planner starts and errors, ...).
See docs/service.md for the list.
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import fields

from companion.service.codec import CodecCounters, MavCodec
from companion.service.connection import Connection
from companion.service.link import Link
from companion.service.statustext import StatusTexts
from companion.service.telemetry import Telemetry

log = logging.getLogger("companion.service")


class ServiceCounters(Counter[str]):
    """All counters by dotted name: link.*, codec.*, conn.*, input.*, signing.*, service.*."""


_CODEC_FIELDS = tuple(f.name for f in fields(CodecCounters))

PROBLEM_PREFIXES = (
    "codec.garbage",
    "codec.bad_",
    "codec.unsigned",
    "codec.unknown",
    "codec.truncated",
    "codec.parser",
    "conn.other",
    "conn.handler",
    "input.rejected",
    "input.out_of_order",
    "input.duplicate",
    "input.time_boot",
    "input.position_jump",
    "input.rejected_position_jump_fault",
    "link.send_dropped",
    "link.oversized",
    "link.kernel_dropped",
    "link.errors",
    "signing.bad",
    "signing.rejected",
    "service.cycle_overruns",
    "service.cycle_errors",
    "service.route_build_failed",
    "service.planner_errors",
    "service.setpoints_refused",
    "statustext.dropped",
)
"""Counters whose growth is logged as a warning (housekeeping, every 10 s)."""

WARN_ONCE = ("conn.other_component", "conn.other_system", "codec.unknown_msgid")
"""Problems that can be a steady, harmless stream (a router sending the companion's
neighbours' messages back; messages of a newer dialect than pymavlink's, which PX4 v1.18
SITL sends at about 24 a second): their first growth is a warning, later growth debug."""


def is_problem(name: str) -> bool:
    """True for a counter whose growth means something went wrong."""
    return name.startswith(PROBLEM_PREFIXES)


def collect(
    link: Link,
    codec: MavCodec,
    conn: Connection,
    tel: Telemetry,
    texts: StatusTexts,
    service: Counter[str],
) -> dict[str, int]:
    """Every counter by dotted name, read now."""
    out: dict[str, int] = {}
    out.update({f"link.{k}": v for k, v in link.refresh_stats().as_dict().items()})
    out.update({f"codec.{k}": getattr(codec.counters, k) for k in _CODEC_FIELDS})
    out.update({f"conn.{k}": v for k, v in conn.counters.items()})
    out.update({f"input.{k}": v for k, v in tel.counters.items()})
    s = codec.mav.signing
    if codec.signing_enabled:
        out.update(
            {
                "signing.good": int(s.goodsig_count),
                "signing.bad": int(s.badsig_count),
                "signing.unsigned_accepted": int(s.unsigned_count),
                "signing.rejected": int(s.reject_count),
            }
        )
    out.update({f"statustext.{k}": getattr(texts, k) for k in ("sent", "dropped")})
    out.update({f"service.{k}": v for k, v in service.items()})
    return out


class ProblemReporter:
    """Logs, for each problem counter, how much it grew since the last report."""

    def __init__(self) -> None:
        self._snapshot: dict[str, int] = {}

    def report(self, values: dict[str, int]) -> None:
        for name, value in values.items():
            prev = self._snapshot.get(name, 0)
            if value > prev and is_problem(name):
                once = name.startswith(WARN_ONCE) and prev > 0
                level = logging.DEBUG if once else logging.WARNING
                log.log(level, "%s: +%d (total %d)", name, value - prev, value)
        self._snapshot = values


__all__ = [
    "PROBLEM_PREFIXES",
    "WARN_ONCE",
    "ProblemReporter",
    "ServiceCounters",
    "collect",
    "is_problem",
]
