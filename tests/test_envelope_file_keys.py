"""An envelope file's keys: a misspelt or unknown key, a key given twice, or a left-out limit is
refused in one line (each used to be replaced by the default silently, e.g. `"floor_z": 0.5`
ran with the 0.02 m floor); files written by `workcell envelope --out` (now or before the
kinematic margin existed) and envelopes recorded in sessions still load. A floor further below
the base than the arm reaches (the check would never act; -100 is millimetres) is refused."""

from __future__ import annotations

import json

import pytest

from workcell.campaign.envelope import (
    DEFAULT_KINEMATIC_MARGIN_M,
    ENVELOPE_KEYS,
    Envelope,
    default_envelope,
    envelope_of_session,
    load_envelope,
)
from workcell.cli import main
from workcell.errors import UserError
from workcell.kinematics.robots import UR5E


@pytest.fixture
def written(tmp_path, capsys) -> dict:
    """The envelope file `workcell envelope --out` writes, as a dict."""
    path = tmp_path / "env.json"
    assert main(["envelope", "--out", str(path)]) == 0
    capsys.readouterr()
    return json.loads(path.read_text())


def refusal(capsys, argv: list[str]) -> str:
    capsys.readouterr()
    rc = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, (rc, err)
    return err[0]


@pytest.mark.parametrize(
    "drop, add, named, nearest",
    [
        ("floor_z_m", {"floor_z": 0.5}, "'floor_z'", "'floor_z_m'"),
        ("max_speed_rad_s", {"max_speed": 0.1}, "'max_speed'", "'max_speed_rad_s'"),
        ("max_accel_rad_s2", {"max_accel_rad_s": 0.5}, "'max_accel_rad_s'", "'max_accel_rad_s2'"),
        (None, {"kinematic_margin": 0.02}, "'kinematic_margin'", "'kinematic_margin_m'"),
        (None, {"box_max": [1, 1, 1]}, "'box_max'", "'box_max_m'"),
    ],
)
def test_a_misspelt_key_is_refused_naming_the_nearest(
    tmp_path, capsys, written, drop, add, named, nearest
):
    d = {k: v for k, v in written.items() if k != drop}
    path = tmp_path / "typo.json"
    path.write_text(json.dumps({**d, **add}))
    for argv in (
        ["envelope", "--check", str(path)],
        ["campaign", "--robot", "sim", "--tracker", "sim", "--plan", "random", "--poses", "4",
         "--dry-run", "--envelope", str(path), "--out", str(tmp_path / "r.mcap")],
    ):  # fmt: skip
        line = refusal(capsys, argv)
        assert f"unknown key {named} (did you mean {nearest}?)" in line, line
        assert all(k in line for k in ENVELOPE_KEYS), line  # what the file may hold
        assert "Traceback" not in line


def test_several_unknown_keys_are_all_named(tmp_path, capsys, written):
    path = tmp_path / "extra.json"
    path.write_text(json.dumps({**written, "comment": 1, "flor": 0.1}))
    line = refusal(capsys, ["envelope", "--check", str(path)])
    assert "unknown keys 'comment', 'flor' (did you mean 'floor_z_m'?)" in line, line


def test_a_key_given_twice_is_refused(tmp_path, capsys, written):
    path = tmp_path / "dup.json"
    path.write_text(json.dumps(written)[:-1] + ', "floor_z_m": 0.5}')
    assert json.loads(path.read_text())["floor_z_m"] == 0.5  # what json alone would keep
    line = refusal(capsys, ["envelope", "--check", str(path)])
    assert "'floor_z_m' is given twice" in line and "give each once" in line, line


@pytest.mark.parametrize("key", ["floor_z_m", "max_speed_rad_s", "max_accel_rad_s2"])
def test_a_file_without_a_limit_is_refused(tmp_path, capsys, written, key):
    path = tmp_path / "short.json"
    path.write_text(json.dumps({k: v for k, v in written.items() if k != key}))
    line = refusal(capsys, ["envelope", "--check", str(path)])
    assert f"missing {key!r}" in line and "workcell envelope --out" in line, line


def test_written_and_older_files_still_load(tmp_path, written):
    """What `--out` writes holds exactly the known keys and loads with nothing defaulted; a file
    from before the kinematic margin gets the default margin, and says it was defaulted."""
    assert sorted(written) == sorted(ENVELOPE_KEYS)
    assert sorted(default_envelope(UR5E).to_dict()) == sorted(ENVELOPE_KEYS)
    path = tmp_path / "env.json"
    path.write_text(json.dumps(written))
    env = load_envelope(path, UR5E)
    assert env.defaulted == () and env.to_dict() == written
    old = {k: v for k, v in written.items() if k != "kinematic_margin_m"}
    path.write_text(json.dumps(old))
    env = load_envelope(path, UR5E)
    assert env.kinematic_margin_m == DEFAULT_KINEMATIC_MARGIN_M
    assert env.defaulted == ("kinematic_margin_m",)
    assert "defaulted" not in env.to_dict()


def test_the_check_says_which_values_are_defaults(tmp_path, capsys, written):
    old = {k: v for k, v in written.items() if k != "kinematic_margin_m"}
    path = tmp_path / "old.json"
    path.write_text(json.dumps(old))
    capsys.readouterr()
    assert main(["envelope", "--check", str(path)]) == 0
    out = capsys.readouterr().out
    assert "  default  kinematic_margin_m: not in the file, the value above is the default" in out


def test_a_recorded_envelope_still_loads_and_an_unknown_key_in_it_is_refused(written):
    """A session's `campaign.envelope` is `to_dict` (with or without the margin); one from
    another tool may leave out the floor and caps (their defaults, as before). A key the tool
    does not know is refused there too: resuming would plan without that limit."""
    assert envelope_of_session({"envelope": written}, UR5E, "rec").to_dict() == written
    old = {k: v for k, v in written.items() if k != "kinematic_margin_m"}
    assert envelope_of_session({"envelope": old}, UR5E, "rec").kinematic_margin_m == 0.0
    bare = {k: written[k] for k in ENVELOPE_KEYS[:3]}
    env = envelope_of_session({"envelope": bare}, UR5E, "rec")
    assert (env.floor_z_m, env.max_speed_rad_s, env.max_accel_rad_s2) == (0.02, 1.0, 2.0)
    assert set(env.defaulted) == {
        "floor_z_m",
        "max_speed_rad_s",
        "max_accel_rad_s2",
        "kinematic_margin_m",
    }
    assert envelope_of_session({}, UR5E, "rec") is None
    with pytest.raises(UserError, match="unknown key 'ceiling_z_m'") as e:
        envelope_of_session({"envelope": {**written, "ceiling_z_m": 1.0}}, UR5E, "rec")
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="did you mean 'floor_z_m'"):
        Envelope.from_dict({**old, "floor_z": 0.5}, margin_if_absent_m=0.0)


@pytest.mark.parametrize(
    "floor, hint",
    [
        (-100.0, "looks like millimetres, give metres (-0.1 m)"),
        (-20.0, "looks like millimetres"),
        (-2.0, "give the table's height in metres"),
    ],
)
def test_a_floor_below_the_arms_reach_is_refused(tmp_path, capsys, written, floor, hint):
    path = tmp_path / "low.json"
    path.write_text(json.dumps({**written, "floor_z_m": floor}))
    line = refusal(capsys, ["envelope", "--check", str(path)])
    assert "floor check would never act" in line and hint in line, line
    assert "1.31 m" in line  # the UR5e's reach, the limit
    if floor == -2.0:
        assert "millimetres" not in line


def test_a_floor_within_reach_below_the_base_is_accepted(tmp_path, capsys, written):
    """A table 1 m below the base (a wall- or ceiling-mounted arm) is within the UR5e's reach."""
    path = tmp_path / "deep.json"
    path.write_text(json.dumps({**written, "floor_z_m": -1.0}))
    assert load_envelope(path, UR5E).floor_z_m == -1.0
