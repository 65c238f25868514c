"""harness.plots: both figures are written as PNGs, from a synthetic trace (no closed loop)."""

from __future__ import annotations

import importlib.util
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.harness.closed_loop import TRACE_COLUMNS
from companion.harness.plots import PlotParams, write_figures
from companion.planner.params import PlannerParams
from companion.planner.route import Route
from companion.sim.world import World, WorldConfig

needs_matplotlib = pytest.mark.skipif(
    importlib.util.find_spec("matplotlib") is None, reason="matplotlib (plots extra) missing"
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
PARAMS = PlotParams.from_planner(
    PlannerParams(h_d_m=2.0, d_min_m=2.0, phi_max_rad=0.6, v_d_mps=1.0)
)
N = 50


def tiny_world() -> World:
    cfg = WorldConfig.model_validate(
        {
            "features": [
                {
                    "type": "gaussian_hill",
                    "name": "hill",
                    "center": [10, 0],
                    "height_m": 2,
                    "sigma_m": 3,
                },
                {
                    "type": "cylinder",
                    "name": "post",
                    "center": [25, 4],
                    "radius_m": 1,
                    "height_m": 5,
                },
            ]
        }
    )
    return World.from_config(cfg)


def straight_trace(world: World, a: np.ndarray, b: np.ndarray) -> dict[str, np.ndarray]:
    """A straight flight from a to b at H_d over the terrain, one row per 0.1 s."""
    u = np.linspace(0.0, 1.0, N)
    x = a[0] + u * (b[0] - a[0])
    y = a[1] + u * (b[1] - a[1])
    z = np.asarray(world.height(x, y)) + PARAMS.h_d_m
    t = 0.1 * np.arange(1, N + 1)
    zeros = np.zeros(N)
    decision = np.array(["vertical"] * N, dtype=object)
    decision[30:40] = "horizontal"
    decision[40:42] = "blocked"
    cols: dict[str, np.ndarray] = {
        "t": t,
        "x": x,
        "y": y,
        "z": z,
        "roll": zeros,
        "pitch": 0.1 * np.sin(t),
        "yaw": np.full(N, math.atan2(b[1] - a[1], b[0] - a[0])),
        "xd": x,
        "yd": y,
        "zd": z,
        "yaw_d": zeros,
        "phi_d": 0.1 * np.sin(t),
        "phi_star_max": np.linspace(0.0, 0.9, N),
        "phi_star_threshold": np.full(N, 0.6),
        "decision": decision,
        "mode": np.array(["route"] * N, dtype=object),
        "side": np.array(["none"] * N, dtype=object),
        "min_range": np.where(np.arange(N) > 25, 5.0, 0.0),
        "clearance": np.where(np.arange(N) > 10, 4.0, np.inf),
        "height": np.full(N, PARAMS.h_d_m) + 0.05 * np.sin(t),
        "speed_ref": np.ones(N),
        "speed_xd": np.ones(N) - 0.01,
        "segment": zeros,
        "parameter": u,
        "replanned": zeros,
    }
    assert set(cols) == set(TRACE_COLUMNS)
    return cols


def assert_pngs(paths: list[Path], out: Path) -> None:
    assert [p.name for p in paths] == ["fig6.png", "fig7.png"]
    for p in paths:
        assert p.parent == out
        data = p.read_bytes()
        assert len(data) > 10_000
        assert data[:8] == PNG_MAGIC


@needs_matplotlib
@pytest.mark.parametrize(
    "points",
    [
        [[0.0, 0.0], [40.0, 0.0]],  # a long strip: the stacked layout
        [[0.0, 0.0], [30.0, 0.0], [30.0, 30.0]],  # square-ish: plan view beside the rest
    ],
    ids=["strip", "square"],
)
def test_write_figures_full(tmp_path: Path, points: list[list[float]]) -> None:
    world = tiny_world()
    route = Route(np.array(points))
    trace = straight_trace(world, np.array(points[0]), np.array(points[-1]))
    out = tmp_path / "figs"
    paths = write_figures(
        out,
        world,
        route,
        trace,
        PARAMS,
        phi_star=np.tile(np.linspace(0.0, 0.9, N)[:, None], (1, 7)) * np.linspace(0.2, 1, 7),
        thresholds=np.full(7, 0.6),
        memory_xy=np.array([[24.0, 3.5], [24.5, 3.2], [25.0, 3.0]]),
        events=[(3.0, "avoiding obstacle on the left (around)"), (4.2, "obstacle passed")],
        title="tiny",
    )
    assert_pngs(paths, out)


@needs_matplotlib
def test_write_figures_minimal(tmp_path: Path) -> None:
    world = World.from_config(WorldConfig())  # flat, no features
    route = Route(np.array([[0.0, 0.0], [20.0, 5.0]]))
    trace = straight_trace(world, np.array([0.0, 0.0]), np.array([20.0, 5.0]))
    trace["clearance"] = np.full(N, np.inf)  # nothing to clear
    paths = write_figures(tmp_path, world, route, trace, PARAMS)
    assert_pngs(paths, tmp_path)


def test_untyped_or_bad_params_are_refused(tmp_path: Path) -> None:
    world = tiny_world()
    route = Route(np.array([[0.0, 0.0], [40.0, 0.0]]))
    trace = straight_trace(world, np.array([0.0, 0.0]), np.array([40.0, 0.0]))
    untyped: Any = {"h_d_m": 2, "d_min_m": 2, "phi_max_rad": 1, "v_d_mps": 1}
    with pytest.raises(TypeError, match="PlotParams"):
        write_figures(tmp_path, world, route, trace, untyped)
    with pytest.raises(ValueError, match="v_d_mps"):
        PlotParams(
            h_d_m=2.0, d_min_m=2.0, phi_max_rad=0.6, v_d_mps=math.nan, side_threshold_rad=0.6
        )


def test_the_side_threshold_is_the_planners_eq7() -> None:
    """The figure's side threshold follows H_d: the planner's own eq. (7), never a copy."""
    for h_d, d_min, phi_max in ((2.0, 2.0, 0.6), (1.0, 4.0, 0.6), (5.0, 1.0, 1.2)):
        planner = PlannerParams(h_d_m=h_d, d_min_m=d_min, phi_max_rad=phi_max)
        plot = PlotParams.from_planner(planner)
        assert plot.side_threshold_rad == planner.side_threshold_rad
        assert plot.side_threshold_rad == min(math.atan2(h_d, d_min), phi_max)


def test_without_matplotlib_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("matplotlib", "matplotlib.figure", "mpl_toolkits", "mpl_toolkits.mplot3d"):
        monkeypatch.setitem(sys.modules, name, None)  # makes `import name` fail
    world = tiny_world()
    route = Route(np.array([[0.0, 0.0], [40.0, 0.0]]))
    trace = straight_trace(world, np.array([0.0, 0.0]), np.array([40.0, 0.0]))
    with pytest.raises(RuntimeError, match="plots"):
        write_figures(tmp_path, world, route, trace, PARAMS)


def test_import_has_no_matplotlib_side_effect() -> None:
    code = "import sys, companion.harness.plots; assert 'matplotlib' not in sys.modules, 'imported'"
    subprocess.run(
        [sys.executable, "-c", code], check=True, timeout=60, cwd=Path(__file__).parents[1]
    )


def test_nothing_detected_is_a_gap_not_a_distance() -> None:
    from companion.harness.plots import _detected

    got = _detected([0.0, 3.5, math.nan, 0.0, 1.2])
    assert np.isnan(got[[0, 2, 3]]).all()
    assert got[1] == 3.5 and got[4] == 1.2


def test_route_terrain_is_taken_at_the_vehicles_progress() -> None:
    """The profile's original-route terrain is on the flown path's axis: a box on the route
    shows up where the vehicle passes it, however far off the route the vehicle is."""
    from companion.harness.plots import _route_terrain_at_progress

    world = World.from_config(
        WorldConfig.model_validate(
            {"features": [{"type": "box", "name": "b", "center": [20, 0], "size_m": [2, 2, 5]}]}
        )
    )
    route_xy = np.column_stack([np.linspace(0, 40, 401), np.zeros(401)])
    x = np.linspace(0, 40, 81)
    y = np.full_like(x, -10.0)  # a detour 10 m south of the route
    y[::7] = 3.0  # back and forth: progress never goes back
    h = _route_terrain_at_progress(world, route_xy, x, y)
    assert h.shape == x.shape
    on_box = np.abs(x - 20.0) < 0.9
    assert np.all(h[on_box] > 4.0) and np.all(h[np.abs(x - 20.0) > 1.2] < 0.5)


@needs_matplotlib
def test_plan_labels_and_legend_hide_nothing() -> None:
    """Obstacle labels side by side do not overlap each other or leave the axes; the legend
    does not cover the goal or start marks."""
    from matplotlib.figure import Figure

    from companion.harness.plots import _place_plan_labels

    fig = Figure(figsize=(12, 4), layout="constrained")
    ax = fig.add_subplot()
    ax.set_xlim(-10, 90)
    ax.set_ylim(-15, 12)
    ax.set_aspect("equal")
    squares = [np.array([[x0, 4.0], [x0 + 3, 4.0], [x0 + 3, 7], [x0, 7]]) for x0 in (30, 33, 36)]
    labels = [(f"long obstacle name {i}\n(obstacle)", sq) for i, sq in enumerate(squares)]
    path = np.column_stack([np.linspace(0, 70, 200), np.zeros(200)])
    goal, start = np.array([70.0, 0.0]), np.array([0.0, 0.0])
    handles = [ax.plot(*path.T, label=f"entry {i}")[0] for i in range(1)]
    handles += [ax.plot(*goal, "*", label="goal")[0], ax.plot(*start, "o", label="start")[0]]
    handles += [ax.plot([], [], label=f"another legend entry {i}")[0] for i in range(6)]
    _place_plan_labels(fig, ax, labels, handles, path, np.array([goal, start]), wide=True)
    fig.draw_without_rendering()
    axbox = ax.get_window_extent()
    boxes = [t.get_window_extent() for t in ax.texts]
    assert len(boxes) == 3
    for i, b in enumerate(boxes):
        assert axbox.contains(b.x0, b.y0) and axbox.contains(b.x1, b.y1)
        for other in boxes[i + 1 :]:
            assert not b.overlaps(other)
    legend = ax.get_legend().get_window_extent()
    for p in (goal, start):
        px, py = ax.transData.transform(p)
        assert not legend.contains(px, py)
