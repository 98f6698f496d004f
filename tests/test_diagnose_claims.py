"""What `workcell diagnose` claims, against what its held-out poses support (audit 7).

- An accepted effect whose held-out gain has a 95 % interval reaching zero is not confirmed, even
  when the point gain is positive; the summary lists such effects apart from the confirmed ones
  and says they stay in the saved model, and why (the selection accepts on the training poses).
- The "explains N %" figure is a cross-validation share on the training poses in acceptance
  order, and the sentence says so; the step table says its rows are cumulative in acceptance
  order and prints each effect's own leave-one-out gain beside them.
- The residual GP's held-out RMS comes with its 95 % interval and with the caveat that the same
  held-out poses accepted it, in the summary and the text output, which names its model file.
- The noise floor says what it holds: the tracker's part (the floor `workcell fit` states) and
  the geometric fit's own uncertainty.

A small simulated recording (60 poses, a joint-3 backlash and a thermal drift at 1.3x the noise
floor, seed 20): the selection accepts both on the training poses, the held-out poses confirm the
drift (gain interval above zero) but not the backlash (positive gain, interval reaching zero).
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from workcell.bench.discovery import make_case
from workcell.commands import diagnose as cmd
from workcell.estimation.discovery import DiagnoseConfig, diagnose, summary_text
from workcell.recording.dataset import Dataset


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    d = tmp_path_factory.mktemp("claims")
    kinds = [("backlash", 3), ("thermal_drift", None)]
    c = make_case(kinds, 20, 60, 1.3, d, np.random.default_rng(20), warmup_s=300.0)
    ds = Dataset.from_recording(c["path"])
    return c["path"], ds, diagnose(ds, DiagnoseConfig(nonparametric=False))


def _split(r: dict) -> tuple[list[dict], list[dict]]:
    conf = [e for e in r["effects"] if e["evidence"]["heldout_confirms"]]
    return conf, [e for e in r["effects"] if not e["evidence"]["heldout_confirms"]]


def test_an_effect_whose_gain_interval_reaches_zero_is_not_confirmed(case):
    _, _, d = case
    r = d.report
    by_key = {e["key"]: e["evidence"] for e in r["effects"]}
    assert set(by_key) == {"backlash/joint3", "thermal_drift"}
    for ev in by_key.values():
        assert ev["heldout_confirms"] == (ev["heldout_gain_ci95_m"][0] > 0.0)
    # the backlash lowers the held-out RMS by a point figure, within chance: not confirmed
    bl = by_key["backlash/joint3"]
    assert bl["heldout_gain_m"] > 0 and bl["heldout_gain_ci95_m"][0] < 0
    assert bl["heldout_confirms"] is False
    assert by_key["thermal_drift"]["heldout_confirms"] is True
    assert "95 % interval" in r["heldout_confirms_basis"]
    # the saved model says which of its terms the held-out poses do not confirm
    nc = d.model.info["effects_not_confirmed_on_heldout"]
    assert nc["effects"] == ["backlash/joint3"] and "stay in the model" in nc["basis"]


def test_summary_separates_confirmed_from_not_confirmed_effects(case):
    _, _, d = case
    r = d.report
    s = r["summary"]
    head = "Physics left out of the nominal model, confirmed on the held-out poses"
    apart = "NOT confirmed on the held-out poses (the 95 % interval of the held-out gain"
    assert head in s and apart in s
    confirmed_part, unconfirmed_part = s.split(apart)
    assert "thermal drift of the link lengths" in confirmed_part.split(head)[1]
    assert "joint 3 backlash" not in confirmed_part
    assert "joint 3 backlash" in unconfirmed_part.split("(+- is one")[0]
    # and it says plainly that they are kept, and why
    assert "kept in the augmented model" in unconfirmed_part
    assert "the selection accepts on the training poses" in unconfirmed_part
    assert "not-confirmed ones included" in s
    # the explained share: cross-validation on the training poses, in acceptance order
    assert "explains" not in s
    assert "training poses: takes out" in s and "added in acceptance order" in s
    assert "cross-validation on" in r["explained_fraction_basis"]

    # none confirmed: the heading says so rather than naming the unconfirmed ones as left out
    r2 = copy.deepcopy(r)
    for e in r2["effects"]:
        e["evidence"]["heldout_confirms"] = False
    s2 = summary_text(r2)
    assert f"{head}: none of the accepted effects." in s2
    assert "these effects are kept in the augmented model" in s2


def test_text_output_says_what_the_step_rows_are_and_prints_leave_one_out_gains(case, capsys):
    _, _, d = case
    r = d.report
    cmd.print_report(r)
    out = capsys.readouterr().out
    flat = " ".join(out.split())  # the note under the table is wrapped
    assert "cumulative, in the order the selection accepted the effects" in flat
    assert f"on the {r['heldout_poses']} held-out poses" in flat
    assert "leave-one-out on the held-out poses" in out
    rows = {ln.split()[0]: ln for ln in out.splitlines() if ln.startswith("  backlash/joint3")}
    rows |= {ln.split()[0]: ln for ln in out.splitlines() if ln.startswith("  thermal_drift")}
    ev = {e["key"]: e["evidence"] for e in r["effects"]}
    bl = rows["backlash/joint3"]
    assert f"{ev['backlash/joint3']['heldout_gain_m'] * 1e6:.1f} um" in bl
    assert "NOT confirmed (kept in the model)" in bl
    assert rows["thermal_drift"].rstrip().endswith("confirmed")
    assert "cumulative" in r["steps_basis"]


def test_noise_floor_names_the_tracker_part_fit_states(case):
    from workcell.estimation.fitting import fit_dataset

    _, ds, d = case
    r = d.report
    _, fr = fit_dataset(ds)
    assert r["tracker_noise_floor_m"] == pytest.approx(fr["tracker_noise_floor_m"], rel=1e-9)
    assert r["tracker_noise_floor_m"] <= r["noise_floor_m"]
    t, f = r["tracker_noise_floor_m"] * 1e6, r["noise_floor_m"] * 1e6
    assert (
        f"the noise floor expected from the tracker ({t:.1f} um, the tracker floor `workcell fit` "
        f"states) and the geometric fit's own uncertainty is {f:.1f} um"
    ) in r["summary"]


def test_gp_correction_states_its_interval_caveat_and_file(case, capsys, tmp_path):
    """The residual GP's held-out figures from `_nonparametric` on a residual with structure in
    joint 2's angle: the summary and the table give the 95 % interval and say the same held-out
    poses accepted the GP; the text output names the GP model file beside the augmented one."""
    from workcell.estimation.discovery import _nonparametric

    _, ds, d = case
    cfg = DiagnoseConfig()
    train, test = ds.holdout_split(cfg.holdout)
    dtr, dte = ds.subset(train), ds.subset(test)

    def structured(q):
        return 60e-6 * np.sin(3.0 * q[:, [1, 1, 1]]) * np.array([1.0, -0.5, 0.7])

    rng = np.random.default_rng(3)
    res_tr = structured(dtr.q) + rng.normal(0, 3e-6, (len(dtr), 3))
    res_te = structured(dte.q) + rng.normal(0, 3e-6, (len(dte), 3))
    after = {"rms_m": float(np.sqrt(np.mean(np.sum(res_te**2, axis=1))))}
    u, model_np = _nonparametric(
        d.model, dtr, res_tr, dte, res_te, after, cfg, lambda m: None, floor=10e-6
    )
    assert u["structured"] and model_np is not None
    npm = u["np_model"]
    lo, hi = npm["heldout_rms_ci95_m"]
    assert lo <= npm["heldout_rms_m"] <= hi
    assert npm["heldout_selection"] == model_np.info["heldout_selection"]

    r = copy.deepcopy(d.report)
    r["unexplained"].update(u)
    s = summary_text(r)
    ci = f"95 % CI {lo * 1e6:.1f}-{hi * 1e6:.1f} um"
    sentence = s.split("A non-parametric correction")[1]
    assert ci in sentence
    assert "accepted on these held-out poses" in sentence and "somewhat optimistic" in sentence

    r["summary"] = s
    r["model"] = str(tmp_path / "aug.json")
    r["unexplained"]["np_model"]["model"] = str(tmp_path / "aug.np.json")
    cmd.print_report(r)
    out = capsys.readouterr().out
    (row,) = [ln for ln in out.splitlines() if ln.startswith("final + non-parametric")]
    assert f"{lo * 1e6:.1f}-{hi * 1e6:.1f} um" in row and "optimistic" in row
    assert "GP row: the residual GP was accepted on these held-out poses" in " ".join(out.split())
    assert f"GP model    {tmp_path / 'aug.np.json'}" in out


def test_cli_report_and_model_file_carry_the_verdicts(case, tmp_path, capsys):
    path, _, _ = case
    ns = type("A", (), {})()
    ns.recording, ns.json, ns.report, ns.out = str(path), False, str(tmp_path / "rep"), None
    ns.holdout, ns.alpha, ns.tracker_mpe, ns.no_np = 0.25, 0.01, "15e-6,6e-6", True
    ns.force, ns.chain_missing = False, "refuse"
    assert cmd.run(ns) == 0
    out = capsys.readouterr().out
    assert "NOT confirmed (kept in the model)" in out
    rep = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert "kept in the augmented model" in (tmp_path / "rep" / "summary.txt").read_text()
    model = json.loads(Path(rep["model"]).read_text())
    assert model["info"]["effects_not_confirmed_on_heldout"]["effects"] == ["backlash/joint3"]


def test_the_located_harmonic_amplitude_std_matches_its_spread():
    """`locate` printed a periodic residual's amplitude with no +- (uncertainty audit,
    2026-11-27): its 1-sigma (residual variance, delta method) agrees with the spread of the
    amplitude over repeated noisy draws."""
    import numpy as np

    from workcell.estimation.discovery import _amplitude_std

    rng = np.random.default_rng(3)
    q = rng.uniform(-3, 3, 200)
    B = np.column_stack([np.sin(2 * q), np.cos(2 * q), np.ones_like(q)])
    amps, stds = [], []
    for _ in range(2000):
        y = 5e-5 * np.sin(2 * q + 0.4) + 1e-5 + rng.normal(0, 3e-5, len(q))
        c, *_ = np.linalg.lstsq(B, y, rcond=None)
        amps.append(np.hypot(c[0], c[1]))
        stds.append(_amplitude_std(B, c, float(np.sum((y - B @ c) ** 2))))
    np.testing.assert_allclose(np.median(stds), np.std(amps), rtol=0.1)
    assert np.isnan(_amplitude_std(B[:3], np.zeros(3), 0.0))  # no residual degree of freedom


def test_the_final_models_1_sigma_is_checked_on_the_held_out_poses(case, capsys):
    """The diagnosis states the final model's 1-sigma at its held-out poses and checks it
    against their errors (as `fit` does): here the model holds the simulated physics, so its
    1-sigma and the tracker's noise should hold the errors."""
    _, _, d = case
    hs = d.report["heldout_model_std"]
    assert hs["poses"] == d.report["heldout_poses"]
    assert 0 < hs["median_m"] <= hs["max_m"]
    assert hs["z2_mean_over_3"] < 2.0  # a 1-sigma 2x too small gives about 4
    cmd.print_report(d.report)
    flat = " ".join(capsys.readouterr().out.split())
    assert f"final model 1-sigma {hs['median_m'] * 1e6:.1f} um median" in flat
