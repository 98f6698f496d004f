"""`workcell sim --faults`: a bad fault description is one line and exit 2, before anything starts."""

from __future__ import annotations

import re

import pytest

from workcell.cli import main
from workcell.commands.sim import parse_faults


@pytest.mark.parametrize(
    "text, match",
    [
        ("xx", "not a preset"),
        ("[1]", "must look like"),
        ('{"robot": 5}', '"robot" must be an object'),
        ('{"robot": {"rtde_drop_at_move": "a"}}', "robot.rtde_drop_at_move must be a number"),
        ('{"tracker": {"garbage_rate": null}}', "tracker.garbage_rate must be a number"),
        ('{"robot": {"rtde_drop_at_move": [1, true]}}', "must be a number or a list"),
        ('{"tracker": {"beam_break_rate": 2}}', r"must be in \[0, 1\]"),
        ('{"robot": {"bogus": 3}}', "unknown UR controller fault"),
    ],
)
def test_bad_faults_are_one_line(capsys, text, match):
    rc = main(["sim", "--faults", text])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith("workcell sim: error: ")
    assert re.search(match, err[0]), err


def test_presets_and_good_json_parse():
    assert parse_faults("none") == ({}, {})
    r, t = parse_faults('{"robot": {"rtde_drop_at_move": [3]}, "tracker": {"garbage_rate": 0.1}}')
    assert r == {"rtde_drop_at_move": [3]} and t == {"garbage_rate": 0.1}
