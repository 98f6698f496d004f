"""What the export files and the export summary state beside the numbers: extrapolation, the
1-sigma, what the model leaves unexplained, which ROS-YAML values were not estimated; and the
refusal of a geometry far from the arm's nominal one."""

import csv
import json
import re

import numpy as np
import pytest
from test_export_table import HI, LO, make_model  # noqa: E402

from workcell.estimation.dh import DHModel
from workcell.estimation.models import save_model
from workcell.export.correction import Corrector, nominal_for
from workcell.export.table import CorrectionRefused, build_table, is_warning
from workcell.kinematics.chain import IDX

VOL = ",".join(str(v) for v in [*LO, *HI])
# held-out RMS 50 um (95 % CI 45-60 um) over a 10 um noise floor: 49.0 um above it, up to 59.2 um
UNEXPLAINED = "49.0 um above the noise floor (up to 59.2 um at the upper end of the 95 % interval)"


def _model(seed: int = 8, joint1=(2.5, 3.0)) -> DHModel:
    """A DH model with a covariance, a held-out figure, and a fitted joint-1 range (rad) that
    the targets in LO..HI lie outside of (the audit: q1 1.08-1.45 rad against [-3.14, -0.78])."""
    m = make_model(seed)
    m.cov = np.diag(np.random.default_rng(4).uniform(1e-10, 1e-8, 39))
    m.info.update(
        heldout_rms_m=50e-6,
        heldout_rms_ci95_m=[45e-6, 60e-6],
        unexplained={"floor_m": 10e-6},
        joint_range_rad=[list(joint1)] + [[-6.0, 6.0]] * 5,
    )
    return m


def _run(argv, capsys) -> tuple[int, list[str], list[str]]:
    from workcell.cli import main

    rc = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out.splitlines(), err.splitlines()


def test_targets_state_extrapolation_units_and_the_1_sigma(tmp_path, capsys):
    """`--format targets` warned about nothing, wrote columns without units under no header, and
    printed only "wrote": it now says which targets are extrapolations (as the table does), heads
    the CSV with model, frame and units, names each column's unit and prints the 1-sigma and
    what the model leaves unexplained; numpy and csv read it with comments skipped."""
    m = _model()
    path = save_model(m, tmp_path / "m.json")
    P = np.random.default_rng(3).uniform(LO, HI, (6, 3))
    src = tmp_path / "targets.csv"
    src.write_text("x,y,z\n" + "".join(f"{x},{y},{z}\n" for x, y, z in P))
    out = tmp_path / "corrected.csv"
    argv = ["export", path, "--format", "targets", "--in", src, "--out", out]
    rc, lines, err = _run(argv, capsys)
    assert rc == 0, err
    text = out.read_text().splitlines()
    head = [x for x in text if x.startswith("#")]
    body = [x for x in text if not x.startswith("#")]
    assert text[: len(head)] == head  # the comments come first
    cols = body[0].split(",")
    assert cols[:9] == ["x_m", "y_m", "z_m", "rx_rad", "ry_rad", "rz_rad"] + [
        f"{a}_cmd_m" for a in "xyz"
    ]
    assert cols[9:] == [f"q{i}_cmd_rad" for i in range(1, 7)] + ["sx_m", "sy_m", "sz_m"]
    with open(out) as f:  # numpy: the comment lines skipped, the one header row named
        assert next(x for x in f if not x.startswith("#")).strip().split(",") == cols
        data = np.loadtxt(f, delimiter=",", comments="#", ndmin=2)
    rows = list(csv.DictReader(x for x in open(out) if not x.startswith("#")))
    assert data.shape == (6, 18) and len(rows) == 6
    np.testing.assert_array_equal(data[:, :3], P)
    q1 = data[:, cols.index("q1_cmd_rad")]
    n_out = int(np.sum((q1 < 2.5) | (q1 > 3.0)))
    assert n_out > 0
    for key in ("model: ", "frame: base", "units: m, rad", "sx_m, sy_m, sz_m: 1 sigma"):
        assert any(x.startswith(f"# {key}") for x in head), (key, head)
    warning = (
        f"WARNING: {n_out} of 6 targets need joints outside the range the model was fitted on "
        "(joint 1 by up to"
    )
    assert any(x.startswith(f"# {warning}") for x in head), head
    # the terminal: the warning, the 1-sigma (median, max of the CSV's), the unexplained part
    assert any(x.strip().startswith(warning) for x in lines), lines
    s3 = np.linalg.norm(data[:, -3:], axis=1)
    sig = f"correction 1-sigma (model uncertainty, 3-D): median {np.median(s3) * 1e6:.1f} um, max"
    assert any(x.strip().startswith(sig) and f"{s3.max() * 1e6:.1f} um" in x for x in lines)
    assert any(f"the model leaves {UNEXPLAINED} on its held-out poses" in x for x in lines)
    assert any(f"# not in that 1-sigma: the model leaves {UNEXPLAINED}" in x for x in head)
    assert lines[-1] == f"6 targets, max correction {_max_mm(data)} mm"
    # the JSON summary: the same warning line, the numbers in SI
    rc, jl, _ = _run([*argv, "--json"], capsys)
    s = json.loads(jl[0])
    assert rc == 0 and len(s["warnings"]) == 1 and s["warnings"][0].startswith(warning)
    assert s["median_std_m"] == pytest.approx(np.median(s3), rel=1e-12)
    assert s["max_std_m"] == pytest.approx(s3.max(), rel=1e-12)
    assert s["model_unexplained"]["rms_m"] == pytest.approx(np.sqrt(50e-6**2 - 10e-6**2))
    assert s["joint_coverage"]["nodes_outside"] == n_out


def _max_mm(data: np.ndarray) -> str:
    return f"{np.linalg.norm(data[:, 6:9] - data[:, :3], axis=1).max() * 1e3:.3f}"


def test_the_urscript_header_states_extrapolation_and_the_unexplained_part(tmp_path, capsys):
    """The script's header gave the 1-sigma only: it now also says how many nodes are
    extrapolations and what the model leaves unexplained (as the terminal does)."""
    path = save_model(_model(9), tmp_path / "m.json")
    out = tmp_path / "c.script"
    argv = ["export", path, "--format", "urscript", "--out", out, f"--volume={VOL}"]
    rc, lines, err = _run([*argv, "--spacing", "0.1"], capsys)
    assert rc == 0, err
    d = json.loads((tmp_path / "c.json").read_text())
    n, n_out = d["meta"]["joint_coverage"]["nodes"], d["meta"]["joint_coverage"]["nodes_outside"]
    assert n_out > 0
    head = [x for x in out.read_text().splitlines() if x.startswith("#")]
    cover = f"# WARNING: {n_out} of {n} nodes need joints outside the range the model was fitted on"
    assert any(x.startswith(cover) for x in head), head
    assert f"# not in that 1-sigma: the model leaves {UNEXPLAINED} on its held-out poses" in head
    assert any(x.startswith("# correction 1-sigma (3-D, model uncertainty): median") for x in head)
    # the terminal said the same
    assert any(x.strip().startswith(cover[2:]) for x in lines)
    # and so does the table's CSV beside the script
    csv_head = [x for x in (tmp_path / "c.csv").read_text().splitlines() if x.startswith("#")]
    assert (
        f"# not in that 1-sigma: the model leaves {UNEXPLAINED} on its held-out poses" in csv_head
    )


@pytest.mark.parametrize("fmt", ["table", "urscript"])
def test_the_json_summary_carries_the_1_sigma_unexplained_and_warnings(tmp_path, capsys, fmt):
    """`export --json` left out the median and max 1-sigma and the unexplained part the text
    prints, and dropped every warning line: they are in the JSON now, the same lines as the
    text run's."""
    path = save_model(_model(10), tmp_path / "m.json")
    out = tmp_path / ("t" if fmt == "table" else "t.script")
    argv = ["export", path, "--format", fmt, "--out", out, f"--volume={VOL}"]
    argv += ["--spacing", "0.1", "--interp-error", "1e-9"]  # coarse: the target is not met
    rc, lines, err = _run(argv, capsys)
    assert rc == 0, err
    said = [x.strip() for x in lines if is_warning(x)]
    assert any(x.startswith("WARNING:") for x in said)  # extrapolation
    assert any(x.startswith("warning: the interpolation error target") for x in said)
    rc, jl, _ = _run([*argv, "--json"], capsys)
    assert rc == 0 and len(jl) == 1
    s = json.loads(jl[0])
    assert s["warnings"] == said
    meta = json.loads((tmp_path / "t.json").read_text())["meta"]
    for key in ("median_std_m", "max_std_m"):
        assert s[key] == meta[key] and s[key] > 0
    assert s["model_unexplained"] == meta["model_unexplained"]
    assert s["model_unexplained"]["rms_m"] == pytest.approx(np.sqrt(50e-6**2 - 10e-6**2))


def test_the_json_summary_says_when_the_1_sigma_is_not_given(tmp_path, capsys, monkeypatch):
    """A model without a covariance of its prediction (lddmm, ekf-ann): the text says the
    1-sigma is not given; the JSON said nothing, now it lists that line too."""
    path = save_model(_model(11), tmp_path / "m.json")
    monkeypatch.setattr(DHModel, "prediction_cov", lambda self, q, **aux: None)
    argv = ["export", path, "--format", "table", "--out", tmp_path / "t", f"--volume={VOL}"]
    argv += ["--spacing", "0.1"]
    rc, lines, _ = _run(argv, capsys)
    assert rc == 0
    rc, jl, _ = _run([*argv, "--json"], capsys)
    s = json.loads(jl[0])
    assert "correction 1-sigma: not given" in " ".join(lines)
    assert any(x.startswith("correction 1-sigma: not given") for x in s["warnings"])
    assert s["median_std_m"] is None and s["max_std_m"] is None


def _partly_fixed_model() -> DHModel:
    """A dh fit that held d5, d6, theta6_offset and the Hayati tilts at nominal (unidentifiable
    on its poses, as the real UR10 series): zero rows/columns of its covariance."""
    m = make_model(12)
    fixed = ["d5", "d6", "theta6_offset", *(f"beta{i}" for i in range(1, 7))]
    m.free = np.ones(39, bool)
    m.free[[IDX[n] for n in fixed]] = False
    m.theta[[IDX[n] for n in fixed[3:]]] = 0.0  # the tilts at their nominal 0
    A = np.random.default_rng(2).normal(size=(39, 39)) * 2e-5
    m.cov = A @ A.T
    m.cov[~m.free, :] = 0.0
    m.cov[:, ~m.free] = 0.0
    m.unidentifiable = [["d5", "alpha5"], ["d6", "tool_z"], ["theta6_offset"]]
    m.info.update(heldout_rms_m=50e-6, heldout_rms_ci95_m=[45e-6, 60e-6])
    m.info["unexplained"] = {"floor_m": 10e-6}
    return m


def test_ros_yaml_marks_values_not_estimated_and_states_the_unexplained_part(tmp_path):
    """Values that follow parameters held at nominal were written with a tiny +- (2e-8 m, a
    by-product of a small rotation) or +- 0, and a dh model's header said "not carried:
    nothing" though the model leaves tens of micrometres unexplained."""
    from workcell.export.ros_yaml import export_ros_yaml, read_ros_yaml

    m = _partly_fixed_model()
    p, info = export_ros_yaml(m, tmp_path / "cal.yaml")
    text = p.read_text()
    lines = {}
    link = None
    for x in text.splitlines():
        if re.match(r"^  \w+:$", x):
            link = x.strip()[:-1]
        elif x.startswith("    "):
            lines[(link, x.split(":")[0].strip())] = x
    # wrist_2 y is -d5 (nominal), wrist_3 y is d6: they move one for one with the fixed values
    for (lk, key), par in {("wrist_2", "y"): "d5", ("wrist_3", "y"): "d6"}.items():
        assert lines[(lk, key)].endswith(f"# fixed, not estimated ({par} at nominal)")
        m2 = _partly_fixed_model()
        m2.theta[IDX[par]] += 1e-3
        moved = read_ros_yaml(export_ros_yaml(m2, tmp_path / "m2.yaml")[0].read_text())
        assert abs(moved[lk][key] - read_ros_yaml(text)[lk][key]) == pytest.approx(1e-3, rel=1e-3)
        assert info["kinematics_std"][lk][key] < 1e-6  # what the old file wrote beside it
    # exactly the values that follow a fixed parameter are marked (the tilts beta1-5 turn the
    # next frame; theta6_offset turns wrist_3), each with the old +- a by-product (< 1e-6); every
    # other value keeps its +-
    assert info["kinematics_fixed"] == {
        "upper_arm": {"yaw": ["beta1"]},
        "forearm": {"pitch": ["beta2"]},
        "wrist_1": {"pitch": ["beta3"]},
        "wrist_2": {"y": ["d5"], "yaw": ["beta4"]},
        "wrist_3": {"y": ["d6"], "pitch": ["theta6_offset"], "yaw": ["beta5"]},
    }
    for (lk, key), x in lines.items():
        if key in info["kinematics_fixed"].get(lk, {}):
            assert "+-" not in x and info["kinematics_std"][lk][key] < 1e-6, x
        else:
            assert re.search(r"# \+- \S+ (m|rad)$", x), x
    head = [x for x in text.splitlines() if x.startswith("#")]
    fixed_head = [x for x in head if x.startswith("# fixed beside a value: not estimated")]
    assert len(fixed_head) == 1 and "d5" in fixed_head[0] and "{d5, alpha5}" in fixed_head[0]
    assert not any("not carried: nothing" in x for x in head)
    assert f"# unexplained by the model: {UNEXPLAINED} on its held-out poses" in " ".join(head)
    assert info["model_unexplained"]["rms_m"] == pytest.approx(np.sqrt(50e-6**2 - 10e-6**2))


@pytest.mark.parametrize(
    "name, delta, limit, match",
    [
        (
            "a2",
            -0.185,
            0.02,
            r"a2 moved 18\d mm from the ur5e nominal \(-0\.425 -> -0\.61\d*; more ",
        ),
        ("d4", 0.025, 0.02, r"d4 moved 25(\.\d)? mm from the ur5e nominal .*more than 20 mm"),
        ("alpha3", 0.08, 0.05, r"alpha3 moved 0\.08\d* rad from the ur5e nominal .*than 0\.05 rad"),
    ],
)
def test_ros_yaml_refuses_a_geometry_far_from_the_nominal(
    tmp_path, capsys, name, delta, limit, match
):
    """The table and URScript refuse such a model by its correction's size; the YAML wrote it
    for the controller (the audit: another arm's data, a2/a3 185 mm from nominal)."""
    m = make_model(13)
    m.theta[IDX[name]] += np.sign(delta) * 0.9 * limit  # large, but within the limit: written
    ok = save_model(m, tmp_path / "ok.json")
    rc, _, err = _run(["export", ok, "--format", "ros-yaml", "--out", tmp_path / "ok.yaml"], capsys)
    assert rc == 0, err
    m.theta[IDX[name]] += delta - np.sign(delta) * 0.9 * limit
    bad = save_model(m, tmp_path / "bad.json")
    out = tmp_path / "bad.yaml"
    rc, _, err = _run(["export", bad, "--format", "ros-yaml", "--out", out, "--json"], capsys)
    assert rc == 2 and len(err) == 1, err
    assert re.search(match, err[0]) and "is the session's robot model right?" in err[0], err
    assert not out.exists()
    if name == "a2":  # the table refuses the same model (by its correction's size)
        with pytest.raises(CorrectionRefused, match="exceeds the bound"):
            build_table(Corrector(m, nominal_for(m)), LO, HI, [[0.0, np.pi, 0.0]], spacing_m=0.1)


def test_targets_near_the_wrist_singularity_are_warned(tmp_path, capsys):
    """Joint targets with joint 5 near 0: a correction under a millimetre swung joints 4 and 6
    by a quarter radian with no word (an audit of the exports). Now a warning names the line,
    the joint and the swing; a target away from the singularity gets none."""
    path = save_model(_model(joint1=(-6.0, 6.0)), tmp_path / "m.json")
    src = tmp_path / "q.csv"
    src.write_text("q1,q2,q3,q4,q5,q6\n1.2,-1.6,2.0,-2.0,-1.57,0\n1.2,-1.6,2.0,-2.0,0.005,0\n")
    out = tmp_path / "c.csv"
    argv = ["export", path, "--format", "targets", "--in", src, "--out", out, "--json"]
    rc, jl, err = _run(argv, capsys)
    assert rc == 0, err
    s = json.loads(jl[0])
    (w,) = [x for x in s["warnings"] if "from the nominal solution" in x]
    assert w.startswith("warning: 1 target(s) move a joint by more than 0.05 rad"), w
    assert "line 3 swings joint " in w and "joint 5 at 0.005 rad" in w, w
    rows = list(csv.DictReader(x for x in open(out) if not x.startswith("#")))
    swing = [
        max(abs(float(r[f"q{j}_cmd_rad"]) - q0) for j, q0 in ((4, -2.0), (6, 0.0))) for r in rows
    ]
    assert swing[0] < 0.05 < swing[1]
    # one target away from the singularity: no such warning
    src.write_text("q1,q2,q3,q4,q5,q6\n1.2,-1.6,2.0,-2.0,-1.57,0\n")
    rc, jl, err = _run([*argv, "--force"], capsys)
    assert rc == 0, err
    assert not [x for x in json.loads(jl[0])["warnings"] if "from the nominal solution" in x]
