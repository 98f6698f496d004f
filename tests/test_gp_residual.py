"""GP residual peer (`--method gp`): hyperparameters carry a calibrated Laplace std."""

from __future__ import annotations

import json

import numpy as np
import pytest
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

from workcell.cli import main
from workcell.estimation.gp_residual import GPResidualModel, laplace_log_std
from workcell.estimation.models import load_model


def _fit(X, y, seed, noise_bounds=(1e-5, 1e1)):
    k = ConstantKernel(1.0, (1e-3, 1e3)) * RBF(1.0, (1e-2, 1e2)) + WhiteKernel(0.6, noise_bounds)
    return GaussianProcessRegressor(k, n_restarts_optimizer=1, random_state=seed).fit(X, y)


def test_laplace_std_matches_the_spread_of_repeated_fits():
    """40 data sets drawn from a known GP (length 0.5, signal 1, noise 0.1, 80 points): the
    spread of the fitted log-hyperparameters equals the Laplace std within sampling error
    (the std of a std from 40 draws is ~11 %)."""
    rng = np.random.default_rng(0)
    est, lap = [], []
    for r in range(40):
        X = rng.uniform(0, 5, (80, 1))
        K = np.exp(-0.5 * (X - X.T) ** 2 / 0.5**2) + 1e-10 * np.eye(80)
        y = np.linalg.cholesky(K) @ rng.normal(size=80) + 0.1 * rng.normal(size=80)
        g = _fit(X, y, r)
        est.append(g.kernel_.theta.copy())
        lap.append(laplace_log_std(g))
    ratio = np.nanmedian(lap, 0) / np.std(est, 0)
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio


@pytest.mark.filterwarnings("ignore::sklearn.exceptions.ConvergenceWarning")
def test_hyperparameter_at_its_bound_has_no_std():
    """Noise variance 0.01 searched in [0.5, 10]: it stops at its lower bound."""
    rng = np.random.default_rng(1)
    X = rng.uniform(0, 5, (60, 1))
    y = np.sin(3 * X[:, 0]) + 0.1 * rng.normal(size=60)
    g = _fit(X, y, 0, noise_bounds=(0.5, 10.0))
    s = laplace_log_std(g)
    th, b = g.kernel_.theta, g.kernel_.bounds
    at = (th - b[:, 0] < 1e-2) | (b[:, 1] - th < 1e-2)
    assert at[2] and np.isnan(s[2])
    assert np.all(np.isfinite(s[~at]))


def test_fit_gp_reports_every_hyperparameter_with_std_or_at_bound(tmp_path, capsys):
    rec = tmp_path / "c.mcap"
    assert (
        main(["campaign", "--robot", "sim", "--tracker", "sim", "--poses", "40", "--out", str(rec)])
        == 0
    )
    capsys.readouterr()
    out = tmp_path / "m.json"
    assert main(["fit", str(rec), "--method", "gp", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rows = [ln.split() for ln in text.splitlines() if ln.strip().startswith("gp_")]
    rows = [r for r in rows if r[0].startswith(("gp_lengthscale_q", "gp_signal_std", "gp_noise"))]
    assert len([r for r in rows if len(r) >= 4]) == 8
    for r in rows:
        if len(r) >= 4:
            # a std in the row's unit, or a factor / "at bound" with no unit after it (the unit
            # is that of '- nominal' and of a std: "x/ 64.4 mrad" read as a range in mrad)
            assert r[-1] == "bound" or r[-2] == "x/" or float(r[-2]) > 0, r
    m = load_model(out)
    assert isinstance(m, GPResidualModel) and m.log_hyper_std is not None
    params = json.loads(json.dumps(m.parameters()))
    for j in range(6):
        p = params[f"gp_lengthscale_q{j + 1}"]
        loose = p.get("factor_95", 1.0) > np.exp(1.96 * 0.5)
        assert (p["std"] is None) == (p["at_bound"] or bool(p.get("no_std")) or loose)
    # a hyperparameter known only within a large factor gets its 95 % range, not a +- std
    # (it printed "0.769 rad +- 42.9 rad")
    import dataclasses

    wide = dataclasses.replace(m, log_hyper_std=np.full(8, 3.0)).parameters()
    q1 = wide["gp_lengthscale_q1"]
    assert q1["std"] is None and q1["factor_95"] == pytest.approx(np.exp(1.96 * 3.0))
    assert "no_std" not in q1  # it has a maximum, only a loose one
    assert q1["range_95"] == pytest.approx([q1["value"] / q1["factor_95"],
                                            q1["value"] * q1["factor_95"]])  # fmt: skip
    tight = dataclasses.replace(m, log_hyper_std=np.full(8, 0.1)).parameters()
    assert tight["gp_lengthscale_q1"]["std"] == pytest.approx(0.1 * q1["value"])
    # a log std so large that exp(1.96 s) overflows (series D's joint 5 length scale did on
    # 2026-11-26: "RuntimeWarning: overflow", range_95 [0, inf]): finite, no warning, "x/ >1000"
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        huge = dataclasses.replace(m, log_hyper_std=np.full(8, 1e3)).parameters()
    h = huge["gp_lengthscale_q1"]
    assert np.isfinite(h["factor_95"]) and h["factor_95"] > 1e3
    assert np.all(np.isfinite(h["range_95"])) and h["std"] is None


def test_fit_report_prints_every_kind_of_parameter(capsys):
    """A std, a bound hit, a cross-validated choice, and no std at all: one row each."""
    from workcell.commands.fit import print_report

    r = {
        "method": "x",
        "recording": "r.mcap",
        "train_poses": 3,
        "heldout_poses": 1,
        "split": "s",
        "nominal_rms_m": 1e-3,
        "heldout_rms_m": 1e-5,
        "heldout_max_m": 2e-5,
        "model": "m.json",
        "fit_seconds": 1.0,
        "parameters": {
            "a2": {"value": -0.425, "nominal": -0.4251, "std": 1e-6, "unit": "m"},
            "ls": {"value": 9.0, "std": None, "unit": "rad", "at_bound": True},
            "sig": {"value": 0.3, "std": None, "unit": "1", "chosen_by": "cv"},
            "other": {"value": 1.0, "std": None, "unit": "1"},
        },
    }
    print_report(r)
    rows = {ln.split()[0]: ln for ln in capsys.readouterr().out.splitlines() if ln.strip()}
    assert "0.0010" in rows["a2"] and "at bound" in rows["ls"]
    assert rows["sig"].endswith("CV grid") and rows["other"].split()[-1] == "-"


def test_gp_prediction_covariance_is_the_posterior_variance_plus_the_geometry(tmp_path, capsys):
    """The GP model's 1-sigma for a correction: its latent posterior variance (checked against
    scikit-learn's, which adds the white noise at the test points) plus the geometry's; small
    where it was measured, the GP's prior signal std far from every measured pose. A table
    exported from it carries a 1-sigma per node (it carried none)."""
    from workcell.export.build import make_table

    rec = tmp_path / "c.mcap"
    argv = ["campaign", "--robot", "sim", "--tracker", "sim", "--poses", "40", "--out", str(rec)]
    assert main(argv) == 0
    out = tmp_path / "m.json"
    assert main(["fit", str(rec), "--method", "gp", "--out", str(out)]) == 0
    capsys.readouterr()
    m = load_model(out)
    k = ConstantKernel(m.signal_var, "fixed") * RBF(m.lengthscales, "fixed")
    k = k + WhiteKernel(m.noise_var, "fixed")
    Xs = m.X / m.scale
    g = GaussianProcessRegressor(k, alpha=1e-20, optimizer=None).fit(Xs, np.zeros(len(Xs)))
    q = np.vstack([m.X[:5] + 0.05, m.X[:3] + 6.0 * m.scale * m.lengthscales])
    _, sd = g.predict(q / m.scale, return_std=True)
    assert m.predict_std(q) ** 2 + m.noise_var == pytest.approx(sd**2, rel=1e-6)
    C, Cb = m.prediction_cov(q), m.base.prediction_cov(q)
    extra = np.einsum("nii->ni", C - Cb)
    assert extra == pytest.approx(np.repeat(m.predict_std(q)[:, None] ** 2, 3, 1))
    assert np.all(m.predict_std(q[:5]) < 0.5 * np.sqrt(m.signal_var))  # measured there
    assert m.predict_std(q[5:]) == pytest.approx(np.sqrt(m.signal_var), rel=1e-3)  # far away
    tab, _ = make_table(m, model_path=str(out), spacing_m=0.15, target_error_m=1e-3)
    assert tab.std_m is not None and np.all(tab.std_m > 0)
    assert "Gaussian-process residual" in tab.meta["std_basis"]


def test_augmented_models_residual_gp_variance_matches_scikit_learn():
    """diagnose's residual GP (`ResidualGP`) gives the posterior variance of the residual in
    metres^2 per axis: scikit-learn's for the same fixed kernel (less its white noise at the
    test point), times the axis' normalisation squared."""
    from workcell.estimation.discovery_np import fit_residual_gp

    rng = np.random.default_rng(3)
    q = rng.uniform(-2, 2, (60, 6))
    r = 1e-5 * np.c_[np.sin(q[:, 1]), np.cos(q[:, 2]), q[:, 0]] + 2e-6 * rng.normal(size=(60, 3))
    g = fit_residual_gp(q, r)
    k = ConstantKernel(g.signal_var, "fixed") * RBF(g.lengthscales, "fixed")
    k = k + WhiteKernel(g.noise_var, "fixed")
    sk = GaussianProcessRegressor(k, alpha=1e-20, optimizer=None).fit(q, np.zeros(len(q)))
    qt = np.vstack([q[:4] + 0.1, rng.uniform(-2, 2, (4, 6)), q[:2] + 50.0])
    _, sd = sk.predict(qt, return_std=True)
    want = (sd**2 - g.noise_var)[:, None] * g.y_std[None, :] ** 2
    assert g.predict_var(qt) == pytest.approx(want, rel=1e-6, abs=1e-24)
    assert g.predict_var(qt[-2:]) == pytest.approx(
        np.tile(g.signal_var * g.y_std**2, (2, 1)), rel=1e-6
    )
