"""Discovery's two acceptance gates: a candidate effect is accepted only if the F-test of the
nested fit passes AND K-fold cross-validation (folds by pose) lowers the out-of-fold error by
more than chance (`workcell.estimation.discovery`, module doc, step 4).

The first tests build the linearised problem (`_Linear`) by hand, so that what each gate sees is
known exactly: a column that fits a gross error on one or two poses passes the F-test (it would be
accepted without the cross-validation) and must be rejected; a column spread over all poses with a
real signal passes both and is accepted. The last tests run the whole diagnosis on several clean
simulated recordings (geometry + tracker noise, no physical effect) and count the claims.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from workcell.bench.discovery import make_case
from workcell.estimation.discovery import (
    _FREE_NAMES_ATTR,
    DiagnoseConfig,
    _fold_ids,
    _ftest,
    _Linear,
    diagnose,
    select_effects,
)
from workcell.estimation.effects import Candidate
from workcell.recording.dataset import Dataset

# ----------------------------------------------------------------------------- constructed
N_POSE = 100  # poses of the constructed problem (rows: 3 per pose, weighted: noise sigma 1)
N_GEO = 8  # free geometric columns
GROSS = 8.0  # size of a gross error on a pose, in noise sigmas (weighted residual units)

SPREAD = Candidate("joint_compliance", 2, idx=(0,))  # a column with signal on every pose
LOCAL = Candidate("backlash", 5, idx=(1,))  # a column concentrated on a few poses


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _problem(local: str, spread_signal: float, seed: int = 0):
    """A linearised problem (`_Linear`) with geometry G (N_GEO columns), the SPREAD column (0) and
    the LOCAL column (1), and the poses that LOCAL lives on.

    Every pose carries tracker noise of sigma 1 (weighted units) and a geometric error (a random
    combination of G, which the geometry absorbs). SPREAD is a random column over the ordinary
    poses with true coefficient `spread_signal` (0: SPREAD is not in the data).

    LOCAL lives on a few special poses, one per fold (`_fold_ids`, as `diagnose` assigns them);
    G and SPREAD are zero on those poses, so the out-of-fold fits of LOCAL decouple from the rest
    and the cross-validation arithmetic below is exact, not a matter of the random draw:
    - "one": on pose A the residual has a gross error of GROSS sigma along LOCAL's direction there
      (|LOCAL_A| = 1); on one pose of each other fold LOCAL has a small part (|LOCAL_i| = 0.5)
      orthogonal to that pose's noise. In sample LOCAL removes GROSS^2 / 2 = 32 of the residual
      sum of squares (F about 32 on 1 and ~290 degrees of freedom). Out of fold: with A held
      out, the coefficient is fitted on the small parts, where LOCAL explains nothing: 0, and A
      is unchanged; with another special pose held out, the coefficient (fitted on A) is
      GROSS / 1.75 and adds (GROSS / 1.75)^2 * 0.25 = 5.2 to that pose's error. The
      cross-validated error gets worse: the column fitted the one gross error, nothing else.
    - "two": gross errors of GROSS sigma on two poses A, B (different folds), each along LOCAL's
      direction there. In sample F is about 128; out of fold each pose predicts the other
      exactly, so the per-pose CV error drops by GROSS^2 on those two poses and is unchanged on
      the other N_POSE - 2. The one-sided paired t statistic over poses of such a difference is
      sqrt(2 (N - 1) / (N - 2)) = 1.42 whatever its size (p = 0.08 > cv_alpha 0.05): an
      improvement carried by two poses is not an improvement "over poses".
    """
    rng = np.random.default_rng(seed)
    folds = _fold_ids(np.arange(N_POSE), 5, 0)
    firsts = [int(np.flatnonzero(folds == f)[0]) for f in range(5)]  # one pose per fold
    special = firsts if local == "one" else firsts[:2]
    ordinary = np.setdiff1d(np.arange(N_POSE), special)

    G = rng.normal(size=(N_POSE, 3, N_GEO))
    G[special] = 0.0
    C = np.zeros((N_POSE, 3, 2))
    C[ordinary, :, 0] = rng.normal(size=(len(ordinary), 3))
    r = rng.normal(size=(N_POSE, 3)) + G @ rng.normal(0.0, 3.0, N_GEO)
    r -= spread_signal * C[:, :, 0]  # r is model - measurement: a true coefficient b adds -b C
    for k, i in enumerate(special):
        if local == "one" and k > 0:  # small part, orthogonal to this pose's noise
            C[i, :, 1] = 0.5 * _unit(np.cross(r[i], rng.normal(size=3)))
            continue
        u = _unit(rng.normal(size=3))
        C[i, :, 1] = u
        r[i] = r[i] - (r[i] @ u) * u + GROSS * u  # noise across u, a gross error along it
    lin = _Linear(r, G, C, folds)
    setattr(lin, _FREE_NAMES_ATTR, [f"g{i}" for i in range(N_GEO)])
    return lin, special


def _f_alone_passes(lin: _Linear, cand: Candidate, given: list[Candidate], tried: int) -> bool:
    """Would the F-test alone accept `cand` given `given` (at select_effects' Bonferroni level)?"""
    cfg = DiagnoseConfig()
    cur = [i for c in given for i in c.idx]
    n, ng = lin.r.size, lin.G.shape[1]
    _, p = _ftest(lin.rss(cur), lin.rss(cur + list(cand.idx)), 1, n, ng + len(cur) + 1)
    return p < cfg.alpha / tried


@pytest.mark.parametrize("local", ["one", "two"])
def test_a_column_fitting_gross_errors_on_few_poses_passes_f_but_is_rejected_by_cv(local):
    """LOCAL fits one (or two) poses' gross errors: the F-test accepts it, cross-validation does
    not, so nothing is accepted. Without the cross-validation gate LOCAL would be accepted."""
    lin, special = _problem(local, spread_signal=0.0)
    assert _f_alone_passes(lin, LOCAL, [], tried=1)
    log: list[str] = []
    M, steps, screen = select_effects(lin, [LOCAL], DiagnoseConfig(), log.append)
    assert M == [] and steps == []
    assert screen[LOCAL.key]["rho"] > 0.99  # identifiable: rejected by the test, not absorbed
    (line,) = [x for x in log if "candidate" in x]
    assert line.endswith("-> set aside (CV)")
    # the out-of-fold errors behave as the problem's docstring derives (1e-9: rounding of exact 0s)
    e0, e1 = lin.cv_errors([]), lin.cv_errors(list(LOCAL.idx))
    d = e0 - e1
    others = np.setdiff1d(np.arange(N_POSE), special)
    assert np.abs(d[others]).max() < 1e-9 * e0.max()
    if local == "one":
        assert abs(d[special[0]]) < 1e-9 * e0.max()
        assert d[special[1:]] == pytest.approx(-((GROSS / 1.75) ** 2) * 0.25, rel=1e-9)
        assert e1.mean() > e0.mean()
    else:
        assert d[special] == pytest.approx(GROSS**2, rel=1e-9)
        t = np.sqrt(2 * (N_POSE - 1) / (N_POSE - 2))
        assert stats.t.sf(t, N_POSE - 1) > DiagnoseConfig().cv_alpha
        assert e1.mean() < e0.mean()  # the mean improves; the paired test over poses does not


def test_a_real_effect_passes_both_gates_and_a_few_pose_fit_after_it_does_not():
    """SPREAD carries a real signal (0.5 sigma per coordinate on every ordinary pose): accepted,
    with a significant cross-validated gain and the right size. LOCAL, tested next (given the
    geometry and SPREAD), passes the F-test and fails the cross-validation: it is set aside and
    the selection ends with SPREAD alone. The size check: within 4 standard errors (sigma 1 / |projected column|)."""
    lin, _ = _problem("one", spread_signal=0.5)
    cfg = DiagnoseConfig()
    M, steps, _ = select_effects(lin, [SPREAD, LOCAL], cfg, lambda m: None)
    assert M == [SPREAD]
    (st,) = steps
    assert st.action == "add" and st.cand == SPREAD
    assert st.p < st.alpha_used and st.cv_p < cfg.cv_alpha and st.cv_ratio < 1.0
    _, (b,) = lin.coef([0])
    se = 1.0 / (np.linalg.norm(lin.Cp[:, 0]) * lin.cs[0])
    assert abs(b - 0.5) < 4 * se
    # LOCAL after SPREAD: the F-test alone would have taken it (one candidate left: level alpha)
    assert _f_alone_passes(lin, LOCAL, [SPREAD], tried=1)


def test_a_few_pose_fit_tested_first_does_not_hide_a_real_effect():
    """LOCAL fits two 8-sigma poses and has the better BIC, so it is tested first: it passes the
    F-test and fails the cross-validation. It is set aside (not a stop), and SPREAD, a real
    0.5-sigma effect on every pose, is then tested and accepted, as it is when alone. Set-aside
    candidates keep counting in the Bonferroni level (2 candidates: alpha / 2)."""
    lin, _ = _problem("two", spread_signal=0.5)
    log: list[str] = []
    alone, _, _ = select_effects(lin, [SPREAD], DiagnoseConfig(), lambda m: None)
    assert alone == [SPREAD]
    M, steps, _ = select_effects(lin, [SPREAD, LOCAL], DiagnoseConfig(), log.append)
    assert M == [SPREAD]
    lines = [x for x in log if "candidate" in x]
    assert LOCAL.key in lines[0] and lines[0].endswith("-> set aside (CV)")
    assert SPREAD.key in lines[1] and lines[1].endswith("-> accept")
    assert steps[0].alpha_used == pytest.approx(DiagnoseConfig().alpha / 2)


# ----------------------------------------------------------------------------- clean recordings
N_REC = 160  # poses per recording, as in test_discovery_selection
FALSE_ALARM_LEVEL = 0.01  # DiagnoseConfig.alpha: family level per step, Bonferroni over candidates


def _allowed(n_rec: int, level: float = FALSE_ALARM_LEVEL, tail: float = 0.005) -> int:
    """The largest count of clean recordings with a claim that n_rec recordings give, at a
    per-recording false-alarm rate `level`, with probability >= 1 - `tail` (binomial)."""
    return int(stats.binom.ppf(1.0 - tail, n_rec, level))


def _claims_on_clean(tmp: Path, seeds) -> dict[int, list[str]]:
    out = {}
    for seed in seeds:
        c = make_case([], seed, N_REC, 1.0, tmp, np.random.default_rng(seed), warmup_s=300.0)
        r = diagnose(Dataset.from_recording(c["path"]), DiagnoseConfig(nonparametric=False))
        out[seed] = [e["key"] for e in r.report["effects"]]
    return out


@pytest.mark.slow  # moved out of `make test` on 2026-11-26 (its time); `make test-all` runs it
def test_clean_recordings_over_several_seeds_claim_no_effect(tmp_path):
    """Eight clean recordings (seeds 1-8; geometric errors and the simulator's tracker noise -
    per-pose systematic and random parts, beam breaks, outliers - and no physical effect).

    The design's false-alarm level is at most alpha = 1 % per recording (the F-test at family
    level alpha per step; the cross-validation gate only removes claims). At that rate 8
    recordings give at most 1 recording with a claim with probability 99.7 % (`_allowed`), which
    is what is asserted. (Measured: no claim on seeds 1-40 at 160 poses.)"""
    claims = _claims_on_clean(tmp_path, range(1, 9))
    bad = {s: k for s, k in claims.items() if k}
    assert len(bad) <= _allowed(len(claims)) == 1, bad


@pytest.mark.slow
def test_clean_recordings_over_many_seeds_claim_no_effect(tmp_path):
    """As above over 40 seeds (1-40): at 1 % per recording, 40 recordings give at most 3 with a
    claim with probability 99.9 % (`_allowed`; at most 2: 99.25 %, below the 99.5 % asked)."""
    claims = _claims_on_clean(tmp_path, range(1, 41))
    bad = {s: k for s, k in claims.items() if k}
    assert len(bad) <= _allowed(len(claims)), bad
