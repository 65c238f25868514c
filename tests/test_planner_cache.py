"""The planner's per-cycle shortcuts give the numbers of measuring afresh: the look-ahead's
clearances kept between cycles and brought up to date from the memory's change log
(`Planner._clearance`) against `min_distance_within` on the cycle's own window, and the
steep-point step against the array form it replaced."""

from pathlib import Path

import numpy as np
import pytest

import companion.planner.planner as planner_mod
from companion.harness.closed_loop import run
from companion.planner import Planner, PlannerParams, Route
from companion.planner.avoidance import min_distance, min_distance_to, min_distance_within
from companion.planner.decision import chord_steepness
from companion.sim.scenario import load_scenario
from companion.sim.world import World
from tests.test_memory import _random_change
from tests.test_planner import SENSORS

SCENARIO_DIR = Path(__file__).parent.parent / "config" / "scenarios"


@pytest.mark.slow
@pytest.mark.parametrize("name", ["wall", "pillars"])
def test_kept_clearances_are_those_measured_afresh(
    name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    checked: list[int] = []
    slice_look = planner_mod.Planner._look_ahead

    def checking_look_ahead(self: planner_mod.Planner) -> planner_mod._LookAhead:
        look = slice_look(self)
        if look.clearance is not None:
            memory = self._memory
            fresh = min_distance_within(
                look.points, memory.points_xy(), self._clearance_cutoff_m, memory.inflation_m()
            )
            cutoff = self._clearance_cutoff_m
            exact = (fresh < cutoff) | (look.clearance < cutoff)
            assert np.array_equal(look.clearance[exact], fresh[exact])
            trigger = self.params.d_min_m + 0.5 * self.params.clearance_margin_m
            assert look.conflict == bool((fresh < trigger).any())
            checked.append(len(look.s))
        return look

    monkeypatch.setattr(planner_mod.Planner, "_look_ahead", checking_look_ahead)
    path = SCENARIO_DIR / f"{name}.yaml"
    scenario = load_scenario(path)
    run(scenario, World.from_config(scenario.world, path.parent))
    assert len(checked) > 100, "the flight never had remembered points ahead"


def chord_steepness_reference(
    points: np.ndarray, min_separation_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The array form `chord_steepness` had before it indexed the chords flat (with its
    separation horizontal or vertical)."""
    n = len(points)
    if n < 2:
        return np.zeros(n), np.full(n, -1, dtype=np.intp)
    x, y, z = points.T
    dz = np.subtract.outer(z, z)
    dx = np.subtract.outer(x, x)
    dy = np.subtract.outer(y, y)
    h = np.sqrt(dx * dx + dy * dy)
    usable = (dz > 0.0) & ((h >= min_separation_m) | (dz >= min_separation_m))
    ratio = np.divide(dz, h, out=np.full((n, n), -1.0), where=usable & (h > 0.0))
    ratio[usable & (h == 0.0)] = np.inf  # straight above
    partner = ratio.argmax(axis=1)
    rows = np.arange(n)
    found = ratio[rows, partner] >= 0.0
    best = np.arctan2(dz[rows, partner], h[rows, partner])
    return np.where(found, best, 0.0), np.where(found, partner, -1).astype(np.intp)


def test_chord_steepness_is_its_array_form_bit_for_bit() -> None:
    rng = np.random.default_rng(11)
    for trial in range(300):
        n = int(rng.integers(0, 80))  # past the 64 rows kept for the flat index too
        pts = rng.normal(size=(n, 3)) * 3.0
        if trial % 3 == 0 and n:  # ties: equal heights, points straight above each other
            pts[:, 2] = np.round(pts[:, 2])
            pts[: n // 2, :2] = pts[0, :2]
        for sep in (0.5, 0.1):
            phi, partner = chord_steepness(pts, sep)
            ref_phi, ref_partner = chord_steepness_reference(pts, sep)
            assert np.array_equal(phi, ref_phi)
            assert np.array_equal(partner, ref_partner)
            assert partner.dtype == np.intp


def test_min_distance_to_is_min_distance_bit_for_bit() -> None:
    rng = np.random.default_rng(2)
    samples = rng.uniform(-20.0, 20.0, (57, 2))
    for k in (0, 1, 2, 3, 4, 9, 30):  # one at a time up to 3, then the array form
        pts = rng.uniform(-20.0, 20.0, (k, 2))
        infl = rng.choice([0.0, 0.25, 0.7], size=k)
        points = [(x, y, e) for (x, y), e in zip(pts.tolist(), infl.tolist(), strict=True)]
        assert np.array_equal(min_distance_to(samples, points), min_distance(samples, pts, infl))


def test_updated_clearances_are_those_measured_afresh_through_random_changes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Property: the memory goes through random adds, re-sees (moved or not, inflation up
    or down), forgets, carves and max_points drops; after each, the kept clearances (brought
    up to date, or measured afresh when the log is too short or the window moved) equal a
    full measure bit for bit below the cutoff, and the close samples are the same."""
    route = Route(np.array([[0.0, 0.0], [8.0, 3.0], [16.0, -2.0], [26.0, 1.0]]), 0.0)
    params = PlannerParams(lookahead_m=12.0)
    planner = Planner(params, SENSORS, route, np.array([0.0, 0.0, 2.0]))
    memory = planner._memory = planner_mod.ObstacleMemory(0.25, 14.0, 60)
    samples = planner_mod._PathSamples.of(route, params.lat_accel_max_mps2, params.v_d_mps)
    cutoff = planner._clearance_cutoff_m
    trigger = params.d_min_m + 0.5 * params.clearance_margin_m
    updates: list[int] = []
    real_update = planner_mod.min_distance_within_updated

    def counting_update(*args):  # type: ignore[no-untyped-def]
        values, stale = real_update(*args)
        updates.append(len(stale))
        return values, stale

    monkeypatch.setattr(planner_mod, "min_distance_within_updated", counting_update)
    rng = np.random.default_rng(8)
    below = 0
    for cycle in range(1, 600):
        _random_change(memory, rng, cycle)
        if len(memory) == 0:
            continue
        planner._s = min(cycle * 0.02, 10.0)  # the window moves on now and then
        ahead = samples.window(planner._s, params.lookahead_m)
        window, close = planner._clearance(samples, ahead)
        kept = planner._clearance_cache
        assert kept is not None
        reach = slice(kept.start, kept.stop)
        fresh = min_distance_within(
            samples.points[reach], memory.points_xy(), cutoff, memory.inflation_m()
        )
        exact = (fresh < cutoff) | (kept.values < cutoff)
        assert np.array_equal(kept.values[exact], fresh[exact])
        assert np.all(kept.values[~exact] >= cutoff)
        assert close == (np.flatnonzero(fresh < trigger) + kept.start).tolist()
        assert np.array_equal(
            window, kept.values[ahead.start - kept.start : ahead.stop - kept.start]
        )
        below += int(exact.sum())
    assert len(updates) > 200, "the clearances were rarely brought up to date"
    assert sum(1 for n in updates if n) > 10, "no nearest point was ever removed"
    assert below > 1000, "the path rarely came near the points"
