"""In-process simulator speed: the paper scenario through `companion.harness.closed_loop.run`
(world, range sensors, planner, vehicle model, trace and clearance metrics), as simulated
seconds per wall second, with where a cycle's time goes (the timed flight of `bench.flight`);
and the clearance metrics on a seeded random world (`World.surface_distance` along its route)
against the reference (the whole terrain raster made up front, its block-pruning search, the
hills one at a time), timed in turns."""

from __future__ import annotations

import statistics
import time

import numpy as np

from bench.flight import Flight, load
from bench.raycast import RANDOM_WORLD_SEED, route_poses
from bench.report import Section
from companion.harness.closed_loop import run as closed_loop_run
from companion.sim.world import World
from companion.sim.world.features import AdditiveSum, Feature
from companion.sim.world.raster import Raster
from companion.sim.worldgen import generate


class _OneByOne(AdditiveSum):
    MAX_BATCH = 0  # every feature on its own, as before the batched sum


def _reference_world() -> World:
    """The same world with the distance queries' reference parts: the whole terrain raster
    made up front, searched by block pruning alone, and the hills summed one at a time."""
    ref = World.from_config(generate(RANDOM_WORLD_SEED).world)
    sums: dict[tuple[int, ...], AdditiveSum] = {}

    def one_by_one(feats: list[Feature]) -> AdditiveSum:
        key = tuple(map(id, feats))
        if key not in sums:
            sums[key] = _OneByOne(feats)
        return sums[key]

    ref.field.sum_of = one_by_one  # type: ignore[method-assign]
    return ref


def _distance_figures(sec: Section, poses: int = 200, repeats: int = 3) -> None:
    gen = generate(RANDOM_WORLD_SEED)
    world = World.from_config(gen.world)
    ref = _reference_world()
    d = ref.distances
    t0 = time.perf_counter()
    whole = Raster(d.extent, d.raster_cell_m, ref.field.terrain_culled)
    made_whole = time.perf_counter() - t0
    whole.WHOLE_WINDOW_BLOCKS = 0
    d._terrain_raster = whole
    t0 = time.perf_counter()
    _ = world.distances._terrain_ras
    made_lazy = time.perf_counter() - t0
    points = [
        st.position_enu
        for st in route_poses(world, np.array(gen.route.points, dtype=np.float64), poses)
    ]
    fast_s: list[float] = []
    ref_s: list[float] = []
    for _ in range(repeats):
        for w, out in ((world, fast_s), (ref, ref_s)):
            t0 = time.perf_counter()
            for p in points:
                w.surface_distance(p)
            out.append((time.perf_counter() - t0) / len(points))
    same = all(world.surface_distance(p) == ref.surface_distance(p) for p in points)
    sec.details["random_world_distances"] = {
        "seed": RANDOM_WORLD_SEED,
        "points": len(points),
        "same_as_reference": same,
        "raster_cells": int(whole.nx * whole.ny),
    }
    sec.add(
        "sim.random_world.surface_distance_us",
        f"random world {RANDOM_WORLD_SEED}: surface distance per query (along its route)",
        min(fast_s) * 1e6,
        "us",
    )
    sec.add(
        "sim.random_world.surface_distance_ref_ratio",
        "same, reference / this",
        min(ref_s) / min(fast_s),
        "x",
    )
    sec.add(
        "sim.random_world.raster_made_ms",
        f"terrain raster made ({whole.nx} x {whole.ny} samples; searches sample its blocks)",
        made_lazy * 1e3,
        "ms",
    )
    sec.add(
        "sim.random_world.raster_whole_ms",
        "same, the whole raster sampled up front (the reference)",
        made_whole * 1e3,
        "ms",
    )


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
    _distance_figures(sec, poses=60 if runs == 1 else 200)
    return sec
