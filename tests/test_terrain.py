"""Eqs (3)-(5): aim point, desired pitch, stepping X_d along the path."""

import math

import numpy as np
import pytest

from companion.planner.route import Route
from companion.planner.terrain import advance_exact, advance_paper, aim_point, desired_pitch


def ground_points(alpha: float, yaw: float, height: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Fore/aft ground points of 45-degree sensors over a plane rising at alpha along yaw."""
    d = np.array([math.cos(yaw), math.sin(yaw)])

    def hit(sign: float) -> np.ndarray:
        # Ray from (0, 0, height) along sign*d horizontally and down at 45 deg; ground z = tan(a) x.
        t = height / (1.0 + sign * math.tan(alpha))
        return np.array([sign * t * d[0], sign * t * d[1], height - t])

    return hit(1.0), hit(-1.0)


def test_flat_ground_gives_zero_pitch() -> None:
    h1, h2 = ground_points(0.0, 0.7)
    x_z = aim_point(h1, h2, 0.7, 2.0)
    assert x_z[2] == pytest.approx(2.0)
    assert desired_pitch(x_z, np.array([0.0, 0.0, 2.0]), 0.6) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("alpha", [0.1, 0.3, -0.2])
def test_constant_slope_gives_its_angle(alpha: float) -> None:
    """On a plane of slope alpha, with X_d already H_d above it, phi_d = alpha."""
    yaw = -1.2
    h1, h2 = ground_points(alpha, yaw)
    x_z = aim_point(h1, h2, yaw, 2.0)
    # X_z is H_d from the forward ground point along the plane's normal.
    assert float(np.linalg.norm(x_z - h1)) == pytest.approx(2.0)
    x_d = np.array([0.0, 0.0, 2.0 / math.cos(alpha)])  # H_d above the plane, perpendicular
    assert desired_pitch(x_z, x_d, 0.6) == pytest.approx(alpha, abs=1e-9)


def test_pitch_is_clamped_to_phi_max() -> None:
    x_z = np.array([1.0, 0.0, 10.0])
    assert desired_pitch(x_z, np.zeros(3), 0.6) == 0.6
    assert desired_pitch(-x_z, np.zeros(3), 0.6) == -0.6


def test_exact_step_moves_xd_at_the_3d_speed() -> None:
    route = Route(np.array([[0.0, 0.0], [30.0, 10.0], [50.0, 0.0]]))
    s, z = 3.0, 1.0
    p0 = np.array([*route.point(s), z])
    s1, z1 = advance_exact(route, s, z, 0.05, 0.4)
    p1 = np.array([*route.point(s1), z1])
    assert s1 - s == pytest.approx(0.05 * math.cos(0.4))
    assert float(np.linalg.norm(p1 - p0)) == pytest.approx(0.05, rel=1e-5)  # chord vs arc


def test_paper_search_overshoots_by_at_most_one_increment() -> None:
    route = Route(np.array([[0.0, 0.0], [30.0, 10.0]]))
    delta = 1e-3
    seg, t, z, iters = advance_paper(route, 0, 0.2, 0.0, 0.05, 0.3, delta)
    assert seg == 0 and iters >= 1
    p0 = route.segments[0].evaluate(0.2)
    p1 = route.segments[0].evaluate(t)
    travelled = float(np.hypot(*(p1 - p0))) / math.cos(0.3)
    assert 0.05 <= travelled <= 0.05 + route.segments[0].speed(t) * delta / math.cos(0.3) + 1e-9
    assert z == pytest.approx(math.tan(0.3) * float(np.hypot(*(p1 - p0))))


def test_aim_point_in_floats_is_eq3_with_r_psi() -> None:
    """`aim_point_xyz` (the planner's per-cycle form) against eq. (3) written with the
    matrix R_psi; both raise on coincident ground points."""
    from companion.planner.rotations import r_psi
    from companion.planner.terrain import aim_point_xyz, desired_pitch_xyz

    rng = np.random.default_rng(3)
    for _ in range(200):
        h1, h2 = rng.normal(size=3) * 5.0, rng.normal(size=3) * 5.0
        yaw = float(rng.uniform(-math.pi, math.pi))
        g = (h1 - h2) / np.linalg.norm(h1 - h2)
        up = r_psi(yaw) @ g
        expected = h1 + 2.0 * up / np.linalg.norm(up)
        got = aim_point_xyz(*h1.tolist(), *h2.tolist(), yaw, 2.0)
        np.testing.assert_allclose(got, expected, atol=1e-9)
        assert aim_point(h1, h2, yaw, 2.0).tolist() == list(got)
        x_d = rng.normal(size=3)
        assert desired_pitch(np.array(got), x_d, 0.6) == desired_pitch_xyz(*got, *x_d.tolist(), 0.6)
    with pytest.raises(ValueError, match="coincide"):
        aim_point_xyz(1.0, 2.0, 3.0, 1.0, 2.0, 3.0, 0.0, 2.0)
