"""Planner.step: steady state and horizontal re-plans, from real flights.

Steady state: every cycle of the paper scenario (7 obstacle + 4 surface sensors) that did
not search for a correction, pooled over `runs` flights; and the same cycles replayed from
their recorded inputs, the least of 5 replays per cycle (the machine's interruptions
removed: steadier on a busy machine, and a floor for the pooled figures).
Re-plan: the cycles that searched (a correction accepted, or none found and the planner
blocked), from every scenario, and the paper's re-plan cycles replayed `replays` times each
from a deep copy of the planner.
"""

from __future__ import annotations

import copy
import time

import numpy as np

from bench.flight import Flight, fly, load, replay_min, scenario_names, split
from bench.report import Section, percentiles_us


def run(runs: int = 3, replays: int = 100) -> tuple[Section, Flight]:
    """The planner section, and the last paper flight (its speeds feed the arc benchmark)."""
    sec = Section("planner")
    scenario, world = load("paper")
    flights = [fly(scenario, world, "paper") for _ in range(runs)]
    flight = flights[-1]
    steady_ns = np.concatenate([split(f)[0] for f in flights])
    paper_replan_ns = np.concatenate([split(f)[1] for f in flights])
    st = percentiles_us(steady_ns)
    sec.details["paper_steady_us"] = st
    sec.details["paper_cycles"] = flight.cycles
    sec.details["paper_runs"] = runs
    sec.details["paper_replan_cycles_us"] = percentiles_us(paper_replan_ns)
    sec.add(
        "planner.steady.median_us",
        "step, paper 7+4 sensors, steady, median",
        st["median"],
        "us",
        ("<=", 50),
    )
    sec.add("planner.steady.p99_us", "step, steady, p99", st["p99"], "us", ("<=", 150))
    sec.add("planner.steady.max_us", "step, steady, max", st["max"], "us")
    best = replay_min(scenario, world, flight, replays=5)
    steady_best = percentiles_us(best[~np.asarray(flight.replan, dtype=bool)])
    sec.details["paper_steady_min_of_5_replays_us"] = steady_best
    sec.add(
        "planner.steady_replayed.median_us",
        "step, steady, median (least of 5 replays per cycle)",
        steady_best["median"],
        "us",
    )
    sec.add(
        "planner.steady_replayed.p99_us",
        "step, steady, p99 (least of 5 replays per cycle)",
        steady_best["p99"],
        "us",
    )

    # Replays of the paper's re-plan cycles: many samples of the same real work.
    replan_cycles = frozenset(int(i) for i in np.flatnonzero(flight.replan))
    snap_flight = fly(scenario, world, "paper", snapshot_cycles=replan_cycles)
    replay_ns: list[int] = []
    clock = time.perf_counter_ns
    for snap in snap_flight.snapshots:
        for _ in range(replays):
            planner = copy.deepcopy(snap.planner)
            t0 = clock()
            planner.step(snap.state, snap.ranges, snap.dt_s)
            replay_ns.append(clock() - t0)
    rp = percentiles_us(replay_ns)
    sec.details["paper_replan_replays_us"] = rp
    sec.details["paper_replan_cycle_indices"] = sorted(replan_cycles)
    sec.add(
        "planner.replan.paper_replay_p99_us",
        f"step, re-plan (paper, {len(snap_flight.snapshots)} cycles x {replays}), p99",
        rp["p99"],
        "us",
        ("<=", 1000),
    )
    sec.add(
        "planner.replan.paper_replay_max_us", "step, re-plan (paper replays), max", rp["max"], "us"
    )

    # Every scenario's searching cycles, as flown (one sample each).
    per_scenario: dict[str, dict[str, float]] = {}
    pooled: list[np.ndarray] = []
    for name in scenario_names():
        f = flight if name == "paper" else fly(*load(name), name)
        _, r = split(f)
        pooled.append(r)
        per_scenario[name] = percentiles_us(r)
    all_rp = percentiles_us(np.concatenate(pooled))
    sec.details["replan_all_scenarios_us"] = per_scenario
    sec.add(
        "planner.replan.all_p99_us",
        f"step, re-plan or blocked (all scenarios, n={all_rp['n']}), p99",
        all_rp["p99"],
        "us",
        ("<=", 1000),
    )
    sec.add("planner.replan.all_max_us", "step, re-plan or blocked (all), max", all_rp["max"], "us")
    return sec, flight
