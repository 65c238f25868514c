"""harness.metrics: principal curvatures of a sampled surface, the window max, and which
cycles fly over gentle relief (radius of curvature >= 10 m)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from companion.harness.metrics import _window_max, gentle_relief, principal_curvature_max
from companion.sim.world import World, WorldConfig


def world(*features: dict[str, Any]) -> World:
    return World.from_config(WorldConfig.model_validate({"features": list(features)}))


def grid(step: float, half: float) -> tuple[np.ndarray, np.ndarray]:
    g = np.arange(-half, half + step / 2, step)
    x, y = np.meshgrid(g, g)
    return x, y


def test_a_plane_has_no_curvature() -> None:
    x, y = grid(0.25, 3.0)
    z = 0.7 * x - 1.3 * y + 2.0  # steep and tilted: curvature is not slope
    assert np.max(principal_curvature_max(z, 0.25)) < 1e-9


@pytest.mark.parametrize("radius", [3.0, 10.0, 40.0])
def test_a_sphere_has_one_over_its_radius_everywhere(radius: float) -> None:
    x, y = grid(0.05, 1.0)
    z = np.sqrt(radius * radius - x * x - y * y)
    kappa = principal_curvature_max(z, 0.05)[5:-5, 5:-5]  # (one-sided differences at edges)
    assert np.allclose(kappa, 1.0 / radius, rtol=2e-3)


def test_a_cylinder_has_one_over_its_radius_across_and_none_along() -> None:
    x, _ = grid(0.05, 1.0)
    z = np.sqrt(5.0**2 - x * x)  # axis along y: curved across x only
    kappa = principal_curvature_max(z, 0.05)[5:-5, 5:-5]
    assert np.allclose(kappa, 0.2, rtol=2e-3)


@pytest.mark.parametrize("half", [0, 1, 2, 3, 7, 12])
def test_window_max_is_the_brute_force_max(half: int) -> None:
    a = np.random.default_rng(half).normal(size=(23, 31))
    for axis in (0, 1):
        got = _window_max(a, half, axis)
        moved = np.moveaxis(a, axis, 0)
        want = np.stack(
            [moved[max(0, i - half) : i + half + 1].max(axis=0) for i in range(moved.shape[0])]
        )
        assert np.array_equal(got, np.moveaxis(want, 0, axis))


def test_gentle_relief_tells_a_broad_hill_from_a_narrow_one_and_a_mesa_foot() -> None:
    broad = {"type": "gaussian_hill", "center": [0, 0], "height_m": 2.0, "sigma_m": 12.0}
    narrow = {"type": "gaussian_hill", "center": [60, 0], "height_m": 2.0, "sigma_m": 2.0}
    mesa = {
        "type": "mesa",
        "center": [120, 0],
        "radius_m": 4.0,
        "height_m": 3.0,
        "side_slope_deg": 30.0,
    }
    w = world(broad, narrow, mesa)
    # A Gaussian's curvature peaks at its top, h / sigma^2: 1/72 m^-1 (broad), 1/2 (narrow).
    xs = np.array([0.0, 30.0, 60.0, 120.0 - 4.0 - 3.0 / math.tan(math.radians(30.0)), 120.0])
    ys = np.zeros_like(xs)
    gentle = gentle_relief(w, xs, ys, reach_m=4.0)
    # The broad hill's top and the flat between are gentle; the narrow hill, the mesa's
    # foot (a crease) and its top (the rim lies within 4 m) are not.
    assert gentle.tolist() == [True, True, False, False, False]
    # Far enough from the rim, the mesa's flat top is gentle again (its radius is 4 m, so
    # with a 1 m reach the centre sees no crease).
    assert gentle_relief(w, np.array([120.0]), np.array([0.0]), reach_m=1.0).tolist() == [True]


def test_no_cycles_no_relief() -> None:
    w = world()
    assert gentle_relief(w, np.zeros(0), np.zeros(0), reach_m=4.0).shape == (0,)
