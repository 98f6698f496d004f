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
