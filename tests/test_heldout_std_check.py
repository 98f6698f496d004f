"""`fit` states its model's 1-sigma at the held-out poses and checks it against their errors
(with the tracker's noise): about 1 when the model holds the physics (DH errors only), well above
when it leaves something out (joint compliance under a DH fit), none without a covariance."""

from __future__ import annotations

import numpy as np
import pytest

from sim_devices.cell import sim_cell
from workcell.campaign.run import run_campaign
from workcell.commands.fit import heldout_std_text
from workcell.estimation.fitting import fit_dataset, heldout_std_check
from workcell.recording.dataset import Dataset


def _report(tmp_path, effects: str, seed: int) -> dict:
    p = tmp_path / f"{effects}.mcap"
    _, robot, tracker, cell = sim_cell("ur5e", effects, seed)
    run_campaign(robot, tracker, cell, p, poses=120, seed=seed)
    return fit_dataset(Dataset.from_recording(p), method="dh")[1]


def test_the_dh_1_sigma_holds_dh_errors_and_says_when_physics_is_left_out(tmp_path):
    ok = _report(tmp_path, "none", 3)["heldout_model_std"]
    # measured 0.89 (seed 3) and 0.62 (seed 4): below 1, the tracker's sigma being MPE / 4
    assert 0.4 < ok["z2_mean_over_3"] < 1.5 and ok["inside_95"] >= 0.85
    assert ok["poses"] == 30 and 0 < ok["median_m"] <= ok["max_m"]
    assert ok["p_mean"] >= 0.05 and ok["p_inside"] >= 0.05
    assert "no evidence against the 1-sigma and the tracker's noise" in heldout_std_text(ok)
    left_out = _report(tmp_path, "joint_compliance", 3)["heldout_model_std"]
    assert left_out["z2_mean_over_3"] > 3  # measured 9.4
    assert left_out["p_mean"] < 1e-6
    assert "what the model leaves out" in heldout_std_text(left_out)


def test_no_covariance_no_check():
    class Blob:
        def predict(self, q, **aux):
            return np.zeros((len(q), 3))

    class Ds:
        q = np.zeros((5, 6))
        p_tracker = np.zeros((5, 3))

    assert heldout_std_check(Blob(), Ds()) is None


@pytest.mark.parametrize("k", [0.9, 9.99])
def test_the_line_gives_the_figures(k):
    hs = {"median_m": 29.5e-6, "max_m": 38.3e-6, "z2_mean_over_3": k, "inside_95": 0.5}
    line = heldout_std_text(hs)
    assert "29.5 um median, 38.3 um max" in line and f"= {k:.2f}" in line


def test_a_1_sigma_too_small_fails_on_its_chances_not_a_fixed_mark():
    """An augmented model's 1-sigma 1.5x too small passed: mean 1.48 over 15 poses, 80 % inside
    the 95 % ellipsoid, under the fixed mark of 1.5 ("the 1-sigma and the tracker's noise hold
    them"; uncertainty audit of 2026-11-29). Judged now by the chance of each figure if the
    1-sigma held: chi2 with 45 dof (p = 0.02) and Binomial(15, 0.95) for 12 inside (p = 0.04)."""
    from scipy import stats

    n = 15
    hs = {"median_m": 6.5e-6, "max_m": 9e-6, "z2_mean_over_3": 1.48, "inside_95": 12 / n,
          "poses": n, "p_mean": float(stats.chi2.sf(1.48 * 3 * n, 3 * n)),
          "p_inside": float(stats.binom.cdf(12, n, 0.95))}  # fmt: skip
    assert hs["p_mean"] < 0.05 and hs["p_inside"] < 0.05
    line = heldout_std_text(hs)
    assert "about 1.2x what the 1-sigma and the tracker's noise say" in line, line
    hs.update(z2_mean_over_3=1.19, p_mean=float(stats.chi2.sf(1.19 * 3 * n, 3 * n)))
    assert hs["p_mean"] > 0.05  # the gp case: the mean passes, the share inside does not
    assert "more errors outside the 95 % ellipsoid" in heldout_std_text(hs)
    old = {k: v for k, v in hs.items() if not k.startswith("p_")}  # a file of before: as then
    assert "no evidence against" in heldout_std_text(old)
