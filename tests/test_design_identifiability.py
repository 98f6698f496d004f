"""Identifiability of the geometric parameters (seed 002, Theorem 1): rank, singular values,
condition, dependent groups, O1 and minimum singular value."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from workcell.campaign.envelope import default_envelope
from workcell.campaign.plans import random_configurations
from workcell.estimation.bounded import jacobian_padded
from workcell.estimation.identifiability import analyse, observability
from workcell.kinematics.chain import PARAM_NAMES, pack, parallel_beta_names
from workcell.kinematics.robots import UR5E

TOOL = np.array([0.0, 0.0, 0.06])


def _candidates():
    betas = set(parallel_beta_names(UR5E.dh))
    return [n for n in PARAM_NAMES if not n.startswith("beta") or n in betas]


@pytest.fixture(scope="module")
def ur5e_jacobian():
    env = default_envelope(UR5E)
    q = random_configurations(UR5E, env, 40, np.random.default_rng(3), TOOL)
    J = jacobian_padded(pack(UR5E.dh, tool=TOOL), np.eye(4), q)
    return q, J


def test_rank_and_groups_of_the_ur5e_chain(ur5e_jacobian):
    _, J = ur5e_jacobian
    ident = analyse(J.reshape(-1, 39), candidates=_candidates())
    # the independently derived count: 4 per joint (24) + 2 Hayati tilts + 6 base + 3 tool = 35
    # columns, minus the dependencies of a position-only measured UR chain
    groups = [set(g) for g in ident.groups]
    for g in (
        {"d1", "base_tz"},
        {"theta1_offset", "base_rz"},
        {"d2", "d3", "d4"},
        {"a6", "tool_x"},
        {"d6", "tool_z"},
    ):
        assert g in groups, (g, groups)
    dep = set(ident.dependent)
    assert ident.rank == len(_candidates()) - len(dep)
    assert set(ident.identifiable).isdisjoint(dep)
    # the kept columns really have full rank and the dropped ones are in their span
    Jk = J.reshape(-1, 39)[:, [PARAM_NAMES.index(n) for n in ident.identifiable]]
    s = np.linalg.svd(Jk / np.linalg.norm(Jk, axis=0), compute_uv=False)
    assert s[-1] / s[0] > 1e-4
    assert np.isclose(ident.condition, s[0] / s[-1], rtol=1e-9)
    np.testing.assert_allclose(ident.singular_values, s, rtol=1e-9)
    for name in dep:
        c = J.reshape(-1, 39)[:, PARAM_NAMES.index(name)]
        if np.linalg.norm(c) == 0:
            continue
        x, *_ = np.linalg.lstsq(Jk, c, rcond=None)
        assert np.linalg.norm(Jk @ x - c) < 1e-6 * np.linalg.norm(c), name


def test_theorem1_rank_needs_enough_rows(ur5e_jacobian):
    """With 3n < L rows the rank is at most 3n: Theorem 1's count 3n >= L is necessary."""
    _, J = ur5e_jacobian
    full = analyse(J.reshape(-1, 39), candidates=_candidates()).rank
    few = analyse(J[:5].reshape(-1, 39), candidates=_candidates())
    assert few.rank <= 15 < full
    assert len(few.identifiable) == few.rank


def test_planted_dependency_is_named():
    rng = np.random.default_rng(0)
    names = ["p", "q", "r", "s"]
    J = rng.normal(size=(30, 4))
    J[:, 3] = 2.0 * J[:, 0] - 0.5 * J[:, 2]  # s = 2 p - 0.5 r
    ident = analyse(J, names, priority=names)
    assert ident.rank == 3
    assert ident.dependent == {"s": ["p", "r"]}
    assert ident.groups == [["p", "r", "s"]]


def test_observability_indices_match_definitions():
    rng = np.random.default_rng(1)
    Js = rng.normal(size=(3 * 12, 5))
    s = np.linalg.svd(Js, compute_uv=False)
    obs = observability(Js)
    assert np.isclose(obs["o1"], np.prod(s) ** (1 / 5) / np.sqrt(12))
    assert np.isclose(obs["min_singular_value"], s.min())
    assert np.isclose(obs["condition"], s.max() / s.min())
    # O1 is the determinant index: det(Js^T Js) = prod s^2
    assert np.isclose(obs["o1"] ** 10 * 12**5, np.linalg.det(Js.T @ Js), rtol=1e-8)
    rank_def = Js.copy()
    rank_def[:, 4] = rank_def[:, 0]
    # a geometric mean: one zero singular value (~1e-16) pulls O1 down by (1e-16)^(1/5)
    assert observability(rank_def)["o1"] < 1e-2 * obs["o1"]


def test_more_spread_poses_are_more_observable(ur5e_jacobian):
    """Poses clustered around one configuration are less observable than spread ones."""
    q, J = ur5e_jacobian
    th = pack(UR5E.dh, tool=TOOL)
    rng = np.random.default_rng(2)
    q_tight = q[0] + rng.normal(0.0, 0.05, size=(40, 6))
    J_tight = jacobian_padded(th, np.eye(4), q_tight)
    a = analyse(J.reshape(-1, 39), candidates=_candidates())
    cols = [PARAM_NAMES.index(n) for n in a.identifiable]

    def idx(Jx):
        Js = Jx.reshape(-1, 39)[:, cols]
        return observability(Js / np.linalg.norm(J.reshape(-1, 39)[:, cols], axis=0))

    spread, tight = idx(J), idx(J_tight)
    assert spread["o1"] > 10 * tight["o1"]
    assert spread["min_singular_value"] > 10 * tight["min_singular_value"]


def test_analyse_rejects_bad_shape():
    with pytest.raises(ValueError, match="expected shape"):
        analyse(np.zeros((6, 5)))


def test_a_near_dependency_is_named_with_its_std_inflation():
    """Two columns at a small angle eps (the others orthogonal): the rank test keeps both, but
    each estimate's std is 1/sin(eps) times what it would be with the other known, and the two
    estimates are correlated -cos(eps). `weak_directions` must find that pair, and only it."""
    from workcell.estimation.identifiability import weak_directions

    rng = np.random.default_rng(0)
    Q, _ = np.linalg.qr(rng.normal(size=(60, 6)))
    names = [f"p{i}" for i in range(6)]
    for eps in (1e-3, 3e-3):
        J = Q * np.array([1.0, 2.0, 0.5, 1.0, 3.0, 1.0])
        J[:, 4] = 3.0 * (np.cos(eps) * Q[:, 1] + np.sin(eps) * Q[:, 4])
        assert analyse(J, names, priority=names).rank == 6
        cov = 4e-6 * np.linalg.inv(J.T @ J)
        weak = weak_directions(cov, names)
        assert [g["parameters"] for g in weak] == [["p1", "p4"]]
        assert weak[0]["std_inflation"] == pytest.approx(1.0 / np.sin(eps), rel=1e-6)
        assert weak[0]["correlation"] == pytest.approx(-np.cos(eps), abs=1e-9)
    # a fixed parameter (zero variance) is skipped; well-separated columns give nothing
    cov = np.diag([1e-6, 2e-6, 0.0, 1e-6, 3e-6, 1e-6])
    assert weak_directions(cov, names) == []
    assert weak_directions(np.full((6, 6), np.nan), names) == []
    with pytest.raises(ValueError, match=r"\(6, 6\)"):
        weak_directions(np.eye(5), names)


REAL = Path(__file__).resolve().parents[2] / "shared/data/ur10-leica"


@pytest.mark.skipif(not REAL.exists(), reason="shared real data not present")
def test_the_real_iso_cube_series_barely_separates_base_y_from_the_smr_offset(capsys, tmp_path):
    """Series D measures an iso cube with one tool orientation: the SMR's offset along the tool
    z axis and the base's y translation move the measured point alike. The rank test keeps both;
    the fit must say they are weakly identified (their std tens of mm). Series B varies the
    joints freely: nothing is flagged."""
    from workcell.cli import main
    from workcell.estimation.fitting import fit_recording

    d = fit_recording(REAL / "series_D_iso_cubes.mcap", method="dh")
    weak = d["identifiability"]["weakly_identified"]
    assert [sorted(g["parameters"]) for g in weak] == [["base_ty", "tool_z"]]
    assert weak[0]["std_inflation"] > 1000 and abs(weak[0]["correlation"]) > 0.9999
    assert d["parameters"]["tool_z"]["std"] > 1e-3  # what the inflation means: mm, not um
    b = fit_recording(REAL / "series_B_joint_configurations.mcap", method="dh")
    assert b["identifiability"]["weakly_identified"] == []
    # the command line says it in words
    capsys.readouterr()
    rc = main(["fit", str(REAL / "series_D_iso_cubes.mcap"), "--out", str(tmp_path / "d.json")])
    out = capsys.readouterr().out
    assert rc == 0
    assert "weakly identified" in out
    line = next(ln for ln in out.splitlines() if ln.strip().startswith("{base_ty, tool_z}"))
    assert "x what it would be with the others known, correlation +1.0000" in line


def test_correlated_pairs_are_named_strongest_first():
    """Pairs whose +- are not independent (|r| >= 0.9) are listed for `fit` to print: series B's
    d4/alpha1 at r = -0.984 sat behind independent-looking +- (metrology audit, 2026-11-29)."""
    from workcell.estimation.identifiability import correlated_pairs

    names = ["a", "b", "c", "fixed"]
    s = np.array([1.0, 2.0, 0.5])
    R = np.array([[1.0, -0.95, 0.1], [-0.95, 1.0, 0.92], [0.1, 0.92, 1.0]])
    cov = np.zeros((4, 4))
    cov[:3, :3] = R * np.outer(s, s)
    got = correlated_pairs(cov, names)
    assert [g["parameters"] for g in got] == [["a", "b"], ["b", "c"]]
    assert got[0]["correlation"] == pytest.approx(-0.95)
    assert correlated_pairs(cov, names, threshold=0.96) == []
    assert correlated_pairs(np.full((4, 4), np.nan), names) == []
