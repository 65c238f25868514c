"""Ray casting cost per ray: the paper's 11 sensors cast from the poses of a real paper
flight, the pillars scenario's sensors from the poses of its in-process flight (five
cylinders: all rays meet all solids in one set of array operations), and the paper's sensors
over a 1000 x 1000 height map (0.1 m cells, seeded smooth terrain) from seeded random poses
1-5 m above it; and a ring of 8 proximity sectors (a fan of 9 rays each) with 4 surface
beams over the paper world; the same ring over a seeded random world (`companion.sim.worldgen`,
hills and solids), against the reference cast that sums the hills one at a time (the two timed
in turns, so their ratio holds on a loaded machine). Each cast is the simulator's: all rays of
a pose in one call."""

from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.flight import SCENARIO_DIR, Flight, load
from bench.report import Section
from companion.harness.closed_loop import run as closed_loop_run
from companion.planner import VehicleState
from companion.planner.rotations import r_g
from companion.planner.types import FloatArray
from companion.sim.scenario import load_scenario
from companion.sim.sensing import SensorFan
from companion.sim.world import HeightmapConfig, World, WorldConfig
from companion.sim.world.features import Feature
from companion.sim.world.raycast import RayCaster
from companion.sim.worldgen import generate

HEIGHTMAP_CELLS = 1000
HEIGHTMAP_RES_M = 0.1
RANDOM_WORLD_SEED = 9
"""A seeded random world of 9 hills (2 elliptic), 2 mesas, a box and a cliff."""


class _HillsOneByOne(RayCaster):
    """The reference cast: the terrain's features summed one at a time (as before the
    batched sum), otherwise the same cast, bit for bit."""

    def _sum_at(
        self, feats: list[Feature], o: FloatArray, d: FloatArray, T: FloatArray
    ) -> FloatArray:
        X, Y = o[:, :2].T[:, :, None] + d[:, :2].T[:, :, None] * T
        N = feats[0].evaluate(X, Y)
        for f in feats[1:]:
            N = N + f.evaluate(X, Y)
        return N


def route_poses(
    world: World, points: np.ndarray, count: int, above_m: float = 2.0
) -> list[VehicleState]:
    """count poses along a route's polyline (points (k, 2), ENU m), above_m over the
    surface, heading along the leg."""
    legs = np.diff(points, axis=0)
    lengths = np.hypot(legs[:, 0], legs[:, 1])
    s = np.linspace(0.0, float(lengths.sum()), count, endpoint=False)
    k = np.minimum(np.searchsorted(np.cumsum(lengths), s, side="right"), len(legs) - 1)
    start = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])[k]
    xy = points[k] + legs[k] * ((s - start) / lengths[k])[:, None]
    z = world.height(xy[:, 0], xy[:, 1]) + above_m
    yaw = np.arctan2(legs[k, 1], legs[k, 0])
    return [
        VehicleState(np.array([x, y, h]), 0.0, 0.0, float(w))
        for (x, y), h, w in zip(xy, z, yaw, strict=True)
    ]


def heightmap(n: int = HEIGHTMAP_CELLS, seed: int = 6) -> np.ndarray:
    """Smooth random terrain, (n, n) metres: a sum of twelve seeded plane waves."""
    rng = np.random.default_rng(seed)
    u = np.linspace(0.0, 1.0, n)
    x, y = np.meshgrid(u, u)
    z = np.zeros((n, n))
    for _ in range(12):
        kx, ky = rng.uniform(1.0, 8.0, 2)
        phase = rng.uniform(0.0, 2.0 * math.pi)
        z += rng.uniform(0.2, 1.5) * np.sin(2.0 * math.pi * (kx * x + ky * y) + phase)
    return z


def _casts(
    sensors_dirs: np.ndarray, max_range: np.ndarray, poses: list[VehicleState]
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(origins, directions, ranges) of each pose's cast."""
    out = []
    for st in poses:
        dirs = sensors_dirs @ r_g(st.roll_rad, st.pitch_rad, st.yaw_rad).T
        out.append((np.broadcast_to(st.position_enu, dirs.shape), dirs, max_range))
    return out


def _time_casts(
    world: World | RayCaster,
    sensors_dirs: np.ndarray,
    max_range: np.ndarray,
    poses: list[VehicleState],
    repeats: int,
) -> float:
    """Mean ns per ray of one `World.raycast` call of all sensors per pose."""
    clock = time.perf_counter_ns
    cast = world.raycast if isinstance(world, World) else world.cast
    total = 0
    rays = 0
    for _ in range(repeats):
        for st in poses:
            rot = r_g(st.roll_rad, st.pitch_rad, st.yaw_rad)
            dirs = sensors_dirs @ rot.T
            origins = np.broadcast_to(st.position_enu, dirs.shape)
            t0 = clock()
            cast(origins, dirs, max_range)
            total += clock() - t0
            rays += len(dirs)
    return total / rays


def run(flight: Flight, poses: int = 300, repeats: int = 3) -> Section:
    """flight: a paper flight; its states are the poses cast from on the paper world."""
    sec = Section("ray casting")
    scenario, world = load("paper")
    sensors = scenario.sensor_table()
    dirs, max_range = sensors.boresights_flu, sensors.max_range_m
    paper_poses = flight.states[:: max(1, len(flight.states) // poses)]
    paper_ns = _time_casts(world, dirs, max_range, paper_poses, repeats)
    sec.add("ray.paper_world_us", "per ray, paper world (11-ray casts)", paper_ns / 1e3, "us")

    # The ring of 8 proximity sectors (a fan of rays each) over the same world and poses: the
    # simulator casts every sector's fan and the surface beams in one call.
    ring = load_scenario(SCENARIO_DIR / "thin-pillar-ring.yaml").sensor_table()
    fan = SensorFan(ring.boresights_flu, ring.fov_rad)
    fan_ns = _time_casts(
        world, fan.directions_flu, ring.max_range_m[fan.owner], paper_poses, repeats
    )
    sec.add(
        "ray.paper_world_fans_us",
        f"per ray, paper world, 8 sector fans + 4 beams ({len(fan.owner)}-ray casts)",
        fan_ns / 1e3,
        "us",
    )

    # The ring over a random world, against the reference cast, in turns.
    gen = generate(RANDOM_WORLD_SEED)
    r_world = World.from_config(gen.world)
    reference = _HillsOneByOne(r_world.field, r_world.ray_step_m, r_world.scan_step_m)
    r_poses = route_poses(r_world, np.array(gen.route.points, dtype=np.float64), poses)
    ring_dirs, ring_range = fan.directions_flu, ring.max_range_m[fan.owner]
    fast_ns, ref_ns = [], []
    for _ in range(repeats):
        fast_ns.append(_time_casts(r_world, ring_dirs, ring_range, r_poses, 1))
        ref_ns.append(_time_casts(reference, ring_dirs, ring_range, r_poses, 1))
    sec.add(
        "ray.random_world_fans_us",
        f"per ray, random world {RANDOM_WORLD_SEED}, 8 sector fans + 4 beams "
        f"({len(fan.owner)}-ray casts)",
        min(fast_ns) / 1e3,
        "us",
    )
    same = all(
        np.array_equal(r_world.raycast(*c), reference.cast(*c))
        for c in _casts(ring_dirs, ring_range, r_poses[:: max(1, len(r_poses) // 20)])
    )
    sec.details["random_world"] = {"seed": RANDOM_WORLD_SEED, "poses": len(r_poses)}
    sec.details["random_world_same_ranges_as_reference"] = same
    sec.add(
        "ray.random_world_fans_ref_ratio",
        "same, reference cast (hills one at a time) / this cast",
        min(ref_ns) / min(fast_ns),
        "x",
    )

    p_scenario, p_world = load("pillars")
    p_sensors = p_scenario.sensor_table()
    trace = closed_loop_run(p_scenario, p_world).trace
    step = max(1, len(trace["t"]) // poses)
    pillar_poses = [
        VehicleState(
            np.array([trace["x"][i], trace["y"][i], trace["z"][i]]),
            float(trace["roll"][i]),
            float(trace["pitch"][i]),
            float(trace["yaw"][i]),
        )
        for i in range(0, len(trace["t"]), step)
    ]
    pillars_ns = _time_casts(
        p_world, p_sensors.boresights_flu, p_sensors.max_range_m, pillar_poses, repeats
    )
    sec.add(
        "ray.pillars_world_us",
        f"per ray, pillars world ({len(p_world.field.solid)} solids, {len(p_sensors)}-ray casts)",
        pillars_ns / 1e3,
        "us",
    )

    with tempfile.TemporaryDirectory(prefix="bench-heightmap-") as tmp:
        path = Path(tmp) / "terrain.npy"
        z = heightmap()
        np.save(path, z)
        cfg = WorldConfig(
            features=[
                HeightmapConfig(
                    name="terrain", file=path.name, resolution_m=HEIGHTMAP_RES_M, origin=(0, 0)
                )
            ]
        )
        hm_world = World.from_config(cfg, tmp)
        rng = np.random.default_rng(6)
        span = (HEIGHTMAP_CELLS - 1) * HEIGHTMAP_RES_M
        xy = rng.uniform(0.1 * span, 0.9 * span, size=(poses, 2))
        ground = hm_world.height(xy[:, 0], xy[:, 1])
        alt = ground + rng.uniform(1.0, 5.0, size=poses)
        yaw = rng.uniform(-math.pi, math.pi, size=poses)
        hm_poses = [
            VehicleState(np.array([x, y, a]), 0.0, 0.0, float(w))
            for (x, y), a, w in zip(xy, alt, yaw, strict=True)
        ]
        hm_ns = _time_casts(hm_world, dirs, max_range, hm_poses, repeats)
    sec.add(
        "ray.heightmap_1000_us",
        f"per ray, {HEIGHTMAP_CELLS}x{HEIGHTMAP_CELLS} height map (11-ray casts)",
        hm_ns / 1e3,
        "us",
    )
    sec.details["poses"] = len(paper_poses)
    sec.details["pillars_poses"] = len(pillar_poses)
    sec.details["heightmap"] = {
        "cells": HEIGHTMAP_CELLS,
        "resolution_m": HEIGHTMAP_RES_M,
        "poses": poses,
    }
    return sec
