"""`--payload`: the payload at the flange as the operator declares it. A campaign on a controller
recorded 0 kg whatever the arm carried (workcell does not read the controller's setting), and
nothing said so (audit of the recording format, 2026-11-26 night)."""

from __future__ import annotations

import argparse

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from workcell.campaign.devices import open_cell, parse_payload, payload_warning
from workcell.cli import main
from workcell.errors import UserError
from workcell.kinematics.robots import UR5E
from workcell.recording.reader import read_recording


def test_parse_payload_reads_kilograms_and_metres_and_refuses_the_rest():
    assert parse_payload("1.5", UR5E) == (1.5, (0.0, 0.0, 0.0))
    assert parse_payload("2,0,0.01,0.05", UR5E) == (2.0, (0.0, 0.01, 0.05))
    for bad, words in (
        ("1500", "looks like grams"),
        ("6", "rated payload 5 kg"),
        ("-1", "negative"),
        ("1,0,0,50", "give it in metres"),
        ("1,2", "KG or KG,CX,CY,CZ"),
        ("nan", "KG or KG,CX,CY,CZ"),
        ("heavy", "KG or KG,CX,CY,CZ"),
    ):
        with pytest.raises(UserError, match=words) as ei:
            parse_payload(bad, UR5E)
        assert "\n" not in str(ei.value)


def _ns(**kw):
    base = dict(robot="ur://127.0.0.91", tracker="serial:///dev/null", model="ur5e", effects=None,
                seed=0, smr_offset=None, envelope=None, time_scale=None)  # fmt: skip
    return argparse.Namespace(**{**base, **kw})


def test_a_controller_without_payload_is_said_and_a_declared_one_recorded():
    cell, *_ = open_cell(_ns())  # constructs the drivers; nothing connects
    w = payload_warning(cell)
    assert cell.payload_kg == 0.0 and w is not None and "--payload KG" in w and "\n" not in w
    cell, *_ = open_cell(_ns(payload="3.2,0,0,0.04"))
    assert payload_warning(cell) is None
    assert cell.session({})["payload"] == {"mass_kg": 3.2, "com_m": [0.0, 0.0, 0.04]}


def test_campaign_records_the_declared_payload_and_resume_keeps_it(tmp_path, capsys):
    out = tmp_path / "p.mcap"
    rc = main(["campaign", "--poses", "3", "--readings", "1", "--settle", "0.1",
               "--payload", "1.25,0,0,0.03", "--out", str(out)])  # fmt: skip
    assert rc == 0
    rec = read_recording(out)
    assert rec.session["payload"] == {"mass_kg": 1.25, "com_m": [0.0, 0.0, 0.03]}
    assert {s["payload_kg"] for s in rec.samples} == {1.25}
    capsys.readouterr()
    rc = main(["campaign", "--resume", str(out), "--payload", "2", "--out",
               str(tmp_path / "q.mcap")])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert rc != 0 and len(err) == 1 and "keeps the payload" in err[0], err
    rc = main(["campaign", "--poses", "3", "--payload", "1500", "--out", str(tmp_path / "g.mcap")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc != 0 and len(err) == 1 and "looks like grams" in err[0], err
    assert not (tmp_path / "g.mcap").exists()


def test_parse_payload_edges():
    assert str(parse_payload("-0", UR5E)[0]) == "0.0"  # not a -0.0 kg in the recording
    with pytest.raises(UserError, match="5.0000001 kg is above"):
        parse_payload("5.0000001", UR5E)
    assert parse_payload("5", UR5E)[0] == 5.0  # the rated payload itself is allowed


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.text(max_size=40), st.lists(st.floats(), min_size=0, max_size=5).map(
    lambda v: ",".join(repr(x) for x in v))))  # fmt: skip
def test_parse_payload_any_text_is_a_payload_or_one_line(text):
    import warnings

    import numpy as np

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no overflow warning on the way to the answer
            mass, com = parse_payload(text, UR5E)
    except UserError as e:
        assert "\n" not in str(e) and str(e).startswith("--payload")
        return
    assert 0.0 <= mass <= UR5E.max_payload_kg and len(com) == 3
    assert np.all(np.isfinite(com)) and float(np.max(np.abs(com))) <= 0.5


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(), min_size=0, max_size=4).map(lambda v: ",".join(repr(x) for x in v)))
def test_parse_smr_offset_any_numbers_is_an_offset_or_one_line(text):
    """The same for --smr-offset (1e300,1e300,0 printed numpy's overflow warning first)."""
    import warnings

    from workcell.campaign.devices import parse_smr_offset

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            v = parse_smr_offset(text)
    except UserError as e:
        assert "\n" not in str(e)
        return
    assert v.shape == (3,)
