"""Validation's closure: the first target measured again at the end shows how far the cell itself
moved during the validation (here the simulator's `tracker_drift`, a settling tracker stand),
and a drift beyond the tracker's noise and larger than the corrected RMS is a warning, since the
after figure then carries it. The truth is read only to score."""

import json

import numpy as np
import pytest
from test_export_validate import _truth_model

from sim_devices.cell import sim_cell
from sim_devices.truth import DEFAULT_MAGNITUDES, EFFECT_KINDS, parse_effects
from workcell.campaign.envelope import Guard, default_envelope
from workcell.cli import main
from workcell.export.build import make_table
from workcell.export.validate import (
    closure_line,
    closure_warning,
    robot_mover,
    run_validation,
    sim_measure,
    tracker_measure,
)


def _validate(v_m_per_s, *, tracker: bool, n: int = 12):
    """Closed loop on a cell with DH errors only (and a tracker drifting at `v_m_per_s`, tracker
    frame), with the table of its true geometry; measured by the simulated truth or, with
    `tracker`, by the simulated tracker (noisy, stated sigmas). (result, world, cell)."""
    eff = {} if v_m_per_s is None else {"tracker_drift": {"velocity_m_per_s": list(v_m_per_s)}}
    world, robot, trk, cell = sim_cell("ur5e", eff, 3, beam_break_prob=0.0, outlier_prob=0.0)
    table, corr = make_table(_truth_model(world.truth), target_error_m=5e-6)
    robot.connect()
    trk.connect()
    res = run_validation(
        corr.nominal,
        table,
        robot_mover(robot),
        tracker_measure(trk, 5) if tracker else sim_measure(world),
        n=n,
        seed=1,
        guard=Guard(default_envelope(cell.spec), cell.spec, cell.tool_m),
        q_start=world.joint_state()[0],
        clock=lambda: float(robot.state().t_s),
    )
    return res, world, corr


def test_tracker_drift_is_outside_the_library_and_only_on_request():
    assert "tracker_drift" not in EFFECT_KINDS and "tracker_drift" not in parse_effects("all")
    assert parse_effects("tracker_drift") == {"tracker_drift": DEFAULT_MAGNITUDES["tracker_drift"]}


def test_without_drift_the_closure_is_zero_and_no_warning():
    res, _, _ = _validate(None, tracker=False)
    c = res["closure"]
    assert c["displacement_m"] < 1e-9 and c["noise_m"] == 0.0 and not c["beyond_noise"]
    assert "warning" not in c
    assert c["elapsed_s"] > 30  # a dozen targets, two visits each, on the arm's clock


def test_the_closure_measures_the_drift_and_warns_when_it_exceeds_the_corrected_rms():
    v = np.array([2e-7, -1e-7, -3e-7])  # 0.37 um/s: a tripod settling fast
    res, world, corr = _validate(v, tracker=False)
    c = res["closure"]
    # scored against the simulator's drift over the closure's own interval, in base_ref axes
    R = corr.nominal.base_ref[:3, :3]
    want = R.T @ (v * c["elapsed_s"])
    np.testing.assert_allclose(c["displacement_base_m"], want, rtol=1e-6, atol=1e-9)
    assert c["displacement_m"] > res["after_rms_m"]  # the drift is the larger: a warning
    assert c["warning"] == closure_warning(c, res["after_rms_m"])
    assert "the after figure carries that drift" in c["warning"]
    line = closure_line(c)
    assert f"{c['displacement_m'] * 1e6:.1f} um from its first reading" in line
    assert f"{c['elapsed_s'] / 60:.1f} min later" in line


def test_a_small_drift_below_the_corrected_rms_is_reported_without_a_warning():
    res, _, _ = _validate(np.array([1e-9, 0.0, 0.0]), tracker=False)
    c = res["closure"]
    assert 0 < c["displacement_m"] < res["after_rms_m"] and c["beyond_noise"]
    assert "warning" not in c


@pytest.mark.parametrize("v, beyond", [(None, False), ((3e-6, 0.0, -3e-6), True)])
def test_with_the_tracker_the_closure_is_judged_against_its_stated_noise(v, beyond):
    """Measured by the (simulated) tracker, the closure carries the tracker's noise: without
    drift it stays inside it (no warning), a drift of ~0.5 mm is beyond it and warned about."""
    res, _, _ = _validate(v, tracker=True)
    c = res["closure"]
    assert c["noise_m"] > 5e-6  # two means, each at least the tracker's stated MPE / 4
    assert c["beyond_noise"] is beyond
    assert ("warning" in c) is beyond


def test_validate_cli_reports_the_closure(tmp_path, capsys):
    rec, model = tmp_path / "c.mcap", tmp_path / "m.json"
    argv = ["campaign", "--effects", "tracker_drift", "--seed", "5", "--poses", "16"]
    assert main([*argv, "--readings", "2", "--out", str(rec)]) == 0
    assert main(["fit", str(rec), "--holdout", "0", "--out", str(model)]) == 0
    capsys.readouterr()
    assert main(["validate", str(model), "--targets", "4"]) == 0
    out = capsys.readouterr().out
    assert "closure: target 0 measured again at the end" in out, out
    assert main(["validate", str(model), "--targets", "4", "--json"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    c = res["closure"]
    v = np.asarray(DEFAULT_MAGNITUDES["tracker_drift"]["velocity_m_per_s"])
    assert c["displacement_m"] == pytest.approx(np.linalg.norm(v) * c["elapsed_s"], rel=1e-3)
    assert (c.get("warning") is not None) == (c["displacement_m"] > res["after_rms_m"])
    if "warning" in c:
        assert c["warning"] in res["warnings"]


class _ScriptedTracker:
    """Readings from a list (position, stated sigma 5 um per axis); counts what it was asked."""

    def __init__(self, positions):
        self.positions, self.asked = list(positions), 0

    def measure(self):
        from workcell.drivers.protocols import TrackerReading

        self.asked += 1
        return TrackerReading(np.asarray(self.positions.pop(0), float), np.full(3, 5e-6))


P0 = np.array([1.5, 0.3, 0.2])
OFF = np.array([0.0, 1e-3, 0.0])  # a 1 mm bad reading


@pytest.mark.parametrize(
    "readings, script, asked, rejected",
    [
        (5, [P0, P0, P0 + OFF, P0, P0], 5, 1),  # one of five off: the median drops it
        (2, [P0, P0 + OFF, P0], 3, 1),  # two that disagree: a third, then the median
        (2, [P0, P0 + 2e-6], 2, 0),  # two that agree: nothing more asked
    ],
)
def test_a_bad_reading_does_not_enter_a_validation_measurement(readings, script, asked, rejected):
    """Validation averaged every reading: a 1 mm bad reading (the simulator's tracker makes them
    at 0.5 %) moved a 2-reading mean by 0.5 mm, and the closure warned of a 638 um drift on a
    cell that had none (the TUI's closed-loop check, 2 targets)."""
    trk = _ScriptedTracker(script)
    m = tracker_measure(trk, readings)
    p = m()
    assert np.linalg.norm(p - P0) < 2e-6
    assert trk.asked == asked and m.rejected == rejected
