"""The SMR registration's exact Jacobian (the margin watch and the registration fit use it in
place of finite differences) against central differences of its residual, at small, moderate
and large base rotations, and the fit's answer unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from workcell.kinematics.frames import matrix_from_rotvec, right_jacobian
from workcell.kinematics.registration import smr_registration_problem


def _problem(seed: int):
    rng = np.random.default_rng(seed)
    n = 12
    R = np.stack([matrix_from_rotvec(rng.normal(0, 1.0, 3)) for _ in range(n)])
    t = rng.uniform(-0.8, 0.8, (n, 3))
    P = rng.uniform(-2, 2, (n, 3))
    return smr_registration_problem(R, t, P, np.array([0.0, 0.0, 0.1]), 0.1), n


@pytest.mark.parametrize("rot", [1e-9, 1e-4, 0.7, 3.0])
def test_the_jacobian_is_the_residuals_derivative(rot):
    (residual, jac, x0), n = _problem(1)
    rng = np.random.default_rng(2)
    x = np.concatenate([rng.normal(size=3), rng.normal(size=6) * 0.1])
    x[:3] *= rot / np.linalg.norm(x[:3])
    rows = np.array([0, 3, 4, 7, 11])
    J = jac(x, rows)
    h = 1e-6
    fd = np.stack(
        [(residual(x + h * e, rows) - residual(x - h * e, rows)) / (2 * h) for e in np.eye(9)],
        axis=1,
    )
    assert J.shape == (3 * len(rows) + 3, 9)
    np.testing.assert_allclose(J, fd, atol=1e-6)


def test_the_right_jacobian_near_zero_joins_its_closed_form():
    """Below 1e-6 rad the series I - K/2 + K^2/6 stands in for the closed form, which loses its
    digits there: its first-order term (J - I) / theta must be -[r/theta]x / 2 (a wrong sign or
    a plain identity fails), and at 1e-3 rad, where the closed form is still exact to ~1e-10,
    the series agrees with it to third order."""
    from workcell.kinematics.frames import skew

    u = np.array([0.6, -0.48, 0.64])  # unit axis
    th = 1e-7
    first = (right_jacobian(u * th) - np.eye(3)) / th
    np.testing.assert_allclose(first, -0.5 * skew(u), atol=1e-6)
    r = u * 1e-3
    K = skew(r)
    series = np.eye(3) - 0.5 * K + K @ K / 6.0
    np.testing.assert_allclose(right_jacobian(r), series, atol=1e-10)
