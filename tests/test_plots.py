"""sim.plots: both figures are written as PNGs, from a synthetic trace (no closed loop)."""

from __future__ import annotations

import importlib.util
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.planner.route import Route
from sim.closed_loop import TRACE_COLUMNS
from sim.plots import write_figures
from sim.world import World, WorldConfig

needs_matplotlib = pytest.mark.skipif(
    importlib.util.find_spec("matplotlib") is None, reason="matplotlib (plots extra) missing"
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
PARAMS = {"h_d_m": 2.0, "d_min_m": 2.0, "phi_max_rad": 0.6, "v_d_mps": 1.0}
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
    z = np.asarray(world.height(x, y)) + PARAMS["h_d_m"]
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
        "height": np.full(N, PARAMS["h_d_m"]) + 0.05 * np.sin(t),
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


def test_missing_params_are_refused(tmp_path: Path) -> None:
    world = tiny_world()
    route = Route(np.array([[0.0, 0.0], [40.0, 0.0]]))
    trace = straight_trace(world, np.array([0.0, 0.0]), np.array([40.0, 0.0]))
    with pytest.raises(ValueError, match="v_d_mps"):
        write_figures(tmp_path, world, route, trace, {"h_d_m": 2, "d_min_m": 2, "phi_max_rad": 1})


def test_without_matplotlib_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("matplotlib", "matplotlib.figure", "mpl_toolkits", "mpl_toolkits.mplot3d"):
        monkeypatch.setitem(sys.modules, name, None)  # makes `import name` fail
    world = tiny_world()
    route = Route(np.array([[0.0, 0.0], [40.0, 0.0]]))
    trace = straight_trace(world, np.array([0.0, 0.0]), np.array([40.0, 0.0]))
    with pytest.raises(RuntimeError, match="plots"):
        write_figures(tmp_path, world, route, trace, PARAMS)


def test_import_has_no_matplotlib_side_effect() -> None:
    code = "import sys, sim.plots; assert 'matplotlib' not in sys.modules, 'imported'"
    subprocess.run(
        [sys.executable, "-c", code], check=True, timeout=60, cwd=Path(__file__).parents[1]
    )
