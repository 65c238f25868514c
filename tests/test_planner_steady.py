"""Planner.step's per-cycle float path against the array forms of eqs (1)-(2), (6)-(7)."""

import numpy as np

from companion.planner import Decision, PlannerParams, VehicleState
from companion.planner.decision import chord_steepness, decide, steepness, thresholds
from companion.planner.rotations import r_g
from companion.planner.sensors import SURFACE_FOR_GROUP, Group, range_points_world
from tests.test_planner import SENSORS, make


def _reference_phi_star(state: VehicleState, ranges: np.ndarray, h_d: float) -> np.ndarray:
    """phi_i* as the planner documents it, with numpy arrays throughout: eq. (6) against
    the group's ground point (the forward one, else H_d below the vehicle, when missing),
    raised to the steepest chord through the reading (`chord_steepness`)."""
    rot = r_g(state.roll_rad, state.pitch_rad, state.yaw_rad)
    valid = SENSORS.valid(ranges)
    points = range_points_world(state.position_enu, rot, SENSORS.boresights_flu, ranges)
    surface = {g: i for g, i in SENSORS.surface_index.items() if valid[i]}
    below = state.position_enu - np.array([0.0, 0.0, h_d])
    fallback = points[surface[Group.SURFACE_FORWARD]] if Group.SURFACE_FORWARD in surface else below
    ground = np.array(
        [
            points[surface[SURFACE_FOR_GROUP[g]]] if SURFACE_FOR_GROUP[g] in surface else fallback
            for g in SENSORS.obstacle_groups
        ]
    )
    obs = SENSORS.obstacle_index
    phi = steepness(points[obs], ground, valid[obs])
    rows = np.flatnonzero(valid)
    chord, _ = chord_steepness(points[rows], 0.5)
    per_row = np.zeros(len(SENSORS))
    per_row[rows] = chord
    return np.maximum(phi, per_row[obs])


def test_phi_star_and_decision_equal_the_array_forms() -> None:
    rng = np.random.default_rng(21)
    params = PlannerParams()
    limit = thresholds(SENSORS.obstacle_groups, params)
    decisions = set()
    for trial in range(300):
        ranges = rng.uniform(0.0, 1.1, len(SENSORS)) * SENSORS.max_range_m
        if trial % 3 == 0:
            ranges[rng.integers(len(SENSORS), size=3)] = np.nan
        state = VehicleState(
            rng.normal(size=3) * 3.0 + np.array([0.0, 0.0, 2.0]),
            float(rng.normal(scale=0.1)),
            float(rng.normal(scale=0.1)),
            float(rng.uniform(-np.pi, np.pi)),
        )
        result = make(params).step(state, ranges, 0.05)  # a fresh planner: no held points
        expected = _reference_phi_star(state, ranges, params.h_d_m)
        diag = result.diagnostics
        assert diag.phi_star_rad.tobytes() == expected.tobytes()
        if diag.decision is not Decision.BLOCKED:
            assert diag.decision is decide(expected, limit)
            decisions.add(diag.decision)
    assert decisions == {Decision.VERTICAL, Decision.HORIZONTAL}
