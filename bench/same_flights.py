"""Do the scenarios fly the same? `python -m bench.same_flights record DIR`, then, after a
change, `python -m bench.same_flights compare DIR`.

`record` flies every scenario of config/scenarios as `companion simulate X.yaml --out
DIR/X --no-plots` does (metrics.json, trace.csv, events.txt) and also keeps the trace at
full precision (DIR/X/trace.npz; trace.csv rounds to 6 significant figures). `compare`
flies them again and prints, per scenario, the largest absolute difference of any metric and
of any trace value (both full precision), and whether the events, the trace's text columns
and its length are the same. Exit status 1 if any difference exceeds --tol (default 1e-6).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from bench.flight import SCENARIO_DIR, scenario_names
from companion.harness import metrics as metrics_mod
from companion.harness.closed_loop import run
from companion.harness.runner import write_outputs
from companion.sim.scenario import load_scenario
from companion.sim.world import World

TEXT_COLUMNS = ("decision", "mode", "side")


def fly_into(name: str, out_dir: Path) -> None:
    """Fly one scenario and write its outputs (as `companion simulate --no-plots`) and the
    full-precision trace and the obstacle memory at the end."""
    path = SCENARIO_DIR / f"{name}.yaml"
    scenario = load_scenario(path)
    world = World.from_config(scenario.world, path.parent)
    result = run(scenario, world)
    metrics = metrics_mod.for_run(scenario, world, result)
    write_outputs(out_dir, scenario, world, result, metrics, plots=False)
    arrays: dict[str, Any] = {"phi_star": result.phi_star, "memory_xy": result.memory_xy}
    for column, values in result.trace.items():
        text = column in TEXT_COLUMNS
        arrays[column] = np.asarray(values, dtype=str) if text else values
    np.savez(out_dir / "trace.npz", **arrays)


def _flatten(doc: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(doc, dict):
        out: dict[str, Any] = {}
        for k, v in doc.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    if isinstance(doc, list):
        out = {}
        for i, v in enumerate(doc):
            out.update(_flatten(v, f"{prefix}{i}."))
        return out
    return {prefix.rstrip("."): doc}


def _metric_diff(a: dict[str, Any], b: dict[str, Any]) -> tuple[float, list[str]]:
    """Largest absolute difference of the numeric metrics, and the keys that differ in kind
    or in a non-numeric value."""
    fa, fb = _flatten(a), _flatten(b)
    worst = 0.0
    other = sorted(set(fa) ^ set(fb))
    for key in set(fa) & set(fb):
        va, vb = fa[key], fb[key]
        numeric = (int, float)
        if isinstance(va, numeric) and isinstance(vb, numeric) and not isinstance(va, bool):
            if math.isfinite(va) and math.isfinite(vb):
                worst = max(worst, abs(float(va) - float(vb)))
            elif va != vb:
                other.append(key)
        elif va != vb:
            other.append(key)
    return worst, other


def compare_one(name: str, before: Path, after: Path) -> tuple[float, float, list[str]]:
    """(max metric difference, max trace difference, what else differs) of one scenario."""
    problems: list[str] = []
    m_before = json.loads((before / "metrics.json").read_text(encoding="utf-8"))
    m_after = json.loads((after / "metrics.json").read_text(encoding="utf-8"))
    metric_diff, other = _metric_diff(m_before, m_after)
    problems += [f"metric {k}" for k in other]
    if (before / "events.txt").read_text() != (after / "events.txt").read_text():
        problems.append("events")
    tb, ta = np.load(before / "trace.npz"), np.load(after / "trace.npz")
    trace_diff = 0.0
    for key in tb.files:
        xb, xa = tb[key], ta[key]
        if xb.shape != xa.shape:
            problems.append(f"trace {key} shape {xb.shape} -> {xa.shape}")
        elif xb.dtype.kind in "US":
            if not np.array_equal(xb, xa):
                problems.append(f"trace {key}")
        elif len(xb):
            same_nan = np.array_equal(np.isnan(xb), np.isnan(xa))
            if not same_nan:
                problems.append(f"trace {key} NaN")
            with np.errstate(invalid="ignore"):
                d = np.abs(xb - xa)
            finite = np.isfinite(d)
            if not np.array_equal(np.isinf(xb), np.isinf(xa)):
                problems.append(f"trace {key} inf")
            if finite.any():
                trace_diff = max(trace_diff, float(d[finite].max()))
    return metric_diff, trace_diff, problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.same_flights", description=__doc__)
    parser.add_argument("action", choices=("record", "compare"))
    parser.add_argument("dir", type=Path, help="where the recorded flights are (or go)")
    parser.add_argument("--tol", type=float, default=1e-6, help="largest difference allowed")
    parser.add_argument("--only", nargs="+", help="these scenarios only")
    args = parser.parse_args(argv)
    names = args.only or scenario_names()
    if args.action == "record":
        for name in names:
            fly_into(name, args.dir / name)
            print(f"recorded {name}", flush=True)
        return 0
    worst = 0.0
    failed = False
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            if not (args.dir / name / "trace.npz").exists():
                print(f"error: no recorded flight of {name} in {args.dir}", file=sys.stderr)
                return 2
            fly_into(name, Path(tmp) / name)
            m, t, problems = compare_one(name, args.dir / name, Path(tmp) / name)
            worst = max(worst, m, t)
            bad = problems or m > args.tol or t > args.tol
            failed |= bool(bad)
            note = "; differs: " + ", ".join(problems) if problems else ""
            print(f"{name:36s} metrics {m:.3g}  trace {t:.3g}{note}", flush=True)
    print(f"largest difference {worst:.3g} ({'FAIL' if failed else 'ok'}, tol {args.tol:g})")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
