"""`--payload`: the payload at the flange as the operator declares it. A campaign on a controller
recorded 0 kg whatever the arm carried, and nothing said so (audit of the recording format,
2026-11-26 night); since 2026-11-27 the controller's own payload setting is read at connect and
reconciled with the declared one (`campaign.payload.settle_payload`)."""

from __future__ import annotations

import argparse

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from workcell.campaign.devices import open_cell, parse_payload
from workcell.campaign.payload import settle_payload
from workcell.cli import main
from workcell.drivers.protocols import PayloadSetting, PayloadUnavailable
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


class _Arm:
    """A robot whose controller reports `setting` (a PayloadSetting, or the exception to raise)."""

    def __init__(self, setting):
        self.setting = setting

    def payload_setting(self):
        if isinstance(self.setting, Exception):
            raise self.setting
        return self.setting


def test_the_controllers_payload_is_recorded_when_nobody_declares_one():
    cell, *_ = open_cell(_ns())  # constructs the drivers; nothing connects
    assert cell.payload_source == "default" and not cell.payload_declared
    notes = settle_payload(cell, _Arm(PayloadSetting(1.8, (0.0, 0.01, 0.06))))
    assert [n["level"] for n in notes] == ["info"] and "1.8 kg" in notes[0]["message"]
    assert "(0.0, 10.0, 60.0) mm" in notes[0]["message"] and "\n" not in notes[0]["message"]
    assert cell.session({})["payload"] == {
        "mass_kg": 1.8,
        "com_m": [0.0, 0.01, 0.06],
        "source": "controller",
        "controller": {"mass_kg": 1.8, "com_m": [0.0, 0.01, 0.06]},
    }


def test_a_controller_that_does_not_say_leaves_0_kg_and_a_warning():
    for arm, why in (
        (object(), "does not read a payload setting"),
        (_Arm(PayloadUnavailable("UR h: the controller does not report it")), "does not report"),
    ):
        cell, *_ = open_cell(_ns())
        notes = settle_payload(cell, arm)
        assert [n["level"] for n in notes] == ["warning"], notes
        w = notes[0]["message"]
        assert why in w and "--payload KG" in w and "0 kg" in w and "\n" not in w
        assert cell.payload_kg == 0.0 and cell.session({})["payload"]["source"] == "default"


def test_a_declared_payload_is_kept_and_a_controller_set_otherwise_is_said():
    cell, *_ = open_cell(_ns(payload="3.2,0,0,0.04"))
    assert cell.payload_declared and cell.payload_source == "declared"
    # the same within the pendant's display resolution: nothing to say
    assert settle_payload(cell, _Arm(PayloadSetting(3.205, (0.0, 0.0, 0.0405)))) == []
    for other, words in (
        (PayloadSetting(2.0, (0.0, 0.0, 0.04)), "2 kg"),  # another mass
        (PayloadSetting(3.2, (0.0, 0.0, 0.1)), "(0.0, 0.0, 100.0) mm"),  # another centre of mass
    ):
        notes = settle_payload(cell, _Arm(other))
        assert [n["level"] for n in notes] == ["warning"], notes
        w = notes[0]["message"]
        assert words in w and "3.2 kg" in w and "declared payload" in w and "\n" not in w
        pay = cell.session({})["payload"]
        assert (pay["mass_kg"], pay["source"]) == (3.2, "declared")
        assert pay["controller"]["mass_kg"] == other.mass_kg
    # a declared payload and a controller that does not say: nothing to warn about
    assert settle_payload(cell, _Arm(PayloadUnavailable("older software"))) == []
    assert cell.session({})["payload"]["controller"] == {"unavailable": "older software"}


def test_campaign_records_the_declared_payload_and_resume_keeps_it(tmp_path, capsys):
    out = tmp_path / "p.mcap"
    rc = main(["campaign", "--poses", "3", "--readings", "1", "--settle", "0.1",
               "--payload", "1.25,0,0,0.03", "--out", str(out)])  # fmt: skip
    assert rc == 0
    rec = read_recording(out)
    pay = rec.session["payload"]
    assert (pay["mass_kg"], pay["com_m"], pay["source"]) == (1.25, [0.0, 0.0, 0.03], "declared")
    # the simulated controller is set to its cell's own payload: said, both recorded
    assert pay["controller"]["mass_kg"] != 1.25
    said = [e["message"] for e in rec.events if e["kind"] == "payload"]
    assert len(said) == 1 and "1.25 kg" in said[0] and "controller is set to" in said[0]
    capsys.readouterr()
    assert main(["info", str(out)]) == 0
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("payload ")]
    assert len(line) == 1 and "1.25 kg at (0.0, 0.0, 30.0) mm (declared)" in line[0], line
    assert "the controller was set to" in line[0]
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


def test_validate_says_where_the_payload_it_compared_came_from(monkeypatch):
    import workcell.export.validate as xv

    monkeypatch.setattr(xv, "payload_mismatch", lambda *a, **k: "the table is for 5 kg")
    for source, words in (
        ("controller", "as the controller is set"),
        ("default", "controller's setting unread, so 0 kg"),
        ("declared", "as declared"),
    ):
        w = xv.payload_check(None, None, 0.0, simulated=False, source=source)
        assert w.startswith("the table is for 5 kg (") and words in w and "\n" not in w
    with pytest.raises(UserError, match="the table is for 5 kg"):  # a simulated arm: refused
        xv.payload_check(None, None, 0.0, simulated=True, source="controller")


_JSON = st.recursive(
    st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=8),
    lambda kids: (
        st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=10), kids, max_size=4)
    ),
    max_leaves=12,
)


@settings(max_examples=300, deadline=None)
@given(
    st.one_of(
        _JSON,
        st.fixed_dictionaries(
            {"mass_kg": _JSON, "com_m": _JSON},
            optional={"source": _JSON, "controller": _JSON},
        ),
    )
)
def test_info_reads_any_recorded_payload_without_failing(payload):
    from workcell.commands.info import payload_line

    line = payload_line(payload)
    assert line is None or ("kg" in line and "\n" not in line)


def test_info_says_when_a_payload_has_no_recorded_source():
    """An imported recording (series B) records 0 kg without saying where it came from: `info`
    says the source is not recorded instead of printing the value as if stated."""
    from workcell.commands.info import payload_line

    assert payload_line({"mass_kg": 0.0, "com_m": [0, 0, 0]}) == (
        "0 kg at (0.0, 0.0, 0.0) mm (its source not recorded)"
    )
    assert payload_line({"mass_kg": 1.5, "com_m": [0, 0, 0.03], "source": "declared"}) == (
        "1.5 kg at (0.0, 0.0, 30.0) mm (declared)"
    )


@pytest.mark.parametrize(
    "setting, why",
    [
        (PayloadSetting(1e300, (1e300, 0.0, 0.0)), "above the ur5e's rated payload of 5 kg"),
        (PayloadSetting(1000.0, (409.0, 0.0, 0.0)), "above the ur5e's rated payload"),
        (PayloadSetting(1.0, (0.0, 0.0, 0.8)), "its centre of mass 0.8 m from the flange"),
    ],
)
def test_a_controller_payload_no_arm_carries_is_not_adopted(setting, why):
    """A controller reporting 1e300 kg had it recorded as the payload the gravity terms are
    fitted against (the same typed as --payload is refused): now a warning, the payload
    assumed as before, and the controller's figure recorded as reported."""
    cell, *_ = open_cell(_ns())
    notes = settle_payload(cell, _Arm(setting))
    assert [n["level"] for n in notes] == ["warning"], notes
    w = notes[0]["message"]
    assert why in w and "not used" in w and "--payload KG" in w and "\n" not in w, w
    assert len(w) < 400, w
    p = cell.session({})["payload"]
    assert p["mass_kg"] == 0.0 and p["source"] == "default"
    assert p["controller"]["mass_kg"] == setting.mass_kg
