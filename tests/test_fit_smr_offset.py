"""`fit` told the engineer to "declare the fitted offset and fit again" when the fitted SMR is
far from the declared one, but no command could: recordings are never modified and `fit` had
no option for it, so series B's correction table stayed at 23.5 mm corrections (refused at the
default 5 mm bound). Now `fit --smr-offset X,Y,Z` declares the SMR (the controller's TCP) for
the fit, and the note gives that command."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest

from workcell.cli import main

REAL_B = (
    Path(__file__).resolve().parents[2]
    / "shared/data/ur10-leica/series_B_joint_configurations.mcap"
)  # noqa: E501


def _fit(capsys, *argv) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = main(["fit", str(REAL_B), "--method", "dh", *argv])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.mark.skipif(not REAL_B.exists(), reason="the UR10 data is beside the repository")
def test_the_smr_note_gives_a_command_that_declares_the_fitted_offset(capsys, tmp_path):
    rc, out, _ = _fit(capsys, "--holdout", "0.3", "--out", str(tmp_path / "b.json"))
    assert rc == 0
    # the command is on a line of its own, with this fit's options, writing beside the model
    line = next((x for x in out.splitlines() if x.startswith("  workcell fit ")), None)
    assert line is not None, out[-800:]
    m = re.search(r"--smr-offset=(\S+)", line)
    assert "--holdout 0.3" in line and line.endswith(f"--out {tmp_path / 'b-smr.json'}"), line
    before = float(re.search(r"calibrated +held-out RMS +([\d.]+) um", out)[1])
    capsys.readouterr()
    rc = main([*shlex.split(line)[1:], "--json"])  # the printed command, as pasted
    out2 = capsys.readouterr().out
    assert rc == 0
    r = json.loads(out2)
    assert r["smr_declared"]["by"] == "--smr-offset"
    assert r["smr_declared"]["recording_m"] == [0.0, 0.0, 0.109]
    assert r["smr_declared"]["offset_m"] == pytest.approx([float(x) for x in m[1].split(",")])
    assert r.get("smr_change") is None  # the fitted SMR is now the declared one (within 1 mm)
    # and the fit is as well posed: declaring the 0.5 mm sideways components too freed the
    # wrist's dependent pairs (rank 25 -> 27, condition 118 -> 2.6e4, a5 11.4 +- 20.7 mm)
    rank, cond = re.search(r"identification +rank (\d+)/\d+, condition ([\d.e+]+)", out).groups()
    assert r["identifiability"]["rank"] == int(rank)
    assert r["identifiability"]["condition"] < 2 * float(cond)
    assert "its sideways components, 0.5" in " ".join(out.split())
    # the geometry fits as well: the base registration took up part of the offset, not the fit
    assert r["heldout_rms_m"] * 1e6 == pytest.approx(before, abs=1.0)
    model = json.loads((tmp_path / "b-smr.json").read_text())
    assert model["info"]["nominal_tool_m"] == pytest.approx(r["smr_declared"]["offset_m"])


@pytest.mark.parametrize(
    "value, match",
    [("0,0,109", "is 109 m from the flange"), ("0,0", "three numbers"), (" ", "is empty")],
)
def test_a_bad_smr_offset_is_one_line(capsys, tmp_path, value, match):
    rec = tmp_path / "none.mcap"  # refused before the recording is read
    capsys.readouterr()
    rc = main(["fit", str(rec), "--smr-offset", value, "--out", str(tmp_path / "m.json")])
    err = [x for x in capsys.readouterr().err.splitlines() if x.strip()]
    assert rc == 2 and len(err) == 1 and match in err[0], err


def test_the_kept_sideways_offset_carries_its_std():
    """The note's sideways figure had no std (uncertainty audit, 2026-11-27): it is the
    components' std along the sideways change, first order, like the note's own std."""
    import numpy as np

    from workcell.estimation.fitting import smr_change

    def par(v, nom, sd):
        return {"value": v, "nominal": nom, "std": sd}

    params = {
        "tool_x": par(3e-4, 0.0, 1e-4),
        "tool_y": par(4e-4, 0.0, 2e-4),
        "tool_z": par(0.125, 0.109, 5e-5),
    }
    c = smr_change(params)
    assert c["sideways_kept_m"] == pytest.approx(5e-4)
    assert c["sideways_std_m"] == pytest.approx(np.sqrt(0.36 * 1e-8 + 0.64 * 4e-8))
    assert c["fitted_std_m"] == [1e-4, 2e-4, 5e-5]
