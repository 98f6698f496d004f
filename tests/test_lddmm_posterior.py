"""The lddmm model's 1-sigma: the deformation's linearised posterior (the kernel ridge regression
the cross-validation scores, read as a Gaussian process) plus its base's covariance.

Here, fast: the posterior covariance against Monte Carlo draws of the Gaussian process it assumes
(an independent path: the joint Gram of landmarks and query points, sampled), the scale's
maximum-likelihood formula, and the model file (kept, older files without it, bad values). The
1-sigma against held-out errors of a simulated UR5e is in tests/test_lddmm_6dof.py (slow)."""

from __future__ import annotations

import numpy as np
import pytest

from workcell._jax import jax, jnp
from workcell.estimation.lddmm import KernelParams, LddmmModel
from workcell.estimation.lddmm.model import _gram


def k0_toy(x):
    """A smooth toy kinematics R^3 -> R^2 (arm-like, nonlinear)."""
    return jnp.array(
        [
            0.6 * jnp.cos(x[0]) + 0.3 * jnp.cos(x[0] + x[1]) + 0.1 * x[2],
            0.6 * jnp.sin(x[0]) + 0.3 * jnp.sin(x[0] + x[1]) - 0.05 * x[2] ** 2,
        ]
    )


KP = KernelParams(0.8, 0.4, 1.0, 1.0)
SIGMA = 0.1


def _model(x: np.ndarray) -> LddmmModel:
    return LddmmModel(k0_toy, x, np.zeros((len(x), 2)), KP, SIGMA, n_steps=4)


def _k0j(X):
    f = jax.vmap(k0_toy)
    J = jax.vmap(jax.jacfwd(k0_toy))
    X = jnp.asarray(X)
    return np.asarray(f(X)), np.asarray(J(X))


def test_the_posterior_covariance_is_the_gaussian_process_one():
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (25, 3))
    xs = np.concatenate([x[:2] + 0.01, rng.uniform(-1.5, 1.5, (3, 3))])  # near and far
    m = _model(x)
    tau2 = 3e-6
    C = m.linear_posterior_cov(xs, tau2)
    # the assumed model, sampled: f over landmarks and query points ~ N(0, tau^2 G_all);
    # observations r = f(x) + N(0, tau^2 sigma^2); the posterior mean is the kernel ridge fit
    allx = np.concatenate([x, xs])
    q_all, J_all = _k0j(allx)
    G_all = _gram(allx, q_all, J_all, KP)
    n = 2 * len(x)
    L = np.linalg.cholesky(tau2 * G_all + 1e-18 * np.eye(len(G_all)))
    draws = 4000
    f = L @ rng.standard_normal((len(G_all), draws))
    r = f[:n] + np.sqrt(tau2) * SIGMA * rng.standard_normal((n, draws))
    A = G_all[:n, :n] + SIGMA**2 * np.eye(n)
    mean = G_all[n:, :n] @ np.linalg.solve(A, r)
    err = (f[n:] - mean).reshape(len(xs), 2, draws)
    emp = np.einsum("iad,ibd->iab", err, err) / draws
    for i in range(len(xs)):
        np.testing.assert_allclose(C[i], emp[i], rtol=0.12, atol=0.12 * np.abs(C[i]).max())
    # small at the landmarks, the prior's far from them
    sd = np.sqrt(np.trace(C, axis1=1, axis2=2))
    assert sd[:2].max() < 0.5 * sd[2:].min()


def test_the_scale_is_the_maximum_likelihood_one():
    """tau^2 = r^T (G + sigma^2 I)^-1 r / n maximises N(r; 0, tau^2 (G + sigma^2 I)); here
    r drawn from that model with tau^2 = 4e-6 comes back within its sampling error."""
    rng = np.random.default_rng(1)
    x = rng.uniform(-1, 1, (150, 3))
    m = _model(x)
    q0, J0 = _k0j(x)
    G = _gram(x, q0, J0, KP) + SIGMA**2 * np.eye(2 * len(x))
    r = np.linalg.cholesky(4e-6 * G) @ rng.standard_normal(len(G))
    tau2 = m.posterior_scale(q0 + r.reshape(-1, 2))
    assert tau2 == pytest.approx(4e-6, rel=3 * np.sqrt(2 / len(G)))


def _calibration(tau2):
    from workcell.estimation.dh import DHModel
    from workcell.estimation.lddmm_fit import LddmmCalibration, _k0
    from workcell.kinematics.chain import pack
    from workcell.kinematics.robots import UR5E

    th = pack(UR5E.dh, tool=(0.0, 0.0, 0.06))
    base_ref = np.eye(4)
    base_ref[:3, 3] = (2.0, -0.5, -0.3)
    A = np.random.default_rng(2).normal(size=(39, 39)) * 1e-5
    base = DHModel(
        robot_model="ur5e",
        nominal_dh=UR5E.dh,
        theta=th,
        base_ref=base_ref,
        cov=A @ A.T,
        free=np.ones(39, bool),
        info={"nominal_tool_m": [0, 0, 0.06]},
    )
    x = np.random.default_rng(3).uniform(-2, 2, (20, 6))
    lm = LddmmModel(_k0(th, base_ref), x, np.zeros((20, 3)), KernelParams(1.0, 0.5, 1, 1), 0.1, 4)
    return LddmmCalibration(base=base, lddmm=lm, on="dh", posterior_scale_m2=tau2)


def test_the_model_file_keeps_the_scale_and_older_files_give_no_1_sigma(tmp_path):
    from workcell.errors import UserError
    from workcell.estimation.models import load_model, model_from_dict, save_model

    m = _calibration(2.5e-9)
    q = np.random.default_rng(4).uniform(-2, 2, (5, 6))
    C = m.prediction_cov(q)
    # the base's covariance plus the deformation's posterior
    np.testing.assert_allclose(
        C, m.base.prediction_cov(q) + m.lddmm.linear_posterior_cov(q, 2.5e-9), rtol=1e-12
    )
    back = load_model(save_model(m, tmp_path / "m.json"))
    assert back.posterior_scale_m2 == 2.5e-9
    np.testing.assert_allclose(back.prediction_cov(q), C, rtol=1e-9)
    d = m.to_dict()
    del d["posterior_scale_m2"]  # a model file from before 2026-11-27
    old = model_from_dict(d)
    assert old.prediction_cov(q) is None
    from workcell.export.table import no_std_why

    assert "fit it again for a 1-sigma" in no_std_why(old) and "predates" in no_std_why(old)
    for bad in (-1e-9, True, float("nan"), 5.0):
        with pytest.raises(UserError, match="posterior_scale_m2 must be a variance"):
            model_from_dict({**d, "posterior_scale_m2": bad})
    with pytest.raises(UserError, match=r"number written as text \(posterior_scale_m2 = '1e-9'"):
        model_from_dict({**d, "posterior_scale_m2": "1e-9"})


def test_what_a_posterior_model_leaves_out_is_not_said_to_be_outside_its_1_sigma():
    """A parametric model's 1-sigma holds none of what it leaves unexplained ("not in that
    1-sigma"); a Gaussian-process posterior (gp, lddmm, a residual GP) holds part of it."""
    from workcell.estimation.models import unexplained_error
    from workcell.export.table import std_is_posterior, unexplained_lines

    m = _calibration(2.5e-9)
    assert std_is_posterior(m) and not std_is_posterior(m.base)
    u = unexplained_error(6e-5, [5e-5, 7e-5], 1.4e-5)
    meta = {"model_unexplained": u, "median_std_m": 4e-5}
    assert unexplained_lines(meta)[0].startswith("not in that 1-sigma:")
    line = unexplained_lines({**meta, "std_posterior": True})[0]
    assert line.startswith("beside that 1-sigma (a Gaussian-process posterior in part")


def test_the_cv_errors_are_the_ones_the_cv_score_is_made_of():
    """`linear_cv_errors` (behind the CV RMS interval and `--on auto`'s paired comparison) uses
    the folds of `linear_cv_scores`: the RMS of its per-point errors is the score."""
    from workcell.estimation.lddmm import linear_cv_scores
    from workcell.estimation.lddmm.model import linear_cv_errors

    rng = np.random.default_rng(6)
    X = rng.uniform(-1, 1, (60, 3))
    Y = np.asarray(jax.vmap(k0_toy)(jnp.asarray(X))) * 1.01 + rng.normal(0, 1e-3, (60, 2))
    scores = linear_cv_scores(k0_toy, X, Y, sigma=[0.05, 0.2], sigma_v=0.8, sigma_w=0.4)
    for (sv, sw, s), rms in scores.items():
        e = linear_cv_errors(k0_toy, X, Y, sigma_v=sv, sigma_w=sw, sigma=s)
        assert e.shape == (60,)
        assert np.sqrt(np.mean(e**2)) == pytest.approx(rms, rel=1e-10)
