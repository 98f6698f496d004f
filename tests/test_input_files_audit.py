"""What an audit of the files the commands read (models, tables, targets; 2026-11-27) found:
tracebacks on a JSON integer beyond a float, on nulls and scalars where arrays go; a negative
held-out RMS in a model that made `envelope --model` suggest a 1 mm margin where 5 mm were
needed; a 7-joint model folded into a UR's six links; a table whose "1" (text) stretched its
grid, or without any identity, validated against any model; an export that wrote half of its
pair before finding a directory in the way; a table's CSV read as 2376 targets. Each is now
one line, before anything is written."""

from __future__ import annotations

import copy
import hashlib
import json

import numpy as np
import pytest

from workcell.cli import main


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("inputs")
    rec, model, table = d / "c.mcap", d / "m.json", d / "t.json"
    argv = ["campaign", "--robot", "sim", "--tracker", "sim", "--poses", "30", "--out", str(rec)]
    assert main(argv) == 0
    assert main(["fit", str(rec), "--method", "dh", "--out", str(model)]) == 0
    argv = ["export", str(model), "--format", "table", "--out", str(table), "--spacing", "0.2"]
    assert main(argv) == 0
    return d, json.loads(model.read_text()), json.loads(table.read_text())


def _one_line(capsys, argv) -> tuple[int, list[str]]:
    rc = main(argv)
    return rc, capsys.readouterr().err.strip().splitlines()


BIG = 10**400  # json.dumps writes it as digits; float() of it raised OverflowError


def _edited(doc: dict, edit, path):
    """A copy of a model or table file's JSON with one hand edit, written to `path`."""
    d = copy.deepcopy(doc)
    edit(d)
    path.write_text(json.dumps(d))
    return path


@pytest.mark.parametrize(
    "edit, words",
    [
        (lambda m: m["info"].__setitem__("heldout_rms_m", -0.001), "heldout_rms_m must be"),
        (lambda m: m["info"].__setitem__("heldout_rms_m", BIG), "heldout_rms_m must be"),
        (lambda m: m["info"]["unexplained"].__setitem__("floor_m", BIG), "floor_m must be"),
        (lambda m: m["info"]["joint_range_rad"][0].__setitem__(0, BIG), "joint_range_rad"),
        (lambda m: m["info"].__setitem__("recording_sha256", 5), "recording_sha256"),
        (lambda m: m["cov"][0].__setitem__(0, 1e300), "standard deviation of 1e+150"),
        (lambda m: m["theta"].__setitem__(1, str(m["theta"][1])), "number written as text"),
        (lambda m: m["base_ref"][0].__setitem__(3, "1.5"), "(base_ref[0][3] = '1.5')"),
        (lambda m: m["base_ref"].pop(3), "base_ref is not a rigid transform (shape (3, 4)"),
        (lambda m: m["base_ref"].pop(0), "base_ref is not a rigid transform (shape (3, 4)"),
        (lambda m: m["base_ref"][3].__setitem__(0, 0.5), "bottom row [0.5, 0.0, 0.0, 1.0]"),
        (
            lambda m: m["base_ref"].__setitem__(
                0, [1.001 * x for x in m["base_ref"][0][:3]] + m["base_ref"][0][3:]
            ),
            "a rotation block that is not a rotation",
        ),
        (
            lambda m: [
                m["theta"].__setitem__(i, float(np.degrees(m["theta"][i]))) for i in range(12, 18)
            ],
            "theta alpha1 is 90",
        ),
        (lambda m: m["theta"].__setitem__(22, 4.4e16), "theta theta5_offset is 4.4e+16 rad"),
        (
            lambda m: m["info"].__setitem__("variance_factor", "1.5"),
            "number written as text (info.variance_factor = '1.5')",
        ),
        (
            lambda m: m["info"]["unexplained"].__setitem__("floor_m", "1e-05"),
            "number written as text (info.unexplained.floor_m = '1e-05')",
        ),
    ],
    ids=[
        "negative rms",
        "huge rms",
        "huge floor",
        "huge joint range",
        "sha a number",
        "cov",
        "text theta",
        "text base_ref",
        "base_ref 3 rows",
        "base_ref row 0 gone",
        "base_ref bottom row",
        "base_ref scaled rotation",
        "alphas in degrees",
        "theta offset 4.4e16",
        "text scalar",
        "text info figure",
    ],  # fmt: skip
)
def test_a_model_with_impossible_figures_is_refused_in_one_line(files, capsys, edit, words):
    d, model, _ = files
    f = _edited(model, edit, d / "bad.json")
    env = d / "env_out.json"
    rc, err = _one_line(capsys, ["envelope", "--model", str(f), "--out", str(env)])
    assert rc == 2 and len(err) == 1 and words in err[0], err
    assert not env.exists()  # no envelope with a margin from a bad figure


def test_a_seven_joint_model_is_refused_by_the_six_joint_commands(files, capsys):
    from workcell.estimation.dh import DHModel
    from workcell.estimation.models import save_model
    from workcell.kinematics.chain import pack
    from workcell.kinematics.robots import WAM7

    d, _, _ = files
    th = pack(WAM7.dh, tool=(0.0, 0.05, 0.0))
    m = DHModel(robot_model="ur5e", nominal_dh=WAM7.dh, theta=th, base_ref=np.eye(4),
                cov=np.zeros((44, 44)), free=np.ones(44, bool), info={})  # fmt: skip
    f = save_model(m, d / "seven.json")
    for argv in (
        ["export", str(f), "--format", "ros-yaml", "--out", str(d / "seven.yaml")],
        ["envelope", "--model", str(f)],
    ):
        rc, err = _one_line(capsys, argv)
        assert rc == 2 and len(err) == 1 and "not the 39 of a 6-joint arm" in err[0], err
    assert not (d / "seven.yaml").exists()


@pytest.mark.parametrize(
    "edit, words",
    [
        (lambda t: t["grid"]["shape"].__setitem__(0, 1e300), "grid shape must be 3 whole numbers"),
        (lambda t: t["grid"]["lo_m"].__setitem__(0, -BIG), "lo_m/hi_m must be 3 finite"),
        (lambda t: t["grid"]["hi_m"].__setitem__(0, "1"), "hi_m holds '1', not a number"),
        (lambda t: t["orientations_rotvec"][0].__setitem__(0, True), "holds 'True'"),
        (lambda t: t.__setitem__("meta", {}), "names neither the model nor the recording"),
    ],
    ids=["shape", "huge lo", "text hi", "bool rotvec", "no identity"],
)
def test_a_malformed_table_is_refused_in_one_line(files, capsys, edit, words):
    d, _, table = files
    f = _edited(table, edit, d / "bad_t.json")
    argv = ["validate", str(d / "m.json"), "--table", str(f), "--targets", "2"]
    rc, err = _one_line(capsys, argv)
    assert rc == 2 and len(err) == 1 and words in err[0], err


@pytest.mark.parametrize(
    "key, value",
    [("approach_sign", None), ("max_interp_error_m", None)],
)
def test_null_table_fields_are_read_as_absent(files, capsys, key, value):
    """`null` where the table's meta allows it was a TypeError in validate."""
    d, _, table = files
    meta = (lambda t: t["meta"]["conditions"]) if key == "approach_sign" else (lambda t: t["meta"])
    f = _edited(table, lambda t: meta(t).__setitem__(key, value), d / "null_t.json")
    rc, err = _one_line(
        capsys, ["validate", str(d / "m.json"), "--table", str(f), "--targets", "2"]
    )
    assert rc == 0 and not any("Traceback" in x for x in err), err


def test_export_refuses_a_directory_in_its_pair_before_writing_anything(files, capsys):
    d, _, _ = files
    (d / "pair.csv").mkdir()
    out = d / "pair.json"
    argv = ["export", str(d / "m.json"), "--format", "table", "--out", str(out), "--spacing", "0.2"]
    rc, err = _one_line(capsys, argv)
    assert rc == 2 and len(err) == 1 and "not a regular file" in err[0], err
    assert not out.exists()


def test_a_tables_csv_is_not_read_as_targets(files, capsys):
    d, _, _ = files
    csv = d / "t.csv"
    before = hashlib.sha256(csv.read_bytes()).hexdigest()
    out = d / "targets_out.csv"
    argv = ["export", str(d / "m.json"), "--format", "targets", "--in", str(csv), "--out", str(out)]
    rc, err = _one_line(capsys, argv)
    assert rc == 2 and len(err) == 1 and "correction table CSV, not a list of targets" in err[0]
    assert not out.exists() and hashlib.sha256(csv.read_bytes()).hexdigest() == before


@pytest.mark.parametrize(
    "free", [lambda f: f + [True], lambda f: ["1"] * len(f), lambda f: [float("nan")] * len(f)]
)
def test_a_models_free_mask_must_be_true_false_values(files, capsys, free):
    """`free` with 40 entries, text or NaN loaded (np.asarray(..., bool) makes a mask of it)."""
    d, model, _ = files
    f = _edited(model, lambda m: m.__setitem__("free", free(m["free"])), d / "free.json")
    rc, err = _one_line(capsys, ["envelope", "--model", str(f)])
    assert rc == 2 and len(err) == 1 and "free must be 39 true/false values" in err[0], err


def test_a_target_with_digit_grouping_is_not_a_number(files, capsys):
    """float() reads "0_1" as 1.0: a target 1 m off where 0.1 was meant."""
    d, _, _ = files
    f = d / "targets.csv"
    f.write_text("x,y,z\n0_1,-0.4,0.3\n")
    argv = ["export", str(d / "m.json"), "--format", "targets", "--in", str(f), "--out",
            str(d / "tout.csv")]  # fmt: skip
    rc, err = _one_line(capsys, argv)
    assert rc == 2 and len(err) == 1 and "'0_1' is not a number" in err[0], err


def test_a_robot_named_by_digits_is_not_a_number_written_as_text(files, capsys):
    """A robot's name is text even when it is digits ("1200"): the check for numbers written as
    text refused every model of such a robot (review of 2026-11-28)."""
    from workcell.estimation.models import load_model

    d, model, _ = files
    f = _edited(model, lambda m: m.__setitem__("robot", "1200"), d / "digits.json")
    try:
        load_model(f)
    except Exception as e:  # noqa: BLE001 - any other refusal is not this check's
        assert "number written as text" not in str(e), e


def test_deep_nesting_and_long_digit_strings_are_bad_json_not_tracebacks():
    """`strict_json.loads` raised a RecursionError for nesting deeper than the parser recurses,
    and Python's 'Exceeds the limit (4300 digits)' ValueError for a long integer; a bounds
    file's loader catches JSONDecodeError only, so both passed it."""
    from workcell import strict_json

    with pytest.raises(json.JSONDecodeError, match="nested too deeply"):
        strict_json.loads('{"a": ' + "[" * 100_000 + "]" * 100_000 + "}")
    assert strict_json.loads("[" + "9" * 5000 + "]") == [float("inf")]
    assert strict_json.loads("[-" + "9" * 5000 + "]") == [float("-inf")]
    assert strict_json.loads("[12345678901234567890123]") == [1.2345678901234568e22]
    assert strict_json.loads("[-9223372036854775808]") == [-(2**63)]


@pytest.mark.parametrize(
    "text, words",
    [
        ('{"a2": [' + "9" * 5000 + ", 1]}", "a2 bound [inf, 1] is empty"),
        ('{"a2": ' + "[" * 100_000 + "]" * 100_000 + "}", "bounds"),
    ],
    ids=["5000 digits", "deep"],
)
def test_a_bounds_file_with_absurd_json_is_one_line(files, capsys, text, words):
    d, _, _ = files
    b = d / "bounds_bad.json"
    b.write_text(text)
    rc, err = _one_line(capsys, ["fit", str(d / "c.mcap"), "--bounds", str(b), "--out",
                                 str(d / "never.json")])  # fmt: skip
    assert rc == 2 and len(err) == 1 and "bounds_bad.json" in err[0] and words in err[0], err
    assert not (d / "never.json").exists()
