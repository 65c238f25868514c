"""Instructions per planner cycle, counted by valgrind: a figure the machine's load does not
move.

On a shared machine the wall-clock figures move 2-3 times between runs; the instructions a
cycle executes do not (the same commit, Python and numpy count the same to within a fraction
of a percent). The planner benchmark's paper flight is replayed from its recorded inputs in a
child process under `valgrind --tool=cachegrind --cache-sim=no` twice: up to the first
cycle of a stretch of steady cycles, and up to its end. The difference over the stretch is
the planner's instructions per steady cycle: the interpreter's start, the imports and the
cycles before the stretch are in both counts and cancel. The paper's equations alone (the
floor of the planner benchmark, `bench.planner.paper_equations`) are counted the same way,
and the ratio of the two is "step / floor" without the machine's noise. Where valgrind is not
installed (Debian: `apt install valgrind`) the figures are n/a and the run says so.

Child mode (what valgrind runs): `python -m bench.instructions FILE KIND CYCLES`, replaying
the first CYCLES cycles of the pickled flight FILE with KIND `planner` or `floor`.
"""

from __future__ import annotations

import os
import pickle
import re
import shutil
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from bench.flight import Flight, load
from bench.planner import paper_equations
from bench.report import REPO, Section
from companion.planner import Planner

KINDS = ("planner", "floor")
_IREFS = re.compile(r"I\s+refs:\s+([\d,]+)")


def parse_irefs(valgrind_stderr: str) -> int:
    """The instruction count (cachegrind's "I refs") in valgrind's report."""
    match = _IREFS.search(valgrind_stderr)
    if match is None:
        raise RuntimeError(f"no instruction count in valgrind's output: {valgrind_stderr[-300:]}")
    return int(match.group(1).replace(",", ""))


def steady_window(searching: list[bool], cycles: int, warmup: int) -> tuple[int, int]:
    """[start, stop) of `cycles` consecutive cycles from `warmup` on with no searching cycle
    (a re-plan costs hundreds of steady cycles' instructions); the longest such stretch when
    none is that long."""
    flags = np.asarray(searching, dtype=bool)
    best = (warmup, warmup)
    start = warmup
    for k in range(warmup, len(flags) + 1):
        if k == len(flags) or flags[k]:
            if k - start > best[1] - best[0]:
                best = (start, k)
            if k - start >= cycles:
                return start, start + cycles
            start = k + 1
    return best


def _count(path: Path, kind: str, cycles: int) -> int:
    """Instructions valgrind counts in a child replaying the first `cycles` cycles."""
    # the same dict layouts and one BLAS thread (a pool of threads spins: a count of its own)
    env = dict(os.environ, PYTHONHASHSEED="0", OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    proc = subprocess.run(
        [
            "valgrind",
            "--tool=cachegrind",
            "--cache-sim=no",
            "--cachegrind-out-file=/dev/null",
            sys.executable,
            "-m",
            "bench.instructions",
            str(path),
            kind,
            str(cycles),
        ],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"valgrind exited with {proc.returncode}: {proc.stderr[-500:]}")
    return parse_irefs(proc.stderr)


def run(flight: Flight, cycles: int = 1000, warmup: int = 100) -> Section:
    """The instructions section: the paper flight's steady cycles, planner and floor."""
    sec = Section("planner, instructions (valgrind)")
    valgrind = shutil.which("valgrind")
    label = "step, paper 7+4 sensors, steady, instructions per cycle"
    if valgrind is None:
        note = "valgrind not found (Debian: apt install valgrind)"
        sec.details["skipped"] = note
        sec.add("instructions.planner_per_cycle_k", label, float("nan"), "k instr", note=note)
        return sec
    start, stop = steady_window(flight.replan, cycles, warmup)
    with tempfile.TemporaryDirectory(prefix="bench-instructions-") as tmp:
        path = Path(tmp) / "flight.pickle"
        with path.open("wb") as fh:
            pickle.dump((flight.scenario, flight.states, flight.ranges, flight.dt_s), fh)
        jobs = [(kind, n) for kind in KINDS for n in (start, stop)]
        with ThreadPoolExecutor(max_workers=min(len(jobs), os.cpu_count() or 1)) as pool:
            counts = list(pool.map(lambda job: _count(path, *job), jobs))
    per_cycle = {  # thousands of instructions
        kind: (counts[2 * i + 1] - counts[2 * i]) / (stop - start) / 1e3
        for i, kind in enumerate(KINDS)
    }
    version = subprocess.run(
        [valgrind, "--version"], capture_output=True, text=True, check=False
    ).stdout.strip()
    sec.details.update(
        valgrind=version,
        window=[start, stop],
        counts=dict(zip([f"{k}@{n}" for k, n in jobs], counts, strict=True)),
    )
    sec.add("instructions.planner_per_cycle_k", label, per_cycle["planner"], "k instr")
    sec.add(
        "instructions.floor_per_cycle_k",
        "floor: the paper's equations alone, instructions per cycle",
        per_cycle["floor"],
        "k instr",
    )
    sec.add(
        "instructions.ratio",
        f"step / floor, in instructions (cycles {start}-{stop})",
        per_cycle["planner"] / per_cycle["floor"],
        "x",
    )
    return sec


def _replay(path: Path, kind: str, cycles: int) -> None:
    """Child mode: replay the first `cycles` cycles of the pickled flight."""
    with path.open("rb") as fh:
        name, states, ranges, dt_s = pickle.load(fh)
    scenario, world = load(name)
    if kind == "planner":
        planner = Planner(
            scenario.params(), scenario.sensor_table(), scenario.route_obj(), scenario.start(world)
        )
        for state, r in zip(states[:cycles], ranges[:cycles], strict=True):
            planner.step(state, r, dt_s)
    else:
        equations = paper_equations(scenario)
        for state, r in zip(states[:cycles], ranges[:cycles], strict=True):
            equations(state, r)


if __name__ == "__main__":
    file, kind, n = sys.argv[1:4]
    if kind not in KINDS:
        raise SystemExit(f"kind must be one of {KINDS}, got {kind!r}")
    _replay(Path(file), kind, int(n))
