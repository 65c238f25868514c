"""Tests for sim.world: feature heights, ray casting, distance queries, config errors."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from companion.sim.world import World, WorldConfig


def world(*features: dict[str, Any], ground_z_m: float = 0.0, **kwargs: Any) -> World:
    cfg = WorldConfig.model_validate({"ground_z_m": ground_z_m, "features": list(features)})
    return World.from_config(cfg, **kwargs)


def h(w: World, x: float, y: float) -> float:
    return float(w.height(x, y))


DOWN = np.array([[0.0, 0.0, -1.0]])


# --------------------------------------------------------------------------- heights


def test_gaussian_hill_heights() -> None:
    w = world({"type": "gaussian_hill", "center": [10, 5], "height_m": 4, "sigma_m": 2})
    assert h(w, 10, 5) == pytest.approx(4.0)
    assert h(w, 12, 5) == pytest.approx(4.0 * math.exp(-0.5))
    assert h(w, 10, 1) == pytest.approx(4.0 * math.exp(-2.0))
    assert h(w, 100, 100) == pytest.approx(0.0, abs=1e-12)


def test_elliptic_gaussian_hill_with_yaw() -> None:
    # sigma 4 along the hill's x axis, turned to point north (+y).
    w = world(
        {
            "type": "gaussian_hill",
            "center": [0, 0],
            "height_m": 2,
            "sigma_xy_m": [4, 1],
            "yaw_deg": 90,
        }
    )
    assert h(w, 0, 4) == pytest.approx(2.0 * math.exp(-0.5))
    assert h(w, 1, 0) == pytest.approx(2.0 * math.exp(-0.5))
    assert h(w, 4, 0) == pytest.approx(2.0 * math.exp(-8.0))


def test_mesa_heights() -> None:
    w = world(
        {"type": "mesa", "center": [0, 0], "radius_m": 5, "height_m": 10, "side_slope_deg": 80},
        ground_z_m=1.0,
    )
    tan80 = math.tan(math.radians(80))
    assert h(w, 0, 0) == pytest.approx(11.0)
    assert h(w, 5, 0) == pytest.approx(11.0)
    assert h(w, 0, 5.5) == pytest.approx(11.0 - 0.5 * tan80)
    assert h(w, 5 + 10 / tan80 + 0.01, 0) == pytest.approx(1.0)
    assert h(w, 20, 0) == pytest.approx(1.0)


def test_vertical_mesa_is_a_cylinder() -> None:
    w = world(
        {"type": "mesa", "center": [0, 0], "radius_m": 5, "height_m": 3, "side_slope_deg": 90}
    )
    assert h(w, 4.999, 0) == pytest.approx(3.0)
    assert h(w, 5.001, 0) == pytest.approx(0.0)


def test_cylinder_heights_and_max_with_terrain() -> None:
    w = world(
        {"type": "gaussian_hill", "center": [0, 0], "height_m": 5, "sigma_m": 10},
        {"type": "cylinder", "center": [0, 0], "radius_m": 1, "height_m": 3},
        {"type": "cylinder", "center": [20, 0], "radius_m": 1, "height_m": 3},
    )
    assert h(w, 0, 0) == pytest.approx(5.0)  # buried in the hill: the hill wins
    assert h(w, 20, 0.5) == pytest.approx(3.0)  # stands on ground_z, top at 3
    assert h(w, 20, 1.5) == pytest.approx(5.0 * math.exp(-(20**2 + 1.5**2) / 200))
    assert float(w.terrain_height(20, 0.5)) == pytest.approx(5.0 * math.exp(-400.25 / 200))


def test_box_with_yaw() -> None:
    w = world({"type": "box", "center": [10, 0], "size_m": [6, 2, 4], "yaw_deg": 90})
    # Turned 90 degrees: 6 m along y, 2 m along x.
    assert h(w, 10, 2.9) == pytest.approx(4.0)
    assert h(w, 10.9, 0) == pytest.approx(4.0)
    assert h(w, 12, 0) == pytest.approx(0.0)
    assert h(w, 10, 3.1) == pytest.approx(0.0)
    w45 = world({"type": "box", "center": [0, 0], "size_m": [4, 4, 1], "yaw_deg": 45})
    assert h(w45, 2.0 * math.sqrt(2) - 0.01, 0) == pytest.approx(1.0)  # a corner on +x
    assert h(w45, 1.9, 1.9) == pytest.approx(0.0)  # the unrotated corner region


def test_plane_heights() -> None:
    w = world(
        {"type": "plane", "slope_deg": 45, "direction_deg": 90, "point": [0, 1]},
        ground_z_m=-2.0,
    )
    assert h(w, 0, 1) == pytest.approx(-2.0)
    assert h(w, 5, 3) == pytest.approx(0.0)
    assert h(w, 7, -1) == pytest.approx(-4.0)


def test_broadcasting() -> None:
    w = world({"type": "gaussian_hill", "center": [0, 0], "height_m": 1, "sigma_m": 1})
    z = w.height(np.arange(3.0)[None, :], np.arange(4.0)[:, None])
    assert z.shape == (4, 3)
    assert z[0, 0] == pytest.approx(1.0)
    assert w.height(0.0, 0.0).shape == ()


def test_heightmap_round_trip(tmp_path: Path) -> None:
    grid = np.array([[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]])  # rows = y, cols = x
    np.save(tmp_path / "hm.npy", grid)
    cfg = WorldConfig.model_validate(
        {
            "ground_z_m": 10.0,
            "features": [
                {"type": "heightmap", "file": "hm.npy", "resolution_m": 2.0, "origin": [1, -1]}
            ],
        }
    )
    w = World.from_config(cfg, base_dir=tmp_path)
    assert h(w, 1, -1) == pytest.approx(10.0)
    assert h(w, 5, 1) == pytest.approx(15.0)
    assert h(w, 2, -1) == pytest.approx(10.5)  # halfway along x
    assert h(w, 4, 0) == pytest.approx(10.0 + 0.5 * (1.5 + 4.5))  # bilinear
    assert h(w, 0.9, 0) == pytest.approx(10.0)  # outside: no contribution
    assert h(w, 3, 1.1) == pytest.approx(10.0)
    with pytest.raises(ValueError, match=r"hm\.npy"):
        World.from_config(cfg, base_dir=tmp_path / "elsewhere")


def test_heightmap_bad_array(tmp_path: Path) -> None:
    np.save(tmp_path / "line.npy", np.arange(5.0))
    cfg = WorldConfig.model_validate(
        {"features": [{"type": "heightmap", "file": "line.npy", "resolution_m": 1}]}
    )
    with pytest.raises(ValueError, match="2-D"):
        World.from_config(cfg, base_dir=tmp_path)


def test_feature_info_and_names() -> None:
    w = world(
        {"type": "gaussian_hill", "center": [0, 0], "height_m": 2, "sigma_m": 3},
        {"type": "gaussian_hill", "center": [9, 0], "height_m": 2, "sigma_m": 3},
        {"type": "cylinder", "name": "pole", "center": [5, 5], "radius_m": 0.5, "height_m": 8},
        {"type": "box", "center": [20, 0], "size_m": [2, 2, 2]},
        {"type": "plane", "slope_deg": 3},
        {"type": "plane", "slope_deg": 0, "name": "gaussian_hill_2"},
    )
    names = [f.name for f in w.features]
    assert names == [
        "gaussian_hill",
        "gaussian_hill_2",
        "pole",
        "box",
        "plane",
        "gaussian_hill_2_2",
    ]
    obstacles = w.obstacle_features
    assert [f.name for f in obstacles] == ["pole", "box"]
    assert obstacles[0].circle == (5.0, 5.0, 0.5)
    assert obstacles[1].polygon is not None and obstacles[1].polygon.shape == (4, 2)
    xmin, xmax, ymin, ymax = w.extent()
    assert xmin < -3 and xmax > 21 and ymin < -3 and ymax > 5.5
    assert float(w.feature_height("pole", 5, 5)) == pytest.approx(8.0)
    assert float(w.feature_height("pole", 0, 0)) == -np.inf
    assert w.is_inside([5, 5, 7.9]) and not w.is_inside([5, 5, 8.1])


# --------------------------------------------------------------------------- raycast


def test_ray_down_over_flat_ground() -> None:
    w = world(ground_z_m=1.0)
    r = w.raycast([[2.0, 3.0, 4.0]], DOWN, 10.0)
    assert r[0] == pytest.approx(3.0, abs=1e-3)


def test_ray_to_cylinder_wall() -> None:
    w = world({"type": "cylinder", "center": [10, 0], "radius_m": 2, "height_m": 5})
    r = w.raycast([[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]], 20.0)
    assert r[0] == pytest.approx(8.0, abs=1e-3)
    # Off-centre at y = 1: the wall is at x = 10 - sqrt(3).
    r = w.raycast([[0.0, 1.0, 1.0]], [[1.0, 0.0, 0.0]], 20.0)
    assert r[0] == pytest.approx(10.0 - math.sqrt(3.0), abs=1e-3)
    # Slanted ray hitting the wall: horizontal 8 m, climbing 0.3 m per metre.
    d = np.array([[1.0, 0.0, 0.3]]) / math.hypot(1.0, 0.3)
    assert w.raycast([[0.0, 0.0, 1.0]], d, 20.0)[0] == pytest.approx(8 * math.hypot(1, 0.3), 1e-4)


def test_ray_beyond_range_and_start_inside() -> None:
    w = world({"type": "cylinder", "center": [10, 0], "radius_m": 2, "height_m": 5})
    o = np.array([[0.0, 0.0, 1.0], [10.0, 0.0, 4.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    d = np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0], [-1.0, 0, -0.001]])
    r = w.raycast(o, d, np.array([7.9, 5.0, 50.0, 30.0]))
    assert r[0] == np.inf  # wall at 8 m, range 7.9
    assert r[1] == 0.0  # starts inside the cylinder
    assert r[2] == np.inf  # straight up
    assert r[3] == np.inf  # meets the ground 1 km away
    assert w.raycast(o[:1], d[:1], 8.0001)[0] == pytest.approx(8.0, abs=1e-3)


def test_ray_per_ray_ranges_and_zero_range() -> None:
    w = world(ground_z_m=0.0)
    o = np.array([[0.0, 0.0, 2.0]] * 3)
    r = w.raycast(o, np.repeat(DOWN, 3, axis=0), np.array([1.0, 3.0, 0.0]))
    assert r[0] == np.inf and r[1] == pytest.approx(2.0, abs=1e-3) and r[2] == np.inf
    assert w.raycast(np.empty((0, 3)), np.empty((0, 3)), 1.0).shape == (0,)


def test_thin_pillar_is_not_skipped() -> None:
    w = world({"type": "cylinder", "center": [5, 0], "radius_m": 0.15, "height_m": 5})
    ys = np.linspace(-0.12, 0.12, 25)
    o = np.column_stack([np.zeros_like(ys), ys, np.ones_like(ys)])
    d = np.tile([1.0, 0.0, 0.0], (ys.size, 1))
    r = w.raycast(o, d, 10.0)
    assert np.allclose(r, 5.0 - np.sqrt(0.15**2 - ys**2), atol=1e-3)


def test_ray_to_yawed_box() -> None:
    w = world({"type": "box", "center": [10, 0], "size_m": [2, 2, 3], "yaw_deg": 45})
    # The near corner points at the origin, at x = 10 - sqrt(2).
    r = w.raycast([[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]], 20.0)
    assert r[0] == pytest.approx(10.0 - math.sqrt(2.0), abs=1e-3)
    # From above, straight down onto the top.
    r = w.raycast([[10.0, 0.5, 5.0]], DOWN, 20.0)
    assert r[0] == pytest.approx(2.0, abs=1e-3)


def test_many_long_rays_take_several_chunks() -> None:
    w = world({"type": "plane", "slope_deg": 10, "direction_deg": 0}, ground_z_m=0.0)
    n = 600
    a = np.linspace(-1.0, 1.0, n)
    d = np.column_stack([np.cos(a), np.sin(a), np.full(n, -0.01)])
    d /= np.linalg.norm(d, axis=1)[:, None]
    o = np.tile([0.0, 0.0, 5.0], (n, 1))
    r = w.raycast(o, d, 100.0)
    # Exact: z0 + t dz = tan(10) * t dx.
    t = 5.0 / (math.tan(math.radians(10)) * d[:, 0] - d[:, 2])
    expected = np.where((t > 0) & (t <= 100.0), t, np.inf)
    finite = np.isfinite(expected)
    assert np.array_equal(np.isfinite(r), finite)
    assert np.allclose(r[finite], expected[finite], atol=1e-3)


def test_raycast_rejects_bad_input() -> None:
    w = world()
    with pytest.raises(ValueError, match="non-zero"):
        w.raycast([[0.0, 0.0, 1.0]], [[0.0, 0.0, 0.0]], 1.0)
    with pytest.raises(ValueError, match="max_range_m"):
        w.raycast([[0.0, 0.0, 1.0]], DOWN, np.inf)


SMOOTH = (
    {"type": "gaussian_hill", "center": [5, 0], "height_m": 3, "sigma_m": 2},
    {"type": "mesa", "center": [-4, 3], "radius_m": 1.5, "height_m": 4, "side_slope_deg": 60},
    {"type": "plane", "slope_deg": 5, "direction_deg": 30},
)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    ox=st.floats(-8, 8),
    oy=st.floats(-8, 8),
    oz=st.floats(0.5, 6),
    az=st.floats(-math.pi, math.pi),
    el=st.floats(-1.4, 0.3),
)
def test_raycast_matches_fine_sampling(
    ox: float, oy: float, oz: float, az: float, el: float
) -> None:
    w = world(*SMOOTH)
    o = np.array([ox, oy, float(w.height(ox, oy)) + oz])
    d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    r = float(w.raycast(o[None, :], d[None, :], 15.0)[0])
    t = np.arange(0.0, 15.0, 5e-4)
    p = o + t[:, None] * d
    below = p[:, 2] < w.height(p[:, 0], p[:, 1])
    brute = float(t[np.argmax(below)]) if below.any() else np.inf
    if math.isfinite(brute) and brute < 14.99:
        assert r == pytest.approx(brute, abs=2e-3)
    elif brute == np.inf:
        assert r == np.inf


# --------------------------------------------------------------------------- distances


def test_surface_distance_flat_ground() -> None:
    w = world({"type": "cylinder", "center": [30, 0], "radius_m": 1, "height_m": 5}, ground_z_m=2)
    assert w.surface_distance([0.03, 0.07, 5.0]) == pytest.approx(3.0, abs=1e-3)
    assert w.surface_distance([1.0, 2.0, 2.5]) == pytest.approx(0.5, abs=1e-3)
    assert w.surface_distance([1.0, 2.0, 1.5]) == 0.0
    # Far outside the raster: analytic fall-back.
    assert w.surface_distance([500.0, -300.0, 6.0]) == pytest.approx(4.0, abs=1e-3)


def test_surface_distance_next_to_wall() -> None:
    w = world(
        {"type": "cylinder", "center": [10, 0], "radius_m": 2, "height_m": 8},
        {"type": "box", "center": [0, 20], "size_m": [4, 4, 8], "yaw_deg": 30},
    )
    assert w.surface_distance([7.3, 0.0, 3.0]) == pytest.approx(0.7, abs=5e-3)
    assert w.surface_distance([10.0, -2.45, 1.0]) == pytest.approx(0.45, abs=5e-3)
    # Above the top edge: distance to the rim.
    assert w.surface_distance([7.0, 0.0, 8.5]) == pytest.approx(math.hypot(1.0, 0.5), abs=5e-3)
    # Box face: the face normal of a box yawed 30 degrees is (cos 30, sin 30).
    n = np.array([math.cos(math.radians(30)), math.sin(math.radians(30)), 0.0])
    p = np.array([0.0, 20.0, 2.0]) + (2.0 + 0.8) * n
    assert w.surface_distance(p) == pytest.approx(0.8, abs=5e-3)


def test_surface_distance_to_mesa_side() -> None:
    w = world(
        {"type": "mesa", "center": [0, 0], "radius_m": 2, "height_m": 4, "side_slope_deg": 45}
    )
    # Side: r + z = 6 for 2 <= r <= 6. From (r, z) = (4, 4) the foot is (3, 3).
    p = np.array([4.0 * math.cos(1.0), 4.0 * math.sin(1.0), 4.0])
    assert w.surface_distance(p) == pytest.approx(math.sqrt(2.0), abs=1e-6)
    assert w.obstacle_distance(p) == pytest.approx(math.sqrt(2.0), abs=1e-6)
    assert w.surface_distance([0.5, 0.0, 5.0]) == pytest.approx(1.0, abs=1e-6)
    assert w.surface_distance([7.0, 0.0, 0.5]) == pytest.approx(0.5, abs=1e-3)  # ground
    assert w.obstacle_distance([7.0, 0.0, 0.5]) == pytest.approx(math.hypot(1.0, 0.5))  # foot


def test_surface_distance_on_a_slope() -> None:
    w = world({"type": "plane", "slope_deg": 20, "direction_deg": 45})
    for p in ([0.0, 0.0, 3.0], [4.0, -2.0, 1.5]):
        c = p[2] - h(w, p[0], p[1])
        assert w.surface_distance(p) == pytest.approx(c * math.cos(math.radians(20)), abs=3e-3)


MIXED = (
    {"type": "gaussian_hill", "center": [3, 0], "height_m": 2, "sigma_m": 2},
    {"type": "cylinder", "center": [-3, 1], "radius_m": 0.8, "height_m": 4},
    {"type": "box", "center": [1, -4], "size_m": [3, 1, 2], "yaw_deg": 20},
    {"type": "mesa", "center": [-2, -3], "radius_m": 1, "height_m": 3, "side_slope_deg": 75},
)


MIXED_WORLD = world(*MIXED)


def brute_distance(
    w: World, p: np.ndarray, solid: str, radius: float, spacing: float = 0.01
) -> float:
    """Distance from p to the solid by exhaustive search on a grid around p."""
    g = np.arange(-radius, radius + spacing / 2, spacing)
    x, y = p[0] + g[None, :], p[1] + g[:, None]
    z = w.height(x, y) if solid == "surface" else w.obstacle_height(x, y)
    d2 = (x - p[0]) ** 2 + (y - p[1]) ** 2 + np.maximum(p[2] - z, 0.0) ** 2
    return float(np.sqrt(d2.min()))


@settings(max_examples=25, deadline=None, derandomize=True)
@given(x=st.floats(-6, 6), y=st.floats(-6, 6), dz=st.floats(0.05, 3.0))
def test_distances_match_brute_force(x: float, y: float, dz: float) -> None:
    w = MIXED_WORLD
    p = np.array([x, y, h(w, x, y) + dz])
    brute = brute_distance(w, p, "surface", radius=dz + 0.02)
    assert w.surface_distance(p) == pytest.approx(brute, abs=0.015)
    brute_obs = brute_distance(w, p, "obstacle", radius=5.0, spacing=0.02)
    if brute_obs < 4.9:  # else the nearest obstacle may lie outside the brute-force window
        assert w.obstacle_distance(p) == pytest.approx(brute_obs, abs=0.02)


def test_obstacle_distance_ignores_ground() -> None:
    assert world(ground_z_m=3).obstacle_distance([0.0, 0.0, 3.5]) == np.inf
    w = world(
        {"type": "cylinder", "center": [10, 0], "radius_m": 1, "height_m": 5},
        {"type": "gaussian_hill", "center": [-20, 0], "height_m": 4, "sigma_m": 3},
    )
    p = [5.0, 0.0, 0.5]  # 0.5 m above the ground, 4 m from the pole
    assert w.surface_distance(p) == pytest.approx(0.5, abs=1e-3)
    assert w.obstacle_distance(p) == pytest.approx(4.0, abs=5e-3)
    assert w.obstacle_distance([10.0, 0.3, 7.0]) == pytest.approx(2.0, abs=5e-3)
    assert w.obstacle_distance([10.0, 0.3, 4.0]) == 0.0


def test_obstacle_distance_buried_and_flagged_hill() -> None:
    buried = world(
        {"type": "gaussian_hill", "center": [0, 0], "height_m": 6, "sigma_m": 5},
        {"type": "box", "center": [0, 0], "size_m": [2, 2, 3]},
    )
    assert buried.obstacle_distance([0.0, 0.0, 8.0]) == np.inf
    hill = world(
        {"type": "gaussian_hill", "center": [0, 0], "height_m": 6, "sigma_m": 1, "obstacle": True}
    )
    assert hill.obstacle_distance([0.0, 0.0, 8.0]) == pytest.approx(2.0, abs=5e-3)
    assert math.isfinite(hill.obstacle_distance([6.0, 0.0, 0.2]))


# --------------------------------------------------------------------------- config errors


@pytest.mark.parametrize(
    ("feature", "field"),
    [
        ({"type": "cylinder", "center": [0, 0], "radius_m": -1, "height_m": 2}, "radius_m"),
        ({"type": "mesa", "center": [0, 0], "radius_m": 1, "height_m": 0}, "height_m"),
        (
            {"type": "mesa", "center": [0, 0], "radius_m": 1, "height_m": 2, "side_slope_deg": 95},
            "side_slope_deg",
        ),
        ({"type": "box", "center": [0, 0], "size_m": [1, -2, 3]}, "size_m"),
        ({"type": "box", "center": [0, 0], "size_m": [1, 2]}, "size_m"),
        ({"type": "gaussian_hill", "center": [0, 0], "height_m": 1, "sigma_m": 0}, "sigma_m"),
        ({"type": "gaussian_hill", "center": [0, 0], "height_m": 1}, "sigma"),
        ({"type": "plane", "slope_deg": 90}, "slope_deg"),
        ({"type": "heightmap", "file": "x.npy", "resolution_m": 0}, "resolution_m"),
        (
            {"type": "cylinder", "center": [0, 0], "radius_m": 1, "height_m": 2, "colour": 1},
            "colour",
        ),
        ({"type": "volcano", "center": [0, 0]}, "volcano"),
        ({"type": "cylinder", "center": [0, "nan"], "radius_m": 1, "height_m": 2}, "center"),
    ],
)
def test_invalid_configs_name_the_field(feature: dict[str, Any], field: str) -> None:
    with pytest.raises(ValueError, match=field):
        WorldConfig.model_validate({"features": [feature]})


def test_validation_error_is_a_value_error() -> None:
    with pytest.raises(ValidationError):
        WorldConfig.model_validate({"ground_z_m": "low"})


# --------------------------------------------------------------------------- fast paths


EVERY_FEATURE = (
    {"type": "gaussian_hill", "center": [4, 2], "height_m": 3, "sigma_m": 2.5},
    {
        "type": "gaussian_hill",
        "center": [-5, -4],
        "height_m": -1.5,
        "sigma_xy_m": [3, 1.5],
        "yaw_deg": 30,
    },
    {"type": "plane", "slope_deg": 6, "direction_deg": 120, "point": [1, 1]},
    {"type": "mesa", "center": [-6, 5], "radius_m": 1.5, "height_m": 5, "side_slope_deg": 70},
    {"type": "cylinder", "center": [6, -6], "radius_m": 0.6, "height_m": 6},
    {"type": "box", "center": [0, -8], "size_m": [4, 1.5, 3], "yaw_deg": 25},
)


def random_rays(
    w: World, n: int, seed: int, span: float = 12.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n seeded rays from 0.2-6 m above the surface, any direction, ranges 0-15 m."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-span, span, size=(n, 2))
    z = w.height(xy[:, 0], xy[:, 1]) + rng.uniform(0.2, 6.0, n)
    o = np.column_stack([xy, z])
    az = rng.uniform(-math.pi, math.pi, n)
    el = rng.uniform(-math.pi / 2, math.pi / 2, n)
    d = np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    d[:20] = [0.0, 0.0, -1.0]  # straight down, and level along the axes
    d[20:40] = [1.0, 0.0, 0.0]
    d[40:60] = [0.0, -1.0, 0.0]
    o[60:80, 2] -= 7.0  # some start inside
    return o, d, rng.uniform(0.0, 15.0, n)


def assert_same_ranges(fast: np.ndarray, ref: np.ndarray, atol: float = 1e-3) -> None:
    assert np.array_equal(np.isfinite(fast), np.isfinite(ref))
    finite = np.isfinite(ref)
    assert np.max(np.abs(fast[finite] - ref[finite]), initial=0.0) <= atol


@pytest.mark.parametrize(("seed", "heightmap"), [(1, False), (2, False), (3, True)])
def test_raycast_matches_the_marching_reference(seed: int, heightmap: bool, tmp_path: Path) -> None:
    u = np.linspace(0.0, 1.0, 60)
    z = 1.2 * np.sin(6.0 * u)[None, :] * np.cos(4.0 * u)[:, None] + 0.5
    np.save(tmp_path / "map.npy", z)
    hm = {"type": "heightmap", "file": "map.npy", "resolution_m": 0.2, "origin": [2, -12]}
    feats = [*EVERY_FEATURE, hm] if heightmap else list(EVERY_FEATURE)
    w = World.from_config(WorldConfig.model_validate({"features": feats}), tmp_path)
    o, d, rng = random_rays(w, 1000, seed)
    ref = w.raycast_march(o, d, rng, step_m=0.005, tol_m=1e-5)
    assert_same_ranges(w.raycast(o, d, rng), ref)
    # Coarser scans give the same answers.
    assert_same_ranges(w.raycast(o, d, rng, step_m=1.0), ref)


def test_raycast_solids_only_is_closed_form() -> None:
    w = world(*EVERY_FEATURE[3:])
    o, d, rng = random_rays(w, 1000, 3)
    ref = w.raycast_march(o, d, rng, step_m=0.005, tol_m=1e-6)
    assert_same_ranges(w.raycast(o, d, rng), ref, atol=1e-4)


def test_raycast_grazing_a_hill_top() -> None:
    # Level rays just above, at and below the top of a hill: the scan's slope bound cannot
    # clear the intervals near the top, which are searched again finely.
    w = world({"type": "gaussian_hill", "center": [10, 0], "height_m": 3, "sigma_m": 2})
    zs = 3.0 + np.array([-0.2, -0.01, -1e-3, 1e-3, 0.01, 0.2])
    o = np.column_stack([np.zeros_like(zs), np.zeros_like(zs), zs])
    d = np.tile([1.0, 0.0, 0.0], (zs.size, 1))
    r = w.raycast(o, d, 20.0)
    assert_same_ranges(r, w.raycast_march(o, d, 20.0, step_m=1e-3, tol_m=1e-6))
    # Below the top: 10 - the hill's half width at that height.
    below = zs < 3.0
    half = 2.0 * np.sqrt(2.0 * np.log(3.0 / zs[below]))
    assert np.allclose(r[below], 10.0 - half, atol=1e-4)
    assert np.all(np.isinf(r[~below]))


def test_surface_distance_newton_matches_the_raster_search() -> None:
    w = world(
        {"type": "gaussian_hill", "center": [4, 2], "height_m": 3, "sigma_m": 6},
        {
            "type": "gaussian_hill",
            "center": [-5, -4],
            "height_m": -1,
            "sigma_xy_m": [6, 3],
            "yaw_deg": 30,
        },
        EVERY_FEATURE[2],
    )
    rng = np.random.default_rng(4)
    for _ in range(300):
        x, y = rng.uniform(-15, 15, 2)
        p = (float(x), float(y), float(h(w, x, y) + rng.uniform(0.05, 2.5)))
        newton = w.distances.terrain_distance_newton(p)
        assert newton is not None
        assert newton == pytest.approx(w.distances.terrain_distance_raster(p, math.inf), abs=1e-3)


def test_surface_distance_falls_back_where_not_convex() -> None:
    # High above a narrow hill the distance function is not convex: the raster search.
    w = world({"type": "gaussian_hill", "center": [0, 0], "height_m": 3, "sigma_m": 1})
    p = (0.5, 0.0, 9.0)
    assert w.distances.terrain_distance_newton(p) is None
    assert w.surface_distance(p) == pytest.approx(
        brute_distance(w, np.array(p), "surface", radius=6.5, spacing=0.01), abs=0.01
    )


def test_raycast_along_the_terrain_ends() -> None:
    # A vehicle standing on the ground: level rays run along the terrain, within a hair of it.
    w = world({"type": "gaussian_hill", "center": [-1, 25.8], "height_m": 3, "sigma_m": 6})
    o = np.array([24.0, 24.0, h(w, 24.0, 24.0)])
    a = np.linspace(0.0, 2.0 * math.pi, 16, endpoint=False)
    d = np.column_stack([np.cos(a), np.sin(a), np.zeros_like(a)])
    origins = np.tile(o, (a.size, 1))
    r = w.raycast(origins, d, 12.0)
    assert_same_ranges(r, w.raycast_march(origins, d, 12.0, step_m=0.01, tol_m=1e-5))
