"""Observability indices as the calibration literature defines them (issue 6): O1 of Borm & Menq
(1991), (sigma_1 ... sigma_L)^(1/L) / sqrt(m), and O3 = sigma_L (Nahvi, Hollerbach & Hayward 1994),
of the identification Jacobian in FIXED units (metres; angles as the arc at 1 m) over the L
parameters the chain can identify at all. Each test failed on the earlier definition (columns scaled
to unit norm over the pose set itself, then divided by sqrt(N) again; L = what the poses identify),
which printed O1 0.196 / 0.146 / 0.104 / 0.0747 at 10 / 30 / 60 / 120 random poses and scored a
rank-deficient 5-pose set (0.255) above a full-rank 30-pose one. Also: `workcell bench design`
option mistakes are one line."""

from __future__ import annotations

import numpy as np
import pytest

from workcell.campaign.envelope import default_envelope
from workcell.campaign.plans import random_configurations
from workcell.estimation.bounded import jacobian_padded
from workcell.estimation.identifiability import (
    analyse,
    candidates_for,
    observability,
    parameter_units,
    pose_set_report,
    priority_for,
    structural_identifiable,
)
from workcell.kinematics.chain import pack, param_names
from workcell.kinematics.robots import UR5E

TOOL = np.array([0.0, 0.0, 0.06])  # on the flange axis, as the simulated cell's SMR
NAMES = param_names(6)


def _q(n: int, seed: int = 0) -> np.ndarray:
    return random_configurations(UR5E, default_envelope(UR5E), n, np.random.default_rng(seed), TOOL)


def _J(q: np.ndarray) -> np.ndarray:
    return jacobian_padded(pack(UR5E.dh, tool=TOOL), np.eye(4), q).reshape(-1, len(NAMES))


def _ident(J: np.ndarray, **kw):
    return analyse(
        J,
        NAMES,
        priority=priority_for(6),
        candidates=candidates_for(UR5E.dh),
        structural=structural_identifiable(UR5E.dh, TOOL),
        **kw,
    )


def test_structural_set_is_the_25_of_the_ur_arms():
    s = structural_identifiable(UR5E.dh, TOOL)
    assert len(s) == 25
    assert {"d2", "d3", "d1", "theta1_offset", "a6", "d6"}.isdisjoint(s)


def test_o1_does_not_drift_with_the_pose_count():
    """Random poses from one envelope: O1 at 30, 60, 120 and 240 poses within 10 % of each
    other (it was proportional to 1 / sqrt(N): 0.146 at 30, 0.0747 at 120), and a pose set
    measured k times has exactly the O1 of the set once."""
    q = _q(240)
    o1 = {n: pose_set_report(UR5E.dh, q[:n], TOOL)["o1"] for n in (30, 60, 120, 240)}
    assert max(o1.values()) / min(o1.values()) < 1.10, o1
    J = _J(q[:30])
    once = _ident(J).o1
    for k in (2, 4):
        assert _ident(np.vstack([J] * k)).o1 == pytest.approx(once, rel=1e-9)
    # the minimum singular value is not normalised (Nahvi et al.): it grows like sqrt(k)
    assert _ident(np.vstack([J] * 4)).min_singular_value == pytest.approx(
        2.0 * _ident(J).min_singular_value, rel=1e-9
    )


def test_a_rank_deficient_set_scores_zero():
    """5 poses (15 equations for 25 parameters) and the same 5 poses measured 8 times both
    leave parameters dependent: O1 = O3 = 0, below every full-rank set (0.255 before)."""
    q5 = _q(5)
    r = pose_set_report(UR5E.dh, q5, TOOL)
    assert r["rank"] == 15 and r["o1"] == 0.0 and r["min_singular_value"] == 0.0
    again = _ident(np.vstack([_J(q5)] * 8))
    assert again.rank == 15 and again.o1 == 0.0 and again.min_singular_value == 0.0
    assert pose_set_report(UR5E.dh, _q(30), TOOL)["o1"] > 0.3


def test_o1_is_the_borm_menq_formula_on_a_hand_made_jacobian():
    """Two poses (6 rows), orthogonal columns of norms 4, 3, 2 (singular values 4, 3, 2) and a
    fourth column, their sum, that no pose set can separate (not in the structural set):
    O1 = (4 * 3 * 2)^(1/3) / sqrt(2), O3 = 2."""
    J = np.zeros((6, 4))
    J[0, 0], J[1, 1], J[5, 2] = 4.0, 3.0, 2.0
    J[:, 3] = J[:, :3].sum(axis=1)
    names = ["a1", "tool_x", "alpha1"]  # lengths and an angle: units 1 with the 1 m lever
    ident = analyse(J, names + ["d1"], priority=names + ["d1"], structural=names)
    assert ident.rank == 3 and ident.dependent == {"d1": ["a1", "tool_x", "alpha1"]}
    assert ident.o1 == pytest.approx(24.0 ** (1 / 3) / np.sqrt(2.0), rel=1e-12)
    assert ident.min_singular_value == pytest.approx(2.0, rel=1e-12)
    obs = observability(J[:, :3])
    assert obs["o1"] ** 6 * 2**3 == pytest.approx(np.linalg.det(J[:, :3].T @ J[:, :3]))
    # one pose alone cannot identify alpha1 (its column is zero there): 0, not a smaller L's O1
    one = analyse(J[:3], names + ["d1"], priority=names + ["d1"], structural=names)
    assert one.o1 == 0.0 and one.min_singular_value == 0.0


def test_indices_are_invariant_to_what_the_docstring_says():
    """O1 and O3 do not change with the order of the poses or of the parameters, or with a
    rotation of the frame the points are measured in; a change of units multiplies O1 by the
    same factor for every pose set (so O1 ranks pose sets the same whatever the units)."""
    q = _q(40, seed=4)
    J = _J(q)
    ref = _ident(J)
    perm = np.random.default_rng(1).permutation(len(q))
    shuffled = _ident(J.reshape(len(q), 3, -1)[perm].reshape(-1, len(NAMES)))
    R = np.linalg.qr(np.random.default_rng(2).normal(size=(3, 3)))[0]
    rotated = _ident(np.einsum("ab,nbp->nap", R, J.reshape(len(q), 3, -1)).reshape(-1, len(NAMES)))
    cols = np.random.default_rng(3).permutation(len(NAMES))
    names_p = [NAMES[i] for i in cols]
    reordered = analyse(
        J[:, cols],
        names_p,
        priority=priority_for(6),
        candidates=candidates_for(UR5E.dh),
        structural=structural_identifiable(UR5E.dh, TOOL),
    )
    for other in (shuffled, rotated, reordered):
        assert other.o1 == pytest.approx(ref.o1, rel=1e-9)
        assert other.min_singular_value == pytest.approx(ref.min_singular_value, rel=1e-9)
    # units: angles at a 0.3 m lever instead of 1 m; two different pose sets
    J2 = _J(_q(25, seed=9))
    u = parameter_units(NAMES, angle_length_m=0.3)
    a, b = _ident(J).o1, _ident(J2).o1
    a3, b3 = _ident(J, units=u).o1, _ident(J2, units=u).o1
    assert a3 != pytest.approx(a, rel=1e-3)
    assert a3 / b3 == pytest.approx(a / b, rel=1e-9)


@pytest.mark.parametrize("index, printed", [("o1", "o1"), ("min_sv", "min_singular_value")])
def test_dopt_maximises_the_printed_index(index, printed):
    """At the nominal chain (no relinearisation), once the first poses identify all L
    parameters, every dopt choice is the candidate that maximises the index as printed (O1, or
    O3 = the minimum singular value for `index="min_sv"`) of the poses so far plus it; and
    dopt's parameters are the structural set. min_sv failed when it took the minimum singular
    value in dopt's own column scale."""
    from workcell.campaign.adaptive import _candidates, identifiable_mask, plan_over_candidates

    env = default_envelope(UR5E)
    q_c, s_c = _candidates(UR5E, env, 120, 5, TOOL, 0.02)
    structural = structural_identifiable(UR5E.dh, TOOL)
    free = identifiable_mask(UR5E, _J(q_c).reshape(len(q_c), 3, -1))
    assert sorted(np.array(NAMES)[free]) == sorted(structural)
    choices: list[dict] = []
    gen = plan_over_candidates(
        "dopt", UR5E, q_c, s_c, TOOL, list(range(14)), seed=5, relinearise_every=0,
        on_choice=choices.append, index=index,
    )  # fmt: skip
    t = next(gen)
    try:
        while True:
            sample = {"q_measured_rad": t.q_rad.tolist(), "tracker_position_m": [0.0, 0.0, 0.0]}
            t = gen.send(sample)
    except StopIteration:
        pass
    chosen = [c["candidate"] for c in choices]
    J_c = _J(q_c).reshape(len(q_c), 3, -1)
    checked = 0
    for k in range(1, len(chosen)):
        so_far = chosen[:k]
        if _ident(J_c[so_far].reshape(-1, len(NAMES))).o1 == 0.0:
            continue  # before full rank every candidate scores O1 = 0; dopt's ridge decides
        rest = [i for i in range(len(q_c)) if i not in so_far]
        o = {i: getattr(_ident(J_c[so_far + [i]].reshape(-1, len(NAMES))), printed) for i in rest}
        best = max(o, key=o.get)
        assert chosen[k] == best or o[chosen[k]] == pytest.approx(o[best], rel=1e-9), k
        checked += 1
    assert checked >= 4


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--target-factor", "-1"], "--target-factor must be a positive number, got -1"),
        (["--target-factor", "nan"], "--target-factor must be a positive number, got nan"),
        (["--target-factor", "0"], "--target-factor must be a positive number"),
        (
            ["--envelope", "compact", "--half-width-deg", "-5"],
            "--half-width-deg must be in (0, 180], got -5",
        ),
        (["--envelope", "compact", "--half-width-deg", "nan"], "--half-width-deg must be in"),
    ],
)
def test_bench_design_option_mistakes_are_one_line(capsys, argv, match):
    """`--target-factor -1` / `nan` ran the whole bench ("target nanx floor"), and
    `--half-width-deg -5` failed with numpy's "high - low < 0"."""
    from test_design_cli_audit_fixes import bench_design

    rc, err, _ = bench_design(capsys, *argv)  # no traceback, no warning
    assert rc == 2 and len(err) == 1 and match in err[0], (rc, err)


def test_a_fits_indices_are_the_dry_runs_whatever_the_weights():
    """`workcell fit` reported O1 of its 1/sigma-weighted Jacobian (19819 on real series D,
    against about 0.4 for a planned set in the dry run): now the same definition as the dry run,
    unweighted, over the chain's structural set, whatever the tracker's sigma."""
    from workcell.estimation.identifiability import fit_identifiability

    q = _q(30, seed=4)
    J = jacobian_padded(pack(UR5E.dh, tool=TOOL), np.eye(4), q)
    dry = analyse(J.reshape(-1, len(NAMES)), NAMES, candidates=candidates_for(UR5E.dh),
                  structural=structural_identifiable(UR5E.dh, TOOL))  # fmt: skip
    for w in (np.full(30, 1e5), np.random.default_rng(1).uniform(1e4, 1e6, 30)):
        fit = fit_identifiability(J * w[:, None, None], w, UR5E.dh, TOOL)
        assert fit.o1 == pytest.approx(dry.o1, rel=1e-9) and 0.1 < fit.o1 < 1.0
        assert fit.min_singular_value == pytest.approx(dry.min_singular_value, rel=1e-9)
        assert len(fit.observability_parameters) == 25 and fit.rank == 25
