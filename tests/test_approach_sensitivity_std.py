"""A table's approach sensitivity (how far the model moves the SMR if every joint arrived from
the other side than declared) carries its 1-sigma from the fit's covariance: checked against
the spread of the same figures over parameter draws from that covariance."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from workcell.estimation.effects import N_EFF, AugmentedModel, FeatureSpec, library
from workcell.export.correction import Conditions, Corrector, Nominal
from workcell.export.table import approach_line, approach_sensitivity
from workcell.kinematics.chain import pack
from workcell.kinematics.robots import UR5E


def _model(cov_scale: float) -> AugmentedModel:
    rng = np.random.default_rng(7)
    th = pack(UR5E.dh, tool=(0.0, 0.0, 0.06))
    th[:24] += rng.normal(0, 3e-4, 24)
    acc = [c for c in library() if c.key in ("joint_compliance/joint2", "backlash/joint3")]
    eff = np.zeros(N_EFF)
    for c, v in zip(acc, (2e-6, 2e-4), strict=True):  # rad/Nm, rad (half-width of the play)
        eff[c.idx[0]] = v
    free = np.ones(39, bool)
    free[30:36] = False
    p = int(free.sum()) + len(acc)
    A = rng.normal(size=(p, p)) * cov_scale
    base_ref = np.eye(4)
    base_ref[:3, 3] = (2.0, -0.5, -0.3)
    c, s = np.cos(0.7), np.sin(0.7)  # a turned base: the Jacobian is in tracker axes
    base_ref[:2, :2] = [[c, -s], [s, c]]
    return AugmentedModel(
        features_spec=FeatureSpec(spec=UR5E, payload_com_m=np.zeros(3), payload_kg_default=0.0),
        theta=th,
        base_ref=base_ref,
        eff=eff,
        accepted=acc,
        free=free,
        cov=A @ A.T / p,
        nominal_tool_m=np.array([0, 0, 0.06]),
    )


def _corrector(m: AugmentedModel) -> Corrector:
    nominal = Nominal(theta=pack(UR5E.dh, tool=(0.0, 0.0, 0.06)), base_ref=m.base_ref)
    return Corrector(m, nominal, Conditions(approach_sign=np.ones(6)))


def test_the_approach_figures_std_matches_draws_from_the_covariance():
    m = _model(2e-5)
    q = np.random.default_rng(3).uniform(-2.0, 2.0, (40, 6))
    a = approach_sensitivity(_corrector(m), q)
    assert a is not None and a["rms_m"] > 20e-6  # 2 x 0.2 mrad of joint-3 play, at the SMR
    assert a["rms_std_m"] > 0.5e-6 and a["max_std_m"] > 0.5e-6  # not a zero by construction
    nf = int(m.free.sum())
    z = np.random.default_rng(4).multivariate_normal(np.zeros(len(m.cov)), m.cov, size=600)
    rms, mx = [], []
    for zi in z:
        th = m.theta.copy()
        th[m.free] += zi[:nf]
        eff = m.eff.copy()
        eff[m.active] += zi[nf:]
        d = approach_sensitivity(_corrector(dataclasses.replace(m, theta=th, eff=eff)), q)
        rms.append(d["rms_m"])
        mx.append(d["max_m"])
    assert a["rms_std_m"] == pytest.approx(np.std(rms), rel=0.1)
    assert a["max_std_m"] == pytest.approx(np.std(mx), rel=0.15)


def test_the_line_gives_the_std_only_when_there_is_one():
    a = {"rms_m": 12.34e-6, "max_m": 40.0e-6, "rms_std_m": 1.5e-6, "max_std_m": 3.2e-6}
    line = approach_line(a)
    assert "12.3 +- 1.5 um RMS, 40.0 +- 3.2 um at most" in line and "1-sigma" in line
    bare = approach_line({"rms_m": 12.34e-6, "max_m": 40.0e-6})
    assert "12.3 um RMS, 40.0 um at most" in bare and "1-sigma" not in bare
