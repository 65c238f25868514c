"""Planner.step: steady state and horizontal re-plans, from real flights.

Steady state: every cycle of the paper scenario (7 obstacle + 4 surface sensors) that did
not search for a correction, pooled over `runs` flights; and the same cycles replayed from
their recorded inputs, the least of 5 replays per cycle (the machine's interruptions
removed: steadier on a busy machine, and a floor for the pooled figures).
Re-plan: the cycles that searched (a correction accepted, none found and the planner
blocked, or a search that used its budget and goes on next cycle), from every scenario (flown
two at a time, each in its own process on its own core where the machine has two: every
step's duration is its own process's), and the paper's re-plan cycles replayed `replays`
times each from a deep copy of the planner.
The work units a cycle spends searching (candidate corrections tried) are counted too: a
bound that does not depend on the machine (`planner.SEARCH_BUDGET_UNITS`).

Ratios: the machine's load moves every duration, so each is also given against the floor
measured in the same run: the paper's equations alone on the same recorded inputs (eqs
(1)-(2), (6) and (7) for every reading, numpy; the least of 5 replays per cycle, median
over the cycles).
"""

from __future__ import annotations

import copy
import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from bench.flight import Flight, fly, load, replay_min, scenario_names, split
from bench.report import Section, percentiles_us
from companion.planner import SEARCH_BUDGET_UNITS, SEARCH_BUDGET_UNITS_AT_REST, VehicleState
from companion.planner.decision import decide, steepness, thresholds
from companion.planner.rotations import r_g
from companion.planner.sensors import SURFACE_FOR_GROUP, Group, range_points_world
from companion.planner.types import FloatArray
from companion.sim.scenario import Scenario


def paper_equations(scenario: Scenario) -> Callable[[VehicleState, FloatArray], object]:
    """One cycle of the paper's equations alone on a state and its ranges: eqs (1)-(2) for
    every reading, eq. (6) for every obstacle reading against its group's surface point,
    eq. (7)'s decision (the floor the planner's step is compared with)."""
    sensors = scenario.sensor_table()
    params = scenario.params()
    obs = sensors.obstacle_index
    surface = sensors.surface_index
    ground_rows = np.array(
        [
            surface.get(SURFACE_FOR_GROUP[g], surface[Group.SURFACE_FORWARD])
            for g in sensors.obstacle_groups
        ],
        dtype=np.intp,
    )
    limit = thresholds(sensors.obstacle_groups, params)

    def cycle(state: VehicleState, ranges: FloatArray) -> object:
        rot = r_g(state.roll_rad, state.pitch_rad, state.yaw_rad)
        valid = sensors.valid(ranges)
        points = range_points_world(state.position_enu, rot, sensors.boresights_flu, ranges)
        return decide(steepness(points[obs], points[ground_rows], valid[obs]), limit)

    return cycle


def equations_floor_us(scenario: Scenario, flight: Flight, replays: int = 5) -> float:
    """Median over the flight's cycles of the least of `replays` timings of the paper's
    equations alone (`paper_equations`) on that cycle's recorded inputs. Microseconds."""
    clock = time.perf_counter_ns
    equations = paper_equations(scenario)
    best = np.full(flight.cycles, np.iinfo(np.int64).max, dtype=np.int64)
    for _ in range(replays):
        for k, (state, ranges) in enumerate(zip(flight.states, flight.ranges, strict=True)):
            t0 = clock()
            equations(state, ranges)
            best[k] = min(best[k], clock() - t0)
    return float(np.median(best)) / 1e3


FLIGHT_WORKERS = 2


def searching_cycles(name: str) -> tuple[np.ndarray, dict[str, int]]:
    """One flight of scenario `name`: its searching cycles' step durations (ns) and the
    search work units it spent (per flight and the most in one cycle)."""
    f = fly(*load(name), name)
    _, replan_ns = split(f)
    spent = np.asarray(f.search_units)
    return replan_ns, {
        "search_cycles": int(np.count_nonzero(f.replan)),
        "units": int(spent.sum()),
        "max_units_per_cycle": int(spent.max()) if len(spent) else 0,
    }


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
        ("<=", 30),
    )
    sec.add("planner.steady.p99_us", "step, steady, p99", st["p99"], "us", ("<=", 100))
    sec.add("planner.steady.max_us", "step, steady, max", st["max"], "us")
    floor_us = equations_floor_us(scenario, flight)
    sec.details["paper_equations_floor_us"] = floor_us
    sec.add("planner.floor_us", "floor: the paper's equations alone, median", floor_us, "us")
    sec.add(
        "planner.steady.median_ratio",
        "step, steady, median / floor",
        st["median"] / floor_us,
        "x",
    )
    sec.add("planner.steady.p99_ratio", "step, steady, p99 / floor", st["p99"] / floor_us, "x")
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
    sec.add(
        "planner.steady_replayed.median_ratio",
        "step, steady, median (least of 5 replays) / floor",
        steady_best["median"] / floor_us,
        "x",
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
    units: dict[str, dict[str, int]] = {}
    names = scenario_names()
    workers = min(FLIGHT_WORKERS, os.cpu_count() or 1)
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for name, (r, spent) in zip(names, pool.map(searching_cycles, names), strict=True):
            pooled.append(r)
            per_scenario[name] = percentiles_us(r)
            units[name] = spent
    sec.details["scenario_flight_workers"] = workers
    all_rp = percentiles_us(np.concatenate(pooled))
    sec.details["replan_all_scenarios_us"] = per_scenario
    sec.details["search_units_per_scenario"] = units
    sec.details["search_budget_units"] = SEARCH_BUDGET_UNITS
    sec.details["search_budget_units_at_rest"] = SEARCH_BUDGET_UNITS_AT_REST
    sec.add(
        "planner.replan.max_units",
        f"search work units in one cycle, max (all scenarios; budget {SEARCH_BUDGET_UNITS}, "
        f"at rest {SEARCH_BUDGET_UNITS_AT_REST})",
        max(u["max_units_per_cycle"] for u in units.values()),
        "units",
        ("<=", SEARCH_BUDGET_UNITS),
    )
    sec.add(
        "planner.replan.all_p99_us",
        f"step, re-plan or blocked (all scenarios, n={all_rp['n']}), p99",
        all_rp["p99"],
        "us",
        ("<=", 1000),
    )
    sec.add(
        "planner.replan.all_max_us",
        "step, re-plan or blocked (all), max",
        all_rp["max"],
        "us",
        ("<=", 5000),
    )
    sec.add(
        "planner.replan.all_p99_ratio",
        "step, re-plan or blocked (all), p99 / floor",
        all_rp["p99"] / floor_us,
        "x",
    )
    sec.add(
        "planner.replan.all_max_ratio",
        "step, re-plan or blocked (all), max / floor",
        all_rp["max"] / floor_us,
        "x",
    )
    return sec, flight
