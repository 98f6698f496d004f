"""`export --format targets --in` reads the targets CSV the command itself writes (its `#` header,
its unit-suffixed columns, an edited copy of it): the desired targets x_m..rz_rad, never the
commanded x_cmd_m.. (a target is corrected once); units stated in a column name are converted;
anything it cannot use is refused in one line naming the file's line and what to do."""

import csv
import json
import math
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_export_table import HI, LO, make_model  # noqa: E402

from workcell.errors import UserError
from workcell.estimation.models import save_model
from workcell.export.correction import Q_REF, Corrector, nominal_for, rotvec_to_matrix

Q_COLS = [f"q{i}_cmd_rad" for i in range(1, 7)]


def _run(argv, capsys) -> tuple[int, list[str], list[str]]:
    from workcell.cli import main

    capsys.readouterr()
    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out.splitlines(), err.splitlines()


def _read(path) -> dict[str, np.ndarray]:
    """The numeric columns of a targets CSV, by name (the `#` lines skipped)."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(x for x in f if not x.startswith("#")))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}


def _cols(d, names) -> np.ndarray:
    return np.stack([d[n] for n in names], axis=1)


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    """A model (with a covariance), 5 desired targets with orientations near tool-down, and the
    targets CSV `export` wrote for them."""
    from workcell.cli import main

    d = tmp_path_factory.mktemp("rt")
    m = make_model(8)
    m.cov = np.diag(np.random.default_rng(4).uniform(1e-10, 1e-8, 39))
    model = save_model(m, d / "m.json")
    rng = np.random.default_rng(3)
    P = rng.uniform(LO, HI, (5, 3))
    rv = np.array([0.0, np.pi, 0.0]) + rng.uniform(-0.1, 0.1, (5, 3))
    src = d / "targets.csv"
    src.write_text(
        "x,y,z,rx,ry,rz\n"
        + "".join(
            ",".join(repr(float(v)) for v in (*p, *r)) + "\n" for p, r in zip(P, rv, strict=True)
        )
    )
    out = d / "corrected.csv"
    argv = ["export", model, "--format", "targets", "--in", src, "--out", out]
    assert main([str(a) for a in argv]) == 0
    return {"dir": d, "model": model, "m": m, "P": P, "rv": rv, "src": src, "out": out}


def test_a_corrected_targets_csv_fed_back_is_read_as_its_desired_targets(cell, capsys):
    """The round trip: `export`'s own targets CSV given back with --in was refused ("need
    columns x,y,z"); now its desired targets are read bit for bit (positions; the same
    rotations) and corrected once: re-correcting with the same model gives the same commanded
    targets, not a second correction on top (which would double it)."""
    first = _read(cell["out"])
    again = cell["dir"] / "again.csv"
    argv = ["export", cell["model"], "--format", "targets", "--in", cell["out"], "--out", again]
    rc, lines, err = _run(argv, capsys)
    assert rc == 0, err
    note = (
        f"{cell['out']}: a workcell corrected-targets CSV (corrected before with "
        f"{cell['model']} (dh)): reading its desired targets x_m..rz_rad, not its commanded "
        "x_cmd_m..q6_cmd_rad (the earlier correction), so no target is corrected twice; "
        "q1_cmd_rad..q6_cmd_rad only seed the IK (same arm configuration)"
    )
    assert note in lines, lines
    second = _read(again)
    np.testing.assert_array_equal(_cols(second, ["x_m", "y_m", "z_m"]), cell["P"])
    R2 = rotvec_to_matrix(_cols(second, ["rx_rad", "ry_rad", "rz_rad"]))
    np.testing.assert_allclose(R2, rotvec_to_matrix(cell["rv"]), rtol=0, atol=1e-12)
    cmd1, cmd2 = (_cols(d, ["x_cmd_m", "y_cmd_m", "z_cmd_m"]) for d in (first, second))
    assert np.abs(cmd2 - cmd1).max() < 1e-9
    size = np.linalg.norm(cmd1 - cell["P"], axis=1)
    assert size.min() > 1e-4  # a correction of 0.1 mm and more: a double one would show
    # the model's robot at the commanded joints lands on the desired targets
    corr = Corrector(cell["m"], nominal_for(cell["m"]))
    assert np.abs(corr.real_base(_cols(second, Q_COLS)) - cell["P"]).max() < 1e-8
    # what the parser hands on: the desired targets, and the corrected joints as seeds only
    from workcell.export.targets_in import read_targets

    t = read_targets(cell["out"])
    text = cell["out"].read_text().splitlines()
    hrow = next(i for i, x in enumerate(text, 1) if not x.startswith("#"))  # the header row
    assert t.corrected_csv and t.q_role == "seeds" and t.lines == list(range(hrow + 1, hrow + 6))
    np.testing.assert_array_equal(t.P, cell["P"])  # repr() floats: exact
    np.testing.assert_allclose(
        rotvec_to_matrix(t.rotvec), rotvec_to_matrix(cell["rv"]), rtol=0, atol=1e-12
    )
    np.testing.assert_array_equal(t.q, _cols(first, Q_COLS))
    # the JSON summary says what was read
    rc, jl, _ = _run([*argv, "--json"], capsys)
    s = json.loads(jl[0])
    assert rc == 0 and s["input"]["corrected_targets_csv"] is True
    assert s["input"]["columns"][:3] == ["x_m", "y_m", "z_m"] and s["input"]["notes"] == [note]


def test_re_correcting_with_a_newer_model_starts_from_the_desired_targets(cell, capsys):
    """A targets CSV corrected with one model, re-corrected with a newer one, gives what the
    newer model gives for the original targets: the earlier correction is not carried over."""
    newer = save_model(make_model(11), cell["dir"] / "newer.json")
    a, b = cell["dir"] / "newer-from-corrected.csv", cell["dir"] / "newer-from-original.csv"
    for src, out in ((cell["out"], a), (cell["src"], b)):
        rc, _, err = _run(
            ["export", newer, "--format", "targets", "--in", src, "--out", out], capsys
        )
        assert rc == 0, err
    da, db, old = _read(a), _read(b), _read(cell["out"])
    cmd = ["x_cmd_m", "y_cmd_m", "z_cmd_m"]
    np.testing.assert_array_equal(_cols(da, ["x_m", "y_m", "z_m"]), cell["P"])
    assert np.abs(_cols(da, cmd) - _cols(db, cmd)).max() < 1e-9
    assert np.abs(_cols(da, cmd) - _cols(old, cmd)).max() > 1e-5  # the models differ


def test_an_edited_copy_and_the_unitless_csv_of_before_are_read(cell, capsys):
    """As a technician hands it on: the `#` lines dropped or quoted by a spreadsheet, Windows
    line ends and a byte-order mark, one target moved by hand (its stale corrected joints
    cleared), a name column; and the targets CSV written before 2026-11-26 (x,y,z,..,x_cmd,..,
    q1_cmd without units or comments): the desired columns are read in each."""
    from workcell.export.targets_in import read_targets

    text = cell["out"].read_text().splitlines()
    head = next(i for i, x in enumerate(text) if not x.startswith("#"))
    rows = [r.split(",") for r in text[head + 1 :]]
    moved = cell["P"].copy()
    moved[2, 0] += 0.01
    rows[2][0] = repr(float(moved[2, 0]))
    rows[2][9:15] = [""] * 6  # the stale q*_cmd_rad of the moved target cleared
    edited = cell["dir"] / "edited.csv"
    body = [f'"# {text[1][2:]}"', "name," + text[head]] + [
        f"p{i}," + ",".join(r) for i, r in enumerate(rows)
    ]
    body.insert(4, "# p2 moved by 1 cm, by hand")
    edited.write_bytes(("\r\n".join(body) + "\r\n").encode("utf-8-sig"))
    t = read_targets(edited)
    np.testing.assert_array_equal(t.P, moved)
    assert t.corrected_csv and t.lines == [3, 4, 6, 7, 8]
    np.testing.assert_array_equal(t.q[2], Q_REF)  # its cleared joints: the reference seed
    out = cell["dir"] / "edited-out.csv"
    rc, lines, err = _run(
        ["export", cell["model"], "--format", "targets", "--in", edited, "--out", out], capsys
    )
    assert rc == 0, err
    d = _read(out)
    np.testing.assert_array_equal(_cols(d, ["x_m", "y_m", "z_m"]), moved)
    corr = Corrector(cell["m"], nominal_for(cell["m"]))
    assert np.abs(corr.real_base(_cols(d, Q_COLS)) - moved).max() < 1e-8

    old = cell["dir"] / "before-units.csv"
    names = ["x", "y", "z", "rx", "ry", "rz", "x_cmd", "y_cmd", "z_cmd"]
    old.write_text(
        ",".join(names + [f"q{i}_cmd" for i in range(1, 7)])
        + "\n"
        + "".join(",".join(r[:15]) + "\n" for r in (x.split(",") for x in text[head + 1 :]))
    )
    t = read_targets(old)
    np.testing.assert_array_equal(t.P, cell["P"])
    assert t.corrected_csv and "not its commanded x_cmd..q6_cmd" in t.notes[0]


def test_units_in_column_names_are_converted_and_said(cell, capsys):
    """x_mm (and `x [mm]`), rx_deg, q1_deg: converted to m and rad, with a line saying so; the
    same targets in m and rad give the same corrections."""
    from workcell.export.targets_in import read_targets

    P, rv = cell["P"], cell["rv"]
    f = cell["dir"] / "mm-deg.csv"
    f.write_text(
        "x_mm,Y [mm],z (mm),rx_deg,ry_deg,rz_deg\n"
        + "".join(
            ",".join(repr(float(v)) for v in (*p * 1e3, *np.degrees(r))) + "\n"
            for p, r in zip(P, rv, strict=True)
        )
    )
    t = read_targets(f)
    np.testing.assert_allclose(t.P, P, rtol=0, atol=1e-15)
    np.testing.assert_allclose(t.rotvec, rv, rtol=0, atol=1e-15)
    out = cell["dir"] / "mm-deg-out.csv"
    rc, lines, err = _run(
        ["export", cell["model"], "--format", "targets", "--in", f, "--out", out], capsys
    )
    assert rc == 0, err
    assert (
        f"{f}: converted x_mm,Y [mm],z (mm) from mm to m; rx_deg,ry_deg,rz_deg from deg to rad "
        "(the unit their names state)"
    ) in lines
    cmd = ["x_cmd_m", "y_cmd_m", "z_cmd_m"]
    assert np.abs(_cols(_read(out), cmd) - _cols(_read(cell["out"]), cmd)).max() < 1e-9
    # joint targets in degrees
    q = np.array([[1.2, -1.7, 1.9, -1.8, -1.57, -0.4], [1.0, -1.6, 1.8, -1.7, -1.57, -0.5]])
    g = cell["dir"] / "q-deg.csv"
    g.write_text(
        ",".join(f"q{i}_deg" for i in range(1, 7))
        + "\n"
        + "".join(",".join(repr(float(v)) for v in np.degrees(r)) + "\n" for r in q)
    )
    t = read_targets(g)
    assert t.P is None and t.q_role == "targets"
    np.testing.assert_allclose(t.q, q, rtol=0, atol=1e-15)


@pytest.mark.parametrize(
    "name, text, match",
    [
        ("empty", "", r"empty file, no header row and no targets; give a header row x,y,z"),
        ("comments", "# only a note\n\n", r"only comment lines, no header row"),
        ("header", "# note\nx_m,y_m,z_m\n", r"line 2 is a header but no target follows it"),
        ("x_deg", "x_deg,y,z\n0.1,-0.4,0.3\n", r"column 'x_deg': x is a position, not in deg; name its unit m"),
        ("q_mm", "q1_mm,q2,q3,q4,q5,q6\n0,-1,1,0,0,0\n", r"q1 is an angle, not in mm; name its unit rad or deg"),
        ("unit", "x [furlong],y,z\n0.1,-0.4,0.3\n", r"unit 'furlong' not accepted"),
        ("inch", "x_in,y_in,z_in\n4,-16,12\n", r"column 'x_in': unit 'in' not accepted"),
        ("q0", "q0,q1,q2,q3,q4,q5\n0,-1,1,0,0,0\n", r"the arm has 6 joints, q1..q6 .*; number them from 1"),
        ("q7", "q1,q2,q3,q4,q5,q6,q7\n0,-1,1,0,0,0,0\n", r"column 'q7': the arm has 6 joints.*; remove q7"),
        ("q5", "q1_rad,q2_rad,q3_rad,q4_rad,q5_rad\n0,-1,1,0,0\n", r"line 1: columns q1_rad,.*,q5_rad without q6"),
        ("seven", "q1,q2,q3,q4,q5,q6\n0,-1,1,0,0,0,0.5\n", r"line 2: 7 values under a header of 6 columns \(line 1\)"),
        ("nan", "# c\nx_m,y_m,z_m\n0.1,-0.4,0.3\n0.1,nan,0.3\n", r"line 4, column y_m: not a finite number \('nan'\); give a number in m"),
        ("text", "x_mm,y_mm,z_mm\n100,-400,300mm\n", r"line 2, column z_mm: '300mm' is not a number; give a plain number in mm"),
        ("gap", "x_m,y_m,z_m\n0.1,,0.3\n", r"line 2, column y_m: missing value; fill in a number in m or delete the line"),
        ("cmd_only", "x_cmd_m,y_cmd_m,z_cmd_m\n0.1,-0.4,0.3\n", r"only commanded columns .* correcting them would correct twice"),
        ("twice", "x,x_mm,y,z\n0.1,100,-0.4,0.3\n", r"line 1: columns 'x' and 'x_mm' both give x; keep one"),
        ("mm_as_m", "x_m,y_m,z_m\n100,-400,300\n", r"line 2: target 509.9 m .* looks like millimetres"),
        ("deg_turn", "x,y,z,rx_deg,ry_deg,rz_deg\n0.1,-0.4,0.3,0,400,0\n", r"line 2: rotation vector of 6.981 rad, more than a full turn; .* at most 360 deg"),
        ("rad_turn", "x,y,z,rx_rad,ry_rad,rz_rad\n0.1,-0.4,0.3,0,180,0\n", r"line 2: rotation vector of 180 rad, .* name the columns rx_deg"),
        ("binary", b"\xff\xfe\x00x,y\x00", r"not a text CSV file"),
        ("hash_name", "name,x,y,z\n#1,0.1,-0.4,0.3\n", r"line 2: starts with '#1' but holds a whole target: commented out, or named"),
        ("hash_only", "x,y,z\n#0.1,-0.4,0.3\n", r"line 1 is a header but no target follows it"),
        ("deg_as_rad", "q1_rad,q2_rad,q3_rad,q4_rad,q5_rad,q6_rad\n0,-100,1,0,0,0\n", r"line 2: column q2_rad is -100, .* looks like degrees"),
    ],
)  # fmt: skip
def test_bad_targets_are_refused_in_one_line_with_their_line(cell, capsys, name, text, match):
    f = cell["dir"] / f"bad-{name}.csv"
    if isinstance(text, bytes):
        f.write_bytes(text)
    else:
        f.write_text(text)
    out = cell["dir"] / f"bad-{name}-out.csv"
    rc, _, err = _run(
        ["export", cell["model"], "--format", "targets", "--in", f, "--out", out], capsys
    )
    assert rc == 2 and len(err) == 1, (name, err)
    assert re.search(match, err[0]), (name, err[0])
    assert "Traceback" not in err[0] and not out.exists()


# --------------------------------------------------------------------------------- fuzzing
# the column groups a targets file is made of (one of each kind at most: most files are
# readable), and columns that break it
_GROUPS = [
    [["x", "y", "z"], ["x_m", "y_m", "z_m"], ["X_mm", "y [mm]", "z (cm)"]],
    [["rx", "ry", "rz"], ["rx_rad", "ry_rad", "rz_rad"], ["rx_deg", "ry (deg)", "rz (°)"]],
    [[f"q{i}" for i in range(1, 7)], [f"q{i}_deg" for i in range(1, 7)]],
    [[f"q{i}_cmd_rad" for i in range(1, 7)], ["x_cmd_m", "y_cmd_m", "z_cmd_m"]],
    [["name"], ["sx_m", "sy_m", "sz_m"], [""], ["x_pos"]],
]  # fmt: skip
_BREAKERS = [
    "q0", "q7", "q1", "x", "rz", "x_deg", "q1_mm", "x [foo]", "x_in", "q3_cmd_rad", "#", " X ",
]  # fmt: skip
_GOOD_CELLS = st.one_of(st.floats(-1.2, 1.2).map(repr), st.integers(-3, 3).map(str))
_CELLS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(-400, 400).map(repr),
    st.sampled_from(["", " ", "nan", "inf", "1e400", "0.3m", "abc", '"', "#", "1_0", "١"]),
    st.text(max_size=6),
)


@st.composite
def _targets_file(draw) -> bytes:
    if draw(st.integers(0, 9)) == 0:  # anything at all
        return draw(st.binary(max_size=200))
    lines = [draw(st.sampled_from(["", "# corrected targets generated by workcell", "# a, b"]))]
    header = []
    for kind in _GROUPS:
        if draw(st.booleans()):
            header += draw(st.sampled_from(kind))
    header = draw(st.permutations(header))
    if draw(st.integers(0, 2)) == 0:
        header.insert(draw(st.integers(0, len(header))), draw(st.sampled_from(_BREAKERS)))
    if header and draw(st.integers(0, 4)) == 0:
        del header[draw(st.integers(0, len(header) - 1))]
    lines.append(",".join(header))
    bad = draw(st.integers(0, 2)) == 0  # some rows with any value at all
    for _ in range(draw(st.integers(0, 4))):
        n = len(header) + (draw(st.integers(-1, 1)) if draw(st.integers(0, 4)) == 0 else 0)
        cells = draw(
            st.lists(_CELLS if bad else _GOOD_CELLS, min_size=max(n, 0), max_size=max(n, 0))
        )
        lines.append(",".join(cells))
        if draw(st.integers(0, 3)) == 0:
            lines.append(draw(st.sampled_from(["", "# note", "#,x", '"# q, "', " , "])))
    return "\n".join(lines).encode("utf-8") + draw(st.sampled_from([b"", b"\n", b"\r\n"]))


@settings(max_examples=300, deadline=None, suppress_health_check=list(HealthCheck))
@given(blob=_targets_file())
def test_the_parser_returns_valid_targets_or_a_one_line_user_error(tmp_path_factory, blob):
    """Any file: `read_targets` returns finite arrays of the right shapes (one row per target
    line, rotation vectors within a full turn, a position or joint targets for each) or raises
    the tool's UserError in one line; never another exception."""
    from workcell.export.targets_in import read_targets

    f = tmp_path_factory.mktemp("fz") / "t.csv"
    f.write_bytes(blob)
    try:
        t = read_targets(f)
    except UserError as e:
        assert "\n" not in str(e) and str(e).startswith(f"{f}: ")
        return
    n = len(t.lines)
    assert n >= 1 and t.lines == sorted(set(t.lines)) and t.lines[0] >= 2
    assert (t.P is not None) or t.q_role == "targets"
    for a, w in ((t.P, 3), (t.rotvec, 3), (t.q, 6)):
        if a is not None:
            assert a.shape == (n, w) and a.dtype == float and np.all(np.isfinite(a))
    if t.rotvec is not None:
        assert t.P is not None and np.linalg.norm(t.rotvec, axis=1).max() <= 2 * math.pi + 1e-9
    assert (t.q is None) == (t.q_role is None)
    assert all("\n" not in x for x in t.notes)


def test_commanded_joints_outside_the_cells_envelope_are_refused(tmp_path, capsys):
    """A target 0.5 m below the base, with a model whose recording ran in the default envelope:
    `export --format targets` wrote commanded joints outside that envelope (q1 3.06 rad against
    +-2.97) with only an extrapolation warning. Now the line is refused; a target inside is
    written and the output says what the joints were checked against."""
    from sim_devices.cell import sim_cell
    from workcell.campaign.executor import CampaignConfig, CampaignControl
    from workcell.campaign.run import run_campaign

    _, robot, tracker, cell_ = sim_cell("ur5e", "none", 1, beam_break_prob=0.0)
    rec = tmp_path / "r.mcap"
    run_campaign(robot, tracker, cell_, rec, poses=2, seed=1,
                 config=CampaignConfig(readings_per_pose=1, settle_s=0.1),
                 control=CampaignControl())  # fmt: skip
    m = make_model(8)
    m.info["recording"] = str(rec)
    model = save_model(m, tmp_path / "m.json")
    below, inside = tmp_path / "below.csv", tmp_path / "inside.csv"
    below.write_text("x,y,z\n-0.4,0.1,0.3\n0.4,0.1,-0.5\n")
    inside.write_text("x,y,z\n-0.4,0.1,0.3\n")
    out = tmp_path / "t.csv"
    rc, _, err = _run(["export", model, "--format", "targets", "--in", below, "--out", out], capsys)
    assert rc == 2 and len(err) == 1 and not out.exists(), err
    assert "line 3: the corrected target's commanded joints" in err[0], err
    assert f"leave the envelope the model's recording {rec} ran in (joint 1 target" in err[0]
    rc, lines, _ = _run(["export", model, "--format", "targets", "--in", inside, "--out", out],
                        capsys)  # fmt: skip
    assert rc == 0 and f"  commanded joints inside the envelope the model's recording {rec}" in (
        "\n".join(lines)
    )
    m.info.pop("recording")
    bare = save_model(m, tmp_path / "bare.json")
    rc, lines, _ = _run(["export", bare, "--format", "targets", "--in", inside, "--out",
                         tmp_path / "t2.csv"], capsys)  # fmt: skip
    assert rc == 0 and any("checked against the arm's joint ranges only" in x for x in lines)


def test_a_target_whose_correction_1_sigma_exceeds_the_bound_is_refused_by_its_line(
    tmp_path, capsys
):
    """Each target is commanded on its own, so one target the model does not determine is
    refused by its CSV line, as an oversized correction is. Joint 1's offset uncertain by 10
    mrad: about 3 mm of 1-sigma at 0.3 m from its axis, 7 mm at 0.7 m. Until 2026-11-28 the
    targets were judged by their median 1-sigma (3 mm here), so the far target was written
    with its 7 mm 1-sigma."""
    m = make_model(8)
    m.cov = np.eye(39) * 1e-14
    m.cov[18, 18] = 0.01**2  # theta1_offset
    model = save_model(m, tmp_path / "m.json")
    rows = [(0.0, -0.3, 0.3), (0.05, -0.3, 0.3), (-0.05, -0.3, 0.3), (0.0, -0.7, 0.3)]
    src = tmp_path / "t.csv"
    src.write_text("x,y,z,rx,ry,rz\n" + "".join(f"{x},{y},{z},0,{math.pi},0\n" for x, y, z in rows))
    out = tmp_path / "c.csv"
    rc, _, err = _run(["export", model, "--format", "targets", "--in", src, "--out", out], capsys)
    assert rc == 2 and len(err) == 1, err
    assert re.search(rf"{re.escape(str(src))}: line 5: the correction's 1-sigma there is 7(\.\d+)? mm, "
                     r"more than 5 mm \(the correction bound\)", err[0]), err[0]  # fmt: skip
    assert not out.exists()
    # the near ones alone are written
    src.write_text(
        "x,y,z,rx,ry,rz\n" + "".join(f"{x},{y},{z},0,{math.pi},0\n" for x, y, z in rows[:3])
    )
    rc, _, err = _run(["export", model, "--format", "targets", "--in", src, "--out", out], capsys)
    assert rc == 0 and out.exists(), err
