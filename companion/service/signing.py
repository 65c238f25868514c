"""MAVLink 2 signing: the secret key file and the persisted signing timestamp.

The key file holds the 32-byte secret either as 64 hexadecimal characters (whitespace
ignored) or as exactly 32 raw bytes. Keep it readable only by the service's user.

The signing timestamp counts 10 microsecond units since 2015-01-01 00:00 UTC and must never
go backwards for a given link, or the autopilot rejects our messages as replays. A companion
computer often has no real-time clock (a Raspberry Pi boots with a stale clock), so the last
timestamp is kept in a small state file, saved periodically and at shutdown, and a restart
resumes from `max(wall clock, saved + margin)`; the margin covers the time between the last
save and a crash.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from companion.service import clock
from companion.signing_key import SigningKeyError, load_key

log = logging.getLogger(__name__)

SIGNING_EPOCH_UNIX_S = 1420070400
"""2015-01-01 00:00:00 UTC, the MAVLink signing epoch."""
TICKS_PER_SECOND = 100_000
"""The signing timestamp's unit is 10 microseconds."""
SAVE_INTERVAL_S = 10.0
RESUME_MARGIN_TICKS = int(2 * SAVE_INTERVAL_S * TICKS_PER_SECOND)


def timestamp_now(unix_time_s: float | None = None) -> int:
    """The signing timestamp of a wall-clock time (now by default)."""
    t = clock.unix_time_s() if unix_time_s is None else unix_time_s
    return max(0, int((t - SIGNING_EPOCH_UNIX_S) * TICKS_PER_SECOND))


class SigningState:
    """The persisted signing timestamp (a JSON file `{"timestamp": N}`)."""

    def __init__(self, path: Path | None) -> None:
        self.path = path

    def load(self) -> int:
        """The saved timestamp, 0 when there is none (missing or unreadable file)."""
        if self.path is None:
            return 0
        try:
            data = json.loads(self.path.read_text())
            value = int(data["timestamp"])
        except FileNotFoundError:
            return 0
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("signing state %s unreadable (%s); starting from the clock", self.path, exc)
            return 0
        return max(0, value)

    def initial_timestamp(self, unix_time_s: float | None = None) -> int:
        """Where to start signing: after the saved value (plus margin) and the clock."""
        saved = self.load()
        start = max(timestamp_now(unix_time_s), saved + RESUME_MARGIN_TICKS if saved else 0)
        return start

    def save(self, timestamp: int) -> None:
        """Write atomically (temp file + rename); errors are logged, never raised."""
        if self.path is None:
            return
        tmp = self.path.with_name(self.path.name + ".tmp")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(json.dumps({"timestamp": int(timestamp)}))
            os.replace(tmp, self.path)
        except OSError as exc:
            log.warning("cannot save signing state to %s: %s", self.path, exc)


__all__ = ["SigningKeyError", "SigningState", "load_key", "timestamp_now"]
