"""Mends of a report-only fuzz audit of every input file (2026-11-29, later session): hand
edits that were read as good input and gave plausible numbers (exit 0)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_export_table import DOWN, HI, LO, make_model

from workcell.errors import UserError
from workcell.estimation.models import load_model, save_model
from workcell.export.correction import Corrector, nominal_for
from workcell.export.table import build_table, load_table


@pytest.fixture(scope="module")
def table_pair(tmp_path_factory):
    m = make_model(5)
    tab = build_table(Corrector(m, nominal_for(m)), LO, HI, [DOWN], spacing_m=0.1, n_check=20)
    d = tmp_path_factory.mktemp("pair")
    pj, pc = tab.save(d / "t")
    return pj, pc


def _copy(pair, tmp_path):
    pj, pc = pair
    (tmp_path / "t.json").write_bytes(pj.read_bytes())
    (tmp_path / "t.csv").write_bytes(pc.read_bytes())
    return tmp_path / "t.json", tmp_path / "t.csv"


def _edit_csv_cell(pc, column: str, row: int, value: str) -> None:
    lines = pc.read_text().splitlines(keepends=True)
    head = next(i for i, x in enumerate(lines) if not x.startswith("#"))
    cols = lines[head].strip().split(",")
    cells = lines[head + 1 + row].rstrip("\n").split(",")
    cells[cols.index(column)] = value
    lines[head + 1 + row] = ",".join(cells) + "\n"
    pc.write_text("".join(lines))


def test_a_csv_edited_beside_a_json_without_its_sha_is_refused(table_pair, tmp_path):
    """The JSON's `csv_sha256` removed and one node's rz in the CSV changed by 2 mrad:
    `validate --table` passed with the untouched table's figures. Now the rows are compared."""
    pj, pc = _copy(table_pair, tmp_path)
    d = json.loads(pj.read_text())
    del d["csv_sha256"]
    pj.write_text(json.dumps(d))
    load_table(pj)  # untouched: one table
    _edit_csv_cell(pc, "rz", 3, "0.002")
    with pytest.raises(UserError, match=r"t.csv and t.json are not one table: .*node row 4's rz"):
        load_table(pj)


def test_a_json_edited_beside_its_csv_is_refused(table_pair, tmp_path):
    """JSON `delta_m` halved (the audit: x3) beside the CSV it was written with (its sha256 still matches): a
    verdict on corrections the controller never reads."""
    pj, pc = _copy(table_pair, tmp_path)
    d = json.loads(pj.read_text())
    d["delta_m"] = (np.asarray(d["delta_m"]) * 0.5).tolist()
    pj.write_text(json.dumps(d))
    with pytest.raises(UserError, match=r"not one table: .*dx_m: 0.00101"):
        load_table(pj)


def test_a_spreadsheets_shorter_numbers_are_still_the_table(table_pair, tmp_path):
    """A CSV re-written with 12 significant digits (a spreadsheet) is the same table."""
    pj, pc = _copy(table_pair, tmp_path)
    d = json.loads(pj.read_text())
    del d["csv_sha256"]
    pj.write_text(json.dumps(d))
    out = []
    for line in pc.read_text().splitlines():
        if line.startswith("#") or line.startswith("orientation"):
            out.append(line)
        else:
            out.append(",".join(f"{float(x):.12g}" for x in line.split(",")))
    pc.write_text("\n".join(out) + "\n")
    assert load_table(pj).shape


def test_a_key_given_twice_in_a_model_or_table_is_refused(table_pair, tmp_path):
    """A model with "theta" given twice was read with the later one (4 mm on a2), and exported
    without a word; the envelope and bounds files already refused a key given twice."""
    m = make_model(6)
    p = save_model(m, tmp_path / "m.json")
    text = p.read_text().rstrip()
    assert text.endswith("}")
    theta = json.loads(text)["theta"]
    p.write_text(text[:-1] + f', "theta": {json.dumps(theta)}}}')
    with pytest.raises(UserError, match=r"the key 'theta' is given twice"):
        load_model(p)
    pj, _ = _copy(table_pair, tmp_path)
    text = pj.read_text().rstrip()
    pj.write_text(text[:-1] + ', "format": "x"}')
    with pytest.raises(UserError, match=r"the key 'format' is given twice"):
        load_table(pj)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A dh and a gp model of 40 simulated poses, as `workcell fit` saves them."""
    from simdata import dh_error_dataset

    from workcell.estimation.fitting import fit_dataset, keep_in_model

    _, ds = dh_error_dataset(40, seed=3)
    d = tmp_path_factory.mktemp("fitted")
    out = {}
    for method in ("dh", "gp"):
        model, report = fit_dataset(ds, method=method, holdout=0.25)
        keep_in_model(model, ds, report)
        out[method] = json.loads(save_model(model, d / f"{method}.json").read_text())
    return out


def _write(tmp_path, name, d):
    p = tmp_path / name
    p.write_text(json.dumps(d))
    return p


def test_a_held_out_rms_outside_its_own_interval_is_refused(fitted, tmp_path):
    """info.heldout_rms_m set to 0.157 m beside its interval of ~0.1 mm: exported as "157000 um
    above the noise floor", and `envelope --model` advised an 18.8 m margin."""
    d = json.loads(json.dumps(fitted["dh"]))
    lo, hi = d["info"]["heldout_rms_ci95_m"]
    assert lo <= d["info"]["heldout_rms_m"] <= hi
    load_model(_write(tmp_path, "ok.json", d))
    d["info"]["heldout_rms_m"] = 0.157
    with pytest.raises(UserError, match=r"heldout_rms_m 0.157 m lies outside its own 95 %"):
        load_model(_write(tmp_path, "edited.json", d))


def test_gp_training_joints_in_degrees_or_mismatched_arrays_are_refused(fitted, tmp_path):
    """X x 57.3 (degrees) was read, and the GP's part of the correction vanished from the
    exported table (0.893 mm, the dh table's, for the GP's 0.914); one alpha row dropped gave a
    matmul error's text."""
    load_model(_write(tmp_path, "ok.json", fitted["gp"]))
    deg = json.loads(json.dumps(fitted["gp"]))
    deg["X"] = (np.degrees(np.asarray(deg["X"]))).tolist()
    with pytest.raises(UserError, match=r"joint angles in degrees\? the file wants radians"):
        load_model(_write(tmp_path, "deg.json", deg))
    short = json.loads(json.dumps(fitted["gp"]))
    short["alpha"] = short["alpha"][:-1]
    with pytest.raises(UserError, match=r"alpha has shape .* they do not belong together"):
        load_model(_write(tmp_path, "short.json", short))
    neg = json.loads(json.dumps(fitted["gp"]))
    neg["lengthscales"][0] = -abs(neg["lengthscales"][0])
    with pytest.raises(UserError, match=r"lengthscales must be finite and > 0"):
        load_model(_write(tmp_path, "neg.json", neg))


def test_replay_says_nothing_of_replacing_a_file_it_then_refuses_to_write(tmp_path, capsys):
    """`replay BAD --save X --force` printed "replacing X: (--force)" and then the recording's
    refusal: X was not replaced, and the first line was false (fit was mended for this)."""
    from workcell.cli import main

    bad = tmp_path / "empty.mcap"
    bad.write_bytes(b"")
    x = tmp_path / "notes.json"
    x.write_text('{"mine": 1}')
    capsys.readouterr()
    rc = main(["replay", str(bad), "--online", "ekf-ann", "--save", str(x), "--force"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "replac" not in err[0], err
    assert x.read_text() == '{"mine": 1}'


def test_joints_far_from_their_command_and_repeats_far_apart_are_noted():
    """Samples measured 1 rad from their commanded joints, and every pose written twice 3 mm
    apart, were fitted without a word (`info` showed the repeats; nothing said the arm missed
    its targets). Both are now notes every reading command prints; clean data has none."""
    from dataclasses import replace

    from simdata import dh_error_dataset

    _, ds = dh_error_dataset(20, seed=2)
    assert ds.suspect_sample_notes() == []
    qc = ds.q.copy()
    qc[:, 0] += 1.0
    (note,) = replace(ds, q_commanded=qc).suspect_sample_notes()
    assert note.startswith("20 of 20 samples were measured with joints more than 1 mrad from")
    assert "up to 1 rad, joint 1" in note and "did not reach its target" in note
    twice = ds.subset(np.r_[np.arange(20), np.arange(20)])
    twice = replace(
        twice, p_tracker=twice.p_tracker + np.r_[np.zeros((20, 3)), np.full((20, 3), 1.7e-3)]
    )
    (note,) = twice.suspect_sample_notes()
    assert note.startswith(
        "20 pose(s) measured again more than 10x the tracker's noise from their previous"
    ), note
    assert "the file holds a pose twice" in note
    # measured again within the noise: no note
    again = ds.subset(np.r_[np.arange(20), np.arange(20)])
    assert again.suspect_sample_notes() == []


def test_a_reference_pose_drifting_smoothly_is_not_a_moved_set_up():
    """A reference pose measured 40 times while it drifts 200 um (the arm warming: what
    `--reference-every` records) got the "set-up moved" note, judged by the distance from its
    first reading (a review); steps between consecutive readings are judged now, and a step
    still gives the note."""
    from dataclasses import replace

    from simdata import dh_error_dataset

    _, ds = dh_error_dataset(20, seed=2)
    idx = np.r_[np.arange(20), np.zeros(40, int)]
    ref = ds.subset(idx)
    p = ref.p_tracker.copy()
    p[20:, 0] += np.linspace(0.0, 200e-6, 40)  # smooth, 5 um a step
    t = np.r_[np.arange(20.0), 20.0 + np.arange(40.0)]
    drift = replace(ref, p_tracker=p, elapsed_s=t)
    assert drift.suspect_sample_notes() == []
    p2 = p.copy()
    p2[40:, 2] += 1e-3  # the tracker bumped half-way: a 1 mm step
    (note,) = replace(ref, p_tracker=p2, elapsed_s=t).suspect_sample_notes()
    assert "(pose 0: a step of 1000 um" in note and "the set-up or the arm moved" in note, note


def test_a_fixed_parameter_has_no_std_rather_than_zero(fitted, tmp_path):
    """`fit --json` gave a fixed parameter (d1, in the group {d1, base_tz}) "std 0.0", an exact
    value it is not; the ROS YAML already said no 1-sigma is given (metrology audit)."""
    params = load_model(_write(tmp_path, "m.json", fitted["dh"])).parameters()
    fixed = [n for n, v in params.items() if not v["estimated"]]
    assert fixed and all(params[n]["std"] is None for n in fixed), fixed
    assert all(v["std"] is not None for v in params.values() if v["estimated"])
