"""Correction of targets and the correction table: exactness, interpolation error, refusals, CLI."""

import json
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from workcell.errors import UserError
from workcell.estimation.dh import DHModel
from workcell.estimation.models import save_model
from workcell.export.correction import (
    Q_REF,
    Corrector,
    nominal_for,
    rotvec_to_matrix,
)
from workcell.export.table import CorrectionRefused, build_table, node_std
from workcell.kinematics.chain import pack
from workcell.kinematics.robots import UR5E

LO, HI = np.array([-0.15, -0.5, 0.2]), np.array([0.15, -0.3, 0.4])
DOWN = [0.0, np.pi, 0.0]


def make_model(seed=0, scale=1.0):
    rng = np.random.default_rng(seed)
    th = pack(UR5E.dh, tool=(0.0, 0.0, 0.06))
    th[:24] += scale * rng.normal(0, [3e-4] * 12 + [5e-4] * 6 + [1e-3] * 6)
    th[36:39] += scale * rng.normal(0, 3e-4, 3)
    base_ref = np.eye(4)
    base_ref[:3, 3] = (2.0, 0.3, -0.4)
    return DHModel(
        robot_model="ur5e",
        nominal_dh=UR5E.dh,
        theta=th,
        base_ref=base_ref,
        cov=np.zeros((39, 39)),
        free=np.ones(39, bool),
        info={"nominal_tool_m": [0, 0, 0.06]},
    )


def test_cartesian_and_joint_corrections_land_on_target():
    m = make_model(1)
    corr = Corrector(m, nominal_for(m))
    R = rotvec_to_matrix(DOWN)[0]
    P = np.random.default_rng(2).uniform(LO, HI, (30, 3))
    c, q, res = corr.correct_positions(P, R, Q_REF)
    assert np.all(np.isfinite(c))
    # the model's robot at the corrected joints lands on the target ...
    assert np.abs(corr.real_base(q) - P).max() < 1e-9
    # ... and the controller's nominal kinematics reaches q when asked for c with orientation R
    p_nom, R_nom = corr.nominal.fk(q)
    assert np.abs(p_nom - c).max() < 1e-9 and np.abs(R_nom - R).max() < 1e-9
    # uncorrected targets miss by the model's error (so the test can fail)
    q_u, _ = corr.nominal.ik(P, R, Q_REF)
    assert np.linalg.norm(corr.real_base(q_u) - P, axis=1).min() > 1e-5
    # joint-space form: q_nominal -> q_corrected with k_real(q_corrected) = k_nominal(q_nominal)
    qc = corr.correct_joints(q_u[:5])
    assert np.abs(corr.real_base(qc) - corr.nominal.fk(q_u[:5])[0]).max() < 1e-9


def test_table_interpolation_error_is_measured_and_met():
    m = make_model(3)
    corr = Corrector(m, nominal_for(m))
    tab = build_table(corr, LO, HI, [DOWN], target_error_m=3e-6, n_check=100)
    assert tab.meta["interp_error_target_met"]
    assert tab.meta["max_interp_error_m"] <= 3e-6
    # independent check on fresh random points against the exact correction
    P = np.random.default_rng(9).uniform(LO, HI, (50, 3))
    c, _, _ = corr.correct_positions(P, rotvec_to_matrix(DOWN)[0], tab.seed_for(P))
    err = np.linalg.norm(tab.correct(P, DOWN) - c, axis=1)
    assert err.max() < 2 * 3e-6
    # at the nodes the table is exact
    X = tab.node_positions().reshape(-1, 3)[:20]
    c, _, _ = corr.correct_positions(X, rotvec_to_matrix(DOWN)[0], tab.seed_for(X))
    assert np.abs(tab.correct(X, DOWN) - c).max() < 1e-9


def test_oversized_correction_is_refused_with_where():
    m = make_model(4, scale=30.0)  # ~1 cm errors
    corr = Corrector(m, nominal_for(m))
    with pytest.raises(CorrectionRefused, match=r"refused: correction .* mm at \[.*\] m \(base\)"):
        build_table(corr, LO, HI, [DOWN], spacing_m=0.1)


def test_non_finite_correction_is_refused_with_where():
    m = make_model(5)

    class Holey:
        method = "holey"
        nominal_dh, base_ref, info, robot_model = m.nominal_dh, m.base_ref, m.info, "ur5e"

        def predict(self, q, **aux):
            p = np.array(m.predict(q))
            p[q[:, 0] > 1.6] = np.nan  # the model is undefined in part of the volume
            return p

    corr = Corrector(Holey(), nominal_for(Holey()))
    with pytest.raises(CorrectionRefused, match="no finite correction"):
        build_table(corr, LO, HI, [DOWN], spacing_m=0.1)


def test_cli_export_refuses_and_writes(tmp_path, capsys):
    from workcell.cli import main

    path = save_model(make_model(6), tmp_path / "m.json")
    vol = ",".join(str(v) for v in [*LO, *HI])
    rc = main(
        [
            "export",
            str(path),
            "--format",
            "table",
            "--out",
            str(tmp_path / "t"),
            f"--volume={vol}",
            "--spacing",
            "0.1",
            "--max-correction",
            "1e-5",
        ]
    )
    assert rc != 0
    rc = main(
        [
            "export",
            str(path),
            "--format",
            "table",
            "--out",
            str(tmp_path / "t"),
            f"--volume={vol}",
            "--spacing",
            "0.1",
            "--json",
        ]
    )
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    # a model without a recorded joint range: the summary says the coverage is unknown
    assert summary["joint_coverage"]["basis"].startswith("unknown")
    assert summary["nodes_std_exceeds_correction"] == 0  # zero covariance: nothing flagged
    d = json.loads((tmp_path / "t.json").read_text())
    assert d["meta"]["robot"] == "ur5e" and d["meta"]["max_interp_error_m"] > 0
    assert (tmp_path / "t.csv").read_text().count("\n") > 20


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"spacing_m": 0.0}, "spacing must be a positive"),
        ({"spacing_m": -0.1}, "spacing must be a positive"),
        ({"spacing_m": float("nan")}, "spacing must be a positive"),
        ({"spacing_m": 1e-5}, r"nodes per orientation \(limit 100000\); use a spacing of at least"),
        ({"target_error_m": 0.0}, "interpolation error target must be a positive"),
        ({"max_correction_m": -1.0}, "max correction must be a positive"),
    ],
)
def test_table_options_out_of_range_are_refused_before_any_work(kw, match):
    m = make_model(7)
    corr = Corrector(m, nominal_for(m))
    with pytest.raises(UserError, match=match):
        build_table(corr, LO, HI, [DOWN], **kw)


def test_cli_targets_land_on_target_and_refuse_bad_rows(tmp_path, capsys):
    """`--format targets`: each corrected target brings the model's robot onto the desired
    position; a NaN, a millimetre position or a joint in degrees is refused with its row."""
    import csv

    from workcell.cli import main

    m = make_model(8)
    m.cov = np.diag(np.random.default_rng(4).uniform(1e-10, 1e-8, 39))  # a 1-sigma to carry
    path = save_model(m, tmp_path / "m.json")
    P = np.random.default_rng(3).uniform(LO, HI, (6, 3))
    good = tmp_path / "good.csv"
    good.write_text("x,y,z\n" + "".join(f"{x},{y},{z}\n" for x, y, z in P))
    out = tmp_path / "out.csv"
    assert (
        main(["export", str(path), "--format", "targets", "--in", str(good), "--out", str(out)])
        == 0
    )
    rows = list(csv.DictReader(x for x in open(out) if not x.startswith("#")))
    q_cmd = np.array([[float(r[f"q{i}_cmd_rad"]) for i in range(1, 7)] for r in rows])
    corr = Corrector(m, nominal_for(m))
    assert np.abs(corr.real_base(q_cmd) - P).max() < 1e-8
    # each target carries the model's 1-sigma (it carried none): here the table's node formula
    sd = np.array([[float(r[f"s{a}_m"]) for a in "xyz"] for r in rows])
    assert np.all(sd > 1e-6)
    assert sd == pytest.approx(node_std(corr, q_cmd), rel=1e-9)
    # as a spreadsheet saves it: a BOM, spaced and capitalised headers, a name column, blank rows
    sheet = tmp_path / "sheet.csv"
    sheet.write_text(
        " Name , X , y ,Z \n" + "".join(f"p{i}, {x},{y}, {z}\n\n" for i, (x, y, z) in enumerate(P)),
        encoding="utf-8-sig",
    )
    out2 = tmp_path / "out2.csv"
    assert (
        main(["export", str(path), "--format", "targets", "--in", str(sheet), "--out", str(out2)])
        == 0
    )
    assert out2.read_text() == out.read_text()
    capsys.readouterr()
    bad = {
        "nan": ("x,y,z\n0.1,-0.4,0.3\nnan,0,0\n", "line 3, column x: not a finite number"),
        "mm": ("x,y,z\n100,-400,300\n", "line 2: target 509.9 m .* looks like millimetres"),
        "gap": ("x,y,z\n0.1,-0.4,0.3\n0.1,,0.3\n", "line 3, column y: missing value"),
        "short": ("x,y,z\n0.1,-0.4\n", "line 2, column z: missing value"),
        "text": ("x,y,z\n0.1,-0.4,0.3m\n", "line 2, column z: '0.3m' is not a number"),
        "cols": ("a,b,c\n0.1,-0.4,0.3\n", "need columns x,y,z .* 'a,b,c'"),
        "part": ("x,y,z,rx,ry\n0.1,-0.4,0.3,0.5,3.0\n", "columns rx,ry without rz"),
        "seed_deg": (
            "x,y,z,q1,q2,q3,q4,q5,q6\n0.1,-0.4,0.3,10,-70,60,-80,-90,12\n",
            "line 2: column q.* looks like degrees",
        ),
        "huge": ("x,y,z\n1e308,1e308,0.3\n", "line 2: target inf m from the base"),
        "origin": ("x,y,z\n0.1,-0.4,0.3\n0,0,0\n", "line 3: no correction for the target"),
        "deg": (
            "q1,q2,q3,q4,q5,q6\n0,-1,1,0,0,0\n0,-100,1,0,0,0\n",
            "line 3: column q2 is -100, .* looks like degrees",
        ),
    }
    for name, (text, match) in bad.items():
        f = tmp_path / f"{name}.csv"
        f.write_text(text)
        o = tmp_path / f"{name}-out.csv"
        rc = main(["export", str(path), "--format", "targets", "--in", str(f), "--out", str(o)])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1, (name, err)
        assert re.search(match, err[0]), (name, err)
        assert not o.exists()


@pytest.fixture(scope="module")
def saved_table() -> dict:
    m = make_model(9)
    return build_table(Corrector(m, nominal_for(m)), LO, HI, [DOWN], spacing_m=0.1).to_dict()


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_a_malformed_table_file_is_refused_in_one_line(saved_table, tmp_path_factory, data):
    """Any JSON in any field of a saved table: `load_table` returns a consistent table (shapes
    match, every correction finite) or refuses it with one UserError line."""
    from jsonfuzz import replace_any_field

    from workcell.export.table import load_table

    d = json.loads(json.dumps(saved_table))
    replace_any_field(data, d)
    f = tmp_path_factory.mktemp("tab") / "t.json"
    f.write_text(json.dumps(d))
    try:
        tab = load_table(f)
    except UserError as e:
        assert "\n" not in str(e)
    else:
        tab.check()
        P = np.random.default_rng(0).uniform(tab.lo_m, tab.hi_m, (5, 3))
        assert np.all(np.isfinite(tab.interpolate(P, 0)))


def test_node_std_is_the_spread_of_the_corrections_over_the_parameter_covariance(tmp_path):
    """Each node's 1-sigma (base axes) agrees with the spread of the exact correction over
    parameters drawn from the model's covariance (a rotated registration, so the tracker-to-base
    rotation must be right), and goes through the JSON and CSV files."""
    from workcell.export.table import load_table, node_std

    m = make_model(4)
    c, s = np.cos(0.9), np.sin(0.9)
    m.base_ref[:3, :3] = [[1, 0, 0], [0, c, -s], [0, s, c]]
    rng = np.random.default_rng(7)
    A = rng.normal(size=(39, 39)) * 5e-6
    A[:, 30:36] = 0.0  # keep the base offsets fixed (as a fit with the registration does)
    m.cov = A @ A.T
    m.cov[6, 6] += 1e-4**2  # d1: moves every SMR along base z, so the axes must be right
    corr = Corrector(m, nominal_for(m))
    tab = build_table(corr, LO, HI, np.array([DOWN]), spacing_m=0.1)
    assert tab.std_m is not None and tab.std_m.shape == tab.delta_m.shape
    assert "std_basis" in tab.meta and tab.meta["max_std_m"] > 0
    R = rotvec_to_matrix(DOWN)[0]
    X = tab.node_positions().reshape(-1, 3)[[0, 5, -1]]
    Q = tab.q_nodes[0].reshape(-1, 6)[[0, 5, -1]]
    want = node_std(corr, Q)
    draws = []
    for th in rng.multivariate_normal(m.theta, m.cov, size=400):
        m2 = make_model(4)
        m2.theta, m2.base_ref = th, m.base_ref
        cc, _, _ = Corrector(m2, corr.nominal).correct_positions(X, R, Q)
        draws.append(cc - X)
    mc = np.std(np.array(draws), axis=0)
    np.testing.assert_allclose(want, mc, rtol=0.15)
    assert want.max() > 1e-5  # tens of micrometres: the test can fail
    # zero covariance: zero std, not None
    m.cov = np.zeros((39, 39))
    assert np.all(node_std(corr, Q) == 0)
    # the files
    tab.save(tmp_path / "t")
    back = load_table(tmp_path / "t.json")
    np.testing.assert_array_equal(back.std_m, tab.std_m)
    rows = [r for r in (tmp_path / "t.csv").read_text().splitlines() if not r.startswith("#")]
    assert rows[0].endswith("dx_m,dy_m,dz_m,sx_m,sy_m,sz_m")
    assert float(rows[1].split(",")[-3]) == tab.std_m[0, 0, 0, 0, 0]


def test_a_model_without_covariance_writes_no_std_and_says_so():
    class Blob:
        method = "lddmm"

        def __init__(self, m):
            self.m = m

        def predict(self, q, **aux):
            return self.m.predict(q)

    m = make_model(5)
    corr = Corrector(Blob(m), nominal_for(m))
    tab = build_table(corr, LO, HI, np.array([DOWN]), spacing_m=0.1)
    assert tab.std_m is None and tab.to_dict()["std_m"] is None
    assert tab.meta["std_basis"].startswith("none")
    assert tab.interpolate_std(np.array([[0.0, -0.4, 0.3]])) is None


@pytest.mark.parametrize("bad", ["shape", "negative", "nan"])
def test_a_table_with_a_bad_std_is_refused(bad):
    from workcell.export.table import CorrectionTable

    m = make_model(6)
    m.cov = np.eye(39) * 1e-12
    tab = build_table(Corrector(m, nominal_for(m)), LO, HI, np.array([DOWN]), spacing_m=0.1)
    d = tab.to_dict()
    s = np.asarray(d["std_m"])
    if bad == "shape":
        s = s[..., :2]
    elif bad == "negative":
        s[0, 0, 0, 0, 0] = -1e-6
    else:
        s[0, 0, 0, 0, 0] = np.nan
    d["std_m"] = s.tolist()
    with pytest.raises(ValueError, match="std_m"):
        CorrectionTable.from_dict(d)


def _thermal_model(source: str):
    """An augmented model with joint-2 compliance and thermal drift driven by `source`."""
    from workcell.estimation import effects as E
    from workcell.estimation.effects import AugmentedModel, FeatureSpec, library

    dh = make_model(8)
    acc = [c for c in library() if c.key in ("joint_compliance/joint2", "thermal_drift")]
    eff = np.zeros(E.N_EFF)
    for c in acc:
        eff[c.idx[0]] = 20e-6  # rad/(N m) and 1/K (or 1/h)
    return AugmentedModel(
        features_spec=FeatureSpec(
            spec=UR5E,
            payload_com_m=np.array([0, 0, 0.03]),
            thermal_source=source,
            thermal_ref=np.full(6, 25.0 if source == "joint" else 0.5),
            payload_kg_default=1.0,
        ),
        theta=dh.theta,
        base_ref=dh.base_ref,
        eff=eff,
        accepted=acc,
        free=np.ones(39, bool),
        cov=np.eye(41) * 1e-14,
        nominal_tool_m=np.array([0, 0, 0.06]),
        info={"nominal_tool_m": [0, 0, 0.06]},
    )


def test_export_conditions_are_stated_applied_and_checked(tmp_path, capsys):
    """The table says which payload and thermal state it is for; a given condition changes the
    correction; a condition that does not drive the model's effect, or in the wrong unit, is
    refused in one line."""
    from workcell.cli import main
    from workcell.export.build import conditions_note, parse_conditions

    m = _thermal_model("joint")
    notes = conditions_note(m, parse_conditions("1,1,1,1,1,1"))
    assert "payload 1 kg, the recording's" in notes[0]
    assert "the recording's mean, link temperatures [25.0" in notes[1]
    notes = conditions_note(m, parse_conditions("1,1,1,1,1,1", "2.5", "35,35,35,35,35,35"))
    assert "payload 2.5 kg (given)" in notes[0] and "[35.0, 35.0" in notes[1]
    with pytest.raises(UserError, match="--elapsed does not set .* joint temperatures"):
        conditions_note(m, parse_conditions("1,1,1,1,1,1", elapsed="3600"), strict=True)
    with pytest.raises(UserError, match="--joint-temperature does not set .* time"):
        conditions_note(
            _thermal_model("time"),
            parse_conditions("1,1,1,1,1,1", None, "30," * 5 + "30"),
            strict=True,
        )
    assert (
        "changes nothing" in conditions_note(make_model(1), parse_conditions("1,1,1,1,1,1", "2"))[0]
    )
    # what validate passes (the cell's joint temperatures) is described, not refused
    notes = conditions_note(
        _thermal_model("time"), parse_conditions("1,1,1,1,1,1", None, "30," * 5 + "30")
    )
    assert "the recording's mean, 1800 s after" in notes[1]
    # applied: a warmer arm, another correction (the model's nominal chain is the DH model's)
    from workcell.export.correction import Conditions

    nom = nominal_for(make_model(8))
    deltas = {}
    for name, t in (("ref", None), ("warm", np.full(6, 45.0))):
        corr = Corrector(m, nom, Conditions(joint_temperature_c=t))
        deltas[name] = build_table(corr, LO, HI, np.array([DOWN]), spacing_m=0.1).delta_m
    # 20 K x 20e-6/K over the arm: tens of micrometres
    assert np.abs(deltas["warm"] - deltas["ref"]).max() > 1e-5
    # the command line states the conditions and refuses one that does not drive the drift
    path = save_model(m, tmp_path / "aug.json")
    # (this bare model has no recording to register its nominal chain on: exit 2 after that)
    assert main(["export", str(path), "--format", "table", "--out", str(tmp_path / "t")]) == 2
    out, err = capsys.readouterr()
    assert "--recording" in err
    assert "conditions: payload 1 kg, the recording's" in out
    assert "conditions: thermal state: the recording's mean" in out
    argv = ["export", str(path), "--format", "table", "--out", str(tmp_path / "t")]
    assert main([*argv, "--elapsed", "60"]) == 2
    err = capsys.readouterr().err
    assert "driven by the joint temperatures" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize(
    ("opt", "value", "what"),
    [
        ("--payload", "3000", "give kilograms"),
        ("--payload", "nan", "expected 1"),
        ("--joint-temperature", "300,300,300,300,300,300", "kelvin or Fahrenheit"),
        ("--joint-temperature", "30,30", "expected 6"),
        ("--elapsed", "-5", "give seconds"),
    ],
)
def test_export_conditions_in_wrong_units_are_refused(tmp_path, capsys, opt, value, what):
    from workcell.cli import main

    path = save_model(_thermal_model("joint"), tmp_path / "aug.json")
    rc = main(["export", str(path), "--format", "table", "--out", str(tmp_path / "t"), opt, value])
    err = capsys.readouterr().err
    assert rc == 2 and what in err and len(err.strip().splitlines()) == 1
    assert not list(tmp_path.glob("t.*"))


@pytest.mark.parametrize(
    ("fmt", "extra", "what"),
    [
        ("ros-yaml", ["--payload", "2", "--elapsed", "60"], "--payload, --elapsed: not used"),
        ("ros-yaml", ["--volume=0,0,0,1,1,1"], "carries the geometry only"),
        ("ros-yaml", ["--approach=-1,1,1,1,1,1"], "--approach: not used"),
        ("table", ["--in", "TARGETS"], "--in: not used by --format table"),
        ("urscript", ["--in", "TARGETS"], "--in is for --format targets"),
        ("targets", ["--in", "TARGETS", "--spacing", "0.1"], "--spacing: not used"),
        ("targets", ["--in", "TARGETS", "--interp-error", "1e-6"], "corrects the --in targets"),
    ],
)
def test_export_refuses_options_its_format_would_ignore(tmp_path, capsys, fmt, extra, what):
    from workcell.cli import main

    path = save_model(make_model(1), tmp_path / "dh.json")
    targets = tmp_path / "targets.csv"
    targets.write_text("x,y,z\n0.4,0.1,0.3\n")
    extra = [str(targets) if x == "TARGETS" else x for x in extra]
    out = tmp_path / "o.json"
    rc = main(["export", str(path), "--format", fmt, "--out", str(out), *extra])
    err = capsys.readouterr().err
    assert rc == 2 and what in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_validate_warns_when_a_table_is_for_another_thermal_state():
    """A table exported for the recording's mean thermal state, validated on a warmer arm, gets
    one warning line with the export option that fixes it; within 2 K, none."""
    from workcell.export.table import CorrectionTable
    from workcell.export.validate import thermal_mismatch

    m = _thermal_model("joint")  # thermal_ref: links at 25 degC
    tab = CorrectionTable(LO, HI, (2, 2, 2), np.array([DOWN]), np.zeros((1, 2, 2, 2, 3)))
    tab.meta = {"conditions": {"joint_temperature_c": None}}
    assert thermal_mismatch(m, tab, np.full(6, 26.0)) is None
    w = thermal_mismatch(m, tab, np.full(6, 31.0))
    assert "the recording's mean" in w and "6.0 K apart" in w
    assert "--joint-temperature 31.0,31.0" in w
    tab.meta = {"conditions": {"joint_temperature_c": [31.0] * 6}}
    assert thermal_mismatch(m, tab, np.full(6, 31.0)) is None
    assert thermal_mismatch(m, tab, None) is None  # a controller without temperatures
    assert thermal_mismatch(_thermal_model("time"), tab, np.full(6, 50.0)) is None


def test_thermal_warning_weighs_the_drift_against_the_tables_own_1_sigma():
    """With the model's fitted joint range and the table's median 1-sigma known, the warning
    follows what the mismatch moves the SMR by, not a fixed 2 K: a 1.6 K mismatch on the
    audit's simulated cell cost 17.8 um against 7.6 um (table 1-sigma 3.8 um) and went unsaid."""
    from workcell.export.table import CorrectionTable
    from workcell.export.validate import thermal_mismatch, thermal_shift_rms_m

    m = _thermal_model("joint")  # thermal_ref: links at 25 degC, 20e-6 /K
    m.info["joint_range_rad"] = [[-1.0, 1.0]] * 6
    tab = CorrectionTable(LO, HI, (2, 2, 2), np.array([DOWN]), np.zeros((1, 2, 2, 2, 3)))
    shift = thermal_shift_rms_m(m, None, np.full(6, 26.0))
    assert shift is not None and 1e-6 < shift < 1e-3
    assert thermal_shift_rms_m(m, None, np.full(6, 25.0)) == pytest.approx(0.0, abs=1e-12)
    tab.meta = {"conditions": {"joint_temperature_c": None}, "median_std_m": shift / 2}
    w = thermal_mismatch(m, tab, np.full(6, 26.0))  # 1 K: within the old 2 K rule
    assert w is not None and "1.0 K apart" in w and "um RMS over its fitted joint range" in w
    tab.meta["median_std_m"] = 10.0 * thermal_shift_rms_m(m, None, np.full(6, 31.0))
    assert thermal_mismatch(m, tab, np.full(6, 31.0)) is None  # 6 K, but below its 1-sigma


def test_a_failed_table_write_keeps_the_earlier_table_whole(tmp_path, monkeypatch):
    """A table write that fails half way (a full disk) used to leave the new JSON beside a CSV
    cut off mid-row, with the earlier good CSV gone; a later run took the truncated CSV for a
    table. Now both files are written to temporaries and renamed only when both are whole."""
    import errno

    import workcell.export.table as table_mod
    from workcell.export.table import load_table

    m = make_model(3)
    corr = Corrector(m, nominal_for(m))
    tab = build_table(corr, LO, HI, [DOWN], spacing_m=0.2, n_check=20)
    tab.save(tmp_path / "t")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert set(before) == {"t.json", "t.csv"}

    class FullDisk:
        def __init__(self, f):
            self.rows = 0

        def writerow(self, row):
            self.rows += 1
            if self.rows > 3:
                raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(table_mod.csv, "writer", FullDisk)
    with pytest.raises(OSError, match="No space left"):
        tab.save(tmp_path / "t")
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # no temporaries
    monkeypatch.undo()
    assert load_table(tmp_path / "t").shape == tab.shape


def test_a_dotted_output_name_keeps_its_dots():
    """`--out cell.v1` wrote cell.json and cell.csv (the '.v1' taken for an extension), and a
    URScript `--out cell.v2` then silently replaced that table. A .json, .csv or .script
    extension is replaced; any other dotted part is kept."""
    from pathlib import Path

    from workcell.export.files import output_files
    from workcell.export.table import table_files

    assert table_files("out/cell.v1") == (Path("out/cell.v1.json"), Path("out/cell.v1.csv"))
    assert table_files("cell.json") == (Path("cell.json"), Path("cell.csv"))
    assert table_files("cell.script") == (Path("cell.json"), Path("cell.csv"))
    assert output_files("table", Path("cell.v1")) == [Path("cell.v1.json"), Path("cell.v1.csv")]
    assert output_files("urscript", Path("cell.v2")) == [
        Path("cell.v2"), Path("cell.v2.json"), Path("cell.v2.csv"),
    ]  # fmt: skip
    assert output_files("urscript", Path("c")) == [
        Path("c.script"), Path("c.json"), Path("c.csv"),
    ]  # fmt: skip


def test_joint_coverage_counts_the_nodes_outside_the_fitted_range():
    from workcell.export.table import coverage_line, joint_coverage

    m = make_model(4)
    corr = Corrector(m, nominal_for(m))
    tab = build_table(corr, LO, HI, [DOWN], spacing_m=0.1, n_check=20)
    assert tab.meta["joint_coverage"]["basis"].startswith("unknown")  # the model says nothing
    q = tab.q_nodes.reshape(-1, 6)
    lo, hi = q.min(0), q.max(0)
    m.info["joint_range_rad"] = np.stack([lo - 0.01, hi + 0.01], 1).tolist()
    cov = joint_coverage(corr, tab.q_nodes)
    assert cov["nodes_outside"] == 0 and cov["per_joint"] == {}
    assert "inside" in coverage_line(cov)
    # narrow joint 2's range to its middle: the nodes beyond it, counted independently
    mid = 0.5 * (lo[1] + hi[1])
    m.info["joint_range_rad"][1] = [lo[1] - 0.01, mid]
    cov = joint_coverage(corr, tab.q_nodes)
    assert cov["nodes_outside"] == int(np.sum(q[:, 1] > mid)) > 0
    assert list(cov["per_joint"]) == ["2"]
    assert cov["per_joint"]["2"]["max_beyond_rad"] == pytest.approx(hi[1] - mid)
    assert coverage_line(cov).startswith("WARNING") and "joint 2" in coverage_line(cov)


def test_a_correction_smaller_than_its_1_sigma_is_flagged():
    """A model whose SMR offset along the tool is uncertain by 4 mm (as a fit whose poses cannot
    tell tool_z from a base offset): every node's correction is undetermined, and export says
    so; with 0.1 um stds none is."""
    m = make_model(4)
    m.cov = np.eye(39) * 1e-14
    corr = Corrector(m, nominal_for(m))
    lines = []
    tab = build_table(corr, LO, HI, [DOWN], spacing_m=0.1, log=lines.append)
    assert tab.meta["nodes_std_exceeds_correction"] == 0
    assert not any("1-sigma is larger" in x for x in lines)
    m.cov[38, 38] = 0.004**2  # tool_z (above 5 mm no table is built: the next test)
    lines = []
    tab = build_table(corr, LO, HI, [DOWN], spacing_m=0.1, log=lines.append)
    n = tab.delta_m[..., 0].size
    assert tab.meta["nodes_std_exceeds_correction"] == n
    assert any(x.strip().startswith(f"WARNING: at {n} of {n} nodes") for x in lines)


def test_corrections_whose_1_sigma_exceeds_the_bound_are_refused_with_the_weak_group():
    """The same model with tool_z uncertain by 20 mm: its corrections' median 1-sigma exceeds 5
    mm, so no table is built, even with --max-correction raised (series D's DH model, whose
    {base_ty, tool_z} the poses barely tell apart, wrote one with a 38 mm median 1-sigma until
    2026-11-28); the refusal names the weakly identified group the fit recorded."""
    m = make_model(4)
    m.cov = np.eye(39) * 1e-14
    m.cov[38, 38] = 0.02**2
    m.info["identifiability"] = {
        "weakly_identified": [{"parameters": ["base_ty", "tool_z"], "std_inflation": 2614.0}]
    }
    corr = Corrector(m, nominal_for(m))
    for bound in (5e-3, 0.05):
        with pytest.raises(CorrectionRefused) as e:
            build_table(corr, LO, HI, [DOWN], spacing_m=0.1, max_correction_m=bound)
        msg = str(e.value)
        assert "median 1-sigma is 20 mm over the nodes, more than 5 mm" in msg, msg
        assert "the fit left {base_ty, tool_z} weakly identified" in msg and "\n" not in msg
    m.cov[38, 38] = 0.004**2  # 4 mm: within the bound, built (and flagged as undetermined)
    tab = build_table(corr, LO, HI, [DOWN], spacing_m=0.1)
    assert tab.meta["nodes_std_exceeds_correction"] == tab.delta_m[..., 0].size


def test_a_crash_between_the_pairs_renames_is_refused_not_read_as_one_table(tmp_path, monkeypatch):
    """The JSON and CSV are renamed one after the other; a kill between the two renames left
    the new grid's JSON beside the earlier grid's CSV, and nothing noticed (crash audit). The
    CSV is renamed first and the JSON records its sha256: the earlier JSON beside the new CSV
    is refused in one line; a whole pair loads."""
    import os as os_mod

    import workcell.atomic as atomic_mod
    from workcell.errors import UserError
    from workcell.export.table import load_table

    m = make_model(3)
    corr = Corrector(m, nominal_for(m))
    coarse = build_table(corr, LO, HI, [DOWN], spacing_m=0.2, n_check=20)
    fine = build_table(corr, LO, HI, [DOWN], spacing_m=0.12, n_check=20)
    coarse.save(tmp_path / "t")
    assert load_table(tmp_path / "t").shape == coarse.shape
    renames, real_replace = [], os_mod.replace

    def replace_then_die(src, dst):
        if renames:
            raise KeyboardInterrupt  # the process killed before the second rename
        renames.append(dst)
        real_replace(src, dst)

    monkeypatch.setattr(atomic_mod.os, "replace", replace_then_die)
    with pytest.raises(KeyboardInterrupt):
        fine.save(tmp_path / "t")
    monkeypatch.undo()
    assert [os_mod.path.basename(p) for p in renames] == ["t.csv"]
    with pytest.raises(UserError, match=r"t.csv is not the CSV written with t.json"):
        load_table(tmp_path / "t.json")
    fine.save(tmp_path / "t")
    assert load_table(tmp_path / "t").shape == fine.shape
