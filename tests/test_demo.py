"""`workcell demo` end to end (what `make demo` runs): campaign, fits, diagnosis, correction.

The assertions are physical bounds, not the figures of one run: the nominal model is off by the
simulated DH errors (hundreds of um), a calibrated model cannot beat the tracker's noise by much
on held-out poses (that would be leakage), and a correction table applied to fresh targets must
do about as well as the model it came from.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from workcell.cli import main


@pytest.fixture(scope="module")
def demo_summary(tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("demo")
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
        assert main(["demo", "--json", "--out", str(out)]) == 0
    return json.loads(buf.getvalue())


def _finite(x) -> bool:
    if isinstance(x, dict):
        return all(_finite(v) for v in x.values())
    if isinstance(x, list | tuple):
        return all(_finite(v) for v in x)
    if isinstance(x, float):
        return math.isfinite(x)
    return True


def test_demo_numbers_hold_together(demo_summary):
    s = demo_summary
    assert _finite(s), "a NaN or infinity in the demo's JSON"
    floor = s["noise_floor_m"]
    assert 1e-6 < floor < 100e-6  # a laser tracker at 2-3 m: a few um to tens of um
    assert s["nominal_rms_m"] > 100e-6  # sigma 0.3 mm / 0.5 mrad DH errors on a 1 m arm
    cal = s["calibrated_rms_m"]
    assert set(cal) >= {"dh", "augmented"}
    for m, rms in cal.items():
        lo, hi = s["calibrated_rms_ci95_m"][m]
        assert lo <= rms <= hi, m
        # held out: no model beats the noise that is in the held-out readings themselves
        assert hi >= 0.8 * floor, f"{m}: held-out RMS interval {hi:.2e} below the noise floor"
    assert cal["dh"] < s["nominal_rms_m"] / 5
    # the realistic cell carries joint compliance under gravity: the diagnosis must add
    # something to the geometry and do better than it on the same held-out poses
    assert s["diagnosis"]["effects"], "the realistic cell's effects went unnamed"
    assert cal["augmented"] < cal["dh"]


def test_demo_correction_delivers_the_models_accuracy(demo_summary):
    c = demo_summary["correction"]
    assert c["before_rms_m"] > 10 * c["after_rms_m"]
    # fresh targets through the exported table: about what the model scored held out (the
    # table's interpolation and a new pose set may cost some, not a factor of two)
    assert c["after_rms_m"] < 2.0 * c["model_heldout_rms_m"]
    lo, hi = c["after"]["rms_ci95_m"]
    assert lo <= c["after_rms_m"] <= hi


def test_demo_models_and_recording_are_written(demo_summary):
    from workcell.estimation.models import load_model
    from workcell.recording.dataset import Dataset

    ds = Dataset.from_recording(demo_summary["recording"])
    assert len(ds) == demo_summary["poses"]
    for m, path in demo_summary["models"].items():
        assert Path(path).is_file(), m
        load_model(path)


def test_sim_cell_declares_what_an_operator_knows():
    """The cell setup carries the declared payload, not the simulator's true one, and the true
    link masses are not the catalogue's (the estimation computes gravity from the catalogue)."""
    from sim_devices.cell import sim_cell

    world, _, _, cell = sim_cell("ur5e", "realistic", 3)
    truth = world.truth
    assert cell.payload_kg == truth.declared_payload_kg
    assert cell.payload_kg != truth.payload_kg
    assert not np.allclose(truth.link_masses_kg, cell.spec.link_masses_kg)
    rel = truth.link_masses_kg / cell.spec.link_masses_kg - 1.0
    assert np.all(np.abs(rel) <= 0.3)
