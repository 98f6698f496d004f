"""Hand edits of ekf-ann and lddmm model files that loaded with exit 0 and changed what the
model says (command-line audit of 2026-11-28): an ekf-ann `ann.u_scale` of 0 moved corrections
by up to 137 um; an lddmm `"on": "foo"` dropped the base's covariance from the 1-sigma (median
44.0 -> 33.6 um); an lddmm `lam_v` of -1 failed in numpy at the first 1-sigma, without the
file's name; a 7-entry `nominal_dh` beside a 6-joint fit was blamed on the targets. Each is
now refused at load, in one line naming the file and the field."""

from __future__ import annotations

import copy
import json

import pytest

from workcell.cli import main
from workcell.errors import UserError
from workcell.estimation.models import load_model


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("edits")
    rec = d / "c.mcap"
    argv = ["campaign", "--robot", "sim", "--tracker", "sim", "--poses", "30", "--out", str(rec)]
    assert main(argv) == 0
    assert main(["replay", str(rec), "--online", "ekf-ann", "--save", str(d / "e.json")]) == 0
    assert main(["fit", str(rec), "--method", "lddmm", "--out", str(d / "l.json")]) == 0
    return d, {m: json.loads((d / f"{m[0]}.json").read_text()) for m in ("ekf-ann", "lddmm")}


def _set(*path_value):
    *path, value = path_value

    def edit(doc):
        for k in path[:-1]:
            doc = doc[k]
        doc[path[-1]] = value

    return edit


def _u_scale_zero(doc):
    doc["ann"]["u_scale"][0] = 0.0


def _seventh_joint(doc):
    for k in ("a", "d", "alpha", "theta_offset"):
        doc["nominal_dh"][k].append(0.0)


@pytest.mark.parametrize(
    "method, edit, words",
    [
        ("ekf-ann", _u_scale_zero, "ann.u_scale[0] must be positive (rad), got 0"),
        ("ekf-ann", _set("ann", "u_scale", [1.0] * 5), "ann.u_scale must be 6 finite numbers"),
        ("ekf-ann", _set("ann", "out_scale_m", -1e-4), "ann.out_scale_m must be positive"),
        ("ekf-ann", _seventh_joint, "nominal_dh has 7 a, 7 d, 7 alpha, 7 theta_offset, not 6"),
        ("lddmm", _set("on", "foo"), "on must be 'dh' (the base this file holds), got 'foo'"),
        (
            "lddmm",
            _set("on", "nominal"),
            "on must be 'dh' (the base this file holds), got 'nominal'",
        ),
        ("lddmm", _set("lddmm", "lam_v", -1.0), "lddmm.lam_v and lam_w must be >= 0"),
        ("lddmm", _set("lddmm", "sigma_v", 0.0), "lddmm.sigma_v must be positive"),
        ("lddmm", _set("lddmm", "n_steps", 2.5), "lddmm.n_steps must be a whole number"),
    ],
    ids=[
        "u_scale 0",
        "u_scale short",
        "out_scale negative",
        "7-entry nominal_dh",
        "on foo",
        "on nominal over a dh base",
        "lam_v negative",
        "sigma_v 0",
        "n_steps 2.5",
    ],
)
def test_a_hand_edit_that_changes_the_model_is_refused_at_load(models, method, edit, words):
    d, docs = models
    doc = copy.deepcopy(docs[method])
    edit(doc)
    p = d / "edited.json"
    p.write_text(json.dumps(doc))
    with pytest.raises(UserError) as e:
        load_model(p)
    msg = str(e.value)
    assert words in msg and str(p) in msg and "\n" not in msg, msg


def test_the_files_as_written_load(models):
    d, _ = models
    for name in ("e.json", "l.json"):
        assert load_model(d / name) is not None


def test_an_edited_model_is_one_line_from_export(models, capsys, tmp_path):
    d, docs = models
    doc = copy.deepcopy(docs["ekf-ann"])
    _u_scale_zero(doc)
    p = tmp_path / "e.json"
    p.write_text(json.dumps(doc))
    capsys.readouterr()
    rc = main(["export", str(p), "--format", "table", "--out", str(tmp_path / "t.json")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "u_scale[0] must be positive" in err[0], err
    assert not (tmp_path / "t.json").exists()
