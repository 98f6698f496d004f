"""Effect library and augmented model: physics, identities, save/replay."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sim_devices.truth import make_truth
from workcell.estimation import effects as E
from workcell.estimation.effects import (
    N_EFF,
    AugmentedModel,
    FeatureSpec,
    candidate_from_list,
    jac_aug,
    library,
    p_aug,
    te_index,
)
from workcell.estimation.models import load_model, save_model
from workcell.kinematics.chain import p_tracker, pack


def _truth_theta(tr):
    return np.concatenate(
        [tr.a, tr.d, tr.alpha, tr.theta_offset, tr.beta, np.zeros(6), tr.smr_flange_m]
    )


def _truth_eff(e: dict) -> np.ndarray:
    eff = np.zeros(N_EFF)
    eff[E.SL_COMP] = e["joint_compliance"]["c_rad_per_nm"]
    eff[E.SL_DEFL] = e["link_deflection"]["flex_m_per_n"]
    for j, hs in e["transmission_error"]["harmonics"].items():
        for k, A, ph in hs:
            eff[te_index(int(j), k, "sin")] = A * np.cos(ph)
            eff[te_index(int(j), k, "cos")] = A * np.sin(ph)
    eff[E.SL_BL] = e["backlash"]["b_rad"]
    eff[E.I_THERM] = e["thermal_drift"]["alpha_per_k"]
    eff[E.I_SCALE] = e["tracker_scale"]["scale"]
    return eff


@pytest.fixture(scope="module")
def poses():
    rng = np.random.default_rng(3)
    n = 24
    return (
        rng.uniform(-3, 3, (n, 6)),
        rng.choice([-1.0, 1.0], (n, 6)),
        rng.uniform(0, 3000, n),
    )


def test_library_covers_the_recording_format_kinds():
    kinds = {c.kind for c in library()}
    assert kinds == set(E.PHYSICAL_KINDS)
    keys = [c.key for c in library()]
    assert len(keys) == len(set(keys))
    # every effect parameter belongs to exactly one candidate
    idx = sorted(i for c in library() for i in c.idx)
    assert idx == list(range(N_EFF))
    for c in library():
        assert candidate_from_list(c.to_list()) == c


def test_zero_effects_reduce_to_the_geometric_chain(poses):
    q, sg, _ = poses
    tr = make_truth("ur5e", "none", 2)
    th = _truth_theta(tr)
    x = np.zeros((len(q), E.N_FEAT))
    x[:, 6:12] = sg
    p = p_aug(th, np.zeros(N_EFF), tr.tracker_T_base, q, x)
    assert np.abs(p - np.asarray(p_tracker(th, tr.tracker_T_base, q))).max() < 1e-12


def test_effect_physics_matches_an_independent_implementation(poses):
    """The simulator's truth (written separately, own kinematics and gravity) with every effect
    on, mapped to the library's physical parameters, gives the same SMR positions."""
    q, sg, t = poses
    tr = make_truth("ur5e", "all", 5)
    th = _truth_theta(tr)
    temps = np.array([tr.joint_temperatures_c(ti) for ti in t])
    # the library given the truth's own inertia (the simulator's link masses and payload are
    # not the catalogue's and the declaration; that mismatch is a model error, not tested here)
    spec = dataclasses.replace(
        tr.nominal, link_masses_kg=tr.link_masses_kg, link_coms_m=tr.link_coms_m
    )
    fs = FeatureSpec(
        spec=spec,
        payload_com_m=tr.payload_com_m,
        thermal_source="joint",
        thermal_ref=np.full(6, tr.ambient_c),
    )
    x = fs.features(
        th,
        q,
        approach_sign=sg,
        joint_temperature_c=temps,
        payload_kg=np.full(len(q), tr.payload_kg),
    )
    p = p_aug(th, _truth_eff(tr.effects), tr.tracker_T_base, q, x)
    pt = np.array([tr.smr_in_tracker(q[i], sg[i], t[i]) for i in range(len(q))])
    p0 = p_aug(th, np.zeros(N_EFF), tr.tracker_T_base, q, x)
    assert np.abs(p0 - pt).max() > 50e-6  # the effects are visible ...
    assert np.abs(p - pt).max() < 1e-9  # ... and modelled exactly


def test_jacobian_matches_finite_differences(poses):
    q, sg, _ = poses
    tr = make_truth("ur5e", "all", 1)
    th = _truth_theta(tr)
    fs = FeatureSpec(spec=tr.nominal, payload_com_m=tr.payload_com_m)
    x = fs.features(th, q[:4], approach_sign=sg[:4], payload_kg=np.full(4, 0.5))
    eff = _truth_eff(tr.effects)
    _, Je = jac_aug(th, eff, tr.tracker_T_base, q[:4], x)
    for i in (0, 6, te_index(2, 2, "cos"), E.SL_BL.start + 1, E.I_SCALE):
        h = 1e-7 if i != E.SL_DEFL.start else 1e-9
        d = np.zeros(N_EFF)
        d[i] = h
        fd = (
            p_aug(th, eff + d, tr.tracker_T_base, q[:4], x)
            - p_aug(th, eff - d, tr.tracker_T_base, q[:4], x)
        ) / (2 * h)
        assert np.allclose(Je[:, :, i], fd, rtol=1e-4, atol=1e-9 * max(1, np.abs(fd).max()))


def test_augmented_model_saves_and_replays(tmp_path, poses):
    q, sg, t = poses
    tr = make_truth("ur5e", "all", 4)
    th = _truth_theta(tr)
    acc = [c for c in library() if c.key in ("backlash/joint3", "joint_compliance/joint2")]
    eff = np.zeros(N_EFF)
    eff[acc[0].idx[0]] = 3e-6
    eff[acc[1].idx[0]] = 50e-6
    free = np.zeros(39, bool)
    free[:5] = True
    m = AugmentedModel(
        features_spec=FeatureSpec(
            spec=tr.nominal,
            payload_com_m=np.array([0, 0, 0.03]),
            thermal_source="time",
            thermal_ref=np.full(6, 0.2),
            payload_kg_default=0.5,
        ),
        theta=th,
        base_ref=tr.tracker_T_base,
        eff=eff,
        accepted=acc,
        free=free,
        cov=np.eye(7) * 1e-14,
        nominal_tool_m=np.array([0, 0, 0.06]),
    )
    path = save_model(m, tmp_path / "aug.json")
    m2 = load_model(path)
    assert isinstance(m2, AugmentedModel)
    aux = {"approach_sign": sg, "elapsed_s": t, "payload_kg": np.full(len(q), 0.5)}
    assert np.allclose(m.predict(q, **aux), m2.predict(q, **aux), atol=1e-12)
    # the approach direction matters to a model with backlash
    assert not np.allclose(m2.predict(q, **aux), m2.predict(q, payload_kg=np.full(len(q), 0.5)))
    ps = m2.parameters()
    assert ps["backlash/joint3:backlash_width"]["unit"] == "rad"
    assert ps["joint_compliance/joint2:compliance"]["unit"] == "rad/(N m)"
    assert ps["backlash/joint3:backlash_width"]["std"] == pytest.approx(1e-7)


def test_augmented_prediction_cov_is_the_spread_over_its_covariance(poses):
    """prediction_cov (used for the correction table's 1-sigma) agrees with the spread of the
    predictions over [theta[free], eff[active]] drawn from the model's covariance."""
    q, sg, t = poses
    tr = make_truth("ur5e", "all", 4)
    acc = [c for c in library() if c.key in ("backlash/joint3", "joint_compliance/joint2")]
    free = np.zeros(39, bool)
    free[[0, 1, 7, 13, 20]] = True
    eff = np.zeros(N_EFF)
    m = AugmentedModel(
        features_spec=FeatureSpec(spec=tr.nominal, payload_com_m=np.array([0, 0, 0.03])),
        theta=_truth_theta(tr),
        base_ref=tr.tracker_T_base,
        eff=eff,
        accepted=acc,
        free=free,
        cov=np.diag([1e-8] * 5 + [1e-10, 1e-10]),
        nominal_tool_m=np.array([0, 0, 0.06]),
    )
    rng = np.random.default_rng(3)
    B = rng.normal(size=(7, 7))
    m.cov = (B @ B.T) * np.outer(np.sqrt(np.diag(m.cov)), np.sqrt(np.diag(m.cov))) / 7
    aux = {"approach_sign": sg[:5], "payload_kg": np.full(5, 0.5)}
    C = m.prediction_cov(q[:5], **aux)
    act = m.active
    draws = []
    for z in rng.multivariate_normal(np.zeros(7), m.cov, size=2000):
        m2 = AugmentedModel(**{**m.__dict__, "theta": m.theta.copy(), "eff": m.eff.copy()})
        m2.theta[free] += z[:5]
        m2.eff[act] += z[5:]
        draws.append(m2.predict(q[:5], **aux))
    mc = np.std(np.array(draws), axis=0)
    np.testing.assert_allclose(np.sqrt(np.einsum("nii->ni", C)), mc, rtol=0.1)
    assert mc.max() > 1e-5
    # a residual GP adds its posterior variance per axis (it had no covariance at all)
    from workcell.estimation.discovery_np import fit_residual_gp

    r = 1e-5 * np.c_[np.sin(q[:, 1]), np.cos(q[:, 2]), q[:, 0]]
    gp = fit_residual_gp(q, r + 1e-6 * rng.normal(size=r.shape))
    m.residual = gp.to_dict()
    v = gp.predict_var(q[:5])
    assert np.all(v > 0)
    np.testing.assert_allclose(m.prediction_cov(q[:5], **aux), C + v[:, :, None] * np.eye(3))


def test_the_bench_simulator_counts_measured_samples_in_order(tmp_path):
    """`index` is the order of measurement, from 0 (recording format): a pose lost to a broken
    beam has no sample, and used to leave a gap in the indices. Its log times follow the
    session's (they were stamped in 2023)."""
    from sim_devices.truth import TrackerNoise, make_truth
    from workcell.bench.discovery import simulate_recording
    from workcell.recording.reader import read_recording

    truth = make_truth("ur5e", "none", 3, noise=TrackerNoise(beam_break_prob=0.6))
    rec = read_recording(simulate_recording(truth, 12, 3, tmp_path / "c.mcap"))
    assert 0 < len(rec.samples) < 12
    assert [s["index"] for s in rec.samples] == list(range(len(rec.samples)))
    assert rec.samples[0]["_log_time_ns"] >= rec.session["_log_time_ns"]


@pytest.mark.parametrize("readings", [1, 2])
def test_the_bench_simulator_records_with_few_readings_a_pose(tmp_path, readings):
    """It wanted 3 good readings a pose whatever was asked, so with 1 or 2 readings it wrote a
    recording without a single sample."""
    from sim_devices.truth import make_truth
    from workcell.bench.discovery import simulate_recording
    from workcell.recording.reader import read_recording

    p = simulate_recording(make_truth("ur5e", "none", 3), 6, 3, tmp_path / "c.mcap",
                           readings=readings)  # fmt: skip
    rec = read_recording(p)
    assert len(rec.samples) == 6
    assert all(s["n_readings"] == readings for s in rec.samples)


def test_a_models_ambient_thermal_term_sees_the_datasets_ambient_temperature():
    """`aux_from_dataset` (fit's and export's evaluation of a model on a recording) left out the
    ambient temperature, which only `diagnose` passed: an augmented model whose thermal term
    follows the air temperature was evaluated without it (its thermal part zero) in the ROS
    YAML's "not carried" figure and the TUI's held-out figures."""
    from types import SimpleNamespace

    from workcell.estimation.models import aux_from_dataset
    from workcell.kinematics.robots import UR5E

    acc = [c for c in library() if c.key == "thermal_drift"]
    eff = np.zeros(E.N_EFF)
    eff[acc[0].idx[0]] = 2e-5  # a thermal coefficient per kelvin
    m = AugmentedModel(
        features_spec=FeatureSpec(
            spec=UR5E,
            payload_com_m=np.zeros(3),
            thermal_source="ambient",
            thermal_ref=np.full(6, 20.0),
        ),  # fmt: skip
        theta=pack(UR5E.dh, tool=(0.0, 0.0, 0.06)),
        base_ref=np.eye(4),
        eff=eff,
        accepted=acc,
        free=np.ones(39, bool),
        cov=np.zeros((40, 40)),
        nominal_tool_m=np.array([0, 0, 0.06]),
    )
    q = np.random.default_rng(1).uniform(-2, 2, (4, 6))
    ds = SimpleNamespace(q=q, approach_sign=np.ones((4, 6)), joint_temperature_c=None,
                         ambient_temperature_c=np.full(4, 30.0), elapsed_s=np.zeros(4),
                         payload_kg=np.zeros(4))  # fmt: skip
    warm = m.predict(q, **aux_from_dataset(ds))
    cold = m.predict(q, **{**aux_from_dataset(ds), "ambient_temperature_c": np.full(4, 20.0)})
    assert np.linalg.norm(warm - cold, axis=1).min() > 1e-7  # 10 K moves the SMR
