"""Bounded identification (seed 002 eq. 11): iterated linearised QP with parameter bounds."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.optimize import least_squares
from simdata import dh_error_dataset

from workcell.errors import UserError
from workcell.estimation.bounded import (
    default_bounds,
    fit_dh_bounded,
    jacobian_padded,
    predict_padded,
    resolve_bounds,
)
from workcell.estimation.dh import fit_dh, nominal_theta, pose_sigma
from workcell.kinematics.chain import IDX, PARAM_NAMES


@pytest.fixture(scope="module")
def sim_ds():
    """40 random poses of a simulated UR5e with DH errors (no other effects), tracker noise."""
    return dh_error_dataset(40, seed=5)


def test_agrees_with_nonlinear_fit_when_bounds_inactive(sim_ds):
    _, ds = sim_ds
    ref = fit_dh(ds)
    for b in (None, "default"):
        m = fit_dh_bounded(ds, bounds=b)
        assert m.info["active_bounds"] == []
        assert m.info["converged"]
        np.testing.assert_array_equal(m.free, ref.free)
        np.testing.assert_allclose(m.theta, ref.theta, rtol=0, atol=1e-10)
        np.testing.assert_allclose(m.predict(ds.q), ref.predict(ds.q), rtol=0, atol=1e-9)
        np.testing.assert_allclose(m.std[m.free], ref.std[ref.free], rtol=1e-6)
        assert m.unidentifiable == ref.unidentifiable


def test_default_bounds_contain_the_truth_and_are_documented(sim_ds):
    truth, ds = sim_ds
    lo, hi = default_bounds(nominal_theta(ds))
    th = nominal_theta(ds)
    assert np.allclose(hi[IDX["a2"]] - th[IDX["a2"]], 5e-3)
    assert np.allclose(hi[IDX["alpha3"]] - th[IDX["alpha3"]], 10e-3)
    # the base (tracker placement) and the SMR offset are no manufacturing tolerance: unbounded
    assert hi[IDX["base_tx"]] == np.inf and lo[IDX["tool_z"]] == -np.inf
    for i in range(6):
        assert lo[IDX[f"a{i + 1}"]] < truth.a[i] < hi[IDX[f"a{i + 1}"]]
        assert lo[IDX[f"alpha{i + 1}"]] < truth.alpha[i] < hi[IDX[f"alpha{i + 1}"]]


def _tight(ds):
    # bounds much tighter than the true errors on some identifiable parameters
    return {"mode": "delta", "bounds": {"a2": [-2e-5, 2e-5], "a3": [-2e-5, 2e-5],
                                       "alpha2": [-5e-5, 5e-5], "d4": [-1e-5, 1e-5]}}  # fmt: skip


def test_active_bounds_are_respected_and_optimal(sim_ds):
    _, ds = sim_ds
    free_fit = fit_dh_bounded(ds, bounds=None)
    spec = _tight(ds)
    m = fit_dh_bounded(ds, bounds=spec)
    lo, hi = resolve_bounds(spec, nominal_theta(ds))
    f = m.free
    assert np.all(m.theta[f] >= lo[f] - 1e-15) and np.all(m.theta[f] <= hi[f] + 1e-15)
    # the unbounded optimum violates them, so some must be active
    viol = [n for n in spec["bounds"] if not lo[IDX[n]] <= free_fit.theta[IDX[n]] <= hi[IDX[n]]]
    assert viol, "test setup: the tight bounds should cut the unbounded optimum"
    assert set(viol) & set(m.info["active_bounds"])
    assert set(m.info["active_bounds"]) <= set(spec["bounds"])
    assert m.info["train_rms_m"] > free_fit.info["train_rms_m"]
    # a parameter held by its bound has no Gaussian std: it was reported as 0 +- 0.0000
    params = m.parameters()
    for n in m.info["active_bounds"]:
        assert params[n]["std"] is None and params[n]["at_bound"], params[n]
    for n, v in params.items():
        if v["estimated"] and n not in m.info["active_bounds"]:
            assert v["std"] > 0 and "at_bound" not in v, (n, v)
    # the same bounded nonlinear problem solved independently (scipy trf with bounds) agrees
    w = 1.0 / pose_sigma(ds)

    def full(x):
        th = m.theta.copy()
        th[f] = x
        return th

    def fun(x):
        return ((predict_padded(full(x), m.base_ref, ds.q) - ds.p_tracker) * w[:, None]).ravel()

    def jac(x):
        J = jacobian_padded(full(x), m.base_ref, ds.q) * w[:, None, None]
        return J.reshape(-1, 39)[:, f]

    x0 = np.clip(nominal_theta(ds)[f], lo[f], hi[f])
    x0 = np.where(np.isfinite(x0), x0, 0.0)
    ref = least_squares(
        fun, x0, jac=jac, bounds=(lo[f], hi[f]), method="trf", x_scale="jac",
        xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=500,
    )  # fmt: skip
    cost_qp = float(np.sum(fun(m.theta[f]) ** 2))
    assert cost_qp <= 2 * ref.cost * (1 + 1e-6)
    np.testing.assert_allclose(m.predict(ds.q), predict_padded(full(ref.x), m.base_ref, ds.q),
                               atol=2e-7)  # fmt: skip
    # KKT: at an active lower (upper) bound the cost must not decrease inwards
    g = jac(m.theta[f]).T @ fun(m.theta[f])  # half the gradient
    names = np.array(PARAM_NAMES)[f]
    scale = np.linalg.norm(jac(m.theta[f]), axis=0) * np.sqrt(2 * ref.cost + 1e-30)
    for k, n in enumerate(names):
        if n in m.info["active_bounds"]:
            at_lo = np.isclose(m.theta[IDX[n]], lo[IDX[n]], rtol=0, atol=1e-12)
            assert (g[k] >= -1e-6 * scale[k]) if at_lo else (g[k] <= 1e-6 * scale[k]), n
        else:
            assert abs(g[k]) < 1e-4 * scale[k], n


def test_bounds_file_and_errors(sim_ds, tmp_path):
    _, ds = sim_ds
    th = nominal_theta(ds)
    path = tmp_path / "b.json"
    a2 = th[IDX["a2"]]
    path.write_text(json.dumps({"a2": [a2 - 1e-5, a2 + 1e-5]}))
    m = fit_dh_bounded(ds, bounds=str(path))
    assert abs(m.theta[IDX["a2"]] - a2) <= 1e-5 + 1e-15
    assert m.info["bounds"]["a2"] == pytest.approx([a2 - 1e-5, a2 + 1e-5])
    lo, hi = resolve_bounds(str(path), th)
    dlo, dhi = default_bounds(th)
    others = np.arange(39) != IDX["a2"]
    np.testing.assert_array_equal(lo[others], dlo[others])
    for bad, msg in (
        ({"a9": [0, 1]}, "unknown parameter"),
        ({"a2": [1, 0]}, "empty"),
        ({"a2": [0]}, "two numbers"),
        ([1, 2], "JSON object"),
    ):
        path.write_text(json.dumps(bad))
        with pytest.raises(UserError, match=msg):
            resolve_bounds(str(path), th)
    with pytest.raises(UserError, match="not found"):
        resolve_bounds(str(tmp_path / "missing.json"), th)
    path.write_text("{not json")
    with pytest.raises(UserError, match="valid JSON"):
        resolve_bounds(str(path), th)
    with pytest.raises(ValueError, match="too few poses"):
        fit_dh_bounded(ds.subset(np.arange(5)))


def test_fit_command_routes_bounds(sim_ds, tmp_path):
    """`workcell fit --method dh --bounds default` goes through fit_dh_bounded."""
    from workcell.estimation.fitting import fit_dataset

    _, ds = sim_ds
    model, rep = fit_dataset(ds, method="dh", holdout=0.25, bounds="default")
    assert "qp_iterations" in model.info and model.info["converged"]
    assert rep["heldout_rms_m"] < 0.2 * rep["nominal_rms_m"]
