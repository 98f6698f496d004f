"""Core LDDMM (calibration by diffeomorphisms) checks: dynamics, gradients, energy, fitting."""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

from workcell._jax import jax, jnp
from workcell.estimation.lddmm import KernelParams, LddmmModel, State, fit_lddmm
from workcell.estimation.lddmm.shooting import (
    data_cost,
    hamiltonian,
    rhs_autodiff,
    rhs_explicit,
    shoot,
)


@functools.partial(jax.jit, static_argnums=3)
def _shoot_jit(s, x, kp, n_steps):
    return shoot(s, x, kp, n_steps, record=True)


def _random_state(N=12, n=3, m=2, seed=0, p_scale=0.1):
    k = jax.random.split(jax.random.PRNGKey(seed), 4)
    x = jax.random.normal(k[0], (N, n))
    q = jax.random.normal(k[1], (N, m))
    J = jax.random.normal(k[2], (N, m, n))
    P = p_scale * jax.random.normal(k[3], (N, m))
    return x, State(q, J, P)


def k0_toy(x):
    """A smooth toy nominal kinematics R^3 -> R^2 (arm-like, nonlinear)."""
    return jnp.array(
        [
            0.6 * jnp.cos(x[0]) + 0.3 * jnp.cos(x[0] + x[1]) + 0.1 * x[2],
            0.6 * jnp.sin(x[0]) + 0.3 * jnp.sin(x[0] + x[1]) - 0.05 * x[2] ** 2,
        ]
    )


def test_autodiff_dynamics_equal_explicit_28():
    x, s = _random_state()
    kp = KernelParams(0.9, 0.7, 1.0, 1.3)
    a = jax.jit(rhs_autodiff)(s, x, kp)
    b = jax.jit(rhs_explicit)(s, x, kp)
    for u, v in zip(a, b, strict=True):
        np.testing.assert_allclose(np.asarray(u), np.asarray(v), rtol=1e-10, atol=1e-12)
    # the optional div term really changes dP (so the comparison above is not vacuous)
    c = jax.jit(functools.partial(rhs_explicit, div_term=True))(s, x, kp)
    assert float(jnp.max(jnp.abs(c.P - b.P))) > 1e-6


def test_hamiltonian_conserved_psi_only_to_rk4_accuracy():
    x, s = _random_state(p_scale=0.3)
    kp = KernelParams(0.9, 0.7, 0.0, 1.0)  # psi only: an exact landmark Hamiltonian system
    drifts = []
    for n_steps in (4, 8, 16):
        _, _, traj = _shoot_jit(s, x, kp, n_steps)
        H = jax.vmap(lambda q, J, P: hamiltonian(State(q, J, P), x, kp))(*traj)
        drifts.append(float(jnp.max(jnp.abs(H - H[0]))) / float(H[0]))
    assert drifts[-1] < 1e-6, drifts
    # fourth order: halving the step divides the drift by ~16 (allow 8)
    assert drifts[0] / drifts[1] > 8 and drifts[1] / drifts[2] > 8, drifts


def test_hamiltonian_drift_with_phi_is_small_and_structural():
    # with phi, J is not canonical: H drifts, independent of the step (documented behaviour)
    x, s = _random_state(p_scale=0.05)
    kp = KernelParams(0.9, 0.7, 1.0, 1.0)
    rel = []
    for n_steps in (4, 16):
        _, _, traj = _shoot_jit(s, x, kp, n_steps)
        H = jax.vmap(lambda q, J, P: hamiltonian(State(q, J, P), x, kp))(*traj)
        rel.append(float(jnp.max(jnp.abs(H - H[0]))) / float(H[0]))
    assert rel[1] < 0.05
    assert abs(rel[0] - rel[1]) < 0.1 * rel[1]


def test_shooting_gradient_matches_finite_differences():
    x, s = _random_state()
    kp = KernelParams(0.9, 0.7, 1.0, 1.0)
    y = s.q + 0.05 * jax.random.normal(jax.random.PRNGKey(5), s.q.shape)
    vg = jax.jit(jax.value_and_grad(lambda P: data_cost(P, s.q, s.J, x, y, kp, 0.1, 6)))

    def f(P):
        return vg(P)[0]

    g = np.asarray(vg(s.P)[1])
    rng = np.random.default_rng(0)
    for _ in range(4):
        d = rng.normal(size=s.P.shape)
        eps = 1e-6
        fd = (float(f(s.P + eps * d)) - float(f(s.P - eps * d))) / (2 * eps)
        assert fd == pytest.approx(float(np.sum(g * d)), rel=1e-6, abs=1e-9)


def _toy_data(n_train=80, n_test=120, seed=0):
    rng = np.random.default_rng(seed)
    Xtr = rng.uniform(-1.0, 1.0, size=(n_train, 3))
    Xte = rng.uniform(-0.9, 0.9, size=(n_test, 3))
    A = np.array([[1.0 + 0.015, 0.01], [-0.012, 1.0 - 0.01]])
    t = np.array([0.004, -0.003])

    def truth(X):
        Y0 = np.asarray(jax.vmap(k0_toy)(jnp.asarray(X)))
        return Y0 @ A.T + t

    return Xtr, truth(Xtr), Xte, truth(Xte)


@pytest.fixture(scope="module")
def toy_fit():
    Xtr, Ytr, Xte, Yte = _toy_data()
    model = fit_lddmm(
        k0_toy, Xtr, Ytr, sigma_v=1.0, sigma_w=0.5, sigma=0.02, n_steps=6, max_iter=60
    )
    return model, Xtr, Ytr, Xte, Yte


def test_affine_deformation_recovered_on_held_out_points(toy_fit):
    model, _, _, Xte, Yte = toy_fit
    before = np.linalg.norm(np.asarray(jax.vmap(k0_toy)(jnp.asarray(Xte))) - Yte, axis=1)
    after = np.linalg.norm(model.predict(Xte) - Yte, axis=1)
    assert np.median(after) < 0.1 * np.median(before)
    assert np.max(after) < 0.3 * np.max(before)


def test_min_jacobian_det_positive(toy_fit):
    model, _, _, Xte, _ = toy_fit
    dphi, dpsi = model.min_jacobian_det(Xte)
    assert 0.0 < dphi and 0.0 < dpsi
    # a small deformation: both flows stay close to the identity
    assert abs(dphi - 1) < 0.5 and abs(dpsi - 1) < 0.5


def test_predict_reproduces_fitted_landmarks(toy_fit):
    model, Xtr, _, _, _ = toy_fit
    np.testing.assert_allclose(model.predict(Xtr), model.fitted_landmarks, atol=1e-12)


def test_to_dict_from_dict_round_trip(toy_fit):
    model, _, _, Xte, _ = toy_fit
    d = json.loads(json.dumps(model.to_dict()))
    m2 = LddmmModel.from_dict(d, k0_toy)
    np.testing.assert_array_equal(m2.predict(Xte), model.predict(Xte))


def test_cv_width_selection_and_validation():
    Xtr, Ytr, Xte, Yte = _toy_data()  # same shapes as the fixture: reuses the compilations
    m = fit_lddmm(k0_toy, Xtr, Ytr, sigma=0.02, n_steps=6, max_iter=20)
    assert m.info is not None and len(m.info.cv_scores) == 16
    assert min(m.info.cv_scores.values()) == pytest.approx(
        m.info.cv_scores[f"{m.kp.sigma_v:.6g},{m.kp.sigma_w:.6g},{m.sigma:.6g}"]
    )
    assert np.median(np.linalg.norm(m.predict(Xte) - Yte, axis=1)) < 0.5 * np.median(
        np.linalg.norm(np.asarray(jax.vmap(k0_toy)(jnp.asarray(Xte))) - Yte, axis=1)
    )
    with pytest.raises(ValueError, match="Y must have shape"):
        fit_lddmm(k0_toy, Xtr, Ytr[:5], sigma_v=1.0, sigma_w=1.0)
    with pytest.raises(ValueError, match="columns"):
        m.predict(np.zeros((3, 2)))
