"""Cubic Bezier: evaluation, derivatives, curvature, split, arc length and its inverse."""

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from companion.planner.bezier import CubicBezier, segment_through

coord = st.floats(-50, 50, allow_nan=False)
controls = st.lists(st.tuples(coord, coord), min_size=4, max_size=4).map(np.array)
unit = st.floats(0.0, 1.0)


def nondegenerate(c: np.ndarray) -> bool:
    return float(np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1))) > 1.0


@given(controls)
def test_end_points_and_tangents(c: np.ndarray) -> None:
    b = CubicBezier(c)
    np.testing.assert_allclose(b.evaluate(0.0), c[0], atol=1e-12)
    np.testing.assert_allclose(b.evaluate(1.0), c[3], atol=1e-12)
    np.testing.assert_allclose(b.derivative(0.0), 3 * (c[1] - c[0]), atol=1e-9)
    np.testing.assert_allclose(b.derivative(1.0), 3 * (c[3] - c[2]), atol=1e-9)


@given(controls, unit)
def test_derivatives_match_finite_differences(c: np.ndarray, t: float) -> None:
    b = CubicBezier(c)
    h = 1e-6
    t = min(max(t, 2 * h), 1 - 2 * h)
    fd1 = (b.evaluate(t + h) - b.evaluate(t - h)) / (2 * h)
    np.testing.assert_allclose(b.derivative(t), fd1, atol=1e-5 * (1 + np.abs(c).max()))
    fd2 = (b.derivative(t + h) - b.derivative(t - h)) / (2 * h)
    np.testing.assert_allclose(b.derivative(t, 2), fd2, atol=1e-4 * (1 + np.abs(c).max()))
    assert math.isclose(
        b.speed(t), float(np.linalg.norm(b.derivative(t))), rel_tol=1e-9, abs_tol=1e-9
    )


@given(controls, st.floats(0.01, 0.99))
def test_split_then_join_equals_original(c: np.ndarray, at: float) -> None:
    b = CubicBezier(c)
    left, right = b.split(at)
    for u in np.linspace(0, 1, 7):
        np.testing.assert_allclose(left.evaluate(u), b.evaluate(at * u), atol=1e-9)
        np.testing.assert_allclose(right.evaluate(u), b.evaluate(at + (1 - at) * u), atol=1e-9)


@settings(max_examples=60, deadline=None)  # 200 001 points a case: slow on a loaded machine
@given(controls)
# A straight curve that doubles back (B' = 0 inside): once integrated across the kink of |B'|.
@example(np.array([(0.0, 0.0), (41.0, 0.0), (38.0, 0.0), (3.1875, 0.0)]))
def test_arc_length_against_dense_polyline(c: np.ndarray) -> None:
    b = CubicBezier(c)
    pts = b.evaluate(np.linspace(0, 1, 200_001))
    poly = float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))
    assert b.length == pytest.approx(poly, rel=1e-6, abs=1e-6)


@settings(max_examples=200)
@given(controls.filter(nondegenerate), unit)
def test_inverse_arc_length_round_trips(c: np.ndarray, frac: float) -> None:
    b = CubicBezier(c)
    s = frac * b.length
    t = b.parameter_at(s)
    assert abs(b.arc_length(t) - s) <= 1e-9


def test_curvature_of_a_parabola() -> None:
    # The quadratic (-1, 1), (0, -1), (1, 1) degree-elevated: exactly y = x^2, x = 2t - 1.
    q = np.array([[-1.0, 1.0], [0.0, -1.0], [1.0, 1.0]])
    b = CubicBezier(np.array([q[0], q[0] / 3 + 2 * q[1] / 3, 2 * q[1] / 3 + q[2] / 3, q[2]]))
    t = np.linspace(0, 1, 11)
    x = 2 * t - 1
    np.testing.assert_allclose(b.evaluate(t)[:, 1], x**2, atol=1e-12)
    np.testing.assert_allclose(b.curvature(t), 2.0 / (1 + 4 * x**2) ** 1.5, rtol=1e-9)
    # Turning right gives negative curvature.
    mirrored = CubicBezier(b.control * np.array([1.0, -1.0]))
    assert float(mirrored.curvature(0.5)) == pytest.approx(-2.0)


def test_rejects_bad_control_points() -> None:
    with pytest.raises(ValueError, match="control points"):
        CubicBezier(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="control points"):
        CubicBezier(np.array([[0, 0], [1, np.nan], [2, 0], [3, 0]]))
    with pytest.raises(ValueError, match="split"):
        CubicBezier(np.array([[0, 0], [1, 0], [2, 0], [3, 0.0]])).split(1.5)


def test_segment_through_leaves_and_arrives_along_directions() -> None:
    seg = segment_through(np.zeros(2), np.array([1.0, 0]), np.array([10.0, 5]), np.array([0, 1.0]))
    assert seg.heading(0.0) == pytest.approx(0.0)
    assert seg.heading(1.0) == pytest.approx(math.pi / 2)
