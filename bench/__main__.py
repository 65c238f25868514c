"""`python -m bench [--quick] [--only NAME ...] [--out FILE]`: run the benchmarks, print the
table, write the results (default bench/results.json)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from bench import arc, instructions, planner, raycast, service, simulator, sweep
from bench.report import Section, machine, table, write_results

NAMES = ("planner", "instructions", "arc", "simulator", "raycast", "service", "sweep")
"""`--quick` leaves out "instructions" (valgrind: about a minute) unless `--only` names it."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__)
    parser.add_argument(
        "--quick",
        action="store_true",
        help="fewer repeats (a smoke run); leaves out 'instructions' unless --only names it",
    )
    parser.add_argument("--only", nargs="+", choices=NAMES, help="run only these benchmarks")
    parser.add_argument(
        "--out",
        type=Path,
        default=Path(__file__).resolve().parent / "results.json",
        help="where to write the results (default: bench/results.json)",
    )
    args = parser.parse_args(argv)
    only = set(args.only or NAMES)
    if args.quick and not args.only:
        only.discard("instructions")
    quick = args.quick
    meta = machine()
    started = time.perf_counter()
    sections: list[Section] = []

    def log(text: str) -> None:
        print(f"[{time.perf_counter() - started:6.1f} s] {text}", file=sys.stderr, flush=True)

    # The planner benchmark's paper flight also feeds the arc, simulator and ray benchmarks.
    log("planner: flying the paper scenario and every scenario")
    sec, flight = planner.run(runs=1 if quick else 3, replays=10 if quick else 100)
    if "planner" in only:
        sections.append(sec)
    if "instructions" in only:
        log("planner instructions per cycle under valgrind (the paper flight replayed)")
        sections.append(instructions.run(flight, cycles=200 if quick else 1000))
    if "arc" in only:
        log("arc-length stepping")
        sections.append(arc.run(flight, max_iterations=50_000 if quick else 400_000))
    if "simulator" in only:
        log("simulator in process")
        sections.append(simulator.run(flight, runs=1 if quick else 3))
    if "raycast" in only:
        log("ray casting")
        sections.append(raycast.run(flight, poses=100 if quick else 300))
    if "service" in only:
        log("service over UDP: real time (about a minute), lockstep for a simulated hour")
        sections.append(service.run(quick))
    if "sweep" in only:
        against = "" if quick else " against 1"
        log(f"random-world sweep: a pool of {sweep.WORKERS} workers{against}")
        sections.append(sweep.run(quick))
    meta["wall_s"] = round(time.perf_counter() - started, 1)
    meta["quick"] = quick
    if only >= set(NAMES) - ({"instructions"} if quick else set()):
        run_sec = Section("this run")
        run_sec.add(
            "bench.wall_s",
            f"wall time of every benchmark{' (--quick)' if quick else ''}",
            meta["wall_s"],
            "s",
            ("<=", 90) if quick else None,
        )
        sections.append(run_sec)
    print(table(sections))
    write_results(args.out, sections, meta)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
