"""FreeFans: where earlier proximity-sector readings saw free space, and the arcs it trims."""

import math
from pathlib import Path

import numpy as np
import pytest

import companion.planner.planner as planner_mod
from companion.harness import metrics as metrics_mod
from companion.harness.closed_loop import run
from companion.planner import VehicleState
from companion.planner.freespace import FreeFans
from companion.planner.memory import ObstacleMemory
from companion.sim.scenario import load_scenario
from companion.sim.world import World
from tests.test_planner_sectors import planner_over_flat_ground, ring8

UP = np.array([0.0, 0.0, 1.0])
HALF = math.radians(22.5)


def at(bearing_deg: float, r: float, z: float = 2.0) -> list[float]:
    b = math.radians(bearing_deg)
    return [r * math.cos(b), r * math.sin(b), z]


def one_fan(free_m: float = 5.0) -> FreeFans:
    fans = FreeFans(sectors=1)
    fans.add(np.array([0.0, 0.0, 2.0]), UP, np.array([[1.0, 0.0, 0.0]]), [HALF], [free_m], 0.0)
    return fans


def test_inside_the_fan_by_the_tolerance_is_seen_free() -> None:
    fans = one_fan()
    pts = np.array(
        [
            at(0.0, 3.0),  # on the boresight, within the free stretch
            at(10.0, 4.5),
            at(0.0, 4.9),  # within the tolerance of the free stretch's end
            at(0.0, 6.0),  # beyond it
            at(21.0, 3.0),  # within the tolerance of the fan's edge (0.25 m at 3 m: 4.8 deg)
            at(40.0, 3.0),  # outside the fan
            at(0.0, 3.0, 3.0),  # 1 m above the fan's surface: a solid there rises through it
            at(0.0, 3.0, 1.6),  # below the surface by more than the tolerance: may be lower
        ]
    )
    assert fans.seen_free(pts).tolist() == [True, True, False, False, False, False, True, False]


def test_a_pose_is_kept_once_moved_or_turned() -> None:
    fans = FreeFans(sectors=1, poses=4)
    b = np.array([[1.0, 0.0, 0.0]])
    assert fans.add(np.zeros(3), UP, b, [HALF], [5.0], 0.0)
    assert not fans.add(np.array([0.1, 0.0, 0.0]), UP, b, [HALF], [5.0], 0.02)
    assert fans.add(np.array([0.3, 0.0, 0.0]), UP, b, [HALF], [5.0], 0.0)
    assert fans.add(np.array([0.3, 0.0, 0.0]), UP, b, [HALF], [5.0], 0.2)
    assert len(fans) == 3


def test_the_oldest_poses_are_forgotten() -> None:
    fans = FreeFans(sectors=1, poses=2)
    fans.add(np.zeros(3), UP, np.array([[1.0, 0.0, 0.0]]), [HALF], [5.0], 0.0)
    p = np.array([[3.0, 0.0, 0.0]])
    assert fans.seen_free(p).all()
    for k in range(2):  # two more poses, looking the other way
        fans.add(
            np.array([0.0, 1.0 + k, 0.0]), UP, np.array([[-1.0, 0.0, 0.0]]), [HALF], [5.0], 0.0
        )
    assert not fans.seen_free(p).any()


def test_seen_free_is_within_what_the_same_fan_carves() -> None:
    """The narrowed fan lies inside the widened one carving uses: a point left out of an arc
    is one the same reading would have carved from the memory."""
    rng = np.random.default_rng(3)
    boresight = np.array([[math.cos(0.4), math.sin(0.4), 0.05]])
    boresight /= np.linalg.norm(boresight)
    free = [6.0]
    fans = FreeFans(sectors=1, tolerance_m=0.25)
    fans.add(np.zeros(3), UP, boresight, [HALF], free, 0.4)
    pts = np.column_stack(
        [rng.uniform(-8, 8, 4000), rng.uniform(-8, 8, 4000), rng.normal(0.3, 0.3, 4000)]
    )
    seen = fans.seen_free(pts)
    assert 50 < seen.sum() < 3000
    memory = ObstacleMemory(cell_m=0.01, radius_m=100.0, max_points=10_000)
    memory.add(pts[seen], 0)
    kept = len(memory)
    memory.carve_sectors(np.zeros(3), UP, boresight, np.array([HALF]), np.array(free), 0.25)
    assert len(memory) == 0 < kept


def test_a_reading_from_another_heading_trims_the_arc() -> None:
    """An object 3.5 m away at 30 degrees left. Heading east, the front-left sector (22.5-67.5
    degrees) reads it and leaves its arc; the front sector sees nothing. Turned 22.5 degrees
    left, the front sector (0-45 degrees) reads it: the part of its arc that the earlier
    front sector saw free (up to about 19 degrees) is left out. Without that evidence the
    memory holds the arc down to 0 degrees."""

    def memory_bearings(use_evidence: bool) -> np.ndarray:
        table = ring8()
        planner, ground = planner_over_flat_ground(table)
        if not use_evidence:
            planner._free_fans = None
        first = ground.copy()
        first[table.index_of_id[7]] = 3.5  # sector 315 (front-left)
        planner.step(VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0), first, 0.05)
        second = ground.copy()
        second[table.index_of_id[0]] = 3.5  # front, now spanning 0-45 degrees
        planner.step(VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, HALF), second, 0.05)
        pts = planner.memory_points_xy
        near = np.hypot(pts[:, 0], pts[:, 1]) < 4.0
        return np.degrees(np.arctan2(pts[near, 1], pts[near, 0]))

    with_evidence, without = memory_bearings(True), memory_bearings(False)
    assert without.min() < 2.0
    assert with_evidence.min() > 15.0
    # The object's own bearing stays held, in both.
    assert np.abs(with_evidence - 30.0).min() < 3.0
    assert np.abs(without - 30.0).min() < 3.0


SCENARIOS = Path(__file__).parent.parent / "config/scenarios"


def fly_scenario(name: str) -> tuple[bool, list[str]]:
    """Fly a scenario in process, cut short once stalled for 40 s: goal reached, events."""
    path = SCENARIOS / f"{name}.yaml"
    scenario = load_scenario(path)
    result = run(scenario, World.from_config(scenario.world, path.parent), stall_stop_s=40.0)
    metrics = metrics_mod.for_run(scenario, World.from_config(scenario.world, path.parent), result)
    return bool(metrics["reached_goal"]), [e for _, e in result.events]


def test_wall_ends_need_the_evidence(monkeypatch: pytest.MonkeyPatch) -> None:
    reached, _ = fly_scenario("wall-ends-sectors")
    assert reached
    monkeypatch.setattr(planner_mod, "FreeFans", lambda *args, **kwargs: None)
    reached, events = fly_scenario("wall-ends-sectors")
    assert not reached, events[-5:]


def test_boxed_in_at_rest_the_vehicle_turns_to_read_across_the_arcs() -> None:
    """Every sector reads 3.5 m, at rest with no track behind (walled in, or arcs wider than
    what is there): no correction and no retreat. The vehicle turns half a sector each way
    and back, holding each heading, then a quarter, and then stays (two turns a place)."""
    table = ring8()
    planner, ranges = planner_over_flat_ground(table)
    ranges[table.obstacle_index] = 3.5
    yaw, yaws, events, moved = 0.0, [], [], 0.0
    for _ in range(600):  # 30 s
        result = planner.step(VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, yaw), ranges, 0.05)
        events += [e for e in result.diagnostics.events if e.startswith("boxed in")]
        yaw = result.setpoint.yaw_rad  # the vehicle turns as told
        yaws.append(yaw)
        moved = max(moved, float(np.linalg.norm(result.setpoint.position_enu[:2])))
    assert events == [
        "boxed in by proximity sector arcs: turning 22 degrees each way to narrow them",
        "boxed in by proximity sector arcs: turning 11 degrees each way to narrow them",
    ]
    assert max(yaws) == pytest.approx(HALF) and min(yaws) == pytest.approx(-HALF)
    assert yaws[-1] == pytest.approx(0.0)
    assert moved < 0.5  # X_d stopped before D_min of the arcs, and stays
