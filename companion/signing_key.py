"""The MAVLink 2 signing key file: 32 secret bytes as 64 hexadecimal characters (whitespace
ignored) or exactly 32 raw bytes. Read by the service (`companion.service.signing`) and checked
by the config at load time, so it lives below both.
"""

from __future__ import annotations

import logging
import stat
from pathlib import Path

log = logging.getLogger("companion.service.signing")


class SigningKeyError(ValueError):
    """The key file is missing, unreadable or not a 32-byte key."""


def load_key(path: Path) -> bytes:
    """The 32-byte secret from `path` (64 hex characters, or 32 raw bytes)."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise SigningKeyError(f"cannot read signing key file {path}: {exc.strerror}") from None
    try:
        mode = path.stat().st_mode
        if mode & (stat.S_IRWXG | stat.S_IRWXO):
            log.warning("signing key file %s is readable by others; chmod 600 it", path)
    except OSError:
        pass
    text = b"".join(raw.split())
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    if len(raw) == 32:
        return raw
    raise SigningKeyError(
        f"signing key file {path}: expected 64 hexadecimal characters or 32 raw bytes, "
        f"found {len(raw)} bytes"
    )


__all__ = ["SigningKeyError", "load_key"]
