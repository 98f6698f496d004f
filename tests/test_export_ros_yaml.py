"""ROS calibration YAML: the published UR defaults for nominal chains, exact FK for calibrated ones."""

import re

import numpy as np
import pytest

from workcell.errors import UserError
from workcell.estimation.dh import DHModel
from workcell.export.ros_yaml import (
    LINKS,
    WRIST3_T_TOOL0,
    export_ros_yaml,
    fk_tool0,
    read_ros_yaml,
    ros_kinematics,
    to_yaml,
)
from workcell.kinematics.chain import base_T_flange, p_tracker, pack
from workcell.kinematics.robots import UR5E, UR10

# Universal_Robots_ROS2_Description config/ur5e/default_kinematics.yaml and ur10 (published data)
PUBLISHED = {
    "ur5e": {
        "shoulder": (0, 0, 0.1625, 0, 0, 0),
        "upper_arm": (0, 0, 0, 1.570796327, 0, 0),
        "forearm": (-0.425, 0, 0, 0, 0, 0),
        "wrist_1": (-0.3922, 0, 0.1333, 0, 0, 0),
        "wrist_2": (0, -0.0997, -2.044881182297852e-11, 1.570796327, 0, 0),
        "wrist_3": (
            0,
            0.09959999999999999,
            -2.042830148012698e-11,
            1.570796326589793,
            3.141592653589793,
            3.141592653589793,
        ),
    },
    "ur10": {
        "shoulder": (0, 0, 0.1273, 0, 0, 0),
        "upper_arm": (0, 0, 0, 1.570796327, 0, 0),
        "forearm": (-0.612, 0, 0, 0, 0, 0),
        "wrist_1": (-0.5723, 0, 0.163941, 0, 0, 0),
        "wrist_2": (0, -0.1157, -2.373046667922381e-11, 1.570796327, 0, 0),
        "wrist_3": (
            0,
            0.0922,
            -1.891053610911353e-11,
            1.570796326589793,
            3.141592653589793,
            3.141592653589793,
        ),
    },
}
KEYS = ("x", "y", "z", "roll", "pitch", "yaw")


@pytest.mark.parametrize("spec", [UR5E, UR10], ids=["ur5e", "ur10"])
def test_nominal_equals_published_default(spec):
    kin = read_ros_yaml(to_yaml(ros_kinematics(pack(spec.dh))))
    for link in LINKS:
        got = np.array([kin[link][k] for k in KEYS])
        np.testing.assert_allclose(
            got, PUBLISHED[spec.model][link], rtol=0, atol=1e-9, err_msg=link
        )


def test_description_fixed_frames_are_identity_and_nominal_fk_matches_dh():
    np.testing.assert_allclose(WRIST3_T_TOOL0, np.eye(4), atol=1e-15)
    q = np.random.default_rng(0).uniform(-3, 3, (20, 6))
    kin = ros_kinematics(pack(UR5E.dh))
    np.testing.assert_allclose(fk_tool0(kin, q), base_T_flange(pack(UR5E.dh), q), atol=1e-12)


def _calibrated_model(seed):
    rng = np.random.default_rng(seed)
    th = pack(UR5E.dh, tool=(0.0, 0.0, 0.06))
    th[:24] += rng.normal(0, [3e-4] * 12 + [5e-4] * 6 + [1e-3] * 6)
    th[[25, 26]] += rng.normal(0, 3e-4, 2)  # Hayati beta2, beta3
    th[30:36] += rng.normal(0, [1e-3] * 3 + [2e-3] * 3)  # base offset
    th[36:39] += rng.normal(0, 3e-4, 3)
    base_ref = np.eye(4)
    base_ref[:3, 3] = (2.0, -0.5, -0.3)
    c, s = np.cos(0.7), np.sin(0.7)
    base_ref[:2, :2] = [[c, -s], [s, c]]
    return DHModel(
        robot_model="ur5e",
        nominal_dh=UR5E.dh,
        theta=th,
        base_ref=base_ref,
        cov=np.zeros((39, 39)),
        free=np.ones(39, bool),
        info={"nominal_tool_m": [0, 0, 0.06]},
    )


@pytest.mark.parametrize("seed", [1, 2])
def test_calibrated_yaml_reproduces_calibrated_fk(tmp_path, seed):
    m = _calibrated_model(seed)
    path, info = export_ros_yaml(m, tmp_path / "cal.yaml")
    kin = read_ros_yaml(path.read_text())
    q = np.random.default_rng(seed + 10).uniform(-3, 3, (50, 6))
    smr_yaml = (fk_tool0(kin, q) @ np.asarray(info["tcp_in_tool0"]))[:, :3, 3]
    p = np.asarray(p_tracker(m.theta, m.base_ref, q))
    smr_model = (p - m.base_ref[:3, 3]) @ m.base_ref[:3, :3]
    assert np.abs(smr_yaml - smr_model).max() < 1e-9
    # and the nominal YAML does not (the test can fail)
    nom = ros_kinematics(pack(UR5E.dh))
    assert (
        np.abs((fk_tool0(nom, q) @ np.asarray(info["tcp_in_tool0"]))[:, :3, 3] - smr_model).max()
        > 1e-5
    )


@pytest.mark.parametrize("robot", ["kuka", "", "ur5e-but-not", "ur1"])
def test_a_model_of_another_arm_is_refused(tmp_path, robot):
    """A model whose robot field is not a UR arm (edited by hand over a UR chain, or of another
    maker's arm) gets no UR ROS driver calibration file: until 2026-11-28 "kuka" was written."""
    from dataclasses import replace

    m = replace(_calibrated_model(1), robot_model=robot)
    with pytest.raises(UserError, match="for Universal Robots arms"):
        export_ros_yaml(m, tmp_path / "x.yaml")
    assert not (tmp_path / "x.yaml").exists()
    for ur in ("ur10", "UR16e", "ur3", "ur8long"):  # any UR arm (not in the catalogue too)
        export_ros_yaml(replace(m, robot_model=ur), tmp_path / f"{ur}.yaml")


def test_a_geometry_the_poses_do_not_determine_is_refused(tmp_path):
    """tool_z uncertain by 27 mm, as series D's DH model ({base_ty, tool_z} weakly identified):
    no calibration file, as no table (until 2026-11-28 the YAML was written with "+- 0.027 m");
    the refusal names the group the fit recorded. 4 mm is written."""
    m = _calibrated_model(1)
    m.cov = np.eye(39) * 1e-14
    m.cov[38, 38] = 0.027**2
    m.info["identifiability"] = {"weakly_identified": [{"parameters": ["base_ty", "tool_z"]}]}
    with pytest.raises(UserError, match=r"the TCP's z has a 1-sigma of 27 mm") as e:
        export_ros_yaml(m, tmp_path / "x.yaml")
    assert "{base_ty, tool_z} weakly identified" in str(e.value)
    assert not (tmp_path / "x.yaml").exists()
    m.cov[38, 38] = 0.004**2
    export_ros_yaml(m, tmp_path / "x.yaml")


def test_model_without_geometry_is_refused(tmp_path):
    class Blob:
        method = "gp"

    with pytest.raises(UserError, match="no geometric"):
        export_ros_yaml(Blob(), tmp_path / "x.yaml")


@pytest.mark.slow  # moved out of `make test` on 2026-11-26 (its time); `make test-all` runs it
def test_each_value_carries_its_propagated_std(tmp_path):
    """The +- beside each YAML value is the parameter covariance propagated to first order:
    it agrees with the spread of the values over parameters drawn from that covariance."""
    from workcell.export.ros_yaml import KEYS, LINKS, kinematics_std

    m = _calibrated_model(3)
    rng = np.random.default_rng(5)
    A = rng.normal(size=(39, 39)) * 2e-5
    m.cov = A @ A.T  # metres and radians: tens of micrometres / microradians
    path, info = export_ros_yaml(m, tmp_path / "cal.yaml")
    std = info["kinematics_std"]
    draws = rng.multivariate_normal(m.theta, m.cov, size=4000)
    vals = []
    for th in draws:
        m2 = _calibrated_model(3)
        m2.theta = th
        k = ros_kinematics(*_geometry(m2))
        vals.append([k[n][x] for n in LINKS for x in KEYS])
    vals = np.array(vals)
    ang = np.tile([False] * 3 + [True] * 3, len(LINKS))
    ref = vals[0]
    vals[:, ang] = ref[ang] + (vals[:, ang] - ref[ang] + np.pi) % (2 * np.pi) - np.pi
    mc = vals.std(axis=0)
    lin = np.array([std[n][x] for n in LINKS for x in KEYS])
    big = lin > 1e-7  # values the parameters move (others are zero by construction)
    assert big.sum() >= 20
    np.testing.assert_allclose(lin[big], mc[big], rtol=0.1)
    assert np.all(mc[~big] < 1e-6)
    # in the file: a comment after whitespace (YAML), the values unchanged for the drivers
    text = path.read_text()
    for line in text.splitlines():
        if line.startswith("    "):
            assert re.match(r"^    \w+: \S+ +# \+- \S+ (m|rad)$", line), line
    assert read_ros_yaml(text) == read_ros_yaml(to_yaml(info["kinematics"]))
    assert kinematics_std(_calibrated_model(3)) is not None  # zero covariance: std 0, not None


def _geometry(m):
    from workcell.export.ros_yaml import model_geometry

    th, B, _, _ = model_geometry(m)
    return th, B


def _yaml_values(theta, like):
    """The YAML values (flattened) of `like`'s geometry with `theta` put in."""
    from workcell.export.ros_yaml import KEYS as K

    m2 = _calibrated_model(3)
    m2.theta, m2.base_ref = np.asarray(theta, float), like.base_ref
    k = ros_kinematics(*_geometry(m2))
    return np.array([k[n][x] for n in LINKS for x in K])


def _monte_carlo_std(theta_draws, like):
    vals = np.array([_yaml_values(th, like) for th in theta_draws])
    ang = np.tile([False] * 3 + [True] * 3, len(LINKS))
    ref = vals[0]
    vals[:, ang] = ref[ang] + (vals[:, ang] - ref[ang] + np.pi) % (2 * np.pi) - np.pi
    return vals.std(axis=0)


@pytest.mark.slow  # moved out of `make test` on 2026-11-26 (its time); `make test-all` runs it
def test_augmented_model_yaml_std_is_its_geometry_marginal(tmp_path):
    """An augmented model's covariance is over [theta[free], effects]: the YAML's +- is the
    geometry's marginal, checked against draws of the joint vector (effects correlated with
    the geometry), and does not move when only an effect's variance does."""
    from workcell.estimation.effects import N_EFF, AugmentedModel, FeatureSpec, library
    from workcell.export.ros_yaml import KEYS as K
    from workcell.export.ros_yaml import kinematics_std

    dh = _calibrated_model(3)
    rng = np.random.default_rng(11)
    free = np.ones(39, bool)
    free[[24, 27, 28, 29]] = False  # as a fit fixes some: the embedding must respect `free`
    acc = [c for c in library() if c.key in ("joint_compliance/joint2", "backlash/joint3")]
    nf, ne = int(free.sum()), 2
    A = rng.normal(size=(nf + ne, nf + ne)) * 2e-5
    cov = A @ A.T
    m = AugmentedModel(
        features_spec=FeatureSpec(
            spec=UR5E,
            payload_com_m=np.zeros(3),
            thermal_source="time",
            thermal_ref=np.zeros(6),
            payload_kg_default=0.0,
        ),
        theta=dh.theta,
        base_ref=dh.base_ref,
        eff=np.zeros(N_EFF),
        accepted=acc,
        free=free,
        cov=cov,
        nominal_tool_m=np.array([0, 0, 0.06]),
    )
    path, info = export_ros_yaml(m, tmp_path / "aug.yaml")
    std = info["kinematics_std"]
    assert std is not None and "effects fitted with it marginalised out" in path.read_text()
    z = rng.multivariate_normal(np.zeros(nf + ne), cov, size=3000)
    draws = np.tile(dh.theta, (len(z), 1))
    draws[:, free] += z[:, :nf]
    mc = _monte_carlo_std(draws, dh)
    lin = np.array([std[n][x] for n in LINKS for x in K])
    big = lin > 1e-7
    assert big.sum() >= 20
    np.testing.assert_allclose(lin[big], mc[big], rtol=0.1)
    # an effect's own variance is not the geometry's
    cov2 = cov.copy()
    cov2[nf, nf] *= 100.0
    m.cov = cov2
    std2 = kinematics_std(m)
    assert all(std2[n][x] == pytest.approx(std[n][x], rel=1e-12) for n in LINKS for x in K)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A small simulated recording (its poses and conditions: approach signs, temperatures)."""
    from sim_devices.cell import sim_cell
    from workcell.campaign.executor import CampaignConfig
    from workcell.campaign.run import run_campaign

    rec = tmp_path_factory.mktemp("rosyaml") / "r.mcap"
    _, robot, tracker, c = sim_cell("ur5e", "none", seed=5)
    cfg = CampaignConfig(readings_per_pose=2, settle_s=0.2)
    run_campaign(robot, tracker, c, rec, plan="random", poses=12, seed=5, config=cfg)
    return rec


def _augmented_with_effects(recording):
    """An augmented model of the calibrated geometry with backlash of joint 3 and compliance of
    joint 2 accepted (non-zero): what the YAML cannot carry."""
    from workcell.estimation.effects import N_EFF, AugmentedModel, FeatureSpec, library

    dh = _calibrated_model(4)
    acc = [c for c in library() if c.key in ("joint_compliance/joint2", "backlash/joint3")]
    eff = np.zeros(N_EFF)
    for c, v in zip(acc, (2e-6, 2e-4), strict=True):  # rad/Nm, rad
        eff[c.idx[0]] = v
    return AugmentedModel(
        features_spec=FeatureSpec(spec=UR5E, payload_com_m=np.zeros(3), payload_kg_default=0.0),
        theta=dh.theta,
        base_ref=dh.base_ref,
        eff=eff,
        accepted=acc,
        free=np.ones(39, bool),
        cov=np.zeros((39 + 2, 39 + 2)),
        nominal_tool_m=np.array([0, 0, 0.06]),
        info={"recording": str(recording)},
    )


def test_the_header_states_the_size_of_what_the_yaml_drops(tmp_path, recording):
    """An augmented model's non-geometric part is not in the YAML: the header says how large it
    is (RMS and max over the recording's poses at their recorded conditions), the same figures
    as the model's prediction minus what the written YAML itself gives there."""
    from workcell.estimation.models import aux_from_dataset
    from workcell.recording.dataset import Dataset

    m = _augmented_with_effects(recording)
    path, info = export_ros_yaml(m, tmp_path / "aug.yaml")
    text = path.read_text()
    head = [line for line in text.splitlines() if line.startswith("# not carried")]
    assert len(head) == 1, text
    got = re.search(
        r"over the (\d+) poses of the recording.*RMS ([\d.]+) um, max ([\d.]+) um", head[0]
    )
    assert got, head[0]
    # independently: the YAML as a driver reads it, the SMR through tcp_in_tool0, in the tracker
    ds = Dataset.from_recording(recording)
    kin = read_ros_yaml(text)
    smr_base = (fk_tool0(kin, ds.q) @ np.asarray(info["tcp_in_tool0"]))[:, :3, 3]
    smr_yaml = smr_base @ m.base_ref[:3, :3].T + m.base_ref[:3, 3]
    d = np.linalg.norm(m.predict(ds.q, **aux_from_dataset(ds)) - smr_yaml, axis=1)
    assert int(got[1]) == len(ds.q)
    assert float(got[2]) == pytest.approx(np.sqrt(np.mean(d**2)) * 1e6, abs=0.06)
    assert float(got[3]) == pytest.approx(d.max() * 1e6, abs=0.06)
    assert d.max() > 20e-6  # the effects are there: the figure is not a zero by construction
    assert info["not_carried"]["max_m"] == pytest.approx(d.max(), rel=1e-6)
    # without its recording the figure cannot be had: said, not left out
    m.info = {"recording": None, "recording_unusable": "the model's recording r.mcap was not found"}
    text = export_ros_yaml(m, tmp_path / "aug2.yaml")[0].read_text()
    assert "their size could not be evaluated: the model's recording r.mcap was not found" in text
    # a dh model drops no term of its own, and says so (what it leaves unexplained is another
    # line: tests/test_export_outputs.py)
    text = export_ros_yaml(_calibrated_model(4), tmp_path / "dh.yaml")[0].read_text()
    assert "# not carried: no term of the model (a dh model is geometric only)" in text


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda th: th.__setitem__(38, 60.0), "SMR/TCP 60 m from the flange .* millimetres"),
        (lambda th: th.__setitem__(38, 1.2), "SMR/TCP 1.2 m from the flange"),
        (lambda th: th.__setitem__(1, -425.0), "link length a2 is 425 m .* millimetres"),
    ],
)
def test_a_geometry_in_millimetres_is_refused_not_written(tmp_path, change, match):
    """A controller uses the YAML's TCP and links as given: a 60 m TCP (millimetres in the
    model file) was written with exit 0; now refused, and no file written."""
    m = _calibrated_model(1)
    export_ros_yaml(m, tmp_path / "ok.yaml")  # the plausible one is written
    change(m.theta)
    with pytest.raises(UserError, match=match):
        export_ros_yaml(m, tmp_path / "bad.yaml")
    assert not (tmp_path / "bad.yaml").exists()


def test_the_tcp_and_base_correction_carry_their_propagated_std(tmp_path):
    """tcp_in_tool0 (the fitted SMR in tool0) and the base correction printed with every export
    had no +- (uncertainty audit, 2026-11-27): both are the parameter covariance propagated to
    first order, which agrees with the spread over parameters drawn from it."""
    from workcell.export.frame import base_correction, base_correction_line
    from workcell.export.ros_yaml import tcp_in_tool0, tcp_std_m
    from workcell.kinematics.chain import base_slice

    m = _calibrated_model(4)
    rng = np.random.default_rng(8)
    A = rng.normal(size=(39, 39)) * 2e-5
    m.cov = A @ A.T
    th, B = _geometry(m)
    draws = rng.multivariate_normal(m.theta, m.cov, size=3000)
    mc = np.array([tcp_in_tool0(t, B)[:3, 3] for t in draws]).std(axis=0)
    np.testing.assert_allclose(tcp_std_m(m, th, B), mc, rtol=0.1)
    path, _ = export_ros_yaml(m, tmp_path / "cal.yaml")
    assert re.search(
        r"tcp_in_tool0 .* m \(1-sigma \[[^]]+\] m, the fit's covariance\)", path.read_text()
    )
    bc = base_correction(m)
    sd = np.sqrt(np.diag(m.cov)[base_slice(6)])
    np.testing.assert_allclose(bc["translation_std_m"] + bc["rotation_std_rad"], sd)
    line = base_correction_line(bc)
    assert line.count(" +- ") == 6 and "1-sigma from the fit's covariance" in line
    m.cov = None  # a model without a covariance says so instead of a bare number
    assert "translation_std_m" not in base_correction(m)
    assert "no covariance in the model" in base_correction_line(base_correction(m))
