"""Pieces of the real-SITL harness that need no SITL: sensor wiring, frame scanning."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.harness.sitl import (
    _heartbeat_frames,
    goal_distance,
    home_height,
    start_heading_deg,
    wire_to_autopilot,
)
from companion.sim.mavlink.bridge import BridgeCore
from companion.sim.mavlink.config import BridgeConfig
from companion.sim.scenario import load_scenario
from companion.sim.world import World

ROOT = Path(__file__).resolve().parent.parent


def _wired_sensors() -> list[object]:
    scenario = load_scenario(ROOT / "config" / "scenarios" / "wall.yaml")
    with (ROOT / "config" / "sensors" / "ardupilot-wired.yaml").open(encoding="utf-8") as f:
        table = yaml.safe_load(f)
    raw = {**scenario.model_dump(), "sensors": table}
    return list(type(scenario).model_validate(raw).sensors)


def test_wiring_maps_sensors_to_proximity_sectors_and_rangefinders() -> None:
    wired = wire_to_autopilot(_wired_sensors())
    ids = {e["name"]: e["id"] for e in wired.companion_sensors}
    # horizontal: proximity sector k re-reported as id 10 + k (YAW_45 * k)
    assert ids == {
        "front": 10,
        "front-left": 17,
        "left": 16,
        "front-right": 11,
        "right": 12,
        "down-forward": 0,
        "down": 1,
    }
    p = wired.params
    assert p["PRX1_TYPE"] == 2
    assert (p["RNGFND1_TYPE"], p["RNGFND1_ORIENT"], p["RNGFND1_MAX"]) == (10, 39, 10.0)
    assert (p["RNGFND2_TYPE"], p["RNGFND2_ORIENT"]) == (10, 25)
    assert "RNGFND3_TYPE" not in p
    assert sorted(wired.optional_ids) == [10, 11, 12, 16, 17]


def test_wiring_refuses_what_ardupilot_cannot_carry() -> None:
    paper = load_scenario(ROOT / "config" / "scenarios" / "paper.yaml")
    with pytest.raises(ValueError, match="custom rotation"):
        wire_to_autopilot(paper.sensors)
    twice = _wired_sensors()
    twice.append(twice[-1].model_copy(update={"sensor_id": 99}))  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="orientation 25 is taken"):
        wire_to_autopilot(twice)


def test_heartbeat_frames_found_among_other_messages() -> None:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    hb = mav.heartbeat_encode(2, 3, 81, 4, 4, 3).pack(mav)
    att = mav.attitude_encode(1, 0.1, 0.2, 0.3, 0, 0, 0).pack(mav)
    frames = _heartbeat_frames(att + hb + att)
    assert frames == [hb]
    assert _heartbeat_frames(b"\x00garbage" + att) == []


def test_start_heading_as_compass() -> None:
    paper = load_scenario(ROOT / "config" / "scenarios" / "paper.yaml")  # west
    wall = load_scenario(ROOT / "config" / "scenarios" / "wall.yaml")  # east
    assert start_heading_deg(paper) == pytest.approx(270.0)
    assert start_heading_deg(wall) == pytest.approx(90.0)


def test_goal_judged_on_the_positions_since_the_route_was_done() -> None:
    """SITL's positions (10 Hz) from when the route was seen done, not from the planner's
    last row: the planner writes rows (20 Hz) while it holds at the goal, so its last row
    often comes after SITL's last position (a wired-wall flight at the goal read nan)."""
    goal = np.array([60.0, 0.0])
    t = 100.0 + 0.1 * np.arange(60)  # 6 s of positions closing on the goal
    x = 60.0 - 0.5 * np.exp(-(t - 100.0))
    track = np.column_stack([t, x, np.full_like(t, 0.002), np.full((60, 4), 0.0)])
    last_row = t[-1] + 0.012  # the planner's last row, 12 ms after SITL's last position
    assert goal_distance(track, goal, last_row) is None  # what the old criterion saw
    d = goal_distance(track, goal, since=101.0)
    assert d == pytest.approx(np.hypot(0.5 * np.exp(-5.9), 0.002))
    assert goal_distance(track[:5], goal, since=101.0) is None  # nothing since: not judged
    assert goal_distance(track[:0], goal, since=0.0) is None


def test_sitl_home_goes_to_the_lowest_terrain_near_the_route() -> None:
    """SITL's flat ground must lie below every relief the route descends to: a home at the
    start's height (the top of steep-descent's mesa, 7 m) left the vehicle sitting on it."""
    for name, start_ground, home in (("steep-descent", 7.0, 0.0), ("paper", 0.0, 0.0)):
        path = ROOT / "config" / "scenarios" / f"{name}.yaml"
        scenario = load_scenario(path)
        world = World.from_config(scenario.world, path.parent)
        start = scenario.start(world)
        ground = float(world.height(start[0], start[1]))
        assert ground == pytest.approx(start_ground, abs=1e-3)
        low = home_height(scenario, world)
        assert low <= ground  # never above the start
        assert low == pytest.approx(home, abs=1e-3)


def test_the_bridge_places_the_home_at_anchor_z() -> None:
    path = ROOT / "config" / "scenarios" / "steep-descent.yaml"
    scenario = load_scenario(path)
    world = World.from_config(scenario.world, path.parent)
    specs = [s.to_spec() for s in scenario.sensors]
    at_terrain = BridgeCore(BridgeConfig(anchor_xy=(0.0, 0.0)), world, specs)
    low = BridgeCore(BridgeConfig(anchor_xy=(0.0, 0.0), anchor_z=0.0), world, specs)
    np.testing.assert_allclose(at_terrain.anchor, [0.0, 0.0, 7.0], atol=1e-9)
    np.testing.assert_allclose(low.anchor, [0.0, 0.0, 0.0])
