"""The JAX EKF steps against filterpy's ExtendedKalmanFilter (the reference oracle)."""

from __future__ import annotations

import numpy as np
import pytest

from workcell._jax import jax, jnp
from workcell.estimation.ekf_ann.core import predict, update

filterpy = pytest.importorskip("filterpy.kalman")


def _run_both(n, m, fx, Fj, hx, Hj, Q, R, x0, P0, zs, joseph):
    ekf = filterpy.ExtendedKalmanFilter(dim_x=n, dim_z=m)
    ekf.x = x0.copy()
    ekf.P = P0.copy()
    ekf.Q = Q
    ekf.R = R
    x, P = jnp.asarray(x0), jnp.asarray(P0)
    upd = jax.jit(update, static_argnames="joseph")
    for z in zs:
        # filterpy: nonlinear prediction done by hand (its predict() is linear), as documented
        F = Fj(ekf.x)
        ekf.x = fx(ekf.x)
        ekf.P = F @ ekf.P @ F.T + ekf.Q
        ekf.update(z, HJacobian=Hj, Hx=hx)
        x, P = predict(jnp.asarray(fx(np.asarray(x))), P, jnp.asarray(Fj(np.asarray(x))), Q)
        r = upd(
            x,
            P,
            jnp.asarray(z),
            jnp.asarray(hx(np.asarray(x))),
            jnp.asarray(Hj(np.asarray(x))),
            jnp.asarray(R),
            joseph=joseph,
        )
        x, P = r.x, r.P
        np.testing.assert_allclose(
            np.asarray(x), ekf.x, rtol=0, atol=1e-9 * (1 + np.abs(ekf.x).max())
        )
        np.testing.assert_allclose(np.asarray(P), ekf.P, rtol=0, atol=1e-9 * np.abs(ekf.P).max())
        assert np.array_equal(np.asarray(P), np.asarray(P).T) or joseph
    return np.asarray(x), ekf.x


@pytest.mark.parametrize("joseph", [False, True])
def test_linear_gaussian_equals_filterpy(joseph):
    rng = np.random.default_rng(1)
    n, m, dt = 4, 2, 0.1
    F = np.eye(n)
    F[0, 2] = F[1, 3] = dt  # constant-velocity model in 2-D
    Hm = np.zeros((m, n))
    Hm[0, 0] = Hm[1, 1] = 1.0
    Q = 1e-3 * np.eye(n) + 1e-4
    R = np.array([[0.05, 0.01], [0.01, 0.08]])
    x_true = np.array([0.0, 0.0, 1.0, -0.5])
    zs = []
    for _ in range(60):
        x_true = F @ x_true + rng.multivariate_normal(np.zeros(n), Q)
        zs.append(Hm @ x_true + rng.multivariate_normal(np.zeros(m), R))
    x, xr = _run_both(
        n,
        m,
        lambda x: F @ x,
        lambda x: F,
        lambda x: Hm @ x,
        lambda x: Hm,
        Q,
        R,
        np.zeros(n),
        np.eye(n),
        zs,
        joseph,
    )
    assert np.linalg.norm(x - x_true) < 1.0  # and it tracks the truth


@pytest.mark.parametrize("joseph", [False, True])
def test_nonlinear_range_bearing_equals_filterpy(joseph):
    rng = np.random.default_rng(2)
    n, m = 3, 2
    omega = 0.3

    def fx(x):  # rotation of a point about the origin, slowly growing radius x[2]
        c, s = np.cos(omega), np.sin(omega)
        return np.array(
            [(c * x[0] - s * x[1]) * (1 + x[2]), (s * x[0] + c * x[1]) * (1 + x[2]), 0.9 * x[2]]
        )

    def Fj(x):
        c, s = np.cos(omega), np.sin(omega)
        g = 1 + x[2]
        return np.array(
            [
                [c * g, -s * g, c * x[0] - s * x[1]],
                [s * g, c * g, s * x[0] + c * x[1]],
                [0.0, 0.0, 0.9],
            ]
        )

    def hx(x):
        return np.array([np.hypot(x[0], x[1]), np.arctan2(x[1], x[0])])

    def Hj(x):
        r2 = x[0] ** 2 + x[1] ** 2
        r = np.sqrt(r2)
        return np.array([[x[0] / r, x[1] / r, 0.0], [-x[1] / r2, x[0] / r2, 0.0]])

    Q = np.diag([1e-3, 1e-3, 1e-5])
    R = np.diag([0.02**2, 0.01**2])
    xt = np.array([2.0, 0.5, 0.02])
    zs = []
    for _ in range(40):
        xt = fx(xt) + rng.multivariate_normal(np.zeros(n), Q)
        zs.append(hx(xt) + rng.multivariate_normal(np.zeros(m), R))
    _run_both(
        n, m, fx, Fj, hx, Hj, Q, R, np.array([1.8, 0.7, 0.0]), np.diag([0.1, 0.1, 1e-3]), zs, joseph
    )


def test_nis_and_symmetry_and_validation_of_shapes():
    P = jnp.eye(5) * 2.0
    H = jnp.zeros((3, 5)).at[0, 0].set(1.0).at[1, 1].set(1.0).at[2, 2].set(1.0)
    r = update(jnp.zeros(5), P, jnp.array([1.0, 2.0, 2.0]), jnp.zeros(3), H, jnp.eye(3))
    assert float(r.nis) == pytest.approx((1 + 4 + 4) / 3.0)
    np.testing.assert_allclose(np.diag(np.asarray(r.P))[:3], 2.0 / 3.0)
