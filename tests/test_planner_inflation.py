"""Inflation of remembered steep points: a vertical wall passed at a few metres sheds the
inflation its shallow early chords gave it; a 45-degree flank keeps what its slope needs.

The vehicle is moved by hand along a straight line beside the solid (x from 0 to 20 m), its
gap to the solid's face at flight height narrowing from 4.4 m to 2.9 m at x = 10 and widening
again; the ranges are ray-cast in the simulator's world."""

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.harness.closed_loop import sense
from companion.planner import Planner, PlannerParams, Route, VehicleState
from companion.planner.avoidance import min_distance
from companion.planner.memory import ObstacleMemory
from companion.sim.sensing import SensorFan
from companion.sim.world import World
from companion.sim.world.schema import WorldConfig
from companion.tuning import SensorConfig, sensor_table

CONFIG = Path(__file__).parent.parent / "config/sensors"
FACE_Y = 5.5
"""The solid's face at flight height (2 m) runs along y = FACE_Y, metres."""
WALL = {"type": "box", "center": [10.0, FACE_Y + 0.5], "size_m": [24.0, 1.0, 10.0]}


def _mesa(slope_deg: float) -> dict:  # type: ignore[type-arg]
    """A mesa 8 m high whose flank crosses flight height (2 m) along y = FACE_Y."""
    edge = FACE_Y + 6.0 / math.tan(math.radians(slope_deg))
    return {
        "type": "mesa",
        "center": [10.0, edge + 40.0],
        "radius_m": 40.0,
        "height_m": 8.0,
        "side_slope_deg": slope_deg,
    }


def _memory_after(
    feature: dict,  # type: ignore[type-arg]
    layout: str,
    positions: list[tuple[float, float]],
) -> ObstacleMemory:
    """The planner's memory after it is stepped (heading east, 2 m up, 20 Hz) through
    `positions` (x, y) beside the solid, the ranges ray-cast in the simulator's world."""
    world = World.from_config(WorldConfig.model_validate({"features": [feature]}), Path("."))
    specs = yaml.safe_load((CONFIG / f"{layout}.yaml").read_text())
    sensors = sensor_table([SensorConfig.model_validate(s) for s in specs])
    x0, y0 = positions[0]
    route = Route(np.array([[x0, y0], [x0 + 60.0, y0]]), 0.0, 0.0)
    planner = Planner(PlannerParams(), sensors, route, np.array([x0, y0, 2.0]))
    fan = SensorFan(sensors.boresights_flu, sensors.fov_rad)
    for x, y in positions:
        state = VehicleState(np.array([x, y, 2.0]), 0.0, 0.0, 0.0)
        planner.step(state, sense(world, sensors, state, fan), 0.05)
    return planner._memory


def _pass_by(feature: dict, layout: str) -> ObstacleMemory:  # type: ignore[type-arg]
    """The pass of the module docstring: the gap narrows from 4.4 m to 2.9 m and widens."""
    xs = np.arange(0.0, 20.0, 0.05)
    gaps = 4.4 - 1.5 * (1.0 - np.abs(xs - 10.0) / 10.0)
    return _memory_after(
        feature, layout, list(zip(xs.tolist(), (FACE_Y - gaps).tolist(), strict=True))
    )


def _middle(memory: ObstacleMemory) -> tuple[np.ndarray, np.ndarray]:
    """Inflation (k,) and slope (k,) radians of the points on the middle 8 m of the face."""
    xy = memory.points_xy()
    slots = np.fromiter(memory._cells.values(), dtype=np.intp, count=len(memory))
    on = (xy[:, 0] > 6.0) & (xy[:, 0] < 14.0) & (xy[:, 1] > FACE_Y - 1.5)
    return memory.inflation_m()[on], memory._slope[slots][on]


def test_a_wall_passed_close_sheds_the_inflation_of_its_shallow_chords(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Ring-8 sectors and tilted surface sensors: a wall 4.4 m away reads 39 degrees (the
    chord to the ground point 2 m out), 2.9 m away 66 degrees. Newest-wins kept what the
    receding half of the pass read; the steepest kept sheds most of it."""
    kept, _ = _middle(_pass_by(WALL, "ring-8"))
    add = ObstacleMemory.add

    def newest_wins(self, points, cycle, inflation_m=None, slope_rad=None, *reach):  # type: ignore[no-untyped-def]
        return add(self, points, cycle, inflation_m, None, *reach)

    monkeypatch.setattr(ObstacleMemory, "add", newest_wins)
    newest, _ = _middle(_pass_by(WALL, "ring-8"))
    assert len(kept) > 50 and len(newest) > 50
    assert float(kept.mean()) <= 0.5 * float(newest.mean())
    # on average no more than a 60-degree flank needs (D_min / sin(theta) - D_min, 0.31 m)
    d_min = PlannerParams().d_min_m
    assert float(kept.mean()) <= d_min / math.sin(math.radians(60.0)) - d_min


@pytest.mark.parametrize("layout", ["ring-8", "horizontal-7", "paper-11"])
@pytest.mark.parametrize("slope_deg", [45.0, 55.0])
def test_a_sloped_flank_keeps_the_inflation_its_slope_needs(layout: str, slope_deg: float) -> None:
    """No slope kept steeper than the flank's, so every point whose slope was measured
    carries at least D_min / sin(theta) - D_min - margin/2 (0.53 m at 45 degrees)."""
    params = PlannerParams()
    theta = math.radians(slope_deg)
    needed = params.d_min_m / math.sin(theta) - params.d_min_m - 0.5 * params.clearance_margin_m
    inflation, slope = _middle(_pass_by(_mesa(slope_deg), layout))
    measured = np.isfinite(slope) & (inflation > 0.0)
    assert measured.sum() >= 20
    assert float(np.nanmax(slope)) <= theta + math.radians(0.5)
    assert float(inflation[measured].min()) >= needed - 0.01


@pytest.mark.parametrize("slope_deg", [45.0, 55.0, 70.0])
def test_a_flank_met_between_the_beams_reaches_down_from_its_high_points(
    slope_deg: float,
) -> None:
    """Paper-11: the vehicle flies straight past a mesa 50 degrees right of its heading,
    where neither the level forward beam nor the level side beam meets it; only the beam
    25 degrees up at 45 degrees meets the flank, 3-5 m above flight height, on chords too
    long to give its slope. The memory holds the flank within 0.25 m of where it crosses
    flight height (3 m away at the end): 3.20, 2.38, 2.00 m, a reach down along the
    chord (at most 2.5 m) bounded by the rays that passed the flank at flight height
    (without the reach, where the beam met it: 5.70, 4.50, 3.64 m)."""
    gap_m, top_r, height = 3.0, 3.0, 8.0
    flank_r = top_r + (height - 2.0) / math.tan(math.radians(slope_deg))  # at flight height
    bearing = math.radians(-50.0)
    centre = ((flank_r + gap_m) * math.cos(bearing), (flank_r + gap_m) * math.sin(bearing))
    mesa = {
        "type": "mesa",
        "center": list(centre),
        "radius_m": top_r,
        "height_m": height,
        "side_slope_deg": slope_deg,
    }
    xs = np.arange(-12.0, 0.001, 0.05).tolist()
    memory = _memory_after(mesa, "paper-11", [(x, 0.0) for x in xs])
    held = min_distance(np.zeros((1, 2)), memory.points_xy(), memory.inflation_m())[0]
    assert len(memory) >= 10
    assert float(held) <= gap_m + 0.25


@pytest.mark.parametrize("slope_deg", [45.0, 50.0, 55.0, 70.0])
def test_the_reach_of_a_flank_is_not_bounded_below_where_the_flank_is(slope_deg: float) -> None:
    """The flank of the test above, met only by the beam tilted up: the rays that pass it
    at flight height bound each point's reach (`ObstacleMemory.bound_reach`), never below
    the true distance from the point to where the flank crosses flight height (at most
    the reach's 2.5 m cap)."""
    gap_m, top_r, height = 3.0, 3.0, 8.0
    flank_r = top_r + (height - 2.0) / math.tan(math.radians(slope_deg))
    bearing = math.radians(-50.0)
    centre = np.array([math.cos(bearing), math.sin(bearing)]) * (flank_r + gap_m)
    mesa = {
        "type": "mesa",
        "center": centre.tolist(),
        "radius_m": top_r,
        "height_m": height,
        "side_slope_deg": slope_deg,
    }
    xs = np.arange(-12.0, 0.001, 0.05).tolist()
    memory = _memory_after(mesa, "paper-11", [(x, 0.0) for x in xs])
    xy = memory.points_xy()
    truth = np.minimum(2.5, flank_r - np.hypot(*(xy - centre).T))
    assert float((memory.inflation_m() - truth).min()) >= 0.0


@pytest.mark.parametrize("gap_m", [2.5, 3.5])
def test_a_pillar_seen_by_the_beams_tilted_up_is_not_widened(gap_m: float) -> None:
    """Paper-11 flies straight past a pillar 8 m tall (1 m radius) gap_m to its left. The
    beams tilted up meet it high on long chords, which alone would widen it by up to 2.5 m
    (the reach); the forward beams measure its face steep on short chords, and the level
    and surface beams pass beside it at flight height: the reach each point keeps is at
    most 0.3 m. (Inflation from short chords is the same as without the reach.)"""
    centre = (10.0, gap_m + 1.0)
    pillar = {"type": "cylinder", "center": list(centre), "radius_m": 1.0, "height_m": 8.0}
    xs = np.arange(0.0, 20.0, 0.05).tolist()
    memory = _memory_after(pillar, "paper-11", [(x, 0.0) for x in xs])
    slots = np.fromiter(memory._cells.values(), dtype=np.intp, count=len(memory))
    on = np.hypot(*(memory.points_xy() - centre).T) < 1.3
    assert on.sum() >= 10
    reach = memory.inflation_m()[on] - memory._base[slots][on]
    assert float(reach.max()) <= 0.3
