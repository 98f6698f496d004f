"""Audit fixes of the exports: the frame contract (base_ref, tracker_T_base, the fitted base
correction) stated alike by every format, the table CSV's header as complete as the URScript's,
an ekf-ann model's 1-sigma said alike across formats, and `validate` refusing a simulated
validation of a model fitted on a real cell."""

import argparse
import json
import re

import numpy as np
import pytest
from test_export_table import DOWN, HI, LO, make_model

from workcell.errors import UserError
from workcell.estimation.ekf_ann import ann as A
from workcell.estimation.ekf_ann.model import EkfAnnModel
from workcell.estimation.models import model_fingerprint, save_model
from workcell.export.correction import Corrector, nominal_for
from workcell.export.table import build_table, load_table, unexplained_lines
from workcell.export.urscript import generate_urscript
from workcell.kinematics.chain import base_slice
from workcell.kinematics.robots import UR5E

BASE_T = (1e-4, -3e-4, 2e-4)
BASE_R = (2e-4, -1e-4, 3e-4)


def _model_with_base(seed=4):
    m = make_model(seed)
    m.base_ref[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    b = base_slice().start
    m.theta[b : b + 3], m.theta[b + 3 : b + 6] = BASE_T, BASE_R
    return m


@pytest.fixture(scope="module")
def table_files(tmp_path_factory):
    m = _model_with_base()
    corr = Corrector(m, nominal_for(m))
    tab = build_table(corr, LO, HI, [DOWN], spacing_m=0.1, n_check=20)
    out = tmp_path_factory.mktemp("t") / "t"
    pj, pc = tab.save(out)
    return m, tab, pj, pc


def _head(text: str) -> list[str]:
    return [x[2:] for x in text.splitlines() if x.startswith("# ")]


def _tracker_T_base(head: list[str]) -> np.ndarray:
    (line,) = [x for x in head if x.startswith("tracker_T_base (base_ref, 4x4 row-major")]
    rows = line.split("[", 1)[1].rstrip("]").split(";")
    return np.array([[float(v) for v in r.split(",")] for r in rows])


def test_every_table_format_states_the_frame_base_ref_and_the_base_correction(table_files):
    m, tab, pj, pc = table_files
    meta = json.loads(pj.read_text())["meta"]
    # the JSON: base_ref, the frame, the fitted base correction from the model's base_* values
    assert np.allclose(meta["base_ref"], m.base_ref)
    assert meta["frame"].startswith("base_ref, the model's rigid registration")
    bc = meta["base_correction"]
    assert np.allclose(bc["translation_m"], BASE_T) and np.allclose(bc["rotation_rad"], BASE_R)
    assert bc["translation_norm_m"] == pytest.approx(np.linalg.norm(BASE_T))
    assert bc["max_shift_m"] > bc["translation_norm_m"] * 0.5
    for head in (_head(pc.read_text()), _head(generate_urscript(load_table(pj)))):
        # tracker_T_base's 16 values, exactly (repr), in the CSV and the URScript alike
        assert np.array_equal(_tracker_T_base(head), m.base_ref)
        assert any(x.startswith("frame: base_ref") for x in head), head
        (line,) = [x for x in head if x.startswith("base correction:")]
        assert "controller's own base frame" in line and "does not remove" in line
        mm = f"{np.linalg.norm(BASE_T) * 1e3:.3f} mm"
        mrad = f"{np.linalg.norm(BASE_R) * 1e3:.3f} mrad"
        assert mm in line and mrad in line, line
        assert not any("taken as the controller's base" in x for x in head)


def test_the_table_csv_header_carries_what_the_urscript_header_does(table_files):
    _, _, pj, pc = table_files
    csv_head = _head(pc.read_text())
    script_head = _head(generate_urscript(load_table(pj)))
    # every URScript header line but its name, usage, loading and scope is in the CSV header
    own = ("wc_correct:", "usage:", "load:", "scope:")
    shared = [x for x in script_head if not x.startswith(own)]
    missing = [x for x in shared if x not in csv_head]
    assert not missing, missing
    for key in ("semantics: commanded = desired + delta", "TCP (SMR) in flange:", "conditions:"):
        assert any(x.startswith(key) for x in csv_head), (key, csv_head)
    assert any(x.startswith("arm configuration (checked") for x in csv_head)
    # the CSV is still read as before: skip the `#` lines, one header row, numbers
    rows = [r for r in pc.read_text().splitlines() if not r.startswith("#")]
    assert rows[0].startswith("orientation,rx,ry,rz,i,j,k,x_m")
    from workcell.export.files import export_kind

    assert export_kind(pc) == "correction table CSV"


def test_targets_and_ros_yaml_state_the_same_frame(tmp_path, capsys):
    from workcell.cli import main

    m = _model_with_base()
    mp = tmp_path / "m.json"
    save_model(m, mp)
    src = tmp_path / "in.csv"
    src.write_text("x,y,z\n0.0,-0.4,0.3\n0.05,-0.35,0.25\n")
    out = tmp_path / "c.csv"
    assert (
        main(["export", str(mp), "--format", "targets", "--in", str(src), "--out", str(out)]) == 0
    )
    printed = capsys.readouterr().out
    assert "base correction: targets expressed in another estimate" in printed
    head = _head(out.read_text())
    assert np.array_equal(_tracker_T_base(head), m.base_ref)
    assert any(x.startswith("base correction:") and "mrad" in x for x in head)
    assert any(x.startswith("TCP (SMR) in flange:") for x in head)
    assert any(x.startswith("arm configuration of the corrected joints") for x in head)
    assert any(x.startswith("conditions:") for x in head)
    y = tmp_path / "c.yaml"
    assert main(["export", str(mp), "--format", "ros-yaml", "--out", str(y)]) == 0
    assert "base correction: targets expressed" in capsys.readouterr().out
    head = _head(y.read_text())
    assert np.array_equal(_tracker_T_base(head), m.base_ref)
    assert any(x.startswith("frame: base_link_inertia = base_ref") for x in head)
    assert any(x.startswith("base correction:") for x in head)


def _ekf_model() -> EkfAnnModel:
    from workcell.kinematics.chain import PARAM_NAMES

    d = make_model(5)
    spec = A.AnnSpec(hidden=3)
    names = ["a2", "a3", "d1"]
    cov = np.diag([1e-8, 2e-8, 3e-8])
    assert all(n in PARAM_NAMES for n in names)
    return EkfAnnModel(
        robot_model="ur5e",
        nominal_dh=UR5E.dh,
        theta=d.theta,
        base_ref=d.base_ref,
        offset_m=np.zeros(3),
        spec=spec,
        w=np.zeros(spec.n_weights),
        geometric_std=dict(zip(names, np.sqrt(np.diag(cov)), strict=True)),
        geometric_cov=cov,
        info={"nominal_tool_m": [0, 0, 0.06]},
    )


def test_an_ekf_ann_models_uncertainty_is_said_alike_in_every_format(tmp_path):
    from workcell.export.ros_yaml import export_ros_yaml

    m = _ekf_model()
    corr = Corrector(m, nominal_for(m))
    tab = build_table(corr, LO, HI, [DOWN], spacing_m=0.2, n_check=10)
    assert tab.std_m is None
    _, pc = tab.save(tmp_path / "e")
    (line,) = [x for x in _head(pc.read_text()) if x.startswith("correction 1-sigma")]
    # the table says why no 1-sigma though the ROS YAML gives +-: the covariance is the
    # geometry's only
    assert "geometric states only" in line and "ROS YAML" in line, line
    assert "carries no covariance" not in line
    y, _ = export_ros_yaml(m, tmp_path / "e.yaml")
    text = y.read_text()
    assert re.search(r"# \+- \S+ m$", text, re.M)  # the YAML keeps its +-
    assert "that +- is the uncertainty of the geometry alone" in text


def test_a_model_without_a_1_sigma_is_not_said_to_have_one():
    from workcell.estimation.models import unexplained_error

    ue = unexplained_error(1e-4, [8e-5, 1.2e-4], 1e-5)
    for meta in ({}, {"model_unexplained": ue}):
        lines = unexplained_lines({**meta, "median_std_m": None})
        assert lines[0].startswith("the model gives no 1-sigma; what it leaves unexplained")
        assert not any("not in that 1-sigma" in x for x in lines)
        with_std = unexplained_lines({**meta, "median_std_m": 1e-5})
        assert with_std[0].startswith("not in that 1-sigma")


def _validate_args(model: str, **kw) -> argparse.Namespace:
    d = dict(
        model=model,
        robot="sim",
        tracker="sim",
        targets=3,
        table=None,
        volume=None,
        envelope=None,
        seed=1,
        sim_seed=None,
        effects=None,
        robot_model=None,
        readings=None,
        json=False,
        max_correction=None,
    )
    d.update(kw)
    return argparse.Namespace(**d)


@pytest.mark.parametrize(
    "campaign",
    [
        {"plan": "imported", "source": "Series_B/measurements.csv"},
        {"plan": "random", "seed": 3, "robot_url": "ur://10.0.0.5", "effects": None},
    ],
)
@pytest.mark.parametrize("sim_seed", [None, 4])
def test_validate_refuses_to_simulate_a_model_of_a_real_cell(
    tmp_path, monkeypatch, campaign, sim_seed
):
    import workcell.export.build as build
    from workcell.commands import validate

    m = make_model(1)
    mp = tmp_path / "m.json"
    save_model(m, mp)
    monkeypatch.setattr(build, "model_session", lambda model: ({"campaign": campaign}, ""))
    rec = str(tmp_path / "real.mcap")
    monkeypatch.setattr(build, "model_recording", lambda model: (rec, "0" * 64))
    args = _validate_args(
        str(mp), sim_seed=sim_seed, effects=None if sim_seed is None else "realistic"
    )
    with pytest.raises(
        UserError,
        match=r"fitted on a real cell \(.*real\.mcap.*\): a simulator "
        r"has another arm; validate it on that cell: --robot ur://HOST",
    ):
        validate.run(args)


def test_validate_keeps_a_way_for_a_simulated_model_whose_recording_moved(tmp_path, monkeypatch):
    import workcell.export.build as build
    from workcell.commands import validate

    m = make_model(1)
    mp = tmp_path / "m.json"
    save_model(m, mp)
    monkeypatch.setattr(build, "model_session", lambda model: ({}, "the recording moved"))
    with pytest.raises(UserError, match="put the recording beside the model, or, for a model "):
        validate.run(_validate_args(str(mp)))
    # with both given it goes on to the simulation (stopped here at the first device call)
    import sim_devices.cell as cellmod

    def stop(*a, **k):
        raise UserError("reached the simulation")

    monkeypatch.setattr(cellmod, "sim_cell", stop)
    with pytest.raises(UserError, match="reached the simulation"):
        validate.run(_validate_args(str(mp), sim_seed=3, effects="realistic"))


def test_validate_has_the_max_correction_its_refusal_names(tmp_path):
    from workcell.commands import validate

    p = argparse.ArgumentParser()
    validate.add_arguments(p)
    a = p.parse_args(["m.json", "--max-correction", "0.01"])
    assert a.max_correction == 0.01
    with pytest.raises(UserError, match="--max-correction: not used with --table"):
        validate.check_options(_validate_args("m.json", table="t.json", max_correction=0.01))


def test_the_before_after_table_keeps_its_columns_apart(capsys):
    from workcell.commands.validate import print_table
    from workcell.estimation.models import interval_um

    def stats(v):
        return {"mean_m": v, "rms_m": v * 1.01, "max_m": v * 1.1, "rms_ci95_m": None}

    res = {"targets": 10, "truth": "simulated robot", "before": stats(3.4275), "after": stats(5e-6)}
    print_table(res, interval_um)
    lines = capsys.readouterr().out.splitlines()
    before = lines[1]
    assert re.search(r"\d um\d", before) is None, before
    cells = re.findall(r"(\S+) um", before)
    assert [float(c) for c in cells] == pytest.approx([3427500.0, 3461775.0, 3770250.0], rel=1e-6)
    # the header's columns end where the numbers' units do
    assert lines[0].index("mean") + 4 == before.index(" um") + 3
    # a normal table is printed exactly as before
    res = {"targets": 10, "truth": "t", "before": stats(1.5e-4), "after": stats(2e-5)}
    print_table(res, interval_um)
    out = capsys.readouterr().out.splitlines()
    assert out[1].startswith("before        150.0 um    151.5 um    165.0 um")
    assert out[0].startswith(f"{'':10}{'mean':>12}{'RMS':>12}{'max':>12}")


# ---------------------------------------------------------------- second export/validate audit
def _tilt(rotvec, axes, angle):
    """Rotations (N, 3, 3): the orientation `rotvec` tilted by `angle` about unit `axes` (N, 3)."""
    from workcell.export.correction import rotvec_to_matrix

    return rotvec_to_matrix(rotvec)[0] @ rotvec_to_matrix(np.asarray(axes) * angle)


def test_the_orientation_tolerance_keeps_the_stated_error():
    """Item 1: the table accepted a tool orientation 0.05 rad off its own, where it was off the
    exact correction by ~10x its stated interpolation error. The tolerance is now measured: a
    tilt that far changes the correction by at most the interpolation error target, and the
    table's error there (interpolation included) is measured and stated."""
    from workcell.export.correction import matrix_to_rotvec

    m = make_model(3)
    corr = Corrector(m, nominal_for(m))
    tab = build_table(corr, LO, HI, [DOWN], target_error_m=5e-6, spacing_m=0.1, n_check=40)
    meta = tab.meta
    tol = tab.orientation_tol_rad
    assert 1e-4 <= tol < 0.05 and meta["orientation_tol_rad"] == tol
    assert meta["orientation_change_at_tol_m"] <= 5e-6
    assert meta["orientation_error_at_tol_m"] <= meta["max_interp_error_m"] + 5e-6
    rng = np.random.default_rng(11)
    P = rng.uniform(LO, HI, (30, 3))
    axes = rng.normal(size=(30, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    c0, _, _ = corr.correct_positions(P, _tilt(DOWN, axes, 0.0), tab.seed_for(P))

    def change(angle):  # how far a tilt moves the exact correction, fresh points and axes
        c, _, _ = corr.correct_positions(P, _tilt(DOWN, axes, angle), tab.seed_for(P))
        return np.linalg.norm(c - c0, axis=1).max()

    assert change(0.999 * tol) <= 5e-6 * 1.02
    assert change(0.049) > 5 * 5e-6  # what the old 0.05 rad tolerance let through
    with pytest.raises(UserError, match="from the nearest orientation of the table"):
        tab.orientation_index(matrix_to_rotvec(_tilt(DOWN, [[0, 1.0, 0]], 1.05 * tol))[0])
    # stated in the URScript's (and the CSV's) header; wc_otol is the tolerance
    text = generate_urscript(tab)
    line = [x for x in _head(text) if x.startswith("orientation tolerance:")]
    assert len(line) == 1 and f"{tol:.3g} rad" in line[0] and "interpolation" in line[0]
    assert f"global wc_otol = {tol!r}" in text


def test_validate_states_the_bias_in_base_ref_axes():
    """Item 2: `bias_base_m` was the mean error in tracker axes. An arm that lands a fixed b
    (base_ref axes) off every commanded position must report bias b before correction, and b
    plus the mean table correction after (hand computation); base_ref here is turned 90 deg
    about z, so tracker axes would differ."""
    from workcell.export.validate import random_targets, run_validation

    m = _model_with_base()
    corr = Corrector(m, nominal_for(m))
    tab = build_table(corr, LO, HI, [DOWN], spacing_m=0.1, n_check=20)
    nom = corr.nominal
    b = np.array([1e-4, -2e-4, 3e-4])
    at = {}

    def move(q):
        at["q"] = np.asarray(q, float)

    def measure():
        return nom.to_tracker(nom.fk(at["q"])[0][0] + b)

    res = run_validation(nom, tab, move, measure, n=6, seed=2)
    assert res["targets"] == 6
    assert np.allclose(res["before"]["bias_base_m"], b, rtol=0, atol=1e-9)
    P, _ = random_targets(tab, 6, 2)
    want = b + tab.interpolate(P, 0).mean(0)
    assert np.allclose(res["after"]["bias_base_m"], want, rtol=0, atol=1e-9)
    assert res["before"]["rms_m"] == pytest.approx(np.linalg.norm(b), rel=1e-6)


def _sim_validate_args(model, table, **kw):
    return _validate_args(str(model), table=str(table), sim_seed=3, effects="none", **kw)


def test_validate_refuses_a_table_for_another_payload(tmp_path, monkeypatch):
    """Item 3: a table exported for 5 kg validated on the simulated arm carrying 0.5 kg gave
    ten times the error of the matching table, silently. Now refused before any motion, with
    the payloads and the remedy (a model without payload-dependent terms is not concerned)."""
    from test_export_table import _thermal_model

    import workcell.export.build as build
    from workcell.commands import validate
    from workcell.export.correction import Conditions

    m = _thermal_model("joint")
    m.info["joint_range_rad"] = [[-0.5, 0.5], [-2.0, -1.0], [0.5, 2.0], [-2, -1], [-2, -1], [0, 1]]
    mp = save_model(m, tmp_path / "aug.json")
    nom = nominal_for(make_model(8))
    monkeypatch.setattr(build, "nominal_for_model", lambda model, recording=None: nom)
    tables = {}
    for kg in (5.0, 0.5):
        corr = Corrector(m, nom, Conditions(payload_kg=kg))
        tab = build_table(corr, LO, HI, [DOWN], spacing_m=0.2, n_check=10)
        tab.meta["model_fingerprint"] = model_fingerprint(m)  # as `export` names its model
        tables[kg] = (tab, tab.save(tmp_path / f"t{kg:g}")[0])
    with pytest.raises(UserError, match=r"payload of 5 kg \(given at export\); the arm carries "):
        validate.run(_sim_validate_args(mp, tables[5.0][1]))
    from workcell.export.validate import payload_mismatch

    assert "--payload 0.5" in payload_mismatch(m, tables[5.0][0], 0.5)
    assert payload_mismatch(m, tables[0.5][0], 0.5) is None
    assert payload_mismatch(make_model(1), tables[5.0][0], 0.5) is None  # no compliance


def test_validate_refuses_a_model_of_another_arm_before_any_motion(tmp_path, monkeypatch):
    """Item 4: with a UR10 connected, validate said "give --model ur10" (an abbreviation of
    --model-name), which then moved the UR10 through the validation with the UR5e model's IK.
    Now --model-name other than the model's arm is refused, and the driver's refusal is said
    with validate's remedy, not --model."""
    import types

    import workcell.campaign.devices as devices
    from workcell.commands import validate
    from workcell.drivers.ur_robot import WrongRobotModel

    mp = save_model(make_model(1), tmp_path / "m.json")
    real = dict(robot="ur://127.0.0.1", tracker="serial:///dev/null")
    with pytest.raises(UserError, match=r"--model-name ur10: the model .* is of a ur5e") as e:
        validate.run(_validate_args(str(mp), robot_model="ur10", **real))
    assert "fit a model on the ur10" in str(e.value)

    class Arm:
        def connect(self):
            raise WrongRobotModel(
                "UR h: the controller says it is a UR10 but --model is ur5e: plans and envelope "
                "checks would use the wrong arm's kinematics; give --model ur10 (nothing moves "
                "until they agree)"
            )

    cell = types.SimpleNamespace(spec=UR5E, payload_kg=0.0)
    monkeypatch.setattr(devices, "open_cell", lambda ns: (cell, Arm(), Arm(), None))
    with pytest.raises(UserError, match="controller's arm is a UR10, not the ur5e") as e:
        validate.run(_validate_args(str(mp), **real))
    assert "--model" not in str(e.value) and "nothing moved" in str(e.value)


def test_a_table_volume_outside_the_envelope_is_refused(tmp_path, monkeypatch, capsys):
    """Item 5: a URScript for a volume 10 cm below the base (the recorded envelope's box starts
    at z 0.05 m) was written, exit 0, where --format targets refuses the same points. Now one
    line, exit 2, nothing written; a volume inside the box whose nodes need joints outside the
    envelope's ranges is refused too."""
    import dataclasses

    import workcell.export.build as build
    from workcell.campaign.envelope import default_envelope
    from workcell.cli import main
    from workcell.export.build import make_table

    env = default_envelope(UR5E)
    session = {"campaign": {"envelope": env.to_dict()}}
    monkeypatch.setattr(build, "model_session", lambda model: (session, ""))
    mp = save_model(make_model(1), tmp_path / "m.json")
    out = tmp_path / "low.script"
    argv = ["export", str(mp), "--format", "urscript", "--out", str(out)]
    assert main([*argv, "--volume=-0.2,-0.5,-0.1,0.2,-0.3,0.1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "reaches outside the envelope" in err and "z range -0.1..0.1 m" in err
    assert len(err.splitlines()) == 1 and not list(tmp_path.glob("low.*"))
    lim = env.joint_limits_rad.copy()
    lim[0] = [1.5, 1.7]  # joint 1 near pi/2 only: the box's corners need more
    narrow = dataclasses.replace(env, joint_limits_rad=lim)
    with pytest.raises(UserError, match=r"reaches outside a narrow envelope: \d+ node.*joint 1"):
        make_table(
            make_model(1),
            volume=np.r_[LO, HI],
            spacing_m=0.1,
            envelope=(narrow, "a narrow envelope"),
        )
    tab, _ = make_table(make_model(1), volume=np.r_[LO, HI], spacing_m=0.1, envelope=(env, "E"))
    assert tab.meta["envelope_check"] == "nodes' corrected joints inside E"


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda m: m.__setitem__("conditions", None), "meta conditions must be an object"),
        (
            lambda m: m["conditions"].__setitem__("approach_sign", "x"),
            "approach_sign must be 6 signs",
        ),
        (
            lambda m: m.__setitem__("max_interp_error_m", "x"),
            "max_interp_error_m must be a non-negative number",
        ),
        (lambda m: m["conditions"].__setitem__("payload_kg", "5"), "payload_kg must be"),
    ],
)
def test_a_table_with_edited_meta_is_refused_on_loading(table_files, tmp_path, edit, match):
    """Item 6: `validate --table` crashed with a traceback on a table whose meta conditions were
    null, approach_sign "x" or max_interp_error_m "x" (the last after every move). Now refused
    when the table is loaded, one line."""
    _, _, pj, _ = table_files
    d = json.loads(pj.read_text())
    edit(d["meta"])
    p = tmp_path / "edited.json"
    p.write_text(json.dumps(d))
    with pytest.raises(UserError, match=match) as e:
        load_table(p)
    assert "\n" not in str(e.value)


def test_a_model_whose_covariance_is_not_one_is_refused(tmp_path):
    """Item 7: a covariance with a positive diagonal but a negative eigenvalue was accepted and
    gave a 1-sigma twice the true one. Refused now, naming the file; and (minor) a model whose
    robot name is not the arm of its nominal chain, or whose nominal SMR is NaN, is refused
    with that reason, not as "no finite correction ... shrink the volume"."""
    from workcell.estimation.models import load_model

    m = make_model(2)
    C = np.zeros((39, 39))
    C[:3, :3] = np.diag([1e-8, 1e-8, 1e-8])
    m.cov = C.copy()
    load_model(save_model(m, tmp_path / "ok.json"))  # positive semi-definite: accepted
    C[0, 1] = C[1, 0] = 1.5e-8  # |correlation| 1.5: an eigenvalue -0.5e-8
    m.cov = C
    p = save_model(m, tmp_path / "nonpsd.json")
    with pytest.raises(UserError, match=r"nonpsd\.json: the dh model's cov is not a covariance"):
        load_model(p)
    d = json.loads((tmp_path / "ok.json").read_text())
    d["robot"] = "ur10"
    (tmp_path / "ur10.json").write_text(json.dumps(d))
    with pytest.raises(UserError, match="says robot 'ur10' but its nominal chain is not a ur10's"):
        load_model(tmp_path / "ur10.json")
    d = json.loads((tmp_path / "ok.json").read_text())
    d["info"]["nominal_tool_m"] = [0, 0, float("nan")]
    (tmp_path / "nan.json").write_text(json.dumps(d))
    with pytest.raises(UserError, match="nominal_tool_m must be 3 finite numbers"):
        load_model(tmp_path / "nan.json")
