"""sim.world's fast paths against their plain references, bit for bit: every hill of a kind
evaluated at once (`AdditiveSum`) against the sum feature by feature, the ray cast built on
it against the cast summing one feature at a time, the local refinement given its grids'
box against the one that measures it, and the raster's whole-window search against its
block pruning. Random worlds of `companion.sim.worldgen` and random points and rays."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from companion.planner.types import FloatArray
from companion.sim.world import World, WorldConfig
from companion.sim.world.features import AdditiveSum, Feature
from companion.sim.world.raster import Raster, local_min
from companion.sim.world.raycast import RayCaster
from companion.sim.worldgen import generate

MIXED = {
    "ground_z_m": 0.5,
    "features": [
        {"type": "gaussian_hill", "center": [3, 4], "height_m": 2.5, "sigma_m": 5},
        {
            "type": "gaussian_hill",
            "center": [-6, 1],
            "height_m": 3,
            "sigma_xy_m": [9, 3],
            "yaw_deg": 30,
        },
        {"type": "plane", "slope_deg": 4, "direction_deg": 20, "point": [0, 0]},
        {"type": "gaussian_hill", "center": [-2, -7], "height_m": -1.5, "sigma_m": 3},
        {
            "type": "gaussian_hill",
            "center": [8, -3],
            "height_m": 1.2,
            "sigma_xy_m": [2, 6],
            "yaw_deg": -70,
        },
        {"type": "gaussian_hill", "center": [0, 9], "height_m": 4, "sigma_m": 7},
        {"type": "mesa", "center": [5, 5], "radius_m": 2, "height_m": 6, "side_slope_deg": 70},
    ],
}


def _random_world(seed: int) -> World:
    return World.from_config(generate(seed).world)


def _one_by_one(
    feats: list[Feature], x: FloatArray, y: FloatArray, base: float | None
) -> FloatArray:
    """The reference: each feature's own `evaluate`, summed in order."""
    if base is None:
        z = feats[0].evaluate(x, y)
        for f in feats[1:]:
            z = z + f.evaluate(x, y)
        return z
    z = np.full(np.broadcast_shapes(x.shape, y.shape), base)
    for f in feats:
        z += f.evaluate(x, y)
    return z


def _heightmap_world(tmp_path: Path) -> World:
    u = np.linspace(0.0, 1.0, 40)
    np.save(tmp_path / "map.npy", np.sin(5.0 * u)[None, :] * np.cos(3.0 * u)[:, None])
    feats = [
        *MIXED["features"][:3],  # type: ignore[index]
        {"type": "heightmap", "file": "map.npy", "resolution_m": 0.5, "origin": [-10, -10]},
        *MIXED["features"][3:],  # type: ignore[index]
    ]
    return World.from_config(WorldConfig.model_validate({"features": feats}), tmp_path)


def test_many_round_hills_at_one_point_sum_front_to_back() -> None:
    """A single point (shapes (1,) and (1, 1)): numpy would sum a (k, 1) stack of k >= 8
    hills pairwise; the batch must give the one-by-one sum there too."""
    rng = np.random.default_rng(11)
    hills = [
        {
            "type": "gaussian_hill",
            "center": rng.uniform(-20.0, 20.0, 2).tolist(),
            "height_m": float(rng.uniform(-3.0, 3.0)),
            "sigma_m": float(rng.uniform(2.0, 9.0)),
        }
        for _ in range(15)
    ]
    world = World.from_config(WorldConfig.model_validate({"features": hills}))
    feats = world.field.additive
    batch = AdditiveSum(feats)
    for shape in [(1,), (1, 1)]:
        for _ in range(100):
            xy = rng.uniform(-25.0, 25.0, size=(2, *shape))
            np.testing.assert_array_equal(batch(xy), _one_by_one(feats, xy[0], xy[1], None))


@pytest.mark.parametrize("which", ["mixed", "heightmap", "random-2", "random-9"])
def test_every_hill_at_once_is_the_sum_one_by_one_bit_for_bit(which: str, tmp_path: Path) -> None:
    if which == "mixed":
        world = World.from_config(WorldConfig.model_validate(MIXED))
    elif which == "heightmap":
        world = _heightmap_world(tmp_path)
    else:
        world = _random_world(int(which.split("-")[1]))
    feats = world.field.additive
    assert len(feats) >= 3
    batch = AdditiveSum(feats)
    rng = np.random.default_rng(5)
    for shape in [(), (1,), (37,), (11, 49), (3, 5, 7)]:
        xy = rng.uniform(-40.0, 40.0, size=(2, *shape))
        for base in (None, world.ground_z):
            expected = _one_by_one(feats, xy[0], xy[1], base)
            got = batch(xy, base)
            assert isinstance(got, np.ndarray) and got.shape == shape
            np.testing.assert_array_equal(got, expected)
    # beyond the batch's size, feature by feature: the same again
    xy = rng.uniform(-40.0, 40.0, size=(2, AdditiveSum.MAX_BATCH // len(feats) + 10))
    np.testing.assert_array_equal(batch(xy, 1.0), _one_by_one(feats, xy[0], xy[1], 1.0))


def test_terrain_is_the_plain_sum_bit_for_bit() -> None:
    world = _random_world(11)
    rng = np.random.default_rng(2)
    x, y = rng.uniform(-150.0, 150.0, size=(2, 300))
    box = world.field.box_of(x, y)
    expected = _one_by_one(world.field.cull(world.field.additive, box), x, y, world.ground_z)
    np.testing.assert_array_equal(world.terrain_height(x, y), expected)
    # broadcast shapes (a raster's rows and columns) take the plain path
    xs, ys = x[:20][None, :], y[:15][:, None]
    plain = _one_by_one(world.field.additive, xs, ys, world.ground_z)
    np.testing.assert_array_equal(world.field.terrain(xs, ys), plain)


class _ReferenceCaster(RayCaster):
    """The cast as it was: the terrain's features summed one at a time."""

    def _sum_at(
        self, feats: list[Feature], o: FloatArray, d: FloatArray, T: FloatArray
    ) -> FloatArray:
        X, Y = o[:, :2].T[:, :, None] + d[:, :2].T[:, :, None] * T
        return _one_by_one(feats, X, Y, None)


def _rays(world: World, n: int, seed: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Rays from 0.3-6 m above the surface, in every direction (a third of them level)."""
    rng = np.random.default_rng(seed)
    x0, x1, y0, y1 = world.extent()
    xy = np.column_stack([rng.uniform(x0, x1, n), rng.uniform(y0, y1, n)])
    z = world.height(xy[:, 0], xy[:, 1]) + rng.uniform(0.3, 6.0, n)
    d = rng.normal(size=(n, 3))
    d[: n // 3, 2] = 0.0
    return np.column_stack([xy, z]), d, rng.uniform(2.0, 15.0, n)


@pytest.mark.parametrize("seed", [2, 5, 9])
def test_the_cast_equals_the_one_by_one_cast_bit_for_bit(seed: int) -> None:
    world = _random_world(seed)
    ref = _ReferenceCaster(world.field, world.ray_step_m, world.scan_step_m)
    o, d, rng = _rays(world, 600, seed)
    fast = world.raycast(o, d, rng)
    np.testing.assert_array_equal(fast, ref.cast(o, d, rng))
    assert 100 < np.isfinite(fast).sum() < 590, "too few or too many hits to test anything"
    # and in small casts, as the simulator makes them (one pose, its sensors)
    for i in range(0, 600, 11):
        part = slice(i, i + 11)
        np.testing.assert_array_equal(
            world.raycast(o[part], d[part], rng[part]), ref.cast(o[part], d[part], rng[part])
        )


@pytest.mark.parametrize("seed", [3, 9])
def test_local_min_given_its_box_equals_the_measured_box(seed: int) -> None:
    world = _random_world(seed)
    field = world.field
    rng = np.random.default_rng(seed)
    x0, x1, y0, y1 = world.extent()
    for _ in range(40):
        px, py = float(rng.uniform(x0, x1)), float(rng.uniform(y0, y1))
        pz = float(world.terrain_height(px, py)) + float(rng.uniform(-0.5, 4.0))
        qx, qy = px + float(rng.uniform(-1, 1)), py + float(rng.uniform(-1, 1))
        args = ((px, py, pz), qx, qy, math.inf, float(rng.uniform(0.05, 3.0)))
        plain = local_min(*args, field.terrain_culled)
        assert local_min(*args, field.terrain_culled, boxed=field.terrain) == plain


def _flat_raster() -> Raster:
    # flat ground with a step: many samples at exactly the same distance (ties)
    def fn(x: FloatArray, y: FloatArray) -> FloatArray:
        return np.where((x > 3.0) & (y < -2.0), 1.5, 0.0) + 0.0 * y

    return Raster((-12.0, 12.0, -10.0, 10.0), 0.1, fn)


@pytest.mark.parametrize("kind", ["flat", "random-9"])
def test_whole_window_search_equals_the_block_pruning(kind: str) -> None:
    if kind == "flat":
        ras = _flat_raster()
        span = (-10.0, 10.0, -8.0, 8.0)
    else:
        world = _random_world(9)
        ras = world.distances._terrain_ras
        x0, x1, y0, y1 = world.extent()
        span = (x0 + 5, x1 - 5, y0 + 5, y1 - 5)
    rng = np.random.default_rng(1)
    whole = pruned = 0
    for k in range(300):
        # on the grid's points and half-way between them (ties), or anywhere
        if k % 3 == 0:
            px = round(float(rng.uniform(span[0], span[1])) * 20.0) / 20.0
            py = round(float(rng.uniform(span[2], span[3])) * 20.0) / 20.0
        else:
            px, py = float(rng.uniform(span[0], span[1])), float(rng.uniform(span[2], span[3]))
        pz = float(rng.uniform(-0.5, 5.0))
        r = float(rng.uniform(0.05, 4.0))
        ub = r if k % 4 else float(rng.uniform(0.0, 1.0))  # small bounds: the pruning decides
        fast = ras.search_window(px, py, pz, r) if ub == r else None
        try:
            ras.WHOLE_WINDOW_BLOCKS = 0
            ref = ras.search_window(px, py, pz, r)
        finally:
            del ras.WHOLE_WINDOW_BLOCKS
        if fast is not None:
            assert fast == ref
        w = _window(ras, px, py, r)
        if w is not None:
            got = ras._search_whole(px, py, pz, ub, w)
            cols = tuple(a[w] for a in (ras.brx0, ras.bry0, ras.bmax, ras.ax, ras.ay, ras.zb))
            expected = ras._search(px, py, pz, ub, cols)
            if got is None:
                pruned += 1
            else:
                whole += 1
                assert got == expected
    assert whole > 100 and pruned > 5


def _window(ras: Raster, px: float, py: float, r: float) -> tuple[slice, slice] | None:
    span = ras.B * ras.cell
    bx0 = max(0, int((px - r - ras.x0) // span))
    bx1 = min(ras.nbx, int((px + r - ras.x0) // span) + 1)
    by0 = max(0, int((py - r - ras.y0) // span))
    by1 = min(ras.nby, int((py + r - ras.y0) // span) + 1)
    if bx0 >= bx1 or by0 >= by1:
        return None
    return (slice(by0, by1), slice(bx0, bx1))


@pytest.mark.parametrize("seed", [5, 9])
def test_a_lazy_raster_samples_what_the_whole_grid_would(seed: int) -> None:
    world = _random_world(seed)
    field = world.field
    cell = 0.25  # (a coarser grid than the world's: the whole one is built here too)
    whole = Raster(world.extent(), cell, field.terrain_culled)
    lazy = Raster(world.extent(), cell, field.terrain_culled, field.terrain)
    rng = np.random.default_rng(seed)
    x0, x1, y0, y1 = world.extent()
    for _ in range(150):  # in the middle third: the rest is never sampled
        px = float(rng.uniform(x0 + (x1 - x0) / 3, x1 - (x1 - x0) / 3))
        py = float(rng.uniform(y0 + (y1 - y0) / 3, y1 - (y1 - y0) / 3))
        pz = float(world.terrain_height(px, py)) + float(rng.uniform(0.1, 4.0))
        r = float(rng.uniform(0.2, 6.0))
        assert lazy.nearest_sample(px, py, pz) == whole.nearest_sample(px, py, pz)
        assert lazy.search_window(px, py, pz, r) == whole.search_window(px, py, pz, r)
    built = lazy.built_blocks
    assert 0 < built.sum() < built.size / 2, "the searches should sample part of the grid"
    np.testing.assert_array_equal(lazy.zb[built], whole.zb[built])
    for name in ("bmax", "ax", "ay"):
        np.testing.assert_array_equal(getattr(lazy, name)[built], getattr(whole, name)[built])
    # every block that holds solid, sampling the rest
    for a, b in zip(lazy._ne_cols, whole._ne_cols, strict=True):
        np.testing.assert_array_equal(a, b)
    assert lazy.built_blocks.all()
