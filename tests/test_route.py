"""Route through base points: C1 joins, headings, arc-length addressing."""

import math

import numpy as np
import pytest

from companion.planner.path import project
from companion.planner.route import Route


def test_single_segment_headings_and_ends() -> None:
    r = Route(np.array([[24.0, 24.0], [-60.0, 30.0]]), math.pi, math.pi)
    np.testing.assert_allclose(r.point(0.0), [24, 24])
    np.testing.assert_allclose(r.point(r.length), [-60, 30])
    assert abs(abs(r.heading(0.0)) - math.pi) < 1e-12
    assert abs(abs(r.heading(r.length)) - math.pi) < 1e-12


def test_joins_are_parametric_c1_and_pass_base_points() -> None:
    w = np.array([[0.0, 0.0], [10.0, 0.0], [12.0, 8.0], [30.0, 10.0]])
    r = Route(w, 0.0, 0.5)
    for i in range(len(r.segments) - 1):
        a, b = r.segments[i], r.segments[i + 1]
        np.testing.assert_allclose(a.evaluate(1.0), b.evaluate(0.0), atol=1e-12)
        np.testing.assert_allclose(a.derivative(1.0), b.derivative(0.0), atol=1e-9)
    for i, s in enumerate(r.base_s):
        np.testing.assert_allclose(r.point(float(s)), w[i], atol=1e-9)


def test_locate_round_trips_arc_length() -> None:
    r = Route(np.array([[0.0, 0.0], [10.0, 0.0], [12.0, 8.0]]))
    for s in np.linspace(0, r.length, 17):
        k, t = r.locate(float(s))
        assert r.arc_length_at(k, t) == pytest.approx(float(s), abs=1e-9)


def test_projection_gives_frenet_coordinates() -> None:
    r = Route(np.array([[0.0, 0.0], [50.0, 0.0]]))
    s, lat = project(r.polyline(), np.array([[10.0, 3.0], [20.0, -2.0]]))
    np.testing.assert_allclose(s, [10, 20], atol=1e-9)
    np.testing.assert_allclose(lat, [3, -2], atol=1e-9)


def test_split_at_keeps_the_curve() -> None:
    r = Route(np.array([[0.0, 0.0], [10.0, 0.0], [12.0, 8.0]]))
    before, after = r.split_at(7.3)
    np.testing.assert_allclose(before[-1].evaluate(1.0), r.point(7.3), atol=1e-9)
    np.testing.assert_allclose(after[0].evaluate(0.0), r.point(7.3), atol=1e-9)
    total = sum(s.length for s in before) + sum(s.length for s in after)
    assert total == pytest.approx(r.length, abs=1e-9)


@pytest.mark.parametrize(
    "points",
    [np.zeros((1, 2)), np.array([[0.0, 0.0], [0.0, 0.0]]), np.array([[0.0, 0.0], [np.inf, 1.0]])],
)
def test_rejects_bad_base_points(points: np.ndarray) -> None:
    with pytest.raises(ValueError, match="base points"):
        Route(points)
