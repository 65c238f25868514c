"""sim.world.features: all rays against all solid columns at once give the ranges of one
feature at a time, bit for bit, and agree with the reference march."""

from __future__ import annotations

import numpy as np
import pytest

from companion.sim.world import BoxConfig, CylinderConfig, MesaConfig, World, WorldConfig
from companion.sim.world.features import SolidColumns, intersects


def _world(seed: int, count: int = 12) -> World:
    rng = np.random.default_rng(seed)
    feats: list[MesaConfig | CylinderConfig | BoxConfig] = []
    for k in range(count):
        centre = (float(rng.uniform(-30, 30)), float(rng.uniform(-30, 30)))
        height = float(rng.uniform(1, 12))
        kind = k % 3
        if kind == 0:
            feats.append(
                MesaConfig(
                    center=centre,
                    radius_m=float(rng.uniform(1, 5)),
                    height_m=height,
                    side_slope_deg=float(rng.uniform(30, 89)),
                )
            )
        elif kind == 1:
            feats.append(
                CylinderConfig(center=centre, radius_m=float(rng.uniform(0.5, 4)), height_m=height)
            )
        else:
            size = (float(rng.uniform(1, 10)), float(rng.uniform(1, 10)), height)
            feats.append(BoxConfig(center=centre, size_m=size, yaw_deg=float(rng.uniform(0, 180))))
    return World(WorldConfig(features=feats))


def _rays(seed: int, n: int = 400) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed + 1000)
    o = np.column_stack(
        [rng.uniform(-35, 35, n), rng.uniform(-35, 35, n), rng.uniform(0.2, 15.0, n)]
    )
    d = rng.normal(size=(n, 3))
    d[: n // 4, 2] = 0.0  # level rays, as the forward sensors
    d[n // 4 : n // 3, :2] = 0.0  # straight down or up
    d /= np.linalg.norm(d, axis=1)[:, None]
    d = np.where(d == 0.0, 1e-200, d)
    return o, d, rng.uniform(5.0, 40.0, n)


@pytest.mark.parametrize("seed", range(4))
def test_all_solids_at_once_equal_one_at_a_time_bit_for_bit(seed: int) -> None:
    world = _world(seed)
    o, d, rng = _rays(seed)
    box = (-1e9, 1e9, -1e9, 1e9)
    batched = SolidColumns(world.field.solid).first_entry(o, d, rng, box)
    one_by_one = rng.copy()
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for f in world.field.solid:
            t_in, t_out = f.ray_interval(o, d)
            np.minimum(one_by_one, np.where(t_in < t_out, t_in, np.inf), out=one_by_one)
    np.testing.assert_array_equal(batched, one_by_one)
    assert (batched < rng).sum() > 20, "too few rays meet a solid to test anything"


def test_culling_by_reach_leaves_the_ranges_unchanged() -> None:
    world = _world(7)
    o, d, rng = _rays(7, n=50)
    o = o * 0.2  # near the middle; reach 15 m: some features are out of it
    rng = np.minimum(rng, 15.0)
    box = (float(o[:, 0].min()) - 15, float(o[:, 0].max()) + 15, -15.0, 15.0)
    box = (box[0], box[1], float(o[:, 1].min()) - 15, float(o[:, 1].max()) + 15)
    cols = SolidColumns(world.field.solid)
    culled = cols.first_entry(o, d, rng, box)
    whole = cols.first_entry(o, d, rng, (-1e9, 1e9, -1e9, 1e9))
    assert not all(intersects(f.cull_bbox, box) for f in world.field.solid)
    np.testing.assert_array_equal(culled, whole)


def test_the_cast_agrees_with_the_reference_march() -> None:
    world = _world(3, count=9)
    o, d, rng = _rays(3, n=120)
    fast = world.raycast(o, d, rng)
    ref = world.raycast_march(o, d, rng, step_m=0.01, tol_m=1e-6)
    hit = np.isfinite(ref)
    assert hit.sum() > 20
    np.testing.assert_array_equal(np.isfinite(fast), hit)
    np.testing.assert_allclose(fast[hit], ref[hit], atol=2e-3)


def test_mesas_alone_at_once_equal_one_at_a_time_bit_for_bit() -> None:
    # every column a cone: the batch takes the cone bounds without selecting per feature
    rng = np.random.default_rng(11)
    feats = [
        MesaConfig(
            center=(float(rng.uniform(-30, 30)), float(rng.uniform(-30, 30))),
            radius_m=float(rng.uniform(1, 5)),
            height_m=float(rng.uniform(1, 12)),
            side_slope_deg=float(rng.uniform(30, 89)),
        )
        for _ in range(8)
    ]
    world = World(WorldConfig(features=feats))
    o, d, rng_m = _rays(11)
    batched = SolidColumns(world.field.solid).first_entry(o, d, rng_m, (-1e9, 1e9, -1e9, 1e9))
    one_by_one = rng_m.copy()
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for f in world.field.solid:
            t_in, t_out = f.ray_interval(o, d)
            np.minimum(one_by_one, np.where(t_in < t_out, t_in, np.inf), out=one_by_one)
    np.testing.assert_array_equal(batched, one_by_one)
    assert (batched < rng_m).sum() > 20


@pytest.mark.parametrize("seed", range(3))
def test_reach_of_all_solids_at_once_is_each_cull_box_test(seed: int) -> None:
    world = _world(seed)
    cols = SolidColumns(world.field.solid)
    rng = np.random.default_rng(seed)
    for _ in range(200):
        x0, y0 = rng.uniform(-45, 45, 2)
        box = (float(x0), float(x0 + rng.uniform(0, 20)), float(y0), float(y0 + rng.uniform(0, 20)))
        for feats, bb in ((cols.mesas, cols._mesa_bb), (cols.boxes, cols._box_bb)):
            expected = [intersects(f.cull_bbox, box) for f in feats]
            assert cols._in_reach(bb, box).tolist() == expected
