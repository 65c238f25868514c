"""Figures, the machine they were measured on, the printed table and bench/results.json."""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class Figure:
    """One measured number. target: the issue's goal as text ("<= 50"), "" if none.
    met: whether the target is met (None without a target); never a pass/fail of the run."""

    key: str
    label: str
    value: float
    unit: str
    target: str = ""
    met: bool | None = None
    note: str = ""


@dataclass
class Section:
    """The figures of one benchmark and the raw details behind them (for results.json)."""

    name: str
    figures: list[Figure] = field(default_factory=list)
    details: dict[str, Any] = field(default_factory=dict)

    def add(
        self,
        key: str,
        label: str,
        value: float,
        unit: str,
        target: tuple[str, float] | None = None,
        note: str = "",
    ) -> None:
        """Record a figure; target is (operator, bound) with operator "<=" or ">="."""
        text, met = "", None
        if target is not None:
            op, bound = target
            text = f"{op} {bound:g}"
            met = value <= bound if op == "<=" else value >= bound
        self.figures.append(Figure(key, label, float(value), unit, text, met, note))


def percentiles_us(samples_ns: list[int] | np.ndarray) -> dict[str, float]:
    """Median, p90, p99, max and mean of durations in nanoseconds, as microseconds."""
    a = np.asarray(samples_ns, dtype=np.float64) / 1e3
    if a.size == 0:
        return {"n": 0}
    return {
        "n": int(a.size),
        "median": float(np.median(a)),
        "p90": float(np.percentile(a, 90)),
        "p99": float(np.percentile(a, 99)),
        "max": float(a.max()),
        "mean": float(a.mean()),
    }


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(
            ["git", *args], cwd=REPO, capture_output=True, text=True, timeout=10, check=True
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip()


def machine() -> dict[str, Any]:
    """What the figures were measured on, and when, at which commit."""
    try:
        load: list[float] | None = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        load = None
    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    status = _git("status", "--porcelain", "--untracked-files=no")
    return {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "commit": _git("rev-parse", "HEAD"),
        "dirty": bool(status) if status is not None else None,
        "platform": platform.platform(),
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "load_average_1_5_15": load,
        "python": sys.version.split()[0],
        "implementation": platform.python_implementation(),
        "numpy": np.__version__,
    }


def _fmt(value: float) -> str:
    if value != value:  # NaN
        return "n/a"
    mag = abs(value)
    if mag == 0.0 or 0.01 <= mag < 1e6:
        return f"{value:,.3g}" if mag < 100 else f"{value:,.0f}"
    return f"{value:.2e}"


def table(sections: list[Section]) -> str:
    """The figures as a plain-text table, one section after another."""
    rows = [("benchmark", "value", "unit", "target", "")]
    for sec in sections:
        rows.append((f"[{sec.name}]", "", "", "", ""))
        for f in sec.figures:
            mark = "" if f.met is None else ("ok" if f.met else "MISSED")
            rows.append((f"  {f.label}", _fmt(f.value), f.unit, f.target, mark))
    widths = [max(len(r[i]) for r in rows) for i in range(5)]
    lines = []
    for i, r in enumerate(rows):
        lines.append(
            f"{r[0]:<{widths[0]}}  {r[1]:>{widths[1]}}  {r[2]:<{widths[2]}}  "
            f"{r[3]:<{widths[3]}}  {r[4]}".rstrip()
        )
        if i == 0:
            lines.append("-" * len(lines[0]))
    return "\n".join(lines)


def write_results(path: Path, sections: list[Section], meta: dict[str, Any]) -> None:
    doc = {
        "machine": meta,
        "figures": {f.key: asdict(f) for sec in sections for f in sec.figures},
        "details": {sec.name: sec.details for sec in sections},
    }
    path.write_text(json.dumps(doc, indent=2, default=float) + "\n", encoding="utf-8")
