"""The flight log: one JSON line per cycle, and a reader that turns it back into arrays.

Files `flight-YYYYmmdd-HHMMSS[-N].jsonl` in the configured directory. The first line of each
file is a header record; then records by `type`:

    {"type": "header", "version": 1, "sensors": [...], "config": {...}, ...}
    {"type": "frame", "t": .., "origin": [lat, lon, alt_amsl], "route": [[x, y], ...]}
    {"type": "cycle", "t": s, "health": "active", "own": "engaged", "verdict": "run",
     "reason": "", "pos": [x, y, z] | null, "rpy": [roll, pitch, yaw] | null,
     "ranges": [m | null, ...], "sp": {"p": [x, y, z], "v": [vx, vy, vz], "a": [ax, ay, az],
     "yaw": rad, "pitch": rad} | null, "sp_kind": "planner" | "hold" | "brake" | "prime" | null,
     "decision": str | null, "mode": str | null, "side": str | null,
     "min_range": m | null, "phi_star": [rad, ...] | null, "phi_star_threshold": [rad, ...]
     | null, "phi_d": rad | null, "v_ref": m/s | null, "replanned": bool, "finished": bool,
     "events": [str, ...]}
    {"type": "route", "t": .., "points": [[x, y], ...], "start_heading_rad": ..,
     "arrival_heading_rad": ..}   (each time the planner starts on a route)
    {"type": "counters", "t": .., "counters": {name: n, ...}}
    {"type": "planner", "t": .., "planner": {...}}   (the `planner:` section in force after
     a change in flight, e.g. a PARAM_SET)

Frames as the planner's: local ENU metres anchored at home, yaw counter-clockwise from east,
ranges in metres with 0 = nothing detected and null = missing/stale. Non-finite numbers are
written as null (JSON has no NaN). Lines are buffered in memory and written by `flush`,
which the service calls about once a second, so a cycle does no file I/O.
"""

from __future__ import annotations

import contextlib
import functools
import json
import json.encoder
import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.planner.types import FloatArray

log = logging.getLogger(__name__)

LOG_VERSION = 1


def clean(value: Any) -> Any:
    """JSON-safe copy: numpy to lists, non-finite floats to None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, np.ndarray):
        return (
            [clean(float(v)) for v in value.ravel()]
            if value.ndim <= 1
            else [clean(row) for row in value]
        )
    if isinstance(value, (np.floating, np.integer)):
        return clean(value.item())
    if isinstance(value, dict):
        return {str(k): clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [clean(v) for v in value]
    return value


def _plain(value: Any) -> Any:
    """`json` hook for numpy values (finite ones; a non-finite one raises and `dumps_record`
    falls back to `clean`)."""
    if isinstance(value, np.ndarray):
        return (
            value.tolist()
            if value.dtype.kind in "iub" or np.isfinite(value).all()
            else clean(value)
        )
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def floats(value: Any) -> Any:
    """A 1-D float array as the list the log writes (non-finite values as None, as `clean`
    does); anything else unchanged. Records built with it encode without `_plain`'s
    per-array hook."""
    if isinstance(value, np.ndarray) and value.ndim == 1 and value.dtype.kind == "f":
        out: list[Any] = value.tolist()
        if all(map(math.isfinite, out)):
            return out
        return [v if math.isfinite(v) else None for v in out]
    return value


def _record_encoder() -> Callable[[Any], str]:
    """`json.dumps(record, separators=(",", ":"), allow_nan=False, default=_plain)`, with
    its encoder made once (json makes one per call): the C encoder where json has it.
    Records are trees (no circular check)."""
    make = getattr(json.encoder, "c_make_encoder", None)
    ascii_str = getattr(json.encoder, "c_encode_basestring_ascii", None)
    if make is None or ascii_str is None:
        return functools.partial(json.dumps, separators=(",", ":"), allow_nan=False, default=_plain)
    encode = make(None, _plain, ascii_str, None, ":", ",", False, False, False)

    def dumps(record: Any) -> str:
        return "".join(encode(record, 0))

    return dumps


_dumps_plain = _record_encoder()


def dumps_record(record: dict[str, Any]) -> str:
    """One compact JSON line, the same text as `json.dumps(clean(record))`: encoded
    directly when every float is finite and every key a str (the usual record), through
    `clean` otherwise (non-finite floats become null)."""
    try:
        return _dumps_plain(record)
    except (ValueError, TypeError):
        return json.dumps(clean(record), separators=(",", ":"))


class FlightLogWriter:
    """Buffered JSON-lines writer with size rotation and a bound on the files kept."""

    def __init__(self, directory: Path, max_bytes: int = 50_000_000, keep_files: int = 20):
        self.directory = directory
        self.max_bytes = max_bytes
        self.keep_files = keep_files
        self._lines: list[str] = []
        self._file: Any = None
        self._size = 0
        self._part = 0
        self._stem = time.strftime("flight-%Y%m%d-%H%M%S")
        self._header: dict[str, Any] | None = None
        self.path: Path | None = None
        self.errors = 0
        self.records = 0
        self.failing = ""
        """Why the last write failed ("" while writing works)."""

    def header(self, header: dict[str, Any]) -> None:
        self._header = {"type": "header", "version": LOG_VERSION, **header}
        self._lines.append(json.dumps(clean(self._header)))

    def write(self, record: dict[str, Any]) -> None:
        self.records += 1
        self._lines.append(dumps_record(record))
        if len(self._lines) > 100_000:  # disk gone: keep memory bounded
            del self._lines[:-10_000]
            self.errors += 1

    def flush(self) -> None:
        if not self._lines:
            return
        lines, self._lines = self._lines, []
        try:
            if self._file is None:
                self._open()
            data = "\n".join(lines) + "\n"
            self._file.write(data)
            self._file.flush()
            self._size += len(data)
            if self._size >= self.max_bytes:
                self._rotate()
        except OSError as exc:
            # disk full, read-only, gone: the records are lost, flying goes on; said once
            self.errors += 1
            why = exc.strerror or str(exc)
            if why != self.failing:
                log.warning("flight log: %s (records are being lost)", exc)
            self.failing = why
            if self._file is not None:
                with contextlib.suppress(OSError):
                    self._file.close()
            self._file = None
            return
        if self.failing:
            log.info("flight log: writing again (%s)", self.path)
            self.failing = ""

    def _open(self) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        suffix = f"-{self._part}" if self._part else ""
        self.path = self.directory / f"{self._stem}{suffix}.jsonl"
        self._file = self.path.open("a", encoding="utf-8")
        self._size = self.path.stat().st_size
        if self._part and self._header is not None:
            line = json.dumps(clean(self._header)) + "\n"
            self._file.write(line)
            self._size += len(line)
        self._prune()

    def _rotate(self) -> None:
        self._file.close()
        self._file = None
        self._part += 1

    def _prune(self) -> None:
        files = sorted(self.directory.glob("flight-*.jsonl"), key=lambda p: p.stat().st_mtime)
        for old in files[: max(0, len(files) - self.keep_files)]:
            if old != self.path:
                with contextlib.suppress(OSError):
                    old.unlink()

    def close(self) -> None:
        self.flush()
        if self._file is not None:
            with contextlib.suppress(OSError):
                self._file.close()
            self._file = None


# --- reading -------------------------------------------------------------------------------


def iter_records(path: Path) -> Iterator[dict[str, Any]]:
    """Records of a flight log file; a torn last line (crash) is skipped."""
    with path.open(encoding="utf-8") as f:
        for line in f:
            line = line.strip()
            if not line:
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(rec, dict):
                yield rec


def _vec(value: Any, n: int) -> list[float]:
    if not isinstance(value, list) or len(value) != n:
        return [math.nan] * n
    return [math.nan if v is None else float(v) for v in value]


@dataclass
class FlightLog:
    """A flight log as arrays, one row per cycle (NaN where a value was absent)."""

    header: dict[str, Any]
    t_s: FloatArray
    position_enu: FloatArray
    """(n, 3) vehicle position."""
    rpy_rad: FloatArray
    """(n, 3) roll, pitch, yaw (ENU/FLU)."""
    ranges_m: FloatArray
    """(n, k) range readings in sensor-table order."""
    setpoint_position_enu: FloatArray
    setpoint_velocity_enu: FloatArray
    setpoint_yaw_rad: FloatArray
    setpoint_pitch_rad: FloatArray
    setpoint_kind: list[str | None]
    health: list[str]
    verdict: list[str]
    decision: list[str | None]
    path_mode: list[str | None]
    side: list[str | None]
    min_range_m: FloatArray
    finished: np.ndarray
    phi_star_rad: FloatArray = field(default_factory=lambda: np.empty((0, 0)))
    """(n, m) phi_i* per obstacle sensor (NaN where the planner did not run)."""
    phi_star_threshold_rad: FloatArray = field(default_factory=lambda: np.empty((0, 0)))
    phi_d_rad: FloatArray = field(default_factory=lambda: np.empty(0))
    speed_ref_mps: FloatArray = field(default_factory=lambda: np.empty(0))
    replanned: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=bool))
    events: list[tuple[float, str]] = field(default_factory=list)
    frames: list[dict[str, Any]] = field(default_factory=list)
    routes: list[dict[str, Any]] = field(default_factory=list)
    """Each route the planner started on: base points (home ENU) and headings."""
    counters: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.t_s)


def read_flight_log(path: Path) -> FlightLog:
    """Read a flight log file (see the module docstring for the format)."""
    header: dict[str, Any] = {}
    frames: list[dict[str, Any]] = []
    routes: list[dict[str, Any]] = []
    counters: dict[str, int] = {}
    events: list[tuple[float, str]] = []
    rows: list[dict[str, Any]] = []
    for rec in iter_records(path):
        kind = rec.get("type")
        if kind == "header" and not header:
            header = rec
        elif kind == "frame":
            frames.append(rec)
        elif kind == "route":
            routes.append(rec)
        elif kind == "counters":
            counters = dict(rec.get("counters", {}))
        elif kind == "cycle":
            rows.append(rec)
            for e in rec.get("events", []):
                events.append((float(rec.get("t", math.nan)), str(e)))
    k = len(header.get("sensors", [])) or max((len(r.get("ranges") or []) for r in rows), default=0)

    m = max((len(r.get("phi_star") or []) for r in rows), default=0)

    def arr(key: str, n: int) -> FloatArray:
        return np.array([_vec(r.get(key), n) for r in rows], dtype=np.float64).reshape(len(rows), n)

    def sp(key: str, n: int) -> FloatArray:
        vals = [_vec((r.get("sp") or {}).get(key), n) for r in rows]
        return np.array(vals, dtype=np.float64).reshape(-1, n)

    def scalar(v: Any) -> float:
        return math.nan if v is None else float(v)

    return FlightLog(
        header=header,
        t_s=np.array([scalar(r.get("t")) for r in rows], dtype=np.float64),
        position_enu=arr("pos", 3),
        rpy_rad=arr("rpy", 3),
        ranges_m=arr("ranges", k),
        setpoint_position_enu=sp("p", 3),
        setpoint_velocity_enu=sp("v", 3),
        setpoint_yaw_rad=np.array(
            [scalar((r.get("sp") or {}).get("yaw")) for r in rows], dtype=np.float64
        ),
        setpoint_pitch_rad=np.array(
            [scalar((r.get("sp") or {}).get("pitch")) for r in rows], dtype=np.float64
        ),
        setpoint_kind=[r.get("sp_kind") for r in rows],
        health=[str(r.get("health", "")) for r in rows],
        verdict=[str(r.get("verdict", "")) for r in rows],
        decision=[r.get("decision") for r in rows],
        path_mode=[r.get("mode") for r in rows],
        side=[r.get("side") for r in rows],
        min_range_m=np.array([scalar(r.get("min_range")) for r in rows], dtype=np.float64),
        finished=np.array([bool(r.get("finished", False)) for r in rows], dtype=bool),
        phi_star_rad=arr("phi_star", m),
        phi_star_threshold_rad=arr("phi_star_threshold", m),
        phi_d_rad=np.array([scalar(r.get("phi_d")) for r in rows], dtype=np.float64),
        speed_ref_mps=np.array([scalar(r.get("v_ref")) for r in rows], dtype=np.float64),
        replanned=np.array([bool(r.get("replanned", False)) for r in rows], dtype=bool),
        events=events,
        frames=frames,
        routes=routes,
        counters=counters,
    )
