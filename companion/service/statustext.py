"""STATUSTEXT to the pilot: rate limited, repeats suppressed, every message also logged.

A token bucket (`max_per_s`, `burst`) bounds the traffic; the same text is not repeated
within `repeat_interval_s`; the queue is bounded and what does not fit is dropped and
counted. A text longer than the 50 characters of one STATUSTEXT goes out in chunks (MAVLink 2
`id`/`chunk_seq`, as ArduPilot sends long texts; ground stations join them), at most
MAX_CHUNKS of them; the log always has the whole text.
"""

from __future__ import annotations

import enum
import logging
from collections import deque

from companion.service.codec import MAVLinkMessage, mavlink2

log = logging.getLogger("companion.pilot")

TEXT_LEN = 50
QUEUE_LEN = 32


class Severity(enum.IntEnum):
    EMERGENCY = 0
    ALERT = 1
    CRITICAL = 2
    ERROR = 3
    WARNING = 4
    NOTICE = 5
    INFO = 6


_LOG_LEVEL = {
    Severity.EMERGENCY: logging.CRITICAL,
    Severity.ALERT: logging.CRITICAL,
    Severity.CRITICAL: logging.ERROR,
    Severity.ERROR: logging.ERROR,
    Severity.WARNING: logging.WARNING,
    Severity.NOTICE: logging.INFO,
    Severity.INFO: logging.INFO,
}


MAX_CHUNKS = 4


def statustext_message(severity: Severity, text: str) -> MAVLinkMessage:
    """One STATUSTEXT with the first 50 bytes of `text` (no chunking)."""
    raw = text.encode("utf-8", "replace")[:TEXT_LEN]
    return mavlink2.MAVLink_statustext_message(int(severity), raw, 0, 0)


def statustext_messages(severity: Severity, text: str, msg_id: int) -> list[MAVLinkMessage]:
    """`text` as STATUSTEXT chunks of 50 bytes sharing `msg_id` (1-65535; 0 = one message)."""
    raw = text.encode("utf-8", "replace")
    if len(raw) <= TEXT_LEN:
        return [mavlink2.MAVLink_statustext_message(int(severity), raw, 0, 0)]
    chunks = [raw[i : i + TEXT_LEN] for i in range(0, len(raw), TEXT_LEN)][:MAX_CHUNKS]
    return [
        mavlink2.MAVLink_statustext_message(int(severity), c, msg_id, seq)
        for seq, c in enumerate(chunks)
    ]


class StatusTexts:
    def __init__(self, max_per_s: float = 2.0, burst: int = 5, repeat_interval_s: float = 5.0):
        self.max_per_s = max_per_s
        self.burst = burst
        self.repeat_interval_s = repeat_interval_s
        self._tokens = float(burst)
        self._t_last: float | None = None
        self._queue: deque[tuple[Severity, str]] = deque()
        self._last_sent: dict[str, float] = {}
        self.sent = 0
        self.dropped = 0
        self.suppressed = 0

    def post(self, now: float, text: str, severity: Severity = Severity.INFO) -> None:
        log.log(_LOG_LEVEL[severity], "%s", text)
        last = self._last_sent.get(text)
        if last is not None and now - last < self.repeat_interval_s:
            self.suppressed += 1
            return
        if any(t == text for _, t in self._queue):
            self.suppressed += 1
            return
        if len(self._queue) >= QUEUE_LEN:
            self.dropped += 1
            return
        self._queue.append((severity, text))

    def drain(self, now: float) -> list[tuple[Severity, str]]:
        """The messages that may go out now."""
        if self._t_last is not None:
            self._tokens = min(
                float(self.burst), self._tokens + (now - self._t_last) * self.max_per_s
            )
        self._t_last = now
        out: list[tuple[Severity, str]] = []
        while self._queue and self._tokens >= 1.0:
            sev, text = self._queue.popleft()
            self._tokens -= 1.0
            self._last_sent[text] = now
            out.append((sev, text))
        self.sent += len(out)
        if len(self._last_sent) > 256:  # bounded memory
            cutoff = now - self.repeat_interval_s
            self._last_sent = {k: v for k, v in self._last_sent.items() if v >= cutoff}
        return out
