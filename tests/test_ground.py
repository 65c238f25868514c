"""The ground store and its quadric fit (companion.planner.ground), and what it does to
terrain following in closed loop."""

import math
from pathlib import Path

import numpy as np
import pytest

from companion.harness import metrics as metrics_mod
from companion.harness.closed_loop import run
from companion.planner.ground import (
    GroundFit,
    GroundPoints,
    fit_floor_z,
    floor_z,
    offsets_from_fit,
)
from companion.sim.scenario import load_scenario
from companion.sim.world import World

SCENARIOS = Path(__file__).parent.parent / "config" / "scenarios"


def _store(fn, xs: np.ndarray, ys: np.ndarray) -> GroundPoints:  # type: ignore[no-untyped-def]
    store = GroundPoints(capacity=len(xs), spacing_m=0.01)
    for k, (x, y) in enumerate(zip(xs.tolist(), ys.tolist(), strict=True)):
        store.add(k, x, y, fn(x, y))
    return store


def test_fit_recovers_a_tilted_plane() -> None:
    rng = np.random.default_rng(3)
    xs, ys = rng.uniform(-3, 3, 40) + 10.0, rng.uniform(-3, 3, 40) - 5.0
    store = _store(lambda x, y: 1.0 + 0.3 * x - 0.2 * y, xs, ys)
    fit = store.fit(10.0, -5.0, 4.0)
    assert fit is not None
    gx, gy = fit.gradient(10.5, -4.5)
    assert gx == pytest.approx(0.3, abs=1e-3)
    assert gy == pytest.approx(-0.2, abs=1e-3)
    assert fit.second_along(0.7) == pytest.approx(0.0, abs=1e-3)


def test_fit_measures_curvature_along_a_heading() -> None:
    """A ridge z = -x^2 / (2 R) along y: second derivative -1/R across it, 0 along it."""
    r = 10.0
    rng = np.random.default_rng(5)
    xs, ys = rng.uniform(-3, 3, 60), rng.uniform(-3, 3, 60)
    fit = _store(lambda x, y: -x * x / (2 * r), xs, ys).fit(0.0, 0.0, 4.0)
    assert fit is not None
    # The ridge term pulls the curvature a little towards 0; within 10 % here.
    assert fit.second_along(0.0) == pytest.approx(-1.0 / r, rel=0.1)
    assert fit.second_along(math.pi / 2) == pytest.approx(0.0, abs=0.01)


def test_too_few_points_fit_nothing_and_close_points_are_not_stored_twice() -> None:
    store = GroundPoints(capacity=16, spacing_m=0.2)
    for k in range(20):
        store.add(0, 0.05 * k, 0.0, 0.0)  # 1 m of track: a point every 0.2 m
    assert len(store) == 5
    assert store.fit(0.0, 0.0, 3.0) is None
    for k in range(40):
        store.add(1, 0.2 * k, 1.0, 0.0)
    assert len(store) == 16  # the ring keeps the newest
    assert store.fit(0.0, 0.0, 3.0) is None  # the oldest (near x = 0) have gone
    assert store.fit(6.0, 1.0, 3.0) is not None


def test_offsets_for_a_side_slope_and_a_crest() -> None:
    h_d = 2.0
    side_slope = GroundFit(0.0, 0.0, (0.0, 0.0, math.tan(math.radians(20)), 0.0, 0.0, 0.0), 9)
    side, bend = offsets_from_fit(side_slope, 0.0, 0.0, 0.0, h_d, 2.0)  # heading +x
    assert side == pytest.approx(h_d / math.cos(math.radians(20)) - h_d)
    assert bend == pytest.approx(0.0)
    crest = GroundFit(0.0, 0.0, (0.0, 0.0, 0.0, -0.05, 0.0, 0.0), 9)  # z'' = -0.1 along x
    side, bend = offsets_from_fit(crest, 0.0, 0.0, 0.0, h_d, 2.0)
    assert side == pytest.approx(0.0)
    assert bend == pytest.approx(0.1 * 2.0**2 / 2)


def test_the_lag_is_counted_only_over_the_fits_reach() -> None:
    """A forward ground point 5 m ahead (a descent): the curvature of a 3 m fit is carried
    over 3 m, not 5 (its error would grow with the square of the lead)."""
    crest = GroundFit(0.0, 0.0, (0.0, 0.0, 0.0, -0.05, 0.0, 0.0), 9)
    _, within = offsets_from_fit(crest, 0.0, 0.0, 0.0, 2.0, 2.5, reach_m=3.0)
    assert within == pytest.approx(0.1 * 2.5**2 / 2)
    _, beyond = offsets_from_fit(crest, 0.0, 0.0, 0.0, 2.0, 5.0, reach_m=3.0)
    assert beyond == pytest.approx(0.1 * 3.0**2 / 2)


def _floor_at(store: GroundPoints, x: float, y: float, h_d: float) -> float:
    points, r2 = store.near(x, y, h_d)
    return floor_z(points[:, 2], r2, h_d)


def test_floor_keeps_h_d_from_every_point_and_is_exact_at_a_points_place() -> None:
    """floor_z: the lowest z at H_d from every stored point. On a step (a rim: the top at
    z = 1 for x <= 0, the ground at 0 beyond) it follows the circle of radius H_d about the
    rim past its edge; at a stored point's own place it is that point's z + H_d; farther
    than H_d from every point it is -inf."""
    xs = np.arange(-3.0, 3.01, 0.25)
    store = _store(lambda x, y: 1.0 if x <= 0.0 else 0.0, xs, np.zeros_like(xs))
    h_d = 2.0
    assert _floor_at(store, -1.0, 0.0, h_d) == pytest.approx(1.0 + h_d)
    assert _floor_at(store, 0.0, 0.0, h_d) == pytest.approx(1.0 + h_d)
    assert _floor_at(store, 0.5, 0.0, h_d) == pytest.approx(1.0 + math.sqrt(h_d**2 - 0.5**2))
    assert _floor_at(store, 1.5, 0.0, h_d) == pytest.approx(1.0 + math.sqrt(h_d**2 - 1.5**2))
    assert _floor_at(store, 10.0, 0.0, h_d) == -math.inf
    # Between stored points 0.25 m apart the spheres' envelope dips by H_d - sqrt(H_d^2 -
    # 0.125^2) (about 4 mm).
    mid = _floor_at(store, -2.125, 0.0, h_d)
    assert mid == pytest.approx(1.0 + math.sqrt(h_d**2 - 0.125**2))


def test_the_fits_floor_keeps_h_d_from_the_fitted_surface_in_every_direction() -> None:
    """Level ground: H_d above it. A plane rising at 0.5 towards +x, +y or any heading:
    about H_d sqrt(1 + 0.25) above the plane at that place (the sphere touches the slope
    uphill), never more (the samples lie on the surface), within the rings' spacing."""
    h_d = 2.0
    level = GroundFit(3.0, 4.0, (1.5, 0.0, 0.0, 0.0, 0.0, 0.0), 9)
    assert fit_floor_z(level, 3.0, 4.0, h_d) == pytest.approx(1.5 + h_d)
    exact = h_d * math.sqrt(1.0 + 0.25)
    for bearing in (0.0, 0.4, 1.0, 2.5, -2.0):
        g = (0.5 * math.cos(bearing), 0.5 * math.sin(bearing))
        plane = GroundFit(0.0, 0.0, (1.0, g[0], g[1], 0.0, 0.0, 0.0), 9)
        floor = fit_floor_z(plane, 2.0, -1.0, h_d) - plane.height(2.0, -1.0)
        assert exact - 0.03 <= floor <= exact + 1e-12
    # the points' own floor along one line misses a rise beside it; the fit's does not
    side = GroundFit(0.0, 0.0, (0.0, 0.0, 0.6, 0.0, 0.0, 0.0), 9)  # rising to the left
    line = np.linspace(-2.0, 2.0, 21)
    on_line = floor_z(side.heights(line, np.zeros(21)), line * line, h_d)
    assert on_line == pytest.approx(h_d)
    assert fit_floor_z(side, 0.0, 0.0, h_d) > h_d + 0.25


def test_near_gives_the_points_within_a_radius_and_their_distances() -> None:
    store = GroundPoints(capacity=8, spacing_m=0.01)
    points, r2 = store.near(1.0, 2.0, 5.0)
    assert points.shape == (0, 3) and r2.shape == (0,)
    store.add(0, 1.0, 1.0, 5.0)
    store.add(1, 3.0, 1.0, -5.0)
    points, r2 = store.near(2.6, 1.2, 1.0)
    assert points.tolist() == [[3.0, 1.0, -5.0]]
    assert r2.tolist() == pytest.approx([0.4**2 + 0.2**2])


@pytest.mark.slow
@pytest.mark.parametrize("name", ["smooth-hill", "crease", "mesa-rim", "steep-descent"])
def test_shaping_holds_the_height_the_paper_alone_does_not(name: str) -> None:
    """Over a hill of radius of curvature 12 m (smooth-hill), the crease between two hills,
    a climbable mesa's rims and feet (mesa-rim) and a multicopter down a flank its forward
    sensor cannot reach (steep-descent), |H - H_d| (H the shortest distance to the surface)
    stays within 0.07 m on the hill and 0.15 m on the others with the ground's shape; eqs
    (3)-(4) alone lag by g'' L^2 / 2, cut the rims, and leave more."""
    path = SCENARIOS / f"{name}.yaml"
    errors = {}
    for shape in (True, False):
        scenario = load_scenario(path)
        planner = scenario.planner.model_copy(update={"shape_terrain": shape})
        scenario = scenario.model_copy(update={"planner": planner})
        world = World.from_config(scenario.world, path.parent)
        m = metrics_mod.for_run(scenario, world, run(scenario, world))
        assert m["reached_goal"]
        errors[shape] = m["max_height_error_m"]
    limit = 0.07 if name == "smooth-hill" else 0.15
    assert errors[True] <= limit
    assert errors[False] > limit


@pytest.mark.slow
@pytest.mark.parametrize(
    ("seed", "layout", "vehicle"),
    [(336, "paper-11", "ideal"), (305, "paper-11", "multicopter"), (344, "ring-8", "multicopter")],
)
def test_a_curving_path_over_a_side_slope_keeps_h_d_on_gentle_relief(
    seed: int, layout: str, vehicle: str
) -> None:
    """Random worlds whose worst height error on gentle relief (radius of curvature >= 10 m)
    came from a curving path over a side slope: the point steered at (a stored ground point
    near the path, or eq. (3)'s aim 3-4 m ahead on the body's heading) lies off the path,
    and its height is not the path's. Carried over to the heading with the fitted slope,
    and on a descent held to H_d off the slope fitted under X_d (over a crest on the way
    down, eq. (4)'s lag left X_d low), |H - H_d| there stays within the issue's 0.07 m
    (it was 0.085, 0.099 and 0.137 m)."""
    from companion.harness.sweep import load_layout, run_task, tasks_for

    (task,) = tasks_for([seed], [load_layout(layout)], [vehicle], ["none"])
    record = run_task(task)
    assert record["reached_goal"]
    assert 0.0 < record["height_err_gentle_max_m"] <= 0.07


@pytest.mark.slow
def test_ground_between_the_surface_sensors_lines_keeps_its_distance() -> None:
    """Random world 301 (ring-8, multicopter): in a trench at a climbable mesa's corner the
    nearest ground lay 1 m ahead and to the right, between the forward and the right
    surface sensors' lines; the stored points said the height was enough and H fell to
    1.79 m (0.207 m short). The fitted surface's floor (`fit_floor_z`) keeps the run's worst
    |H - H_d| away from solids within the issue's 0.15 m."""
    from companion.harness.sweep import load_layout, run_task, tasks_for

    (task,) = tasks_for([301], [load_layout("ring-8")], ["multicopter"], ["none"])
    record = run_task(task)
    assert record["reached_goal"]
    assert 0.0 < record["height_err_max_m"] <= 0.15


def test_a_lone_spurious_surface_range_never_enters_the_ground_store() -> None:
    """Over flat ground, one cycle's forward surface range 1 m short (a point 0.7 m in the
    air) stays out of the store: its sensor's previous range disagrees, and so does the
    next one's with it. The store's floor would otherwise hold X_d up while it is kept."""
    from companion.planner import VehicleState
    from companion.planner.sensors import Group
    from tests.test_planner import SENSORS, flat_ranges, make

    planner = make()
    forward = SENSORS.surface_index[Group.SURFACE_FORWARD]
    state = VehicleState(np.array([0.0, 0.0, 2.0]), 0.0, 0.0, 0.0)
    for k in range(60):
        ranges = flat_ranges(float(state.position_enu[2]))
        if k == 30:
            ranges[forward] -= 1.0
        res = planner.step(state, ranges, 0.05)
        sp = res.setpoint  # flown level: the ranges are those of a level vehicle
        state = VehicleState(sp.position_enu, 0.0, 0.0, sp.yaw_rad)
    points, _ = planner._ground_store.near(0.0, 0.0, 100.0)
    assert len(points) > 10
    assert float(np.abs(points[:, 2]).max()) < 1e-6


def test_carry_to_heading_measures_along_the_line_and_the_slope_across() -> None:
    """A place 3 m along and 0.5 m left of an eastward line, on ground rising 0.2 northward:
    3 m along it, and the line's ground lies 0.1 m lower."""
    from companion.planner.ground import carry_to_heading

    along, shift = carry_to_heading(0.0, 0.2, 13.0, 5.5, 10.0, 5.0, 0.0)
    assert along == pytest.approx(3.0)
    assert shift == pytest.approx(-0.1)
