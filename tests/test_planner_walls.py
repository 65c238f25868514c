"""A wall that two obstacle beams meet one above the other is steep from as far as they
reach it: the chord between their points is vertical (`decision.chord_steepness`).

The paper's layout flies level by hand towards a box 6.4 m tall (random world 520's), its
face 12 m ahead at first; the ranges are ray-cast in the simulator's world."""

from pathlib import Path

import numpy as np
import yaml

from companion.harness.closed_loop import sense
from companion.planner import Planner, PlannerParams, Route, VehicleState
from companion.planner.types import Decision
from companion.sim.sensing import SensorFan
from companion.sim.world import World
from companion.sim.world.schema import WorldConfig
from companion.tuning import SensorConfig, sensor_table

CONFIG = Path(__file__).parent.parent / "config/sensors"
FACE_X = 12.0
BOX = {"type": "box", "center": [FACE_X + 1.3, 0.0], "size_m": [2.6, 1.0, 6.4]}


def test_a_wall_met_by_two_beams_one_above_the_other_is_steep_at_10_m() -> None:
    world = World.from_config(WorldConfig.model_validate({"features": [BOX]}), Path("."))
    specs = yaml.safe_load((CONFIG / "paper-11.yaml").read_text())
    sensors = sensor_table([SensorConfig.model_validate(s) for s in specs])
    route = Route(np.array([[0.0, 0.0], [60.0, 0.0]]), 0.0, 0.0)
    planner = Planner(PlannerParams(), sensors, route, np.array([0.0, 0.0, 2.0]))
    fan = SensorFan(sensors.boresights_flu, sensors.fov_rad)
    decisions = []
    for x in np.arange(0.0, 2.0, 0.05):  # the face from 12 m to 10 m ahead
        state = VehicleState(np.array([x, 0.0, 2.0]), 0.0, 0.0, 0.0)
        ranges = sense(world, sensors, state, fan)
        decisions.append(planner.step(state, ranges, 0.05).diagnostics.decision)
    front = [s.name for s in sensors.specs].index("front")
    assert abs(float(ranges[front]) - (FACE_X - 2.0 + 0.05)) < 0.1  # the level beam on it
    # Eq. (6)'s chord from the ground point 2 m ahead is 11-17 degrees here (not steep),
    # the chord between the level beam and the one 15 degrees up is vertical.
    assert Decision.HORIZONTAL in decisions
    xy = planner.memory_points_xy
    on_face = np.abs(xy[:, 0] - FACE_X) < 0.3
    assert on_face.sum() >= 1
