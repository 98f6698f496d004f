"""`workcell fit --method dh --bounds`: what the default bounds hold, and saying when bounds hold.

The audit of 2026-11-26: `--bounds default` held series B's SMR (15.8 mm nearer the flange than
declared) at its +-10 mm bound and a4 at its +-2 mm one, doubling the held-out RMS (946 against
446 um) without a word, then noted the clipped SMR with a std and recommended declaring it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from simdata import dh_error_dataset

from workcell.cli import main
from workcell.errors import UserError
from workcell.estimation.bounded import default_bounds, fit_dh_bounded
from workcell.estimation.dh import nominal_theta
from workcell.estimation.fitting import fit_dataset
from workcell.kinematics.chain import IDX, PARAM_NAMES
from workcell.recording.dataset import Dataset

DATA = Path(__file__).resolve().parents[2] / "shared/data/ur10-leica"
REAL_B = DATA / "series_B_joint_configurations.mcap"
REAL_D = DATA / "series_D_iso_cubes.mcap"
SMR_OFF_M = 0.015  # declared SMR this much too long, as on the real UR10 (15.8 mm)


@pytest.fixture(scope="module")
def sim_ds():
    """40 random poses of a simulated UR5e with DH errors whose declared SMR offset is 15 mm too
    long (the truth's SMR is nearer the flange), tracker noise."""
    return dh_error_dataset(40, seed=5, declared_smr_shift_m=SMR_OFF_M)[1]


def test_default_bounds_are_on_the_dh_corrections_only(sim_ds):
    """DH corrections +-5 mm / +-10 mrad (manufacturing errors with a margin); the tracker
    placement (base) and the declared SMR offset (tool) are no manufacturing tolerance: free."""
    th = nominal_theta(sim_ds)
    lo, hi = default_bounds(th)
    for n in PARAM_NAMES:
        i = IDX[n]
        if n.startswith(("base_", "tool_")):
            assert lo[i] == -np.inf and hi[i] == np.inf, n
        elif n[0] in "ad" and n[1:].isdigit():
            assert hi[i] - th[i] == pytest.approx(5e-3) and th[i] - lo[i] == pytest.approx(5e-3)
        else:
            assert hi[i] - th[i] == pytest.approx(10e-3), n
    # the real UR10's unbounded corrections (series B and D) sit well inside: a2 -1.29 mm,
    # alpha3 -1.9 mrad, theta4_offset -1.1 mrad
    for n, d in (("a2", -1.29e-3), ("alpha3", -1.9e-3), ("theta4_offset", -1.1e-3)):
        assert lo[IDX[n]] < th[IDX[n]] + 2.5 * d and th[IDX[n]] + 2.5 * d < hi[IDX[n]]


def test_default_bounds_let_a_wrong_declared_smr_be_found(sim_ds):
    """A declared SMR 15 mm off: `--bounds default` gives the unbounded fit, and the SMR note."""
    _, free_rep = fit_dataset(sim_ds, method="dh", bounds=None)
    _, rep = fit_dataset(sim_ds, method="dh", bounds="default")
    assert rep["heldout_rms_m"] == pytest.approx(free_rep["heldout_rms_m"], rel=1e-6)
    smr = rep["smr_change"]
    assert smr is not None and smr["change_m"] == pytest.approx(SMR_OFF_M, abs=1e-3)
    b = rep["bounds"]
    assert b["at_bound"] == [] and b["heldout_rms_unbounded_m"] is None
    assert "none holds a parameter" in b["line"]
    assert free_rep["bounds"] is None


def test_active_bounds_are_said_with_the_unbounded_rms_and_no_smr_std(sim_ds, capsys):
    from workcell.commands.fit import print_report

    spec = {"mode": "delta", "bounds": {"tool_z": [-3e-3, 3e-3]}}
    _, free_rep = fit_dataset(sim_ds, method="dh", bounds=None)
    model, rep = fit_dataset(sim_ds, method="dh", bounds=spec)
    b = rep["bounds"]
    # the SMR held 12 mm from where it is; other (default-bounded) corrections may follow it
    at = {a["name"]: a for a in b["at_bound"]}
    assert at["tool_z"]["side"] == "lower" and "tool_z" in model.info["active_bounds"]
    assert at["tool_z"]["value"] == pytest.approx(sim_ds.tool_offset_m[2] - 3e-3, abs=1e-12)
    assert at["tool_z"]["bound"] == at["tool_z"]["value"]
    assert b["heldout_rms_unbounded_m"] == pytest.approx(free_rep["heldout_rms_m"], rel=1e-9)
    assert rep["heldout_rms_m"] > 2 * b["heldout_rms_unbounded_m"]
    # no std for the held value, and no SMR note recommending the clipped offset with a std
    assert rep["parameters"]["tool_z"]["std"] is None
    assert rep["smr_change"] is None and free_rep["smr_change"] is not None
    rep["model"] = None
    print_report(rep)
    out = " ".join(capsys.readouterr().out.split())
    assert "note: the fitted SMR" not in out
    ratio = rep["heldout_rms_m"] / b["heldout_rms_unbounded_m"]
    held = ", ".join(f"{a['name']} ({a['side']})" for a in b["at_bound"])
    n = len(b["at_bound"])
    assert (
        f"bounds (a dict): {n} parameter{'s' if n > 1 else ''} held at a bound, not estimated "
        f"there (no std): {held}; held-out RMS {rep['heldout_rms_m'] * 1e6:.1f} um with the "
        f"bounds, {b['heldout_rms_unbounded_m'] * 1e6:.1f} um without (`--method dh` alone): "
        f"the bounds make the fit {ratio:.2f}x worse" in out
    )
    for a in b["at_bound"]:
        assert rep["parameters"][a["name"]]["std"] is None
    assert "the SMR offset (tool_z) is held by its bound: fit without --bounds" in out
    json.dumps(rep)  # the report stays JSON


def test_a_qp_that_does_not_converge_is_warned_about(sim_ds, capsys, monkeypatch):
    import workcell.estimation.bounded as bounded
    from workcell.commands.fit import print_report

    iterate = bounded._iterate_qp

    def one_step(ds, keep, w, theta, base_ref, free, lo, hi, max_iter, xtol):
        return iterate(ds, keep, w, theta, base_ref, free, lo, hi, 1, xtol)

    monkeypatch.setattr(bounded, "_iterate_qp", one_step)
    _, rep = fit_dataset(sim_ds, method="dh", bounds="default")
    assert rep["extra"]["converged"] is False and rep["bounds"]["converged"] is False
    rep["model"] = None
    print_report(rep)
    out = " ".join(capsys.readouterr().out.split())
    assert "warning: the bounded QP stopped after" in out and "LDDMM" not in out


def test_empty_bounds_is_refused(sim_ds, capsys, tmp_path):
    with pytest.raises(UserError, match="--bounds is empty"):
        fit_dataset(sim_ds, method="dh", bounds="")
    capsys.readouterr()
    argv = ["fit", str(tmp_path / "missing.mcap"), "--bounds", "", "--out", str(tmp_path / "m")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--bounds is empty" in err[0], err


@pytest.mark.skipif(not REAL_D.exists(), reason="shared real data not present")
def test_a_bound_on_a_parameter_not_estimated_is_warned_about(tmp_path, capsys):
    """Series D: d2 is dependent ({d2, d3, d4}, d4 kept): its bound does nothing; one line says
    so. D's SMR is barely identifiable (tool_z std 27 mm): no bound holds it either."""
    path = tmp_path / "b.json"
    path.write_text(json.dumps({"mode": "delta", "bounds": {"d2": [-1e-3, 1e-3]}}))
    capsys.readouterr()
    argv = ["fit", str(REAL_D), "--bounds", str(path), "--out", str(tmp_path / "m.json")]
    assert main([*argv, "--json"]) == 0
    cap = capsys.readouterr()
    rep = json.loads(cap.out)
    warn = [x for x in cap.err.splitlines() if "d2" in x]
    assert warn == [
        f"warning: --bounds {path} bounds d2, which the fit does not estimate (dependent or "
        "fixed at nominal): that bound has no effect"
    ]
    assert rep["bounds"]["not_estimated"] == ["d2"] and rep["bounds"]["at_bound"] == []
    assert rep["smr_change"] is None  # as the unbounded fit: tool_z is known only to 27 mm
    assert rep["heldout_rms_m"] == pytest.approx(396.3e-6, abs=0.5e-6)


@pytest.mark.skipif(not REAL_B.exists(), reason="shared real data not present")
def test_real_series_b_default_bounds_hold_nothing():
    """Series B with `--bounds default`: the unbounded fit (446.5 um held out, SMR 93.2 mm),
    where the old +-10 mm tool bound gave 945.9 um with tool_z and a4 at their bounds."""
    ds = Dataset.from_recording(REAL_B)
    _, rep = fit_dataset(ds, method="dh", bounds="default")
    assert rep["heldout_rms_m"] == pytest.approx(446.5e-6, abs=0.5e-6)
    assert rep["smr_change"]["fitted_m"][2] == pytest.approx(0.0932, abs=0.2e-3)
    p = rep["parameters"]
    assert p["a4"]["value"] - p["a4"]["nominal"] == pytest.approx(0.05e-3, abs=0.1e-3)
    assert rep["bounds"]["at_bound"] == []


def test_bounded_fit_records_what_it_ignored(sim_ds):
    # loose but plausible (a bound reaching beyond 0.1 m of nominal is refused as millimetres)
    spec = {"mode": "delta", "bounds": {"d2": [-0.05, 0.05], "a2": [-0.05, 0.05]}}
    m = fit_dh_bounded(sim_ds, bounds=spec)
    assert m.info["bounds_not_estimated"] == ["d2"]
    assert fit_dh_bounded(sim_ds, bounds="default").info["bounds_not_estimated"] == []


def test_ros_yaml_marks_a_value_held_at_a_bound_as_not_estimated(sim_ds, tmp_path):
    """The ROS calibration YAML wrote a value a bound held (`forearm.x`, a2) with "+- 0 m", as
    if measured to the nanometre: now it says the bound set it, in the line and the header."""
    from workcell.export.ros_yaml import export_ros_yaml

    spec = {"mode": "delta", "bounds": {"a2": [-1e-7, 1e-7]}}
    model, _ = fit_dataset(sim_ds, method="dh", bounds=spec)
    assert "a2" in model.info["active_bounds"]
    p, info = export_ros_yaml(model, tmp_path / "cal.yaml")
    text = p.read_text()
    link = None
    for line in text.splitlines():
        if line.startswith("  ") and not line.startswith("    "):
            link = line.strip().rstrip(":")
        elif link == "forearm" and line.strip().startswith("x:"):
            assert line.endswith("# fixed, not estimated (a2 at its bound)"), line
            break
    else:
        raise AssertionError("no forearm x line")
    assert "held at a bound of the bounded fit (`fit --bounds`): a2" in text
    assert info["kinematics_fixed"]["forearm"]["x"] == ["a2 (at its bound)"]
