"""6-joint calibration by diffeomorphisms (`fit --method lddmm`) on simulated UR5e recordings with
joint compliance and transmission error (errors a DH model cannot represent): the deformation
must beat the DH fit on the held-out poses, with everything chosen on the training poses only.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from sim_devices.cell import sim_cell
from workcell.campaign.run import run_campaign
from workcell.estimation.fitting import fit_dataset
from workcell.estimation.lddmm_fit import EVAL_TOL_M, LddmmCalibration
from workcell.estimation.models import error_stats, load_model, save_model
from workcell.recording.dataset import Dataset

EFFECTS = "joint_compliance,transmission_error"


def _recording(tmp_path_factory, poses: int, seed: int) -> Dataset:
    p = tmp_path_factory.mktemp("lddmm6") / f"ur5e_{poses}.mcap"
    _, robot, tracker, cell = sim_cell("ur5e", EFFECTS, seed)
    run_campaign(robot, tracker, cell, p, poses=poses, seed=seed)
    return Dataset.from_recording(p)


# the 120-pose LDDMM fits (a shared 18 s fixture): moved out of `make test` on 2026-11-26 (its time); `make test-all` runs it
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    ds = _recording(tmp_path_factory, 120, 7)
    lm, rep_lm = fit_dataset(ds, method="lddmm", holdout=0.25, on="dh")
    # `--method dh` is fit_dh on the same training poses: the base of the on-dh deformation
    # (not refitted here, to keep this file fast; the slow test runs both methods)
    _, test = ds.holdout_split(0.25)
    rep_dh = {
        "heldout_poses": len(test),
        "heldout_rms_m": error_stats(lm.base.predict(ds.q[test]), ds.p_tracker[test])["rms_m"],
    }
    return ds, rep_dh, lm, rep_lm


def test_lddmm_beats_dh_on_held_out_120_poses(small):
    _, rep_dh, _, rep_lm = small
    assert rep_lm["heldout_poses"] == rep_dh["heldout_poses"] == 30
    assert rep_lm["heldout_rms_m"] < rep_dh["heldout_rms_m"], (
        rep_lm["heldout_rms_m"],
        rep_dh["heldout_rms_m"],
    )
    # and by a margin (measured 48 vs 124 um): "beats" alone let a deformation that adds a
    # fifth of its correction to the DH prediction pass; 0.6x is well outside the +-25 % a
    # 30-pose RMS can move by chance
    assert rep_lm["heldout_rms_m"] <= 0.6 * rep_dh["heldout_rms_m"]


def test_gp_residual_takes_a_real_share_of_what_dh_leaves(small):
    """`--method gp` had no accuracy test: a GP whose correction was multiplied by 0 passed the
    whole suite. On the same recording (compliance and transmission error the DH model leaves)
    it must take a real share off the DH held-out RMS (measured 78 vs 124 um)."""
    ds, rep_dh, _, _ = small
    _, rep_gp = fit_dataset(ds, method="gp", holdout=0.25)
    assert rep_gp["heldout_poses"] == rep_dh["heldout_poses"]
    assert rep_gp["heldout_rms_m"] <= 0.8 * rep_dh["heldout_rms_m"], (
        rep_gp["heldout_rms_m"],
        rep_dh["heldout_rms_m"],
    )


def test_report_has_widths_sigma_and_positive_jacobians(small):
    _, _, _, rep = small
    e = rep["extra"]
    assert e["on"] == "dh"
    assert e["sigma_v_rad"] > 0 and e["sigma_w_m"] > 0
    assert e["sigma"] in e["cv_grid"]["sigma"]
    assert e["min_jacobian_det_phi"] > 0 and e["min_jacobian_det_psi"] > 0
    # the fit did reduce the training error of its base
    assert e["train_rms_after_m"] < e["train_rms_before_m"]
    assert set(rep["parameters"]) >= {"lddmm_sigma_v", "lddmm_sigma_w", "lddmm_sigma"}


def test_tuned_evaluation_within_tolerance_on_unseen_poses(small, tmp_path):
    ds, _, lm, rep = small
    _, test = ds.holdout_split(0.25)
    q = ds.q[test]
    tuned = lm.predict(q)
    ev = rep["extra"]["evaluation"]
    lm.lddmm.set_evaluation(None, False, False)  # reference: the fit's RK4 steps, float64
    ref = lm.predict(q)
    lm.lddmm.set_evaluation(ev["eval_steps"], ev["eval_float32"], ev["eval_frozen_jacobian"])
    assert np.max(np.linalg.norm(tuned - ref, axis=1)) < 2 * EVAL_TOL_M
    # saved and reloaded: same predictions, same evaluation settings
    path = save_model(lm, tmp_path / "m.json")
    json.loads(path.read_text())
    lm2 = load_model(path)
    assert isinstance(lm2, LddmmCalibration)
    assert lm2.lddmm.eval_steps == ev["eval_steps"]
    assert lm2.lddmm.eval_frozen_jacobian == ev["eval_frozen_jacobian"]
    np.testing.assert_allclose(lm2.predict(q), tuned, atol=1e-12)


@pytest.mark.slow
def test_lddmm_beats_dh_on_held_out_300_poses(tmp_path_factory):
    """The issue's acceptance case: 300 poses, 25 % held out, `--method lddmm` (on=auto)."""
    ds = _recording(tmp_path_factory, 300, 0)
    _, rep_dh = fit_dataset(ds, method="dh", holdout=0.25)
    model, rep_lm = fit_dataset(ds, method="lddmm", holdout=0.25, on="auto")
    assert rep_lm["heldout_poses"] == 75
    assert rep_lm["extra"]["on"] in ("dh", "nominal")
    assert rep_lm["heldout_rms_m"] < rep_dh["heldout_rms_m"]
    train, test = ds.holdout_split(0.25)
    e = error_stats(model.predict(ds.q[test]), ds.p_tracker[test])
    assert e["rms_m"] == pytest.approx(rep_lm["heldout_rms_m"], rel=1e-9)


def test_the_1_sigma_covers_the_held_out_errors(small):
    """The model's prediction covariance (the DH base's plus the deformation's linearised
    posterior) against its held-out errors, each with the tracker's per-pose uncertainty the fits
    use (max(recorded, MPE / 4)): a right 1-sigma makes e^T C^-1 e a chi-square of 3 degrees of
    freedom, mean 3 and 95 % of them below its 95 % point (measured 0.98 x 3 and 29 of 30; a
    1-sigma off by 2x gives 4 x 3 or 0.25 x 3)."""
    from scipy import stats

    from workcell.estimation.dh import pose_sigma_model

    ds, _, lm, _ = small
    _, test = ds.holdout_split(0.25)
    dte = ds.subset(test)
    C = lm.prediction_cov(dte.q)
    e = dte.p_tracker - lm.predict(dte.q)
    n2 = pose_sigma_model(dte) ** 2
    z2 = np.einsum("ni,nij,nj->n", e, np.linalg.inv(C + n2[:, None, None] * np.eye(3)), e)
    assert 0.6 < z2.mean() / 3 < 1.6, z2.mean() / 3  # 30 poses: the mean is good to ~15 %
    assert np.mean(z2 < stats.chi2.ppf(0.95, 3)) >= 0.85
