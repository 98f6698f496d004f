"""A pose measured again (a reference pose, `campaign --reference-every`) is one pose: it counts
once towards the poses a fit or a diagnosis needs, and diagnose's cross-validation keeps its
repeats in one fold. Found by an audit on 2026-11-26: the count rounded the measured joints at
1 urad, below the encoders' 2 urad noise, and the folds were drawn per sample."""

import numpy as np

from workcell.cli import main
from workcell.estimation.discovery import _fold_ids
from workcell.recording.dataset import distinct_poses


def test_a_pose_measured_again_with_encoder_noise_counts_once():
    rng = np.random.default_rng(0)
    q = rng.uniform(-3, 3, (6, 6))
    again = q[[0, 0, 0, 3, 3]] + rng.normal(0, 2e-6, (5, 6))  # the encoders' noise
    assert distinct_poses(np.r_[q, again]) == 6
    near = q[:1] + 5e-4  # another pose, 0.5 mrad away on every joint
    assert distinct_poses(np.r_[q, again, near]) == 7


def test_folds_keep_a_poses_repeats_together_and_are_unchanged_without_repeats():
    n, k, seed = 40, 5, 3
    old = np.random.default_rng(seed + 17).permutation(n) % k  # the folds before, per sample
    np.testing.assert_array_equal(_fold_ids(np.arange(n), k, seed), old)
    groups = np.r_[np.arange(n), [0, 0, 7, 7, 7]]  # poses 0 and 7 measured again
    f = _fold_ids(groups, k, seed)
    assert len(set(f[groups == 0])) == 1 and len(set(f[groups == 7])) == 1
    np.testing.assert_array_equal(f[:n], old)  # the first measurements keep their folds


def test_fit_refuses_a_recording_whose_repeats_made_up_the_pose_count(tmp_path, capsys):
    """The plan's first pose measured again after every second pose: with 40 % held out, the
    fit trained on 14 samples of 6 poses and printed a held-out RMS of 61.6 mm, exit 0."""
    rec = tmp_path / "r.mcap"
    argv = ["campaign", "--effects", "none", "--seed", "3", "--poses", "16"]
    assert main([*argv, "--reference-every", "2", "--readings", "2", "--out", str(rec)]) == 0
    capsys.readouterr()
    assert main(["fit", str(rec), "--holdout", "0.4", "--out", str(tmp_path / "m.json")]) == 2
    err = capsys.readouterr().err
    assert "distinct joint configurations" in err and "at least 12 different poses" in err
    assert not (tmp_path / "m.json").exists()
