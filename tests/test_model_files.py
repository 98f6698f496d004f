"""Malformed model files (hand-edited, cut short, wrong types): one line, exit 2, no traceback."""

from __future__ import annotations

import copy
import json

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jsonfuzz import replace_any_field

from workcell.cli import main
from workcell.errors import UserError
from workcell.estimation.models import load_model


@pytest.fixture(scope="module")
def dh_model(tmp_path_factory):
    d = tmp_path_factory.mktemp("models")
    rec, model = d / "c.mcap", d / "m.json"
    argv = ["campaign", "--robot", "sim", "--tracker", "sim", "--poses", "30", "--out", str(rec)]
    assert main(argv) == 0
    assert main(["fit", str(rec), "--method", "dh", "--out", str(model)]) == 0
    return json.loads(model.read_text())


@settings(max_examples=50, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_any_field_replaced_loads_or_is_refused_in_one_line(dh_model, tmp_path_factory, data):
    m = copy.deepcopy(dh_model)
    replace_any_field(data, m)
    f = tmp_path_factory.mktemp("mf") / "m.json"
    f.write_text(json.dumps(m))
    try:
        model = load_model(f)
    except UserError as e:
        assert "\n" not in str(e) and str(f) in str(e)
    else:
        assert model.predict is not None


@pytest.mark.parametrize(
    "edit",
    [
        lambda m: m.__setitem__("theta", m["theta"][:10]),
        lambda m: m.__setitem__("base_ref", []),
        lambda m: m.__setitem__("robot", 5),
        lambda m: m.__setitem__("method", ["dh"]),
        lambda m: m.__setitem__("info", [1]),
    ],
    ids=["theta cut short", "empty base_ref", "robot not a string", "method a list", "info list"],
)
def test_export_refuses_a_malformed_model_in_one_line(dh_model, tmp_path, capsys, edit):
    m = copy.deepcopy(dh_model)
    edit(m)
    f = tmp_path / "m.json"
    f.write_text(json.dumps(m))
    out = tmp_path / "t.json"
    rc = main(["export", str(f), "--format", "table", "--out", str(out), "--spacing", "0.2"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("workcell export: error: "), err
    assert not out.exists()


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda m: m["nominal_dh"].__setitem__("a", [x * 1e3 for x in m["nominal_dh"]["a"]]),
         "nominal_dh a.* millimetres"),
        (lambda m: m["nominal_dh"].__setitem__("alpha", [57.3 * x for x in m["nominal_dh"]["alpha"]]),
         "nominal_dh alpha.* degrees"),
        (lambda m: m["info"].__setitem__("nominal_tool_m", [0, 0, 60.0]), "nominal_tool_m .*60 m"),
        (lambda m: m["theta"].__setitem__(38, 60.0), "fitted SMR offset"),
    ],
    ids=["a in mm", "alpha in degrees", "tool in mm", "fitted SMR in mm"],
)  # fmt: skip
def test_a_model_in_millimetres_or_degrees_is_refused_on_loading(dh_model, tmp_path, edit, match):
    """A model file whose nominal chain or SMR is in mm or degrees used to load, then fail in
    export as "no finite correction ... shrink the volume" or write a 60 m TCP."""
    m = copy.deepcopy(dh_model)
    edit(m)
    f = tmp_path / "m.json"
    f.write_text(json.dumps(m))
    with pytest.raises(UserError, match=match) as e:
        load_model(f)
    assert "\n" not in str(e.value)


def test_a_saved_model_states_the_units_and_frames_of_its_arrays(dh_model, tmp_path):
    from workcell.estimation.models import model_fingerprint, save_model
    from workcell.kinematics.chain import PARAM_NAMES

    c = dh_model["conventions"]
    assert set(c["theta_units"]) == set(PARAM_NAMES)
    assert c["theta_units"]["a2"] == "m" and c["theta_units"]["alpha2"] == "rad"
    assert "tracker_T_base" in c["base_ref"] and c["parameter_frames"]
    f = tmp_path / "m.json"
    f.write_text(json.dumps(dh_model))
    m = load_model(f)
    assert model_fingerprint(load_model(save_model(m, tmp_path / "m2.json"))) == model_fingerprint(
        m
    )


def test_the_fingerprint_of_a_model_is_that_of_earlier_versions():
    """Tables name the model they were built from by its fingerprint. On 2026-11-27 the model
    file's derived tracker_T_base gained its 1-sigma, which changed every fingerprint: every
    earlier table was refused as 'built from another model' of its own recording (bad-input
    audit). The hash below was computed by the code before that change (d9a59a2)."""
    import numpy as np

    from workcell.estimation.dh import DHModel
    from workcell.estimation.models import model_fingerprint
    from workcell.kinematics.chain import pack
    from workcell.kinematics.robots import UR5E

    th = pack(UR5E.dh, tool=(0.0, 0.0, 0.06))
    th[:24] += np.linspace(-3e-4, 3e-4, 24)
    th[30:36] += np.array([1e-3, -2e-3, 5e-4, 2e-3, -1e-3, 3e-3])
    ref = np.eye(4)
    ref[:3, 3] = (2.0, -0.5, -0.3)
    cov = np.diag(np.linspace(1e-10, 4e-10, 39))
    m = DHModel(robot_model="ur5e", nominal_dh=UR5E.dh, theta=th, base_ref=ref, cov=cov,
                free=np.ones(39, bool), info={})  # fmt: skip
    assert "translation_std_m" in m.to_dict()["tracker_T_base"]  # the file carries the std
    assert model_fingerprint(m) == (
        "d4d2620b038799c5be08fd4a6087a1ef5968583712c43a920789c3c79e49acf6"
    )
