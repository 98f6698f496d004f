"""Discrepancy discovery: locate the mismatch between the nominal model and a recording, name the
physics that was left out, model it, and show the held-out fit improve.

Pipeline (`diagnose(ds)`):
1. Split. The recording's deterministic hold-out split (`Dataset.holdout_split`); everything
   below up to step 7 sees the training poses only.
2. Geometry. `fit_dh` (simultaneous DH + joint offsets + Hayati tilts + base + SMR, with its
   identifiability analysis). Poses whose geometric residual is a gross outlier are set aside.
   Weights: per pose sigma = max(recorded sigma, tracker MPE model (A + B * range) / 4) - the
   recorded sigma of a mean often misses the tracker's per-pose systematic error.
3. Locate. The geometry-only residual, made out-of-sample by K-fold cross-validation, is examined
   along each joint's direction of motion against gravity torque, approach direction and the
   joint angle's harmonics, against time/temperature and over the workspace.
4. Name: joint estimation, not sequential. The augmented forward model
   (`workcell.estimation.effects`) is linearised at the geometric solution with respect to all
   free geometric parameters and every candidate of the library at once; each candidate is then
   always estimated *together with the whole geometry* (and the effects already accepted), so an
   effect the geometry can partly absorb is judged only on what the geometry cannot absorb.
   - Identifiability per candidate: rho = smallest singular value of the candidate's
     column-normalised signature after projecting out the geometry and the accepted effects
     (1: orthogonal to them, 0: fully absorbed). rho < `rho_min` -> "not identifiable", with the
     geometric parameters that absorb it.
   - Selection: greedy forward selection with backward pruning. At each step the candidate with
     the best BIC is tested, and accepted only if BOTH
       (a) a likelihood-ratio (F) test of the nested linear-Gaussian models rejects "no effect"
           at level `alpha` / m (Bonferroni over the m identifiable candidates of that step;
           variance from the residual, so stated sigmas need not be right), and
       (b) K-fold cross-validation (folds by pose) lowers the out-of-fold error by more than
           chance: one-sided paired t-test over poses of the per-pose CV squared error at
           level `cv_alpha`.
     A candidate that passes (a) and fails (b) fits something carried by a few poses (gross
     errors the outlier screen let through); it is set aside and the next best tested, so it
     cannot hide a real effect. A compliance or a link flexibility estimated negative (a joint
     stiffening against gravity's pull, a link bending against its load: `SIGN_FIXED_KINDS`) is
     set aside the same way: it fits the pattern of some cause outside the library (a pedestal
     yielding under the arm's moment did that in simulation), and the report says so. Set-aside
     candidates still count in the next steps' m. A candidate that fails (a) ends the selection.
     After each acceptance, every earlier effect is re-tested given the others (F-test at
     `alpha`); those no longer significant are removed (backward pruning).
   Why greedy + pruning and not sparse regression over the library: the candidates come in groups
   of very different signature sizes (sin/cos pairs, per-joint parameters), several are strongly
   correlated with each other and with the geometry (compliance of joint 3 vs deflection of link
   2), and the user needs a test statistic and a p-value per accepted effect. A lasso path on
   correlated groups picks one of a correlated pair for reasons of scaling, and its penalty
   biases the physical sizes; greedy selection with a stated test gives unbiased sizes with
   covariance, an explicit false-alarm level (clean recordings), and pruning repairs an early
   wrong pick.
5. Model. The accepted effects are re-estimated with the geometry by nonlinear least squares
   (full augmented model); covariance with the a-posteriori variance factor.
6. Show. Held-out RMS / max before (geometry) and after, step by step per accepted effect
   (cumulative, in acceptance order), and each effect's own held-out test: the final model
   without it minus with it, paired 95 % interval. An effect is confirmed on the held-out poses
   only when that interval lies above zero; the others stay in the model (the held-out poses
   judge, they do not select) and the summary lists them apart, as not established.
7. Unknown effects. A GP over joint space (`discovery_np`, or `gp_residual` if present) is fitted
   to the final training residual and judged on the held-out poses (one-sided paired test,
   level 0.01, and at least 5 % RMS reduction). If it helps, a structured residual remains that
   no candidate explains: it is reported, located (ARD length scales -> joints; workspace region)
   and offered as a non-parametric correction with its held-out improvement.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg
from scipy import stats
from scipy.optimize import least_squares

from workcell.errors import UserError
from workcell.estimation.dh import TRACKER_MPE_M, DHModel, fit_dh, pose_sigma_model
from workcell.estimation.effects import (
    EFF_NAMES,
    EFF_UNITS,
    N_EFF,
    SIGN_FIXED_KINDS,
    AugmentedModel,
    Candidate,
    FeatureSpec,
    batch_bucket,
    jac_aug,
    library,
    p_aug,
    padded_call,
    thermal_signal,
    thermal_source,
)
from workcell.estimation.fitting import heldout_std_check
from workcell.estimation.models import (
    RMS_INTERVAL_BASIS,
    aux_from_dataset,
    error_stats,
    interval_um,
    note_joint_range,
    rms_gain_interval,
    rms_interval,
    unexplained_error,
    unexplained_text,
)
from workcell.kinematics.chain import PARAM_NAMES, PARAMETER_FRAMES, jac_joints
from workcell.recording.dataset import Dataset, distinct_poses
from workcell.recording.repeats import repeat_beyond_noise, repeat_drift, repeat_line

GP_HELDOUT_CAVEAT = (
    "the residual GP was accepted on these held-out poses (paired test), so its "
    "held-out RMS is somewhat optimistic; the closed-loop check measures it afresh"
)
HELDOUT_CONFIRMS_BASIS = (
    "an effect is confirmed on the held-out poses when the paired 95 % interval (bootstrap over "
    "the held-out poses) of its held-out gain - the RMS of the final model without it minus with "
    "it, both linearised - lies above zero; an interval reaching zero is within chance. Effects "
    "not confirmed stay in the model: the selection accepts on the training poses (F test and "
    "cross-validation), the held-out poses only judge"
)
EXPLAINED_FRACTION_BASIS = (
    "share of the geometry-only residual power that the effect takes out in cross-validation on "
    "the training poses (folds by pose), when it is added to the effects accepted before it (in "
    "acceptance order: the shares add up to the total; not a held-out figure)"
)
STEPS_BASIS = (
    "cumulative, in acceptance order: each step adds one effect to those of the steps above it "
    "(linearised, fitted on the training poses) and gives the held-out RMS and max of that "
    "model; a step's drop depends on the order. An effect's own held-out test is its leave-one-"
    "out gain (effects[].evidence.heldout_gain_m: the final model without it minus with it)"
)


@dataclass
class DiagnoseConfig:
    holdout: float = 0.25
    alpha: float = 0.01  # family level of the LR/F test per step (Bonferroni over candidates)
    cv_folds: int = 5
    cv_alpha: float = 0.05  # one-sided paired test of per-pose CV errors
    rho_min: float = 0.05  # identifiability threshold
    max_effects: int = 12
    orders: tuple[int, ...] = (1, 2, 3)
    tracker_mpe: tuple[float, float] = TRACKER_MPE_M  # A [m] + B [m/m] * range; sigma=MPE/4
    np_alpha: float = 0.01
    np_min_gain: float = 0.05
    nonparametric: bool = True
    seed: int = 0
    physical_signs: bool = True  # set aside a compliance or flexibility fitted negative


@dataclass
class Diagnosis:
    report: dict
    dh_model: DHModel
    model: AugmentedModel
    model_np: AugmentedModel | None
    plots: dict = field(default_factory=dict)  # arrays for the report plots


# ----------------------------------------------------------------------------- helpers
def _with_sigma(ds: Dataset, sig: np.ndarray) -> Dataset:
    return replace(ds, sigma_m=np.repeat(sig[:, None], 3, 1))


def _fold_ids(groups: np.ndarray, k: int, seed: int) -> np.ndarray:
    """Cross-validation fold of each sample, drawn per pose: the samples of one pose measured
    again (`Dataset.pose_groups`) share a fold, so no pose is validated on its own repeat.
    Without repeats, the folds of each sample as before 2026-11-26 (drawn per sample)."""
    _, first, inv = np.unique(np.asarray(groups), return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))  # groups numbered in order of first appearance
    return (np.random.default_rng(seed + 17).permutation(len(first)) % k)[order[inv.ravel()]]


class _Linear:
    """The linearised joint problem on the training poses: residual r (N,3) and columns.

    Rows are poses x 3 axes, weighted by 1/sigma. Columns: free geometry (G) then all effect
    candidates (C), each normalised to unit norm (`scale` keeps the factors)."""

    def __init__(self, r: np.ndarray, G: np.ndarray, C: np.ndarray, folds: np.ndarray):
        n = r.shape[0]
        self.n_pose = n
        self.r = r.reshape(-1)
        self.gs = np.linalg.norm(G.reshape(3 * n, -1), axis=0) + 1e-300
        self.cs = np.linalg.norm(C.reshape(3 * n, -1), axis=0)
        self.G = G.reshape(3 * n, -1) / self.gs
        csafe = np.where(self.cs > 0, self.cs, 1.0)
        self.C = C.reshape(3 * n, -1) / csafe
        self.folds = np.repeat(folds, 3)
        self.pose_of_row = np.repeat(np.arange(n), 3)
        self.Qg, _ = np.linalg.qr(self.G)
        self.rp = self.r - self.Qg @ (self.Qg.T @ self.r)
        self.Cp = self.C - self.Qg @ (self.Qg.T @ self.C)
        self._cv_cache: dict[tuple, np.ndarray] = {}

    def cols(self, idx: list[int]) -> np.ndarray:
        return self.Cp[:, idx]

    def rss(self, idx: list[int]) -> float:
        if not idx:
            return float(self.rp @ self.rp)
        A = self.cols(idx)
        x, *_ = np.linalg.lstsq(A, self.rp, rcond=None)
        e = self.rp - A @ x
        return float(e @ e)

    def coef(self, idx: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Least squares of [G, C_idx]: (geometry coefficients, effect coefficients), unscaled."""
        A = np.hstack([self.G, self.C[:, idx]])
        x, *_ = np.linalg.lstsq(A, -self.r, rcond=None)
        ng = self.G.shape[1]
        cs = np.where(self.cs[idx] > 0, self.cs[idx], 1.0)
        return x[:ng] / self.gs, x[ng:] / cs

    def rho(self, cand: list[int], given: list[int]) -> float:
        """Share of the candidate's (unit) signature not absorbed by geometry + `given`."""
        if np.any(self.cs[cand] <= 0):
            return 0.0
        B = self.cols(cand)
        if given:
            Q, _ = np.linalg.qr(self.cols(given))
            B = B - Q @ (Q.T @ B)
        return float(np.linalg.svd(B, compute_uv=False).min())

    def absorbers(self, cand: list[int], names: list[str], top: int = 4) -> list[str]:
        """Geometric parameters that best reproduce the candidate's signature."""
        b = self.C[:, cand[0]]
        x, *_ = np.linalg.lstsq(self.G, b, rcond=None)
        contrib = np.abs(x) * np.linalg.norm(self.G, axis=0)
        order = np.argsort(-contrib)[:top]
        return [names[i] for i in order if contrib[i] > 0.05 * contrib.max()]

    def cv_errors(self, idx: list[int]) -> np.ndarray:
        """Per-pose out-of-fold squared error (weighted) of the model geometry + C_idx."""
        key = tuple(sorted(idx))
        if key in self._cv_cache:
            return self._cv_cache[key]
        A = np.hstack([self.G, self.C[:, list(key)]]) if key else self.G
        e = np.zeros_like(self.r)
        for f in np.unique(self.folds):
            tr = self.folds != f
            x, *_ = np.linalg.lstsq(A[tr], -self.r[tr], rcond=None)
            e[~tr] = self.r[~tr] + A[~tr] @ x
        per_pose = np.bincount(self.pose_of_row, weights=e * e, minlength=self.n_pose)
        self._cv_cache[key] = per_pose
        return per_pose

    def cv_residual_vectors(self, idx: list[int]) -> np.ndarray:
        """Out-of-fold weighted residual vectors (N, 3)."""
        A = np.hstack([self.G, self.C[:, idx]]) if idx else self.G
        e = np.zeros_like(self.r)
        for f in np.unique(self.folds):
            tr = self.folds != f
            x, *_ = np.linalg.lstsq(A[tr], -self.r[tr], rcond=None)
            e[~tr] = self.r[~tr] + A[~tr] @ x
        return e.reshape(-1, 3)


def _ftest(rss0: float, rss1: float, k: int, n: int, p1: int) -> tuple[float, float]:
    dof = max(n - p1, 1)
    if rss1 <= 0 or k <= 0:
        return float("inf"), 0.0
    F = ((rss0 - rss1) / k) / (rss1 / dof)
    return float(F), float(stats.f.sf(F, k, dof))


def _cv_test(e0: np.ndarray, e1: np.ndarray) -> tuple[float, float]:
    """(CV MSE ratio new/old, one-sided p of 'new is better')."""
    d = e0 - e1
    ratio = float(e1.mean() / max(e0.mean(), 1e-300))
    if np.allclose(d, 0):
        return ratio, 1.0
    p = float(stats.ttest_1samp(d, 0.0, alternative="greater").pvalue)
    return ratio, p


# ----------------------------------------------------------------------------- selection
@dataclass
class Step:
    action: str  # "add" | "remove" | "set aside (sign)"
    cand: Candidate
    f: float
    p: float
    alpha_used: float
    cv_ratio: float
    cv_p: float
    bic_change: float
    rho: float
    value: float | None = None  # the linear estimate, for a term set aside for its sign


def select_effects(
    lin: _Linear, cands: list[Candidate], cfg: DiagnoseConfig, log: Callable[[str], None]
) -> tuple[list[Candidate], list[Step], dict[str, dict]]:
    """Greedy forward selection with backward pruning (see module doc)."""
    n = lin.r.size
    ng = lin.G.shape[1]
    M: list[Candidate] = []
    steps: list[Step] = []
    screen: dict[str, dict] = {}
    removed: set[str] = set()
    aside: set[str] = set()  # passed the F-test, failed cross-validation or the physical sign

    def idx_of(cs: list[Candidate]) -> list[int]:
        return [i for c in cs for i in c.idx]

    def bic(rss: float, p: int) -> float:
        return n * np.log(max(rss, 1e-300) / n) + p * np.log(n)

    for _it in range(3 * cfg.max_effects):
        if len(M) >= cfg.max_effects:
            break
        cur = idx_of(M)
        rss0 = lin.rss(cur)
        best = None
        tried = 0
        for c in cands:
            if c in M or c.key in removed or c.key in aside:
                continue
            rho = lin.rho(list(c.idx), cur)
            if not M:
                screen[c.key] = {"rho": rho}
            if rho < cfg.rho_min:
                if not M:
                    screen[c.key]["absorbed_by"] = lin.absorbers(list(c.idx), _free_names(lin))
                continue
            tried += 1
            rss1 = lin.rss(cur + list(c.idx))
            db = bic(rss1, ng + len(cur) + len(c.idx)) - bic(rss0, ng + len(cur))
            if not M:
                screen[c.key]["r2"] = 1.0 - rss1 / rss0
            if best is None or db < best[1]:
                best = (c, db, rss1, rho)
        if best is None:
            break
        c, db, rss1, rho = best
        p1 = ng + len(cur) + len(c.idx)
        F, p = _ftest(rss0, rss1, len(c.idx), n, p1)
        a_used = cfg.alpha / max(tried + len(aside), 1)
        ratio, cv_p = _cv_test(lin.cv_errors(cur), lin.cv_errors(cur + list(c.idx)))
        f_ok = p < a_used
        est = lin.coef(cur + list(c.idx))[1]
        sign_ok = not cfg.physical_signs or physical_sign_ok(c, est)
        ok = f_ok and sign_ok and cv_p < cfg.cv_alpha and ratio < 1.0
        verdict = (
            "accept"
            if ok
            else ("stop" if not f_ok else "set aside (CV)" if sign_ok else "set aside (sign)")
        )
        log(
            f"  candidate {c.key:34s} F={F:9.1f} p={p:.2e} (level {a_used:.1e}) "
            f"CV ratio {ratio:.3f} p={cv_p:.2e} -> {verdict}"
        )
        if not f_ok:
            break
        if not ok:
            aside.add(c.key)
            if not sign_ok:  # recorded: the report says which term was refused and why
                steps.append(
                    Step("set aside (sign)", c, F, p, a_used, ratio, cv_p, db, rho, float(est[-1]))
                )
            continue
        M.append(c)
        steps.append(Step("add", c, F, p, a_used, ratio, cv_p, db, rho))
        # backward pruning
        changed = True
        while changed and len(M) > 1:
            changed = False
            full = idx_of(M)
            rss_full = lin.rss(full)
            worst = None
            for d in M[:-1]:
                rest = [x for x in M if x is not d]
                F_d, p_d = _ftest(lin.rss(idx_of(rest)), rss_full, len(d.idx), n, ng + len(full))
                if p_d > cfg.alpha and (worst is None or p_d > worst[2]):
                    worst = (d, F_d, p_d)
            if worst is not None:
                d, F_d, p_d = worst
                M.remove(d)
                removed.add(d.key)
                steps.append(Step("remove", d, F_d, p_d, cfg.alpha, float("nan"), 1.0, 0.0, 0.0))
                log(f"  prune     {d.key:34s} F={F_d:9.1f} p={p_d:.2e} -> removed")
                changed = True
    return M, steps, screen


def physical_sign_ok(c: Candidate, coef: np.ndarray) -> bool:
    """False when the candidate's estimate (the last ``len(c.idx)`` of ``coef``) has the sign its
    physics excludes (`SIGN_FIXED_KINDS`): the term would fit some other cause's pattern."""
    if c.kind not in SIGN_FIXED_KINDS:
        return True
    return bool(np.all(np.asarray(coef, float)[-len(c.idx) :] >= 0.0))


_FREE_NAMES_ATTR = "_free_names"


def _free_names(lin: _Linear) -> list[str]:
    return getattr(lin, _FREE_NAMES_ATTR)


# ----------------------------------------------------------------------------- locate
def _amplitude_std(B: np.ndarray, c: np.ndarray, rss: float) -> float:
    """1-sigma of hypot(c0, c1), the amplitude of a least-squares sine/cosine fit y ~ B c: the
    residual variance rss / (n - p) times (B^T B)^-1, to first order (delta method)."""
    n, p = B.shape
    amp = float(np.hypot(c[0], c[1]))
    if n <= p or amp <= 0.0:
        return float("nan")
    C = rss / (n - p) * np.linalg.pinv(B.T @ B)
    g = np.array([c[0], c[1]]) / amp
    return float(np.sqrt(max(g @ C[:2, :2] @ g, 0.0)))


def locate(
    ds_tr: Dataset,
    X: np.ndarray,
    E: np.ndarray,
    theta: np.ndarray,
    base_ref: np.ndarray,
    source: str,
) -> dict:
    """Where the geometry-only (out-of-fold) residual E (N, 3) [m] concentrates."""
    n = len(E)
    Jq = padded_call(lambda qq: jac_joints(theta, base_ref, qq), ds_tr.q)  # (N, 3, 6)
    norms = np.linalg.norm(Jq, axis=1)  # (N, 6)
    U = Jq / np.maximum(norms[:, None, :], 1e-12)
    # apparent joint error along each joint's direction of motion (rad): residual . u / |J|
    s = np.einsum("nk,nkj->nj", E, U)
    dq = s / np.maximum(norms, 1e-3)
    tau, sgn, dT = X[:, 0:6], X[:, 6:12], X[:, 12:18]
    thr = 3.0 / np.sqrt(n)
    findings: list[dict] = []
    per_joint = []
    for j in range(6):
        row: dict = {"joint": j + 1}
        ok = norms[:, j] > 0.05  # joint moves the SMR by > 5 cm per rad
        if ok.sum() < 10:
            row["note"] = "joint barely moves the target; not observable"
            per_joint.append(row)
            continue
        y = dq[ok, j]
        w_rms = float(np.sqrt(np.mean(s[ok, j] ** 2)))
        row["residual_along_motion_rms_m"] = w_rms
        if np.std(tau[ok, j]) > 1e-6:
            r = float(np.corrcoef(tau[ok, j], y)[0, 1])
            (slope, _), cov = np.polyfit(tau[ok, j], y, 1, cov=True)
            slope, slope_sd = float(slope), float(np.sqrt(max(cov[0, 0], 0.0)))
            row["torque_corr"] = r
            row["torque_slope_rad_per_n_m"] = slope
            row["torque_slope_std_rad_per_n_m"] = slope_sd
            if abs(r) > thr:
                findings.append(
                    {
                        "score": abs(r),
                        "text": f"residual along joint {j + 1}'s motion "
                        + ("grows" if r > 0 else "falls")
                        + f" with the gravity torque on joint {j + 1} (r = {r:+.2f}, "
                        f"{slope * 1e6:+.2f} +- {slope_sd * 1e6:.2f} urad/(N m))",
                    }
                )
        pos, neg = sgn[ok, j] > 0, sgn[ok, j] < 0
        if pos.sum() > 3 and neg.sum() > 3:
            diff = float(y[pos].mean() - y[neg].mean())
            se = float(np.sqrt(y[pos].var() / pos.sum() + y[neg].var() / neg.sum()))
            row["approach_flip_rad"] = diff
            row["approach_flip_std_rad"] = se
            z = abs(diff) / max(se, 1e-15)
            if z > 4:
                findings.append(
                    {
                        "score": min(z / np.sqrt(n), 1.0),
                        "text": f"residual flips sign with the approach direction of joint {j + 1} "
                        f"({diff * 1e6:+.1f} +- {se * 1e6:.1f} urad between + and - approach, "
                        f"{z:.0f} sigma)",
                    }
                )
        qj = ds_tr.q[ok, j]
        best_h = (0.0, 0)
        for k in (1, 2, 3):
            B = np.column_stack([np.sin(k * qj), np.cos(k * qj), np.ones_like(qj)])
            c, *_ = np.linalg.lstsq(B, y, rcond=None)
            rss = float(np.sum((y - B @ c) ** 2))
            r2 = 1 - rss / max(np.sum((y - y.mean()) ** 2), 1e-300)
            if r2 > best_h[0]:
                best_h = (float(r2), k, float(np.hypot(c[0], c[1])), _amplitude_std(B, c, rss))
        if best_h[1]:
            row["periodic_r2"] = best_h[0]
            row["periodic_order"] = best_h[1]
            row["periodic_amplitude_rad"] = best_h[2]
            row["periodic_amplitude_std_rad"] = best_h[3]
            if np.sqrt(best_h[0]) > thr * 1.2:
                findings.append(
                    {
                        "score": float(np.sqrt(best_h[0])),
                        "text": f"residual along joint {j + 1}'s motion is periodic in joint "
                        f"{j + 1}'s angle (order {best_h[1]}, amplitude "
                        f"{best_h[2] * 1e6:.1f} +- {best_h[3] * 1e6:.1f} urad, R2 {best_h[0]:.2f})",
                    }
                )
        per_joint.append(row)
    e = np.linalg.norm(E, axis=1)
    total = float(np.sqrt(np.mean(e**2)))
    # time / temperature
    t = ds_tr.elapsed_s
    time_trend = None
    if np.all(np.isfinite(t)) and np.ptp(t) > 0:
        order = np.argsort(t)
        thirds = np.array_split(order, 3)
        rm = [float(np.sqrt(np.mean(e[i] ** 2))) for i in thirds]
        time_trend = {"rms_first_third_m": rm[0], "rms_last_third_m": rm[2]}
        # the mean radial residual (distance from tracker) vs time: length drift
        pr = ds_tr.p_tracker / np.linalg.norm(ds_tr.p_tracker, axis=1)[:, None]
        radial = np.einsum("nk,nk->n", E, pr)
        r_t = float(np.corrcoef(t, np.abs(E).sum(1))[0, 1]) if n > 3 else 0.0
        time_trend["corr_abs_residual_time"] = r_t
        if source != "none":
            sig = dT.mean(1)
            if np.std(sig) > 0:
                r_T = float(np.corrcoef(sig, radial)[0, 1])
                time_trend["corr_radial_temperature"] = r_T
    # workspace regions: distance from the base axis and height, in tertiles
    p_b = ds_tr.p_tracker - ds_tr.p_tracker.mean(0)
    regions = {}
    for name, v in (
        ("height", p_b[:, 2]),
        ("reach", np.linalg.norm(p_b[:, :2], axis=1)),
    ):
        order = np.argsort(v)
        thirds = np.array_split(order, 3)
        regions[name] = [float(np.sqrt(np.mean(e[i] ** 2))) for i in thirds]
    joint_region = []
    for j in range(6):
        order = np.argsort(ds_tr.q[:, j])
        thirds = np.array_split(order, 3)
        rms3 = [float(np.sqrt(np.mean(e[i] ** 2))) for i in thirds]
        joint_region.append(
            {
                "joint": j + 1,
                "rms_by_angle_tertile_m": rms3,
                "ratio": max(rms3) / max(min(rms3), 1e-15),
            }
        )
    jr = max(joint_region, key=lambda d: d["ratio"])
    if jr["ratio"] > 1.5:
        k = int(np.argmax(jr["rms_by_angle_tertile_m"]))
        findings.append(
            {
                "score": 0.1 * jr["ratio"],
                "text": f"residual is largest in the {['low', 'middle', 'high'][k]} third of "
                f"joint {jr['joint']}'s range ({jr['ratio']:.1f}x the quietest third)",
            }
        )
    findings.sort(key=lambda f: -f["score"])
    return {
        "rms_m": total,
        "statements": [f["text"] for f in findings[:5]],
        "per_joint": per_joint,
        "time": time_trend,
        "workspace_rms_by_tertile_m": regions,
        "joint_angle_tertiles": joint_region,
    }


# ----------------------------------------------------------------------------- final fit
def _fit_augmented(
    ds_tr: Dataset,
    w: np.ndarray,
    X: np.ndarray,
    theta0: np.ndarray,
    base_ref: np.ndarray,
    free: np.ndarray,
    eff0: np.ndarray,
    active: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, int]:
    """Nonlinear weighted least squares over theta[free] and eff[active] -> (theta, eff, cov,
    s0^2, its degrees of freedom)."""
    nf = int(free.sum())

    def unpack(x):
        th = theta0.copy()
        th[free] = x[:nf]
        ef = eff0.copy()
        ef[active] = x[nf:]
        return th, ef

    def fun(x):
        th, ef = unpack(x)
        return ((p_aug(th, ef, base_ref, ds_tr.q, X) - ds_tr.p_tracker) * w[:, None]).ravel()

    def jac(x):
        th, ef = unpack(x)
        Jt, Je = jac_aug(th, ef, base_ref, ds_tr.q, X)
        J = np.concatenate([Jt[:, :, free], Je[:, :, active]], axis=2) * w[:, None, None]
        return J.reshape(-1, J.shape[2])

    x0 = np.concatenate([theta0[free], eff0[active]])
    res = least_squares(fun, x0, jac=jac, method="lm", x_scale="jac", max_nfev=50)
    th, ef = unpack(res.x)
    J = jac(res.x)
    r = res.fun
    dof = max(len(r) - len(x0), 1)
    s0_2 = float(r @ r / dof)
    cov = s0_2 * np.linalg.pinv(J.T @ J)
    return th, ef, cov, s0_2, dof


SPLIT_HALF_Z = 3.0  # |z| beyond which an effect's +- is said to understate its spread
SPLIT_HALF_BASIS = (
    "the final model refitted on two halves of the training poses (a seeded permutation), "
    "z = (value_1 - value_2) / sqrt(std_1^2 + std_2^2) per effect parameter: |z| is about 1 when "
    "the +- is honest; z_rms = sqrt(mean z^2) over the effect parameters estimates how many times "
    "the +- understates the spread of a value over data sets"
)


def _split_half(dfit, w, X, theta, base_ref, free, eff, active, seed: int = 7) -> dict | None:
    """Refit geometry + effects on two halves of the training poses; z per effect index."""
    n = len(dfit)
    if n < 40:
        return None
    perm = np.random.default_rng(seed).permutation(n)
    halves = (np.sort(perm[: n // 2]), np.sort(perm[n // 2 :]))
    vals, var = [], []
    nf = int(free.sum())
    for h in halves:
        _, ef, cov, *_ = _fit_augmented(
            dfit.subset(h), w[h], X[h], theta, base_ref, free, eff, active
        )
        vals.append(ef[active])
        var.append(np.clip(np.diag(cov)[nf:], 0.0, None))
    sd = np.sqrt(var[0] + var[1])
    z = np.where(sd > 0, (vals[0] - vals[1]) / np.where(sd > 0, sd, 1.0), 0.0)
    return {
        "z": {int(i): float(zi) for i, zi in zip(active, z, strict=True)},
        "z_rms": float(np.sqrt(np.mean(z**2))),
        "n_parameters": int(len(active)),
        "basis": SPLIT_HALF_BASIS,
    }


# ----------------------------------------------------------------------------- main entry
def diagnose(
    ds: Dataset,
    cfg: DiagnoseConfig | None = None,
    progress: Callable[[str], None] | None = None,
) -> Diagnosis:
    """Locate, name, model and show (see the module doc). Needs >= 40 poses."""
    with batch_bucket(len(ds)):
        return _diagnose(ds, cfg or DiagnoseConfig(), progress)


def _diagnose(ds: Dataset, cfg: DiagnoseConfig, progress) -> Diagnosis:
    log = progress or (lambda m: None)
    t0 = time.perf_counter()
    if not 0.1 <= cfg.holdout <= 0.5:
        raise ValueError(f"holdout must be in [0.1, 0.5], got {cfg.holdout}")
    if len(ds) < 40:
        raise UserError(f"only {len(ds)} poses; diagnosis needs at least 40")
    if (n_distinct := distinct_poses(ds.q)) < 40:
        raise UserError(
            f"only {n_distinct} distinct joint configurations among {len(ds)} poses; diagnosis "
            "needs at least 40 different poses"
        )
    sig = pose_sigma_model(ds, cfg.tracker_mpe)
    dsw = _with_sigma(ds, sig)
    train, test = dsw.holdout_split(cfg.holdout)
    dtr, dte = dsw.subset(train), dsw.subset(test)
    log(f"{len(ds)} poses: {len(train)} train, {len(test)} held out")

    # ---- 2. geometry
    dh = fit_dh(dtr, tracker_mpe=cfg.tracker_mpe)
    theta, base_ref, free = dh.theta.copy(), dh.base_ref.copy(), dh.free.copy()
    e_tr = np.linalg.norm(padded_call(dh.predict, dtr.q) - dtr.p_tracker, axis=1) / sig[train]
    med = np.median(e_tr)
    mad = 1.4826 * np.median(np.abs(e_tr - med)) + 1e-12
    keep = e_tr < med + 15.0 * mad
    if keep.sum() < 0.8 * len(train):
        keep = np.ones(len(train), bool)
    n_out = int((~keep).sum())
    dfit = dtr.subset(np.flatnonzero(keep))
    w = 1.0 / sig[train][keep]
    log(
        f"geometry: train RMS {dh.info['train_rms_m'] * 1e6:.1f} um, {n_out} outlier poses set aside"
    )

    # ---- features
    src = thermal_source(dfit.joint_temperature_c, dfit.ambient_temperature_c, dfit.elapsed_s)
    tsig = thermal_signal(
        src, dfit.joint_temperature_c, dfit.ambient_temperature_c, dfit.elapsed_s, len(dfit)
    )
    fs = FeatureSpec(
        spec=ds.robot,
        payload_com_m=np.asarray(ds.payload_com_m, float),
        thermal_source=src,
        thermal_ref=tsig.mean(0),
        payload_kg_default=float(np.nanmedian(ds.payload_kg)) if len(ds) else 0.0,
    )

    aux = aux_from_dataset

    X = fs.features(theta, dfit.q, **aux(dfit))
    eff0 = np.zeros(N_EFF)
    p0 = p_aug(theta, eff0, base_ref, dfit.q, X)
    Jt, Je = jac_aug(theta, eff0, base_ref, dfit.q, X)
    folds = _fold_ids(dfit.pose_groups(), cfg.cv_folds, cfg.seed)
    lin = _Linear(
        (p0 - dfit.p_tracker) * w[:, None],
        Jt[:, :, free] * w[:, None, None],
        Je * w[:, None, None],
        folds,
    )
    setattr(lin, _FREE_NAMES_ATTR, [PARAM_NAMES[i] for i in np.flatnonzero(free)])

    # ---- 3. locate (geometry-only out-of-fold residual, metres)
    E_geo = lin.cv_residual_vectors([]) / w[:, None]
    loc = locate(dfit, X, E_geo, theta, base_ref, src)
    for s in loc["statements"]:
        log(f"locate: {s}")

    # ---- 4. name
    cands = library(tuple(cfg.orders))
    M, steps, screen = select_effects(lin, cands, cfg, log)

    # ---- 5. model: joint nonlinear refit of geometry + accepted effects
    idx = [i for c in M for i in c.idx]
    _, beta = lin.coef(idx)
    eff_lin = eff0.copy()
    eff_lin[idx] = beta
    active = np.asarray(sorted(idx), int)
    if len(active):
        th_f, eff_f, cov, s0_2, s0_dof = _fit_augmented(
            dfit, w, X, theta, base_ref, free, eff_lin, active
        )
    else:
        th_f, eff_f = theta, eff0
        cov = dh.cov[np.ix_(free, free)]
        s0_2 = (getattr(dh, "info", None) or {}).get("variance_factor")
        s0_dof = 3 * len(dfit) - int(free.sum())
    model = AugmentedModel(
        features_spec=fs,
        theta=th_f,
        base_ref=base_ref,
        eff=eff_f,
        accepted=list(M),
        free=free,
        cov=cov,
        nominal_tool_m=np.asarray(ds.tool_offset_m, float),
        info={
            **ds.provenance(),  # the recording, and every file of a resumed one
            "train_poses": int(len(train)),
            "outliers_rejected": n_out,
            "thermal_source": src,
        },
    )

    split = _split_half(dfit, w, X, th_f, base_ref, free, eff_f, active) if len(active) else None
    split_note = (
        f"not run: {len(dfit)} training poses fitted, it needs 40 (20 a half)"
        if len(active) and split is None
        else None
    )

    # ---- 6. show: held-out before/after, per step (linearised prefix models)
    pred_dh_te = padded_call(dh.predict, dte.q)
    pred_te = model.predict_parametric(dte.q, **aux(dte))
    before = error_stats(pred_dh_te, dte.p_tracker, interval=True)
    after = error_stats(pred_te, dte.p_tracker, interval=True)
    X_te = fs.features(theta, dte.q, **aux(dte))
    Jt_te, Je_te = jac_aug(theta, eff0, base_ref, dte.q, X_te)
    p0_te = p_aug(theta, eff0, base_ref, dte.q, X_te)

    def lin_pred_te(sel: list[Candidate]) -> np.ndarray:
        ii = [i for c in sel for i in c.idx]
        g, b = lin.coef(ii)
        return p0_te + Jt_te[:, :, free] @ g + (Je_te[:, :, ii] @ b if ii else 0.0)

    e_all_te = np.linalg.norm(lin_pred_te(M) - dte.p_tracker, axis=1)
    per_step = []
    for k in range(len(M)):
        st = error_stats(lin_pred_te(M[: k + 1]), dte.p_tracker, interval=True)
        per_step.append(
            {
                "after": M[k].key,
                "heldout_rms_m": st["rms_m"],
                "heldout_max_m": st["max_m"],
                "heldout_rms_ci95_m": st["rms_ci95_m"],
            }
        )

    # explained fractions (CV, training) and per-effect held-out change when left out
    cv_geo = lin.cv_errors([])
    floor = noise_floor_m(dh, dtr, dte, sig[train], sig[test])
    # the tracker's part alone: what `workcell fit` calls its tracker-accuracy floor (the same
    # per-pose sigma on the same held-out poses), without the geometric fit's uncertainty
    tracker_floor = float(np.sqrt(np.mean(3.0 * sig[test] ** 2)))
    effects_out = []
    step_of = {s.cand.key: s for s in steps if s.action == "add"}
    for k, c in enumerate(M):
        # share of the geometry-only CV error power removed when this effect joined the model
        # (in acceptance order: the shares add up to the total explained)
        prev = [i for d in M[:k] for i in d.idx]
        upto = prev + list(c.idx)
        frac = float(
            (lin.cv_errors(prev).mean() - lin.cv_errors(upto).mean()) / max(cv_geo.mean(), 1e-300)
        )
        p_wo = lin_pred_te([d for d in M if d is not c])
        wo = error_stats(p_wo, dte.p_tracker, interval=True)
        # paired over the held-out poses, both linearised: the final model with / without c
        e_wo = np.linalg.norm(p_wo - dte.p_tracker, axis=1)
        gain = float(np.sqrt(np.mean(e_wo**2)) - np.sqrt(np.mean(e_all_te**2)))
        gain_ci = list(rms_gain_interval(e_wo, e_all_te))
        # confirmed: the paired 95 % interval of the held-out gain lies above zero (a point gain
        # whose interval reaches zero is within chance and does not confirm it)
        confirms = bool(gain_ci[0] > 0.0) if np.all(np.isfinite(gain_ci)) else bool(gain > 0.0)
        s = step_of.get(c.key)
        effects_out.append(
            {
                "kind": c.kind,
                "joint": c.joint,
                "order": c.order,
                "key": c.key,
                "description": c.describe(),
                "parameters": model.effect_parameters(c),
                "explained_fraction": max(frac, 0.0),
                "evidence": {
                    "f_statistic": s.f if s else None,
                    "p_value": s.p if s else None,
                    "test_level": s.alpha_used if s else None,
                    "cv_mse_ratio": s.cv_ratio if s else None,
                    "cv_p_value": s.cv_p if s else None,
                    "bic_change": s.bic_change if s else None,
                    "identifiability_rho": s.rho if s else None,
                    "heldout_rms_without_m": wo["rms_m"],
                    "heldout_rms_without_ci95_m": wo["rms_ci95_m"],
                    "heldout_rms_with_m": after["rms_m"],
                    "heldout_confirms": confirms,
                    "heldout_gain_m": gain,
                    "heldout_gain_ci95_m": gain_ci,
                    # after the joint refit with the other terms (the selection checked its own)
                    "physical_sign_ok": physical_sign_ok(c, model.eff[list(c.idx)]),
                    # the effect's largest |z| between two halves of the training poses
                    "split_half_z": (
                        float(max(abs(split["z"][i]) for i in c.idx)) if split else None
                    ),
                },
            }
        )
        if c.kind == "transmission_error":
            qj = dfit.q[:, c.joint - 1]
            others = [
                k
                for k in cfg.orders
                if k != c.order
                and not any(d.kind == c.kind and d.joint == c.joint and d.order == k for d in M)
            ]
            effects_out[-1]["evidence"].update(
                {
                    "joint_range_rad": [float(qj.min()), float(qj.max())],
                    "harmonic_overlap": {str(k): harmonic_overlap(qj, c.order, k) for k in others},
                }
            )

    not_identifiable = [
        {"candidate": k, "rho": v["rho"], "absorbed_by": v.get("absorbed_by", [])}
        for k, v in screen.items()
        if v["rho"] < cfg.rho_min
    ]

    # ---- 7. unexplained structure
    res_tr = dfit.p_tracker - model.predict_parametric(dfit.q, **aux(dfit))
    res_te = dte.p_tracker - pred_te
    excess = unexplained_error(after["rms_m"], after["rms_ci95_m"], floor)
    unexplained = {
        "heldout_rms_m": after["rms_m"],  # the excess over the floor is below (as `fit`'s rms_m)
        "excess_over_floor_m": excess["rms_m"] if excess else float("nan"),
        "excess_over_floor_upper_m": excess["upper_m"] if excess else None,
        "excess_basis": excess["basis"] if excess else None,
        "structured": False,
        "where": [],
    }
    # the model file carries its held-out figures, for `export` to state beside its 1-sigma
    model.info.update(
        heldout_rms_m=after["rms_m"], heldout_rms_ci95_m=after["rms_ci95_m"], unexplained=excess
    )
    # effects the model holds that the held-out poses do not confirm (kept: the selection
    # accepts on the training poses), so the file says which of its terms are not established
    if not_confirmed := [e["key"] for e in effects_out if not e["evidence"]["heldout_confirms"]]:
        model.info["effects_not_confirmed_on_heldout"] = {
            "effects": not_confirmed,
            "basis": HELDOUT_CONFIRMS_BASIS,
        }
    note_joint_range(model, dfit.q)
    unexplained["serial_correlation"] = _serial_correlation(res_tr, dfit.elapsed_s)
    model_np = None
    if cfg.nonparametric:
        unexplained_np, model_np = _nonparametric(
            model, dfit, res_tr, dte, res_te, after, cfg, log,
            serial=unexplained["serial_correlation"]["significant"], floor=floor,
        )  # fmt: skip
        unexplained.update(unexplained_np)
        if model_np is not None:
            note_joint_range(model_np, dfit.q)

    from workcell.estimation.identifiability import weak_directions

    # the final model's geometry (refit jointly with the accepted effects: the values and stds
    # `parameter_std_basis` describes), and the groups its poses barely tell apart
    geometry = _geometry_items(model)
    weak = weak_directions(model.theta_cov(), PARAM_NAMES)
    report = {
        **ds.provenance(),
        **({"chain": ds.chain_line} if ds.chain_line else {}),
        "robot": ds.robot.model,
        "poses": int(len(ds)),
        "train_poses": int(len(train)),
        "heldout_poses": int(len(test)),
        "outliers_rejected": n_out,
        "rms_before_m": before["rms_m"],
        "rms_before_ci95_m": before["rms_ci95_m"],
        "max_before_m": before["max_m"],
        "rms_after_m": after["rms_m"],
        "rms_after_ci95_m": after["rms_ci95_m"],
        # the final model's own 1-sigma at the held-out poses, checked against their errors
        "heldout_model_std": heldout_std_check(model, dte, cfg.tracker_mpe, pred=pred_te),
        # does the final model's held-out RMS reach the noise floor within its 95 % interval?
        "floor_reached": _floor_reached(after["rms_ci95_m"], floor),
        "max_after_m": after["max_m"],
        "rms_interval_basis": RMS_INTERVAL_BASIS,
        "parameter_std_basis": PARAMETER_STD_BASIS,
        "variance_factor": s0_2,  # s0^2 of the joint refit, its degrees of freedom below
        "variance_factor_dof": int(s0_dof),
        "parameter_frames": PARAMETER_FRAMES,
        "noise_floor_m": floor,
        "noise_floor_basis": (
            f"per-pose sigma = max(recorded, tracker MPE ({cfg.tracker_mpe[0] * 1e6:.0f} um + "
            f"{cfg.tracker_mpe[1] * 1e6:.0f} um/m) / 4), plus the geometric fit's uncertainty"
        ),
        # the tracker's part alone, on the held-out poses: `workcell fit`'s tracker floor
        "tracker_noise_floor_m": tracker_floor,
        "effects": effects_out,
        "explained_fraction_basis": EXPLAINED_FRACTION_BASIS,
        "heldout_confirms_basis": HELDOUT_CONFIRMS_BASIS,
        "steps": per_step,
        "steps_basis": STEPS_BASIS,
        "selection": [
            {
                "action": s.action,
                "candidate": s.cand.key,
                "f_statistic": s.f,
                "p_value": s.p,
                "test_level": s.alpha_used,
                "cv_mse_ratio": s.cv_ratio,
                "cv_p_value": s.cv_p,
                **(
                    {"value": s.value, "unit": EFF_UNITS[s.cand.idx[0]]}
                    if s.value is not None
                    else {}
                ),
            }
            for s in steps
        ],
        "method": {
            "selection": "greedy forward selection (BIC-ranked) with backward pruning",
            "acceptance": f"F (likelihood-ratio) test at {cfg.alpha} / m candidates (Bonferroni) "
            f"AND {cfg.cv_folds}-fold CV improvement, one-sided paired t-test at {cfg.cv_alpha}",
            "identifiability": f"rho >= {cfg.rho_min} (unabsorbed share of the signature)",
            "estimation": "every candidate estimated jointly with all free geometric parameters",
        },
        "not_identifiable": not_identifiable,
        "locate": loc,
        "geometry": geometry,
        "split_half": (
            {k: split[k] for k in ("z_rms", "n_parameters", "basis")} if split else None
        ),
        "split_half_note": split_note,
        "geometry_basis": (
            "the final model's geometric parameters, estimated jointly with the accepted "
            "effects (deviations from the session's nominal chain)"
        ),
        "weakly_identified": weak,
        "unexplained": unexplained,
        "thermal_source": src,
        "joints_tied_to_time": _joints_tied_to_time(dfit),
        "repeats": repeat_drift(ds),
        "seconds": time.perf_counter() - t0,
    }
    report["summary"] = summary_text(report)
    plots = {
        "p_te": dte.p_tracker,
        "res_before": dte.p_tracker - pred_dh_te,
        "res_after": res_te,
        "q_te": dte.q,
    }
    if model_np is not None and unexplained.get("np_model"):
        plots["res_np"] = dte.p_tracker - model_np.predict(dte.q, **aux(dte))
    log(f"diagnosis done in {report['seconds']:.1f} s")
    return Diagnosis(report=report, dh_model=dh, model=model, model_np=model_np, plots=plots)


def _floor_reached(ci, floor: float) -> bool | None:
    """False when the whole 95 % interval of the held-out RMS lies above the noise floor (None
    without an interval)."""
    if ci is None or not np.all(np.isfinite(ci)):
        return None
    return bool(ci[0] <= floor)


def _serial_correlation(res: np.ndarray, t: np.ndarray) -> dict:
    """Lag-1 autocorrelation of the residual in recording order (mean over axes): a slow drift
    or a change of set-up shows as correlation between consecutive poses."""
    n = len(res)
    order = np.argsort(np.nan_to_num(t, nan=0.0), kind="stable")
    r = res[order] - res.mean(0)
    den = float(np.sum(r * r))
    rho = float(np.sum(r[1:] * r[:-1]) / den) if den > 0 and n > 3 else 0.0
    return {"lag1": rho, "significant": bool(abs(rho) > 3.0 / np.sqrt(max(n, 1)))}


def _lengthscale_text(ls: float, std, j: int) -> str:
    """'0.45 +- 0.06 rad' (the residual GP's Laplace 1-sigma), or why there is none."""
    sd = None if std is None else float(std[j - 1])
    if sd is None or not np.isfinite(sd):
        return f"{ls:.2f} rad, no 1-sigma: at a search bound, or no proper likelihood maximum"
    return f"{ls:.2f} +- {sd:.2f} rad"


def _nonparametric(
    model, dfit, res_tr, dte, res_te, after, cfg, log, *, serial: bool = False, floor: float
):
    """Fit a residual GP; judge it on the held-out poses. `serial`: the residual is correlated
    in recording order (`_serial_correlation`), which calls for the drift check too. `floor`:
    the noise floor, for what the GP-corrected model leaves unexplained."""
    from workcell.estimation.discovery_np import fit_residual_gp, relevant_joints

    out: dict = {}
    try:
        gp = fit_residual_gp(dfit.q, res_tr, seed=cfg.seed)
    except Exception as e:  # noqa: BLE001 - the optional part must not sink the diagnosis
        log(f"non-parametric residual model failed: {e}")
        return {"np_error": str(e)}, None
    corr = gp.predict(dte.q)
    e0 = np.sum(res_te**2, axis=1)
    e1 = np.sum((res_te - corr) ** 2, axis=1)
    rms1 = float(np.sqrt(e1.mean()))
    gain = 1.0 - rms1 / max(after["rms_m"], 1e-300)
    p = float(stats.ttest_1samp(e0 - e1, 0.0, alternative="greater").pvalue) if len(e0) > 2 else 1.0
    structured = bool(p < cfg.np_alpha and gain >= cfg.np_min_gain)
    q_range = np.ptp(dfit.q, axis=0)
    joints = relevant_joints(gp, q_range)
    where = []
    if structured:
        if joints:
            where.append(
                "depends on joint(s) "
                + ", ".join(
                    f"{j} (length scale {_lengthscale_text(ls, gp.lengthscale_std, j)})"
                    for j, ls in joints[:3]
                )
            )
        en = np.linalg.norm(res_tr, axis=1)
        for j, _ in joints[:2]:
            order = np.argsort(dfit.q[:, j - 1])
            thirds = np.array_split(order, 3)
            rms3 = [float(np.sqrt(np.mean(en[i] ** 2))) for i in thirds]
            k = int(np.argmax(rms3))
            lo, hi = dfit.q[thirds[k], j - 1].min(), dfit.q[thirds[k], j - 1].max()
            where.append(
                f"largest for joint {j} in [{lo:+.2f}, {hi:+.2f}] rad "
                f"(RMS {rms3[k] * 1e6:.1f} um vs {min(rms3) * 1e6:.1f} um elsewhere)"
            )
    if structured or serial:
        # joint-space structure, or residuals correlated in recording order: drift or joints?
        drift = _drift(dfit, res_tr, dte, res_te, cfg, gp)
        if drift is not None:
            out["drift_check"] = drift
            if structured:
                where.append(drift["text"])
    out.update(
        {
            "structured": structured,
            "where": where,
            "np_test": {
                "method": "gp (discovery_np: ARD-RBF GP over joint angles)",
                "heldout_rms_with_m": rms1,
                "heldout_rms_without_m": after["rms_m"],
                "gain": gain,
                "p_value": p,
                "level": cfg.np_alpha,
                "lengthscales_rad": gp.lengthscales.tolist(),
                # Laplace 1-sigma from the marginal likelihood's curvature (null: at a bound
                # of the search range, or no proper maximum)
                "lengthscales_std_rad": None
                if gp.lengthscale_std is None
                else [None if not np.isfinite(v) else float(v) for v in gp.lengthscale_std],
            },
        }
    )
    model_np = None
    if structured:
        # the GP-corrected model's own held-out figures (it carried the parametric model's):
        # on the same poses that accepted it, which the file says
        ci1 = rms_interval(np.sqrt(e1))
        info = dict(model.info)
        info.update(
            heldout_rms_m=rms1,
            heldout_rms_ci95_m=ci1,
            unexplained=unexplained_error(rms1, ci1, floor),
            heldout_selection=GP_HELDOUT_CAVEAT,
        )
        if "drift_check" in out:  # for `export` to say when the GP may be carrying a drift
            info["residual_drift_check"] = {
                k: out["drift_check"][k]
                for k in ("verdict", "time_adds", "heldout_rms_joints_m", "heldout_rms_time_m")
            }
        model_np = replace(model, residual=gp.to_dict(), info=info)
        out["np_model"] = {
            "method": "augmented + gp residual",
            "heldout_rms_m": rms1,
            "heldout_rms_ci95_m": ci1,
            "heldout_max_m": float(np.sqrt(e1.max())),
            "heldout_selection": GP_HELDOUT_CAVEAT,
        }
    log(
        f"non-parametric check: held-out RMS {after['rms_m'] * 1e6:.1f} -> {rms1 * 1e6:.1f} um "
        f"(p={p:.1e}) -> {'structured residual remains' if structured else 'no structure left'}"
    )
    return out, model_np


TIED_TO_TIME = 0.9  # |rank correlation| of a joint's angle with the recording time


def _joints_tied_to_time(ds: Dataset) -> dict[str, float]:
    """{joint (1-based, str): rank correlation} of the joints whose angle rises or falls with
    the recording time (|Spearman| >= `TIED_TO_TIME`): an angle-periodic term of such a joint
    and a drift during the recording are confounded."""
    t = ds.elapsed_s
    if t is None or not np.all(np.isfinite(t)) or np.ptp(t) <= 0 or len(t) < 10:
        return {}
    out = {}
    for j in range(ds.q.shape[1]):
        if np.ptp(ds.q[:, j]) <= 0:
            continue
        rho = float(stats.spearmanr(ds.q[:, j], t).statistic)
        if np.isfinite(rho) and abs(rho) >= TIED_TO_TIME:
            out[str(j + 1)] = rho
    return out


def _drift(dfit: Dataset, res_tr, dte: Dataset, res_te, cfg: DiagnoseConfig, gp) -> dict | None:
    """`discovery_np.drift_check` on the structure the joints GP found, with its sentence."""
    from workcell.estimation.discovery_np import drift_check

    if dfit.elapsed_s is None or dte.elapsed_s is None:
        return None
    d = drift_check(
        dfit.q, dfit.elapsed_s, res_tr, dte.q, dte.elapsed_s, res_te, alpha=cfg.np_alpha,
        seed=cfg.seed, gp_joints=gp,
    )  # fmt: skip
    if d is None:
        return None
    j, t, b = (
        f"{d[k] * 1e6:.1f} um"
        for k in ("heldout_rms_joints_m", "heldout_rms_time_m", "heldout_rms_both_m")
    )
    if d["verdict"] == "joints":
        text = (
            f"it follows the joints, not the recording order (held out, a GP over the joints "
            f"{j}, over the recording time alone {t}"
            + (
                f"; the time adds a drift on top: {b} with both)"
                if d["time_adds"]
                else "; given the joints the time adds nothing)"
            )
        )
    elif d["verdict"] == "time":
        text = (
            f"it follows the recording order more than the joints (held out, a GP over the "
            f"recording time {t}, over the joints {j}): a drift during the recording (temperature, "
            "the tracker or its set-up moving); a correction over the joints would not carry "
            "to another day"
        )
    else:
        text = (
            f"the joints and the recording order cannot be told apart on these poses (held out, "
            f"a GP over the joints {j}, over the recording time {t}): the arm's path ties them "
            "together, so a drift is not ruled out"
        )
    return {**d, "text": text}


def noise_floor_m(
    dh: DHModel, dtr: Dataset, dte: Dataset, sig_tr: np.ndarray, sig_te: np.ndarray
) -> float:
    """Expected held-out RMS from noise alone: sqrt(mean(3 sigma^2 + tr(J Cov J^T)))."""
    from workcell.kinematics.chain import jac_params

    free = dh.free
    Jt = padded_call(lambda qq: jac_params(dh.theta, dh.base_ref, qq), dtr.q)[:, :, free]
    Jh = padded_call(lambda qq: jac_params(dh.theta, dh.base_ref, qq), dte.q)[:, :, free]
    A = np.einsum("nkp,n,nkq->pq", Jt, 1.0 / sig_tr**2, Jt)
    cov = np.linalg.pinv(A)
    par = np.einsum("nkp,pq,nkq->n", Jh, cov, Jh)
    return float(np.sqrt(np.mean(3 * sig_te**2 + par)))


def _deviation(v: dict) -> dict:
    """A fitted geometric parameter as `fit` reports it (value absolute, as `fit --json` has it)
    with its deviation from nominal beside it."""
    return {
        "value": v["value"],
        "nominal": v["nominal"],
        "deviation": v["value"] - v["nominal"],
        "std": v["std"],
        "unit": v["unit"],
    }


def _geometry_items(model) -> list[dict]:
    """Geometric kinds of a DH or augmented model: the estimated deviations from nominal,
    grouped."""
    params = model.parameters()
    items = []
    for j in range(1, 7):
        n = f"theta{j}_offset"
        v = params[n]
        if v["estimated"]:
            items.append(
                {
                    "kind": "joint_offset",
                    "joint": j,
                    "parameters": {n: _deviation(v)},
                }
            )
    for j in range(1, 7):
        ps = {}
        for base in ("a", "d", "alpha", "beta"):
            n = f"{base}{j}"
            v = params[n]
            if v["estimated"]:
                ps[n] = _deviation(v)
        if ps:
            items.append({"kind": "link_geometry", "joint": j, "parameters": ps})
    items.append(
        {
            "kind": "base_frame",
            "joint": None,
            "parameters": {
                n: {"value": params[n]["value"], "std": params[n]["std"], "unit": params[n]["unit"]}
                for n in ("base_tx", "base_ty", "base_tz", "base_rx", "base_ry", "base_rz")
                if params[n]["estimated"]
            },
        }
    )
    items.append(
        {
            "kind": "tool_offset",
            "joint": None,
            "parameters": {
                n: {"value": params[n]["value"], "std": params[n]["std"], "unit": "m"}
                for n in ("tool_x", "tool_y", "tool_z")
                if params[n]["estimated"]
            },
        }
    )
    return items


# ----------------------------------------------------------------------------- plain language
_DISPLAY_UNITS = {  # SI unit -> (factor, unit shown)
    "rad/(N m)": (1e6, "urad/(N m)"),
    "rad": (1e6, "urad"),
    "m/N": (1e6, "um/N"),
    "1/K": (1e6, "ppm/K"),
    "1/h": (1e6, "ppm/h"),
    "1": (1e6, "ppm"),
    "m": (1e6, "um"),
}


def _fmt_value(v: float, sd: float, unit: str) -> str:
    k, u = _DISPLAY_UNITS.get(unit, (1.0, unit))
    return f"{v * k:.3g} +- {sd * k:.2g} {u}"


def _fmt_plain(v: float, unit: str) -> str:
    k, u = _DISPLAY_UNITS.get(unit, (1.0, unit))
    return f"{v * k:.3g} {u}"


def effect_sentence(e: dict) -> str:
    p = e["parameters"]
    if e["kind"] == "transmission_error":
        a = p["amplitude"]
        ph = p["phase"]
        ph_sd = ph.get("std")
        size = (
            f"amplitude {_fmt_value(a['value'], a['std'], 'rad')}, phase {ph['value']:+.2f}"
            + (f" +- {ph_sd:.2g}" if ph_sd is not None and np.isfinite(ph_sd) else "")
            + " rad"
        )
    else:
        ((name, v),) = [(k, x) for k, x in p.items()]
        size = f"{name.replace('_', ' ')} {_fmt_value(v['value'], v['std'], v['unit'])}"
    ev = e["evidence"]
    conf = "" if ev.get("heldout_confirms", True) else " - NOT confirmed on the held-out poses"
    gain = ""
    ci = ev.get("heldout_gain_ci95_m")
    if ci is not None and ev.get("heldout_gain_m") is not None and all(np.isfinite(ci)):
        gain = (
            f", a gain of {ev['heldout_gain_m'] * 1e6:.1f} um (95 % CI "
            f"{ci[0] * 1e6:.1f} to {ci[1] * 1e6:.1f} um"
            + ("; within chance)" if ci[0] <= 0.0 else ")")
        )
    if ev.get("physical_sign_ok") is False:
        conf += (
            f" - its sign is not physical ({SIGN_FIXED_KINDS[e['kind']]}) after the joint refit: "
            "the term stands in for a cause outside the library"
        )
    return (
        f"{e['description']}: {size}; training poses: takes out "
        f"{100 * e['explained_fraction']:.0f} % of the geometry-only residual power in "
        f"cross-validation, added in acceptance order (F test p = {ev['p_value']:.1g}, CV p = "
        f"{ev['cv_p_value']:.1g}); held-out poses: RMS without it "
        f"{ev['heldout_rms_without_m'] * 1e6:.1f} um"
        + (f" ({ci_wo})" if (ci_wo := interval_um(ev.get("heldout_rms_without_ci95_m"))) else "")
        + f"{gain}{conf}{_range_note(e)}"
    )


PARAMETER_STD_BASIS = (
    "+- is one standard deviation from the joint refit of geometry and the accepted effects, "
    "s0^2 (J^T W J)^-1 with s0^2 the weighted residual variance; it holds for the selected model: "
    "an effect left out that the accepted ones can reproduce biases them beyond it"
)


def harmonic_overlap(q: np.ndarray, order: int, other: int) -> float:
    """How much of a harmonic of order `other` in the joint angle (the worst phase) a harmonic of
    `order` plus a constant (the joint offset) reproduces over the angles `q` (R^2, 0..1). Over a
    full turn, evenly covered, 0; over part of a turn the orders are not separable, and an
    amplitude fitted for `order` takes up the `other` one's share."""
    q = np.asarray(q, float)
    X = np.c_[np.ones_like(q), np.sin(order * q), np.cos(order * q)]
    Y = np.c_[np.sin(other * q), np.cos(other * q)]
    Y = Y - Y.mean(axis=0)
    PY = X @ np.linalg.lstsq(X, Y, rcond=None)[0]
    # the worst phase: max over v of |P Y v|^2 / |Y v|^2, a generalised eigenvalue
    try:
        lam = scipy.linalg.eigh(Y.T @ PY, Y.T @ Y, eigvals_only=True)
    except np.linalg.LinAlgError:  # too few distinct angles to tell the orders apart at all
        return 1.0
    return float(np.clip(lam.max(), 0.0, 1.0))


def _range_note(e: dict) -> str:
    """For a transmission error fitted over part of a turn: which other order it can stand in for."""
    ev = e.get("evidence", {})
    ov = {int(k): v for k, v in (ev.get("harmonic_overlap") or {}).items() if v >= 0.5}
    lo_hi = ev.get("joint_range_rad")
    if not ov or lo_hi is None:
        return ""
    k, v = max(ov.items(), key=lambda kv: kv[1])
    lo, hi = np.degrees(lo_hi)
    return (
        f" [joint {e['joint']} covered {lo:.0f}..{hi:.0f} deg: over it this term and the offset "
        f"reproduce {100 * v:.0f} % of an order-{k} harmonic, so the amplitude is order "
        f"{e.get('order')}'s share of the joint's periodic error there, not a separable gear "
        "harmonic]"
    )


def _ci(r: dict, key: str) -> str:
    s = interval_um(r.get(key))
    return s + ", " if s else ""


def summary_text(r: dict) -> str:
    um = lambda x: f"{x * 1e6:.1f} um"  # noqa: E731
    tracker = r.get("tracker_noise_floor_m")
    floor_what = (
        f"expected from the tracker ({um(tracker)}, the tracker floor `workcell fit` states) and "
        "the geometric fit's own uncertainty is"
        if tracker is not None
        else "expected from the tracker and the geometric fit's own uncertainty is"
    )
    lines = [
        f"Geometric calibration alone (DH, joint offsets, base, SMR; estimated jointly) leaves a "
        f"held-out RMS of {um(r['rms_before_m'])} ({_ci(r, 'rms_before_ci95_m')}max "
        f"{um(r['max_before_m'])}); the noise floor {floor_what} {um(r['noise_floor_m'])} "
        f"({r['rms_before_m'] / r['noise_floor_m']:.1f}x).",
    ]
    if r["locate"]["statements"]:
        lines.append(
            "Where the residual concentrates: " + "; ".join(r["locate"]["statements"][:3]) + "."
        )
    aside_sign = [st for st in r.get("selection", []) if st["action"] == "set aside (sign)"]
    if r["effects"]:
        confirmed = [e for e in r["effects"] if e["evidence"].get("heldout_confirms", True)]
        unconfirmed = [e for e in r["effects"] if e not in confirmed]
        if confirmed:
            lines.append(
                "Physics left out of the nominal model, confirmed on the held-out poses (each "
                "accepted on the training poses by an F test, by cross-validation and, for a "
                "compliance or a flexibility, by its physical sign; leaving it out of the final "
                "model raises the held-out RMS by more than chance, 95 % interval above zero):"
            )
            for e in confirmed:
                lines.append("  - " + effect_sentence(e))
        else:
            lines.append(
                "Physics left out of the nominal model, confirmed on the held-out poses: none of "
                "the accepted effects."
            )
        if unconfirmed:
            lines.append(
                "Accepted on the training poses (F test, cross-validation and, for a "
                "compliance or a flexibility, the physical sign) but NOT confirmed on the "
                "held-out poses (the 95 % interval of the held-out gain reaches zero): "
                + ("this effect is" if len(unconfirmed) == 1 else "these effects are")
                + " kept in the augmented model and in what is exported from it, because the "
                "selection accepts on the training poses and the held-out poses only judge; "
                "treat " + ("it" if len(unconfirmed) == 1 else "them") + " as not established:"
            )
            for e in unconfirmed:
                lines.append("  - " + effect_sentence(e))
        s02 = r.get("variance_factor")
        lines.append(
            f"  ({r.get('parameter_std_basis', PARAMETER_STD_BASIS)}"
            + (
                f"; here s0^2 = {s02:.3g} over {r['variance_factor_dof']} degrees of freedom"
                if isinstance(s02, (int, float)) and r.get("variance_factor_dof")
                else ""
            )
            + ".)"
        )
        sh = r.get("split_half")
        if sh is None and r.get("split_half_note"):
            lines.append(f"  Split-half check of the +-: {r['split_half_note']}.")
        if sh:
            moved = [
                f"{e['description']} (|z| {e['evidence']['split_half_z']:.1f})"
                for e in r["effects"]
                if (e["evidence"].get("split_half_z") or 0.0) > SPLIT_HALF_Z
            ]
            line = (
                "  Split-half check (the model refitted on two halves of the training poses): "
                f"the effect values differ by z_rms = {sh['z_rms']:.1f} standard deviations of "
                f"the difference over {sh['n_parameters']} parameters (about 1 if the +- were "
                "the whole spread"
            )
            if moved:
                line += (
                    f"; beyond {SPLIT_HALF_Z:g}: {', '.join(moved)}): read the +- as a lower "
                    "bound on how much the values move with the data."
                )
            elif sh["z_rms"] > 1.5:
                line += "); above 1.5 the +- understates how much the values move with the data."
            else:
                line += ")."
            lines.append(line)
        tied = r.get("joints_tied_to_time") or {}
        for j, rho in tied.items():
            terms = [
                e
                for e in r["effects"]
                if e["kind"] == "transmission_error" and e["joint"] == int(j)
            ]
            if terms:
                lines.append(
                    f"  Joint {j} moved with the recording time (rank correlation {rho:+.2f}, as a "
                    "grid plan's joint 1 does): its transmission-error term(s) may carry a drift "
                    "during the recording rather than the gear; a random plan separates the two."
                )
        lines.append(
            (
                "With all the accepted effects (the not-confirmed ones included) "
                if unconfirmed
                else "With these effects "
            )
            + f"the held-out RMS is {um(r['rms_after_m'])} "
            f"({_ci(r, 'rms_after_ci95_m')}max "
            f"{um(r['max_after_m'])}), {r['rms_after_m'] / r['noise_floor_m']:.2f}x the noise floor."
        )
        if r.get("floor_reached") is False:
            lo = r["rms_after_ci95_m"][0]
            lines.append(
                f"  The named effects do not bring the held-out error down to the noise floor (the "
                f"95 % interval starts at {um(lo)}, above the floor's {um(r['noise_floor_m'])}): "
                "something the library does not hold remains, and the terms named above may "
                "partly stand in for it. Read their sizes as the library's best description of "
                "this recording, not as measurements of those mechanisms."
            )
    elif aside_sign:
        lines.append(
            "No physical effect of the library is accepted: the only ones that improve the fit "
            "have a sign their physics excludes."
        )
    else:
        lines.append(
            "No physical effect of the library improves the fit by more than chance: the geometric "
            "model explains the recording "
            + (
                "down to the noise floor."
                if r["rms_before_m"] < 1.3 * r["noise_floor_m"]
                else "as well as any candidate does."
            )
        )
    for st in aside_sign:
        c = next(c for c in library() if c.key == st["candidate"])
        lines.append(
            f"  Set aside: {c.describe()}, fitted at {_fmt_plain(st['value'], st['unit'])} "
            f"(F test p = {st['p_value']:.1g}): {SIGN_FIXED_KINDS[c.kind]}, so the pattern it "
            "fitted belongs to a cause outside the library."
        )
    for g in r.get("weakly_identified") or []:
        lines.append(
            "Weakly identified geometry: the poses barely tell {"
            + ", ".join(g["parameters"])
            + f"}} apart (std {g['std_inflation']:.0f}x what it would be with the others known); "
            "only their combination is meaningful."
        )
    ni = [x["candidate"] for x in r["not_identifiable"]]
    if ni:
        short = ", ".join(ni[:6]) + (" ..." if len(ni) > 6 else "")
        lines.append(
            f"Not identifiable from this recording (absorbed by the geometry or not excited): {short}."
        )
        if "tracker_scale" in ni:
            lines.append(
                "A uniform tracker scale error is absorbed by the link lengths and base position "
                "(a point-only tracker without a length reference cannot see it); check the "
                "tracker's scale with a calibrated scale bar."
            )
    u = r["unexplained"]
    if u.get("structured"):
        lines.append(
            "What is not explained: a structured residual of "
            + unexplained_text(
                {"rms_m": u["excess_over_floor_m"], "upper_m": u.get("excess_over_floor_upper_m")}
            )
            + " remains that no candidate explains; it "
            + "; ".join(u["where"])
            + f". A non-parametric correction (GP over joint space) lowers the held-out RMS from "
            f"{um(u['np_test']['heldout_rms_without_m'])} to {um(u['np_test']['heldout_rms_with_m'])}"
            + (
                f" ({ci_np})"
                if (ci_np := interval_um((u.get("np_model") or {}).get("heldout_rms_ci95_m")))
                else ""
            )
            + f"; {GP_HELDOUT_CAVEAT} (`workcell validate`)."
        )
    elif "np_test" in u:
        sc = u.get("serial_correlation", {})
        big = r["rms_after_m"] > 1.5 * r["noise_floor_m"]
        txt = (
            "What is not explained: "
            + unexplained_text(
                {"rms_m": u["excess_over_floor_m"], "upper_m": u.get("excess_over_floor_upper_m")}
            )
            + "; a non-parametric model over the joint angles finds no further structure on the "
            "held-out poses"
        )
        if sc.get("significant"):
            txt += (
                f"; the residual is correlated between consecutive poses (lag-1 "
                f"{sc['lag1']:+.2f}): look for a drift or a change of set-up during the recording"
            )
            dc = u.get("drift_check")
            if dc:
                helps = dc["p_time_helps"] < dc["alpha"]
                txt += (
                    f" (a GP over the recording time {'lowers' if helps else 'does not lower'} "
                    f"the held-out RMS: {um(dc['heldout_rms_m'])} -> {um(dc['heldout_rms_time_m'])}"
                    f", p = {dc['p_time_helps']:.1g})"
                )
        elif big:
            txt += (
                " and it is not correlated in time: it behaves like pose-to-pose scatter "
                "(repeatability of the arm or of the measurement) larger than the stated noise"
            )
        lines.append(txt + ".")
    for rp in (r.get("repeats") or [])[:3]:
        verdict = (
            "more than the tracker alone explains: the arm's repeatability, or a drift during "
            "the recording (arm, tracker or set-up)"
            if repeat_beyond_noise(rp)
            else "within what the tracker alone explains: no sign of a drift"
        )
        lines.append(f"Measured again (no model involved): {repeat_line(rp)}; {verdict}.")
    return "\n".join(lines)


__all__ = [
    "DiagnoseConfig",
    "Diagnosis",
    "diagnose",
    "locate",
    "select_effects",
    "summary_text",
    "EFF_NAMES",
]
