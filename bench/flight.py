"""A closed-loop flight with a stopwatch on every part of the cycle.

The same loop as `companion.harness.closed_loop.run` (sense -> Planner.step -> vehicle model),
minus the
trace, plus timing of each part and the two clearance queries the closed loop makes every
cycle. Same inputs, so the same flight: the cycle count is checked against the real run by
the simulator benchmark.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bench.report import REPO
from companion.harness.closed_loop import sense
from companion.planner import Decision, Planner, VehicleState
from companion.planner.types import FloatArray
from companion.sim.scenario import Scenario, load_scenario
from companion.sim.sensing import SensorFan
from companion.sim.vehicle import make_vehicle
from companion.sim.world import World

SCENARIO_DIR = REPO / "config" / "scenarios"


def load(name: str) -> tuple[Scenario, World]:
    """A scenario of config/scenarios by name, and its world."""
    path: Path = SCENARIO_DIR / f"{name}.yaml"
    scenario = load_scenario(path)
    return scenario, World.from_config(scenario.world, path.parent)


def scenario_names() -> list[str]:
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml"))


@dataclass
class Snapshot:
    """The planner just before a cycle, with that cycle's inputs: replayable."""

    cycle: int
    planner: Planner
    state: VehicleState
    ranges: FloatArray
    dt_s: float


@dataclass
class Flight:
    """Per-cycle durations (ns) of each part of a flight, and what the planner did."""

    scenario: str
    dt_s: float
    sense_ns: list[int] = field(default_factory=list)
    step_ns: list[int] = field(default_factory=list)
    vehicle_ns: list[int] = field(default_factory=list)
    clearance_ns: list[int] = field(default_factory=list)
    replan: list[bool] = field(default_factory=list)
    """Cycles that searched for a correction (`avoidance.detour_search`): accepted, blocked,
    or a search that goes on next cycle."""
    search_units: list[int] = field(default_factory=list)
    """Work units the search spent each cycle (`Diagnostics.search_units`)."""
    phi_d: list[float] = field(default_factory=list)
    speed_ref: list[float] = field(default_factory=list)
    states: list[VehicleState] = field(default_factory=list)
    """The vehicle state each cycle was sensed from."""
    ranges: list[FloatArray] = field(default_factory=list)
    """The ranges the planner was given each cycle."""
    snapshots: list[Snapshot] = field(default_factory=list)
    finished: bool = False

    @property
    def cycles(self) -> int:
        return len(self.step_ns)


def fly(
    scenario: Scenario,
    world: World,
    name: str,
    snapshot_cycles: frozenset[int] = frozenset(),
) -> Flight:
    """Fly the scenario in process, timing each part; deep-copy the planner before the
    cycles in snapshot_cycles (for replaying them)."""
    clock = time.perf_counter_ns
    params = scenario.params()
    sensors = scenario.sensor_table()
    route = scenario.route_obj()
    start = scenario.start(world)
    planner = Planner(params, sensors, route, start)
    vehicle = make_vehicle(scenario.vehicle, VehicleState(start, 0.0, 0.0, route.start_heading_rad))
    fan = SensorFan(sensors.boresights_flu, sensors.fov_rad)  # built once, as the closed loop does
    dt = scenario.dt_s
    flight = Flight(name, dt)
    state = vehicle.state
    for k in range(round(scenario.duration_s / dt)):
        state_before = state
        t0 = clock()
        ranges = sense(world, sensors, state, fan)
        t1 = clock()
        if k in snapshot_cycles:
            flight.snapshots.append(Snapshot(k, copy.deepcopy(planner), state, ranges, dt))
        t2 = clock()
        result = planner.step(state, ranges, dt)
        t3 = clock()
        state = vehicle.step(result.setpoint, dt)
        t4 = clock()
        world.obstacle_distance(state.position_enu)
        world.surface_distance(state.position_enu)
        t5 = clock()
        diag = result.diagnostics
        flight.states.append(state_before)
        flight.ranges.append(ranges)
        flight.sense_ns.append(t1 - t0)
        flight.step_ns.append(t3 - t2)
        flight.vehicle_ns.append(t4 - t3)
        flight.clearance_ns.append(t5 - t4)
        flight.replan.append(
            diag.replanned
            or diag.decision is Decision.BLOCKED
            or diag.search_units > 0
            or diag.searching
        )
        flight.search_units.append(diag.search_units)
        flight.phi_d.append(diag.phi_d_rad)
        flight.speed_ref.append(diag.speed_ref_mps)
        if diag.finished:
            flight.finished = True
            break
    return flight


def replay_min(scenario: Scenario, world: World, flight: Flight, replays: int) -> np.ndarray:
    """Planner.step durations (ns) of each cycle of the flight, replayed from its recorded
    inputs by `replays` fresh planners: the least of them per cycle (what the step costs
    without the machine's interruptions)."""
    clock = time.perf_counter_ns
    best = np.full(flight.cycles, np.iinfo(np.int64).max, dtype=np.int64)
    route = scenario.route_obj()
    for _ in range(replays):
        planner = Planner(scenario.params(), scenario.sensor_table(), route, scenario.start(world))
        for k, (state, ranges) in enumerate(zip(flight.states, flight.ranges, strict=True)):
            t0 = clock()
            planner.step(state, ranges, flight.dt_s)
            best[k] = min(best[k], clock() - t0)
    return best


def split(flight: Flight) -> tuple[np.ndarray, np.ndarray]:
    """Planner step durations (ns) of the steady cycles and of the re-planning ones."""
    ns = np.asarray(flight.step_ns)
    replan = np.asarray(flight.replan, dtype=bool)
    return ns[~replan], ns[replan]
