"""Malformed model files (hand-edited, cut short, wrong types): one line, exit 2, no traceback."""

from __future__ import annotations

import copy
import json

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

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


JSON = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**6), 10**6)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=5),
    lambda inner: (
        st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=4), inner, max_size=3)
    ),
    max_leaves=6,
)


def _paths(obj, prefix=()):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield (*prefix, k)
            yield from _paths(v, (*prefix, k))


@settings(max_examples=50, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_any_field_replaced_loads_or_is_refused_in_one_line(dh_model, tmp_path_factory, data):
    m = copy.deepcopy(dh_model)
    path = data.draw(st.sampled_from(sorted(_paths(m), key=str)), label="field")
    value = data.draw(JSON, label="value")
    obj = m
    for k in path[:-1]:
        obj = obj[k]
    obj[path[-1]] = value
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
