"""Eqs (6)-(7): how steep is what the obstacle sensors see, and which way to avoid it."""

from __future__ import annotations

import numpy as np

from companion.planner.params import PlannerParams
from companion.planner.sensors import Group
from companion.planner.types import BoolArray, Decision, FloatArray


def steepness(
    obstacle_points: FloatArray, ground_points: FloatArray, detected: BoolArray
) -> FloatArray:
    """Eq. (6): phi_i* = arctan((z_di - z_hj) / |[x_di, y_di] - [x_hj, y_hj]|), radians.

    obstacle_points: X_di, (m, 3) world ENU. ground_points: the paired surface point X_hj of
    each sensor's group, (m, 3) (left group with the left point, forward with forward, right
    with right; PAPER_NOTES). detected: (m,) bool; phi_i* = 0 where d_i = 0 (nothing seen).
    """
    rel = obstacle_points - ground_points
    horizontal = np.hypot(rel[:, 0], rel[:, 1])
    phi = np.arctan2(rel[:, 2], horizontal)
    return np.where(detected, phi, 0.0)


def thresholds(groups: tuple[Group, ...], params: PlannerParams) -> FloatArray:
    """Eq. (7): phi*_max per obstacle sensor: phi_max for the forward group and
    min(arctan(H_d / D_min), phi_max) for the left and right groups. Radians."""
    side = params.side_threshold_rad
    return np.array([params.phi_max_rad if g is Group.FORWARD else side for g in groups])


def decide(phi_star: FloatArray, threshold: FloatArray) -> Decision:
    """Eq. (7) decision: horizontal if any phi_i* exceeds its threshold, else vertical."""
    return Decision.HORIZONTAL if (phi_star > threshold).any() else Decision.VERTICAL
