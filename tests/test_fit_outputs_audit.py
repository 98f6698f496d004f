"""Outputs an audit of 2026-11-26 found misleading: a fit without held-out poses stored its
training figures as held-out ones, `fit --method gp --on nominal` was accepted and ignored, and
`validate` warmed the simulated arm to warm-up + 1 h instead of the recording's end."""

from __future__ import annotations

import json

import numpy as np
import pytest

from workcell.cli import main


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    d = tmp_path_factory.mktemp("fitout")
    rec = d / "c.mcap"
    argv = ["campaign", "--effects", "none", "--seed", "3", "--poses", "20", "--readings", "2"]
    assert main([*argv, "--out", str(rec)]) == 0
    return rec


def test_a_fit_without_held_out_poses_stores_no_held_out_figures(small, tmp_path, capsys):
    m = tmp_path / "m.json"
    assert main(["fit", str(small), "--holdout", "0", "--out", str(m), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["heldout_poses"] == 0 and rep["evaluated_on"] == "training poses (no hold-out)"
    info = json.loads(m.read_text())["info"]
    assert "heldout_rms_m" not in info and "unexplained" not in info
    assert info["heldout"].startswith("none")
    m2 = tmp_path / "m2.json"
    assert main(["fit", str(small), "--out", str(m2), "--json"]) == 0
    rep2 = json.loads(capsys.readouterr().out)
    assert rep2["evaluated_on"] == "held-out poses"
    info2 = json.loads(m2.read_text())["info"]
    assert info2["heldout_rms_m"] == pytest.approx(rep2["heldout_rms_m"])


def test_gp_on_nominal_is_refused_not_ignored(small, tmp_path, capsys):
    rc = main(
        ["fit", str(small), "--method", "gp", "--on", "nominal", "--out", str(tmp_path / "g")]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert rc != 0 and len(err) == 1 and "always sits on the DH fit" in err[0]


def test_validate_warms_the_simulated_arm_to_the_recordings_last_sample(small):
    from workcell.commands.validate import recorded_end_s
    from workcell.recording.reader import read_recording

    e = [s["elapsed_s"] for s in read_recording(small).samples]
    assert recorded_end_s(str(small)) == pytest.approx(max(e))
    assert recorded_end_s(None) is None
    assert recorded_end_s(str(small) + ".missing") is None
    assert np.isfinite(max(e)) and max(e) > 0


def test_the_combined_base_carries_its_propagated_std():
    """`fit` never stated tracker_T_base, the base `replay` says to compare, and the model file
    kept it without a std (uncertainty audit, 2026-11-27): base_pose_with_std propagates the
    parameter covariance to first order, which agrees with draws from it."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from workcell.kinematics.chain import base_pose_with_std, pack, tracker_T_base
    from workcell.kinematics.robots import UR5E

    rng = np.random.default_rng(1)
    th = pack(UR5E.dh, tool=(0.0, 0.0, 0.06))
    th[30:36] += rng.normal(0, 1e-3, 6)
    ref = np.eye(4)
    ref[:3, :3] = Rotation.from_rotvec([0.1, -0.2, 0.7]).as_matrix()
    ref[:3, 3] = (2.0, -0.5, 0.3)
    A = rng.normal(size=(39, 39)) * 3e-5
    cov = A @ A.T
    got = base_pose_with_std(th, ref, cov)
    T0 = np.asarray(tracker_T_base(th, ref))
    draws = rng.multivariate_normal(th, cov, size=3000)
    Ts = np.array([np.asarray(tracker_T_base(t, ref)) for t in draws])
    np.testing.assert_allclose(got["translation_std_m"], Ts[:, :3, 3].std(0), rtol=0.1)
    rot = Rotation.from_matrix(Ts[:, :3, :3] @ T0[:3, :3].T).as_rotvec()  # about tracker axes
    np.testing.assert_allclose(got["rotation_std_rad"], rot.std(0), rtol=0.1)
    assert "translation_std_m" not in base_pose_with_std(th, ref)  # no covariance, no std


def test_extra_figures_are_spelled_out_not_printed_as_python_dictionaries():
    """lddmm's text printed "cv_rms_m {'dh': 5.287564923947397e-05, ...}" under a first line
    giving the same as "52.9 um" (metrology audit, 2026-11-29)."""
    from workcell.commands.fit import extra_text

    assert extra_text("cv_rms_m", {"dh": 5.287564923947397e-05, "nominal": 8.9e-4}) == (
        "dh 52.88 um; nominal 890 um"
    )
    assert extra_text("cv_rms_ci95_m", {"dh": [4.7e-05, 6.05e-05]}) == "dh [47 um, 60.5 um]"
    assert extra_text("posterior_noise_std_m", 1.8546985266961562e-05) == "18.55 um"
    assert extra_text("converged", True) == "True" and extra_text("on", "dh") == "dh"
