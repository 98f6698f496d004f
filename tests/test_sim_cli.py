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
        ('{"robot": {"restart_power_off": 1}}', "restart_power_off must be true or false"),
        # int(inf) raised OverflowError, a traceback; 1.5 was read as move 1 (2026-11-28)
        ('{"robot": {"rtde_drop_at_move": 1e400}}', "move numbers are whole numbers from 1"),
        ('{"robot": {"restart_at_move": NaN}}', "move numbers are whole numbers from 1"),
        ('{"robot": {"protective_stop_at_move": [1.5]}}', "whole numbers from 1, got \\[1.5\\]"),
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
    # a documented boolean setting (it was refused as "must be a number")
    r, _ = parse_faults('{"robot": {"restart_at_move": [4], "restart_power_off": true}}')
    assert r == {"restart_at_move": [4], "restart_power_off": True}


def _listening(host: str, port: int) -> bool:
    import socket

    try:
        with socket.create_connection((host, port), timeout=0.5):
            return True
    except OSError:
        return False


@pytest.mark.parametrize(
    "host, text, match",
    [
        ("127.0.0.33", '{"tracker": {"garbage_len": 1e12}}', r"garbage_len must be 1\.\.4096"),
        ("127.0.0.34", '{"tracker": {"beam_break_rate": 2}}', r"must be in \[0, 1\]"),
        ("127.0.0.35", '{"tracker": {"slow_delay_s": 1e12}}', r"slow_delay_s must be in"),
    ],
)
def test_bad_tracker_faults_are_refused_before_anything_listens(capsys, host, text, match):
    """garbage_len 1e12 was accepted (the simulator would draw up to a terabyte of garbage per
    reply); a bad tracker setting was found only after the UR controller had started listening,
    which stayed up in the calling process."""
    rc = main(["sim", "--host", host, "--faults", text])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert re.search(match, err[0]), err
    assert not _listening(host, 29999) and not _listening(host, 30004)


def test_garbage_mode_is_a_string_setting():
    """`garbage_mode` ("before", "instead", "mixed") is documented but was refused as
    'must be a number'."""
    _, t = parse_faults('{"tracker": {"garbage_rate": 0.1, "garbage_mode": "before"}}')
    assert t == {"garbage_rate": 0.1, "garbage_mode": "before"}
