"""The JAX EKF steps against filterpy's ExtendedKalmanFilter (the reference oracle)."""

from __future__ import annotations

from functools import partial

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


@pytest.mark.parametrize("block", [1, 4, 7])
def test_blocked_scan_equals_filterpy(block):
    """The delayed-update filter (covariance written once per block) against filterpy's dense
    EKF run sample by sample: random-walk prediction P <- P + Q (a diagonal part and a 2x2 block,
    as the EKF-ANN uses) and a nonlinear 3-D observation."""
    from workcell.estimation.ekf_ann.core import Step, blocked_scan

    rng = np.random.default_rng(3)
    n, m, N = 6, 3, 28
    qd = np.linspace(1e-4, 6e-4, n)
    qb = np.array([[2e-3, 5e-4], [5e-4, 1e-3]])
    off = 3

    def h(x, u):
        return jnp.stack(
            [jnp.sin(x[0] * u[0]) + x[1] * x[2], x[3] ** 2 + u[1] * x[4], x[0] * x[5] + u[2]]
        )

    def model(x, inp, ctx):
        u, r = inp
        return Step(
            x, jnp.asarray(qd), jnp.asarray(qb), h(x, u), jax.jacfwd(h)(x, u), jnp.diag(r), 0
        )

    U = rng.normal(size=(N, 3))
    Rd = rng.uniform(0.01, 0.05, size=(N, m))
    xt = rng.normal(size=n)
    Z = np.array([np.asarray(h(xt, u)) for u in U]) + rng.normal(0, 0.1, (N, m))
    x0 = xt + rng.normal(0, 0.3, n)
    P0 = np.diag(rng.uniform(0.05, 0.2, n))

    run = jax.jit(partial(blocked_scan, model, block=block, blk_off=off, blk_dim=2))
    x, P, (e, S, nis, _) = run(jnp.asarray(x0), jnp.asarray(P0), jnp.asarray(Z), (U, Rd))

    ekf = filterpy.ExtendedKalmanFilter(dim_x=n, dim_z=m)
    ekf.x, ekf.P = x0.copy(), P0.copy()
    Q = np.diag(qd)
    Q[off : off + 2, off : off + 2] += qb
    nis_ref = []
    for z, u, r in zip(Z, U, Rd, strict=True):
        ekf.P = ekf.P + Q
        ekf.update(
            z,
            HJacobian=lambda x, u=u: np.asarray(jax.jacfwd(h)(jnp.asarray(x), u)),
            Hx=lambda x, u=u: np.asarray(h(jnp.asarray(x), u)),
            R=np.diag(r),
        )
        nis_ref.append(float(ekf.y @ ekf.SI @ ekf.y))
    np.testing.assert_allclose(np.asarray(x), ekf.x, rtol=0, atol=1e-9 * (1 + np.abs(ekf.x).max()))
    np.testing.assert_allclose(np.asarray(P), ekf.P, rtol=0, atol=1e-9 * np.abs(ekf.P).max())
    np.testing.assert_allclose(np.asarray(nis), nis_ref, rtol=1e-7)
    assert np.array_equal(np.asarray(P), np.asarray(P).T)


def test_blocked_scan_refuses_a_partial_block():
    from workcell.estimation.ekf_ann.core import Step, blocked_scan

    def model(x, inp, ctx):
        return Step(x, None, None, x[:1], jnp.eye(1, 2), jnp.eye(1), 0)

    with pytest.raises(ValueError, match="multiple of the block"):
        blocked_scan(model, jnp.zeros(2), jnp.eye(2), jnp.zeros((5, 1)), jnp.zeros(5), block=2)


def test_hand_written_ann_jacobian_equals_autodiff():
    from workcell.estimation.ekf_ann import ann as A

    for hidden, seed in ((1, 0), (5, 1), (29, 2)):
        w = jnp.asarray(A.random_weights(hidden, seed) * 2)
        u = jnp.asarray(np.random.default_rng(seed).normal(size=6))
        o, J = A.apply_raw_and_jac(w, u, hidden)
        np.testing.assert_allclose(o, A.apply_raw(w, u, hidden), rtol=1e-14, atol=1e-14)
        J_ad = jax.jacrev(A.apply_raw)(w, u, hidden)
        assert J.shape == (3, A.n_weights(hidden))
        np.testing.assert_allclose(J, J_ad, rtol=1e-13, atol=1e-14)


def test_structured_jacobian_products_equal_dense():
    """J @ M through the block context (what the filter uses for H P_0) equals the dense product."""
    from workcell.estimation.ekf_ann import ann as A

    rng = np.random.default_rng(4)
    for hidden in (1, 4, 29):
        K = A.n_weights(hidden)
        w = jnp.asarray(A.random_weights(hidden, hidden) * 2)
        M = jnp.asarray(rng.normal(size=(K, K + 5)))
        U = jnp.asarray(rng.normal(size=(7, 6)))
        V, shared = A.jac_context(M, U, hidden)
        for i in range(len(U)):
            _, J = A.apply_raw_and_jac(w, U[i], hidden)
            got = A.jac_times(w, U[i], hidden, V[i], shared)
            np.testing.assert_allclose(
                got, J @ M, rtol=1e-12, atol=1e-12 * float(jnp.abs(J @ M).max())
            )


def test_saved_network_of_another_layout_is_refused():
    from workcell.estimation.ekf_ann import ann as A

    d = A.AnnSpec(hidden=3).to_dict()
    assert A.AnnSpec.from_dict(d) == A.AnnSpec(hidden=3)
    del d["layout"]  # what networks saved before the input-major layout look like
    with pytest.raises(ValueError, match="refit the ekf-ann model"):
        A.AnnSpec.from_dict(d)
