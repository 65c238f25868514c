"""In-process simulator speed: the paper scenario through `companion.harness.closed_loop.run`
(world, range sensors, planner, vehicle model, trace and clearance metrics), as simulated
seconds per wall second, with where a cycle's time goes (the timed flight of `bench.flight`)."""

from __future__ import annotations

import statistics
import time

import numpy as np

from bench.flight import Flight, load
from bench.report import Section
from companion.harness.closed_loop import run as closed_loop_run


def run(flight: Flight, runs: int = 3) -> Section:
    sec = Section("simulator, in process")
    scenario, world = load("paper")
    speeds = []
    cycle_us = []
    cycles = 0
    for _ in range(runs):
        t0 = time.perf_counter()
        result = closed_loop_run(scenario, world)
        wall = time.perf_counter() - t0
        cycles = len(result.trace["t"])
        speeds.append(cycles * scenario.dt_s / wall)
        cycle_us.append(wall / cycles * 1e6)
    speed = statistics.median(speeds)
    sec.details["speeds_x"] = speeds
    sec.details["cycles"] = cycles
    sec.details["same_flight_as_timed_loop"] = cycles == flight.cycles
    sec.add(
        "sim.inprocess.speed_x",
        f"paper scenario ({cycles * scenario.dt_s:.0f} s simulated), median of {runs}",
        speed,
        "x real time",
        (">=", 500),
    )
    parts = {
        "range sensors (World.raycast)": flight.sense_ns,
        "Planner.step": flight.step_ns,
        "vehicle model": flight.vehicle_ns,
        "clearance metrics (World distances)": flight.clearance_ns,
    }
    means_us = {label: float(np.mean(ns)) / 1e3 for label, ns in parts.items()}
    # The closed loop's own bookkeeping (the trace row, events): its cycle less the parts
    # timed in the flight above (two runs on a busy machine: an estimate, clamped at 0).
    rest = max(statistics.median(cycle_us) - sum(means_us.values()), 0.0)
    means_us["trace and bookkeeping (closed loop less the parts)"] = rest
    total = sum(means_us.values())
    sec.details["cycle_breakdown_mean_us"] = means_us
    for label, mean_us in means_us.items():
        key = "sim.cycle." + label.split()[0].lower().replace(".", "_")
        sec.add(key, f"per cycle: {label}", mean_us, f"us ({100 * mean_us / total:.0f}%)")
    return sec
