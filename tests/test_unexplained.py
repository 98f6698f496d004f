"""What a model leaves unexplained beyond the noise floor (`unexplained_error`), stated by `fit`,
`diagnose` and the correction table beside the model's own 1-sigma."""

from __future__ import annotations

import numpy as np
import pytest

from workcell.estimation.models import unexplained_error, unexplained_text


def test_quadrature_difference_and_its_upper_end():
    u = unexplained_error(5e-6, [4e-6, 6e-6], 3e-6)
    assert u["rms_m"] == pytest.approx(4e-6)
    assert u["upper_m"] == pytest.approx(np.sqrt(36e-12 - 9e-12))
    assert u["floor_m"] == 3e-6
    below = unexplained_error(2e-6, [1.5e-6, 3.5e-6], 3e-6)  # at the floor: nothing detected
    assert below["rms_m"] == 0.0 and below["upper_m"] == pytest.approx(np.sqrt(3.25) * 1e-6)
    assert unexplained_error(5e-6, None, 3e-6)["upper_m"] is None
    assert unexplained_error(5e-6, [np.nan, np.nan], 3e-6)["upper_m"] is None
    for bad in (float("nan"), "x", None, -1e-6):
        assert unexplained_error(bad, [1e-6, 2e-6], 3e-6) is None
        assert unexplained_error(5e-6, [1e-6, 2e-6], bad) is None
    # a hand-edited model file's extremes: no overflow, no figure that is not finite
    assert unexplained_error(1e308, [1e308, 1e308], 1e308)["rms_m"] == 0.0
    assert unexplained_error(1e308, [1e308, 1e308], 0.0) is None
    assert unexplained_error(1e-6, [1e-6, 1e308], 0.0)["upper_m"] is None
    assert unexplained_text(None) == ""
    assert unexplained_text(u) == (
        "4.0 um above the noise floor (up to 5.2 um at the upper end of the 95 % interval)"
    )


def _truth_scored_heldout_rms(model, ds, truth) -> float:
    """RMS of the model's error against the simulator's noise-free SMR at the held-out poses
    (tests may read the truth to score)."""
    _, test = ds.holdout_split(0.25)
    d = ds.subset(test)
    p_true = np.array(
        [truth.smr_in_tracker(q, s, 0.0) for q, s in zip(d.q, d.approach_sign, strict=True)]
    )
    return float(np.sqrt(np.mean(np.sum((model.predict(d.q) - p_true) ** 2, axis=1))))


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("effects", ["joint_compliance", "none"])
def test_the_figure_matches_the_models_true_error_at_the_heldout_poses(effects, seed, tmp_path):
    """A DH fit of a cell with gravity compliance leaves tens of um unexplained; of a DH-only
    cell, only its estimation error. The stated figure must track the model's true error at the
    held-out poses (scored against the simulator's truth), and the upper end must cover it."""
    from sim_devices.cell import sim_cell
    from workcell.campaign.executor import CampaignConfig
    from workcell.campaign.run import run_campaign
    from workcell.estimation.fitting import fit_recording
    from workcell.estimation.models import load_model
    from workcell.export.build import make_table
    from workcell.recording.dataset import Dataset

    # no outlier readings: one in the held-out set inflates the RMS and the floor alike (its
    # recorded sigma), which this test of the figure's calibration is not about
    world, robot, tracker, cell = sim_cell(
        "ur5e", effects, seed, beam_break_prob=0.0, outlier_prob=0.0
    )
    folder = tmp_path
    path = folder / "c.mcap"
    cfg = CampaignConfig(readings_per_pose=2, settle_s=0.2)
    run_campaign(robot, tracker, cell, path, poses=80, seed=seed, config=cfg)
    rep = fit_recording(path, method="dh", out=folder / "m.json")
    u = rep["unexplained"]
    model = load_model(folder / "m.json")
    true_rms = _truth_scored_heldout_rms(model, Dataset.from_recording(path), world.truth)
    assert u["upper_m"] >= true_rms, (u, true_rms)
    if effects == "none":
        assert u["upper_m"] < 15e-6
        assert true_rms < 15e-6
    else:
        assert true_rms > 20e-6  # the effect is there, and the figure sees it
        assert u["rms_m"] == pytest.approx(true_rms, rel=0.3)
    # the model file carries it, and the correction table states it beside its 1-sigma
    lines: list[str] = []
    table, _ = make_table(model, target_error_m=20e-6, log=lines.append)
    assert table.meta["model_unexplained"]["rms_m"] == pytest.approx(u["rms_m"])
    assert any(ln.strip().startswith("not in that 1-sigma") for ln in lines)
    # a hand-edited entry is recomputed from the stored held-out figures, never copied
    model.info["unexplained"]["rms_m"] = 1.0
    model.info["heldout_rms_ci95_m"] = "garbage"
    t2, _ = make_table(model, target_error_m=20e-6)
    assert t2.meta["model_unexplained"]["rms_m"] == pytest.approx(u["rms_m"])
    assert t2.meta["model_unexplained"]["upper_m"] is None


def test_any_stored_value_gives_a_finite_figure_or_none():
    """Whatever a hand-edited model file holds in its held-out fields, `export` states a finite
    figure or none: never an exception."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st
    from jsonfuzz import JSON

    from workcell.export.build import model_unexplained

    big = st.floats(allow_nan=True, allow_infinity=True)

    @settings(max_examples=300, deadline=None, suppress_health_check=list(HealthCheck))
    @given(
        rms=JSON | big,
        ci=JSON | st.lists(big, min_size=2, max_size=2),
        floor=JSON | big,
        u=st.one_of(st.just("dict"), JSON),
        ids=JSON | st.lists(st.integers(), max_size=3),
        ho=st.one_of(st.just("dict"), JSON),
    )
    def check(rms, ci, floor, u, ids, ho):
        info = {"heldout_rms_m": rms, "heldout_rms_ci95_m": ci}
        info["unexplained"] = {"floor_m": floor} if u == "dict" else u
        info["heldout_outliers"] = (
            {"heldout_rms_m": rms, "heldout_rms_ci95_m": ci, "floor_m": floor, "pose_ids": ids}
            if ho == "dict"
            else ho
        )
        model = type("M", (), {"info": info})()
        for out in (model_unexplained(model), model_unexplained(model, without_outliers=True)):
            if out is not None:
                assert np.isfinite(out["rms_m"]) and out["rms_m"] >= 0.0
                up = out["upper_m"]
                assert up is None or (np.isfinite(up) and up >= 0)

    check()


def test_an_outlier_reading_among_the_heldout_poses_is_named_and_set_aside(tmp_path):
    """One bad reading at a held-out pose (0.46 mm off, its recorded sigma inflated as a
    disagreeing reading does) makes the held-out RMS several times the model's error. `fit`
    names that pose and gives the figures without it: with the training poses untouched the
    model is the same, so they must equal the clean recording's figures over the other poses."""
    from sim_devices.cell import sim_cell
    from workcell.campaign.executor import CampaignConfig
    from workcell.campaign.run import run_campaign
    from workcell.estimation.fitting import fit_dataset
    from workcell.estimation.models import error_stats
    from workcell.recording.dataset import Dataset

    _, robot, tracker, cell = sim_cell("ur5e", "none", 1, beam_break_prob=0.0, outlier_prob=0.0)
    path = tmp_path / "c.mcap"
    cfg = CampaignConfig(readings_per_pose=2, settle_s=0.2)
    run_campaign(robot, tracker, cell, path, poses=80, seed=1, config=cfg)
    clean = Dataset.from_recording(path)
    model, rep = fit_dataset(clean, method="dh")
    assert rep["heldout_outliers"] is None  # nothing to name in a clean recording
    # the model file carries the joint range it was fitted on (export compares its nodes)
    train, _ = clean.holdout_split(0.25)
    qt = clean.q[train]
    assert model.info["joint_range_rad"] == np.stack([qt.min(0), qt.max(0)], 1).tolist()

    bad = Dataset.from_recording(path)
    _, test = bad.holdout_split(0.25)
    k = int(test[3])
    bad.p_tracker = bad.p_tracker.copy()
    bad.sigma_m = bad.sigma_m.copy()
    bad.p_tracker[k] += np.array([0.0004, -0.0001, 0.0002])
    bad.sigma_m[k] = 2.5e-4
    model_b, rep_b = fit_dataset(bad, method="dh")
    assert np.allclose(model_b.predict(clean.q), model.predict(clean.q), atol=1e-9)
    assert rep_b["heldout_rms_m"] > 3 * rep["heldout_rms_m"]
    ho = rep_b["heldout_outliers"]
    assert ho["pose_ids"] == [int(bad.pose_id[k])]
    rest = clean.subset(np.array([i for i in test if i != k]))
    want = error_stats(model.predict(rest.q), rest.p_tracker)["rms_m"]
    assert ho["heldout_rms_m"] == pytest.approx(want, rel=1e-9)
    assert ho["unexplained"]["upper_m"] < 15e-6
    # the model file keeps both figures and the correction table states both
    from workcell.estimation.fitting import keep_in_model
    from workcell.export.build import make_table

    keep_in_model(model_b, bad, rep_b)
    lines: list[str] = []
    table, _ = make_table(model_b, target_error_m=20e-6, log=lines.append)
    w = table.meta["model_unexplained_without_outliers"]
    assert w["pose_ids"] == ho["pose_ids"]
    assert w["rms_m"] == pytest.approx(ho["unexplained"]["rms_m"], abs=1e-12)
    assert w["upper_m"] == pytest.approx(ho["unexplained"]["upper_m"], rel=1e-9)
    # with the outlier, what the model leaves unexplained lies beyond the upper end of the
    # clean figure's 95 % interval (26.5 against 11.1 um here; the outlier pose's inflated sigma
    # raises the floor too, so the excess over it is far smaller than the outlier). Until the
    # simulator's encoder noise got its own stream (2026-11-26) this asked for 3x that upper
    # end, an arbitrary factor the new draw misses (2.4x); the claim is "beyond the interval".
    assert table.meta["model_unexplained"]["rms_m"] > max(w["upper_m"], 1e-6)
    assert table.meta["model_unexplained"]["upper_m"] > 10 * w["upper_m"]
    assert any(f"outlier pose(s) {ho['pose_ids'][0]} " in ln for ln in lines), lines
    keep_in_model(model_b, clean, rep)  # refitted without outliers: the old entry goes
    assert "heldout_outliers" not in model_b.info
    t2, _ = make_table(model_b, target_error_m=20e-6)
    assert "model_unexplained_without_outliers" not in t2.meta


def test_the_export_headers_give_the_combined_uncertainty_the_readme_advises():
    """The README advised adding what the model leaves unexplained to the 1-sigma in
    quadrature, "as the reports advise"; no output said so (metrology audit, 2026-11-29)."""
    from workcell.export.table import unexplained_lines

    meta = {
        "median_std_m": 4e-6,
        "model_unexplained": {"rms_m": 3e-6, "upper_m": 1.08e-5, "floor_m": 1e-5},
    }
    lines = unexplained_lines(meta)
    assert lines[1] == (
        "for a target's uncertainty add the two in quadrature (3-D): median "
        "sqrt(1-sigma^2 + unexplained^2) = 5e-06 m, 1.15e-05 m with the upper end of the "
        "unexplained"
    ), lines
    assert len(unexplained_lines({**meta, "median_std_m": None})) == 1  # no 1-sigma: no sum
