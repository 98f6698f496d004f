"""Adaptive campaign plans: each next pose is chosen from the measurements so far (seed 002).

Both plans choose from a finite candidate set drawn once per campaign: joint configurations
sampled uniformly inside the envelope (`plans.random_configurations`), so every candidate is
reachable and *is* its own IK solution; approach signs are chosen so the approach pre-pose stays
inside the envelope too (`plans.approach_signs`). A candidate's pose on S3 x R3 is the nominal
flange quaternion (wxyz, base frame) and the nominal SMR position (base frame). Each step takes
the best-scored candidate the arm may move to from where it is, the way the executor moves
(approach path inside the envelope; direct joint path to the pre-pose, else via the upright
posture: `Reach`), all candidates tried in score order. Where the arm is: what the executor read
before asking (`arm`, a `plans.ArmPosture`: the start posture, a pose skipped after the arm went
there, a jog), else the last measured pose. So an adaptive campaign is not left with refused
poses; when no candidate is reachable from where the arm is, the plan raises `plans.PlanStuck`
(the campaign stops and says which limit the paths cross) instead of proposing poses the
executor refuses one after another.

``bo`` (Das, Touma & Burdick, Algorithm 1): GP-UCB over the candidates with the S3 x R3 product
kernel (heat kernel on S3 times SE on R3, `workcell.estimation.design`). The objective is the
paper's eq. (6)-(7) restricted to position (the tracker measures position only):
``f = -||p_measured - p_model|| / max``, where ``p_model`` is the *current calibrated model*:
after every pose the geometry is refitted on all poses so far (iterated bounded QP,
`workcell.estimation.bounded`, warm-started from the previous fit); before enough poses for an
identifiable fit exist, the nominal chain with the base registered by Kabsch is used (as the
paper's Algorithm 1 does with nominal DH). The first ``n_seed`` poses are space-filling
(greedy max-min distance on S3 x R3). Beta: the Srinivas et al. finite-domain schedule.

``dopt``: greedy maximisation of the D-optimality / O1 observability index. With the
identification Jacobian Js restricted to the identifiable parameters (Theorem 1 analysis on the
candidates) and column-scaled once, O1 = det(Js^T Js)^(1/2L) / sqrt(N); for a fixed N the
candidate that maximises O1 of the augmented set maximises
``log det(I_3 + J_c (A + eps I)^-1 J_c^T)`` (matrix determinant lemma, A = information so
far; eps regularises the first, rank-deficient steps). The column scale here is dopt's own (the
columns' RMS over the candidates), not the fixed SI units of the printed O1
(`identifiability.parameter_units`): a fixed diagonal scale adds a constant to log det, so once
the poses identify every parameter the choice is the one with the highest printed O1 (tested);
the ridge eps of the first steps depends on the scale. ``index="min_sv"`` (an API option, not a
plan) maximises, once A has full rank, the minimum singular value in the printed indices' fixed
units: the printed O3 (tested). The Jacobian is re-linearised at the current
calibrated model every ``relinearise_every`` poses once a fit is possible, and skipped poses
(sample None) add no information.

``vopt``: greedy V-optimal (I-optimal) design, with dopt's information matrix A (identifiable
parameters, column-scaled, relinearised the same way): the next pose is the one that most
reduces the mean prediction variance of the SMR position over the candidate poses,
``tr(W A^-1)`` with ``W = mean_c J_c^T J_c`` (Woodbury update with the candidate's 3x3 block);
until A has full rank the D-optimal rule chooses. Its aim is what a calibration is judged on,
the position error over the workspace, rather than the joint confidence volume of the
parameters (D-optimality), which rewards extreme postures.

`skip_ids`: pose ids that are not yielded; the plan then chooses the remaining
``n - |skip_ids & range(n)|`` poses without knowing those measurements.
`history` (resume): the samples of a recording being resumed, by pose id. The plan is re-created
with the same seed and the recorded samples are fed back in the order they were taken (a pose id
below the last recorded one without a sample was skipped by the old run: None is fed back, as
the executor did), so the plan's state is what it was when the old process died. Each recorded
commanded pose must be one of the re-created plan's candidates (else the recording comes from
another envelope, seed or version: ValueError, before anything moves); at each recorded step the
plan takes that candidate (the old run chose it from where its arm was, which the replay cannot
know), and at a skipped one its best-scored candidate other than the recorded ones. The replay
runs when the continuation is first asked for its next pose (so the arm's posture then is
known). `replace_skipped` (what a resume does): the continuation goes on past pose id n - 1 with
new pose ids n, n+1, ... until it has offered n - (poses recorded) poses, so each pose skipped
before is replaced by a new choice, as a static plan's resume measures its skipped poses again.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from workcell.campaign.envelope import Envelope
from workcell.campaign.plans import (
    ADAPTIVE_KINDS,
    ArmPosture,
    Plan,
    PlanStuck,
    PoseTarget,
    Reach,
    approach_signs,
    random_configurations,
)
from workcell.estimation.identifiability import analyse, candidates_for, parameter_units
from workcell.kinematics.chain import (
    base_T_flange,
    pack,
    param_names,
)
from workcell.kinematics.robots import RobotSpec
from workcell.recording.dataset import Dataset

if TYPE_CHECKING:
    from workcell.estimation.design.gp import BetaSchedule

# ---------------------------------------------------------------------------- candidates


def candidate_poses(spec: RobotSpec, q: np.ndarray, tool_m: np.ndarray) -> np.ndarray:
    """(M, 7) = [qw qx qy qz px py pz]: nominal flange orientation and SMR position in base."""
    q = np.atleast_2d(np.asarray(q, float))
    T = np.asarray(base_T_flange(pack(spec.dh), q))
    xyzw = Rotation.from_matrix(T[:, :3, :3]).as_quat()
    wxyz = np.column_stack([xyzw[:, 3], xyzw[:, :3]])
    p = np.einsum("nab,b->na", T[:, :3, :3], np.asarray(tool_m, float)) + T[:, :3, 3]
    return np.hstack([wxyz, p])


def pose_distance2(
    a: np.ndarray, b: np.ndarray, length_m: float = 0.3, angle_rad: float = 1.0
) -> np.ndarray:
    """Squared distance on S3 x R3 between pose sets (N, 7), (M, 7) -> (N, M): position over
    `length_m` plus rotation angle (q ~ -q) over `angle_rad`."""
    dp = np.sum((a[:, None, 4:] - b[None, :, 4:]) ** 2, axis=-1) / length_m**2
    c = np.clip(np.abs(a[:, :4] @ b[:, :4].T), 0.0, 1.0)
    ang = 2.0 * np.arccos(c)
    return dp + (ang / angle_rad) ** 2


def maximin_indices(poses: np.ndarray, k: int, first: int = 0) -> list[int]:
    """Greedy farthest-point (max-min distance) selection of k rows of `poses`."""
    k = min(k, len(poses))
    chosen = [first]
    d = pose_distance2(poses, poses[[first]])[:, 0]
    while len(chosen) < k:
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, pose_distance2(poses, poses[[i]])[:, 0])
    return chosen


def _candidates(spec, env, n_candidates, seed, tool_m, approach_rad):
    rng = np.random.default_rng(seed)
    q = random_configurations(spec, env, int(n_candidates * 1.1) + 2, rng, tool_m)
    q, s = approach_signs(spec, env, q, tool_m, approach_rad, seed)
    return q[:n_candidates], s[:n_candidates]


def identifiable_mask(spec: RobotSpec, J: np.ndarray) -> np.ndarray:
    """Bool (P,): identifiable parameters for the Jacobian J (N, 3, P), P = 5 n + 9 (Theorem 1
    analysis)."""
    names = param_names(spec.n_joints)
    ident = analyse(J.reshape(-1, len(names)), candidates=candidates_for(spec.dh))
    free = np.zeros(len(names), bool)
    free[[names.index(n) for n in ident.identifiable]] = True
    return free


_NOT_REPLAYED = -1


def _pick(reach: Reach | None, order, info: dict, replayed: int | None = _NOT_REPLAYED,
          kind: str = "adaptive") -> int:  # fmt: skip
    """The best candidate of `order` the arm may reach (the first when reach is None), every
    candidate tried in turn; none: `PlanStuck`. `replayed` (a resume's replay): the candidate
    the old run recorded for this step, taken as it is; None for a step the old run skipped:
    the first of `order` (which the replay leaves out of the recorded candidates), unchecked."""
    order = np.asarray(order, int)
    if replayed is None or replayed != _NOT_REPLAYED:
        info["replayed"] = True
        return int(order[0]) if replayed is None else int(replayed)
    if reach is None:
        return int(order[0])
    i, passed = reach.first(order)
    if passed:
        info["passed_over_unreachable"] = passed
    if i is None:
        raise reach.stuck(order, kind)
    return i


# ------------------------------------------------------------------------- measurements


class _Measurements:
    """What the plan has learnt: measured configurations, SMR positions, and the current fit."""

    def __init__(
        self, spec: RobotSpec, tool_m: np.ndarray, free: np.ndarray, bounds: str | None = "default"
    ) -> None:
        self.spec, self.tool_m, self.free = spec, np.asarray(tool_m, float), free
        self.bounds = bounds  # the refit's parameter bounds (`fit_dh_bounded`'s)
        self.q: list[np.ndarray] = []
        self.p: list[np.ndarray] = []
        self.sigma: list[np.ndarray] = []
        self.theta = pack(spec.dh, tool=self.tool_m)
        self.base_ref: np.ndarray | None = None
        self.calibrated = False
        # the first pose count that can identify the L parameters (Theorem 1: 3 n >= L); the
        # paper refits at every iteration. Until 2026-11-28 it was that + 3, so on the UR5e bo
        # chased the nominal chain's errors up to 11 poses, where the design bench ends
        self.n_fit = int(math.ceil(free.sum() / 3.0))

    def add(self, sample: dict) -> None:
        self.q.append(np.asarray(sample["q_measured_rad"], float))
        self.p.append(np.asarray(sample["tracker_position_m"], float))
        sig = np.asarray(sample.get("tracker_sigma_m") or [1e-5] * 3, float)
        self.sigma.append(np.where(np.isfinite(sig) & (sig > 0), sig, 1e-5))

    def __len__(self) -> int:
        return len(self.q)

    def dataset(self) -> Dataset:
        return Dataset(
            robot=self.spec,
            tool_offset_m=self.tool_m,
            tracker_T_base_nominal=np.eye(4),
            q=np.array(self.q),
            p_tracker=np.array(self.p),
            sigma_m=np.array(self.sigma),
        )

    def refit(self) -> None:
        """Current model: bounded QP fit once identifiable, else nominal + Kabsch registration."""
        from workcell.estimation.bounded import fit_dh_bounded
        from workcell.estimation.dh import register_base

        if len(self) < 3:
            return
        ds = self.dataset()
        if len(self) < self.n_fit:
            self.theta = pack(self.spec.dh, tool=self.tool_m)
            self.base_ref = register_base(ds, self.theta)
            return
        try:
            m = fit_dh_bounded(
                ds,
                bounds=self.bounds,
                theta0=self.theta if self.calibrated else None,
                base_ref=self.base_ref if self.calibrated else None,
                free=self.free,
                robust=False,
                max_iter=15,
                xtol=1e-9,
                min_poses=self.n_fit,
            )
        except (ValueError, np.linalg.LinAlgError):
            return
        self.theta, self.base_ref, self.calibrated = m.theta, m.base_ref, True

    def errors_m(self) -> np.ndarray:
        from workcell.estimation.bounded import predict_padded

        if self.base_ref is None:
            return np.zeros(len(self))
        pred = predict_padded(self.theta, self.base_ref, np.array(self.q))
        return np.linalg.norm(np.array(self.p) - pred, axis=1)


# ---------------------------------------------------------------------------------- plans


def make_adaptive_plan(
    kind: str,
    spec: RobotSpec,
    env: Envelope,
    n: int,
    *,
    seed: int,
    tool_m: np.ndarray,
    skip_ids: set[int] | None = None,
    history: dict[int, dict] | None = None,
    approach_rad: float = 0.02,
    n_candidates: int = 1000,
    n_seed: int | None = None,
    index: str = "o1",
    beta_schedule: BetaSchedule = "srinivas",
    negate_objective: bool = True,
    relinearise_every: int = 5,
    refit_bounds: str | None = "default",
    on_choice: Callable[[dict], None] | None = None,
    arm: ArmPosture | None = None,
    replace_skipped: bool = False,
) -> Plan:
    """A generator of `PoseTarget`s that receives each recorded sample (or None) via `.send()`.

    kind "bo", "dopt" or "vopt" (see the module docstring). `n_candidates` reachable
    configurations are drawn once (seeded); `n_seed` space-filling poses start the campaign
    (default 5 for bo, 1 for dopt and vopt); `index` is dopt's criterion ("o1" or "min_sv").
    `refit_bounds`: the bounds of the plans' own refits (`fit_dh_bounded`; None: unbounded, for
    errors beyond a manufacturing tolerance, as the paper's WAM setting has).
    `on_choice` is called with a small dict per chosen pose (for logs and tests). `arm`: where
    the arm is (the executor keeps it up to date); `replace_skipped`: with `history`, new poses
    in place of the ones the old run skipped (module docstring).
    """
    _check_kind(kind)
    if n <= 0:
        raise ValueError(f"number of poses must be positive, got {n}")
    if index not in ("o1", "min_sv"):
        raise ValueError(f"index must be 'o1' or 'min_sv', got {index!r}")
    if n_candidates < n:
        raise ValueError(
            f"an adaptive plan chooses each pose from {n_candidates} candidate configurations; "
            f"ask for at most {n_candidates} poses (got {n}), or use --plan random or grid"
        )
    tool_m = np.asarray(tool_m, float)
    q_c, s_c = _candidates(spec, env, n_candidates, seed, tool_m, approach_rad)
    if len(q_c) < n:
        raise ValueError(f"only {len(q_c)} candidate poses fit the envelope; need {n}")
    if history and skip_ids:
        raise ValueError("give either history (resume) or skip_ids, not both")
    ids = [i for i in range(n) if not (skip_ids and i in skip_ids)]
    replay: dict[int, int | None] = {}
    if history:
        replay = _recorded_candidates(history, q_c)
        last = max(history)
        if replace_skipped:  # one more pose id for each one skipped up to the last recorded
            ids = list(range(min(max(n, last + 1 + max(0, n - len(history))), len(q_c))))
    plan = plan_over_candidates(
        kind, spec, q_c, s_c, tool_m, ids, seed=seed, n_seed=n_seed, index=index,
        beta_schedule=beta_schedule, negate_objective=negate_objective,
        relinearise_every=relinearise_every, refit_bounds=refit_bounds, on_choice=on_choice,
        reach=Reach(spec, env, tool_m, q_c, s_c, approach_rad, arm=arm), replay=replay,
    )  # fmt: skip
    return _replayed(plan, history, max(history)) if history else plan


def _recorded_candidates(history: dict[int, dict], q_c: np.ndarray) -> dict[int, int | None]:
    """For the replay of a resumed campaign: every pose id up to the last recorded one -> the
    candidate its recorded commanded configuration is (None: skipped by the old run). A recorded
    pose that is no candidate of the re-created plan, or one candidate recorded twice, means
    another envelope, seed or version: ValueError."""
    out: dict[int, int | None] = dict.fromkeys(range(max(history) + 1))
    used: dict[int, int] = {}
    for pid, rec in sorted(history.items()):
        q_rec = np.asarray(rec.get("q_commanded_rad", []), float)
        i = None
        if pid >= 0 and q_rec.shape == q_c.shape[1:] and np.all(np.isfinite(q_rec)):
            d = np.max(np.abs(q_c - q_rec), axis=1)
            k = int(np.argmin(d))
            i = k if d[k] <= 1e-9 and k not in used else None
        if i is None:
            raise ValueError(
                f"recorded pose {pid} is not one the re-created plan can choose (different "
                "envelope, seed or version); cannot resume this adaptive campaign"
            )
        used[i] = pid
        out[pid] = i
    return out


def plan_over_candidates(
    kind: str,
    spec: RobotSpec,
    q_c: np.ndarray,
    s_c: np.ndarray,
    tool_m: np.ndarray,
    ids: list[int],
    *,
    seed: int,
    n_seed: int | None = None,
    index: str = "o1",
    beta_schedule: BetaSchedule = "srinivas",
    negate_objective: bool = True,
    relinearise_every: int = 5,
    refit_bounds: str | None = "default",
    on_choice: Callable[[dict], None] | None = None,
    reach: Reach | None = None,
    replay: dict[int, int | None] | None = None,
) -> Plan:
    """The adaptive plan `kind` choosing, for each pose id in `ids`, one of the given candidate
    configurations q_c (M, n) with approach signs s_c (M, n) (each at most once). Used by
    `make_adaptive_plan` (candidates drawn in the envelope) and to replay a design over the
    poses of an existing recording (`workcell bench design-real`). With `reach` (a live
    campaign), each step takes the best-scored candidate the arm may move to from where it is
    (see `Reach`; `PlanStuck` when none); without, the best-scored one. `replay` (a resume):
    pose id -> the candidate the old run recorded there (None: skipped), taken as recorded."""
    from workcell.estimation.bounded import jacobian_padded

    _check_kind(kind)
    q_c, s_c = np.asarray(q_c, float), np.asarray(s_c, float)
    if len(q_c) < len(ids):
        raise ValueError(f"only {len(q_c)} candidates for {len(ids)} poses")
    poses = candidate_poses(spec, q_c, tool_m)
    th_nom = pack(spec.dh, tool=tool_m)
    J_c = jacobian_padded(th_nom, np.eye(4), q_c)  # (M, 3, 5 n + 9)
    free = identifiable_mask(spec, J_c)
    n_seed = (5 if kind == "bo" else 1) if n_seed is None else int(n_seed)
    replay = replay or {}
    if kind == "bo":
        return _bo_plan(
            spec, q_c, s_c, poses, free, tool_m, ids, n_seed, seed, beta_schedule,
            negate_objective, on_choice, reach, replay, refit_bounds,
        )  # fmt: skip
    return _dopt_plan(
        spec, q_c, s_c, poses, J_c, free, tool_m, ids, n_seed, seed,
        "v" if kind == "vopt" else index, relinearise_every, on_choice, reach, kind, replay,
        refit_bounds,
    )  # fmt: skip


def _check_kind(kind: str) -> None:
    if kind not in ADAPTIVE_KINDS:
        raise ValueError(f"unknown adaptive plan {kind!r}; choose {', '.join(ADAPTIVE_KINDS)}")


def _replayed(plan: Plan, history: dict[int, dict], last: int) -> Plan:
    """The plan's continuation after pose id `last`: when first asked, it feeds the recorded
    samples (None for a pose id without one) back into the re-created plan, which takes the
    recorded candidates (`replay`), then goes on choosing from where the arm is then. (A
    foreign history was refused by `_recorded_candidates` before anything was opened.)"""
    try:
        target = next(plan)
        while target.pose_id <= last:
            target = plan.send(history.get(target.pose_id))
        while True:
            sample = yield target
            target = plan.send(sample)
    except StopIteration:  # every pose was already measured, or the plan's end
        return


def _seed_order(poses: np.ndarray, n_seed: int, seed: int) -> list[int]:
    first = int(np.random.default_rng(seed + 2).integers(len(poses)))
    return maximin_indices(poses, max(n_seed, 1), first=first)[:n_seed] if n_seed > 0 else []


def _visit(i, pid, info, q_c, s_c, available, meas, measured_idx, on_choice, reach) -> Plan:
    """Move to candidate `i` as pose `pid`: mark it taken, report the choice, and add what was
    measured there (None: the pose was skipped) to the plan's measurements."""
    available[i] = False
    info["candidate"] = i
    if on_choice:
        on_choice(info)
    sample = yield PoseTarget(pose_id=pid, q_rad=q_c[i].copy(), approach_sign=s_c[i].copy())
    if sample is not None:
        meas.add(sample)
        measured_idx.append(i)
        if reach is not None:
            reach.last = q_c[i]


def _bo_plan(
    spec, q_c, s_c, poses, free, tool_m, ids, n_seed, seed, beta_schedule, negate, on_choice,
    reach, replay, refit_bounds="default",
) -> Plan:  # fmt: skip
    from workcell.estimation.design.gp import pose_error_objective, ucb_scores

    meas = _Measurements(spec, tool_m, free, refit_bounds)
    available = np.ones(len(q_c), bool)
    measured_idx: list[int] = []
    seeds = _seed_order(poses, n_seed, seed)
    free_now = _replay_mask(available, replay)
    for k, pid in enumerate(ids):
        info: dict = {"plan": "bo", "pose_id": pid, "k": k}
        rec = replay.get(pid, _NOT_REPLAYED)
        avail = free_now(pid)
        if k < len(seeds) or len(measured_idx) < 3:
            pending = [i for i in seeds if avail[i]]
            order = pending + [i for i in _farthest_order(poses, measured_idx, avail)
                               if i not in pending]  # fmt: skip
            i = _pick(reach, order, info, rec, "bo")
            info["rule"] = "space-filling seed"
        else:
            meas.refit()
            err = meas.errors_m()
            y = pose_error_objective(err, negate=negate)
            cand = np.where(avail)[0]
            score = ucb_scores(
                poses[cand], poses[measured_idx], y, beta_schedule=beta_schedule,
                iteration=len(measured_idx) + 1,
            )  # fmt: skip
            i = _pick(reach, _ucb_order(score, cand, poses, measured_idx), info, rec, "bo")
            info.update(
                rule="GP-UCB",
                calibrated=meas.calibrated,
                rms_error_m=float(np.sqrt(np.mean(err**2))),
            )
        yield from _visit(i, pid, info, q_c, s_c, available, meas, measured_idx, on_choice, reach)


def _replay_mask(available: np.ndarray, replay: dict[int, int | None]):
    """available(pid): the candidates a step may take. At a step the old run skipped (replayed
    as None), the candidates recorded at other steps are left out, so the replay takes them
    where they were recorded."""
    recorded = np.zeros(len(available), bool)
    recorded[[i for i in replay.values() if i is not None]] = True

    def free_now(pid: int) -> np.ndarray:
        if pid in replay and replay[pid] is None:
            return available & ~recorded
        return available

    return free_now


def _ucb_order(score, cand, poses, measured_idx) -> np.ndarray:
    """Candidates by UCB score, ties (within 1e-9 of the score range) farthest from the measured
    poses first, where the exploration term points: a GP that predicts its prior everywhere
    scores every candidate alike, and the tie went to the lowest candidate index, a random pick
    (a safeguard: in the design bench no pick changed). A non-finite score goes last."""
    score = np.where(np.isfinite(score), score, -np.inf)  # a non-finite score last
    fin = score[np.isfinite(score)]
    span = float(np.ptp(fin)) if len(fin) else 0.0
    key = (
        np.round(score / (span * 1e-9), 0) if span > 0 else np.where(np.isfinite(score), 0.0, -1.0)
    )
    d = pose_distance2(poses[cand], poses[measured_idx]).min(axis=1)
    return cand[np.lexsort((-d, -key))]


def _farthest_order(poses, measured_idx, available) -> np.ndarray:
    """Available candidates, farthest from the measured poses first (S3 x R3 distance)."""
    cand = np.where(available)[0]
    if not measured_idx:
        return cand
    d = pose_distance2(poses[cand], poses[measured_idx]).min(axis=1)
    return cand[np.argsort(-d, kind="stable")]


def _dopt_plan(
    spec, q_c, s_c, poses, J_c, free, tool_m, ids, n_seed, seed, index, relin_every, on_choice,
    reach, kind="dopt", replay=None, refit_bounds="default",
) -> Plan:  # fmt: skip
    from workcell.estimation.bounded import jacobian_padded

    L = int(free.sum())
    scale = np.linalg.norm(J_c[:, :, free].reshape(-1, L), axis=0) / math.sqrt(len(J_c))
    scale = np.where(scale > 0, scale, 1.0)

    def scaled(J):
        return J[:, :, free] / scale  # (M, 3, L)

    # the printed indices' fixed units (metres; angles as the arc at 1 m): J_SI = Js * si
    si = scale * parameter_units(np.array(param_names(spec.n_joints))[free])

    def mean_information(Js):  # W: the mean prediction-variance weight over the candidates
        return np.einsum("mkl,mkp->lp", Js, Js) / len(Js) if index == "v" else None

    Js = scaled(J_c)
    W = mean_information(Js)
    eps = 1e-6 * float(np.mean(np.einsum("mkl,mkl->l", Js, Js))) / len(Js)
    meas = _Measurements(spec, tool_m, free, refit_bounds)
    available = np.ones(len(q_c), bool)
    measured_idx: list[int] = []
    seeds = _seed_order(poses, n_seed, seed)
    last_relin = 0
    replay = replay or {}
    free_now = _replay_mask(available, replay)
    for k, pid in enumerate(ids):
        info: dict = {"plan": kind, "pose_id": pid, "k": k}
        rec = replay.get(pid, _NOT_REPLAYED)
        avail = free_now(pid)
        if relin_every > 0 and len(meas) >= meas.n_fit and len(meas) - last_relin >= relin_every:
            meas.refit()
            if meas.calibrated:
                Js = scaled(jacobian_padded(meas.theta, np.eye(4), q_c))
                W = mean_information(Js)
                last_relin = len(meas)
                info["relinearised"] = True
        A = np.einsum("mkl,mkp->lp", Js[measured_idx], Js[measured_idx]) if measured_idx else None
        if A is None:
            A = np.zeros((L, L))
        pending = [i for i in seeds if avail[i]] if k < len(seeds) else []
        i = None
        if pending:
            if rec != _NOT_REPLAYED:
                i = (
                    _pick(reach, pending, info, rec, kind)
                    if rec is None or rec in pending
                    else None
                )
            else:
                i = pending[0] if reach is None else reach.first(pending)[0]
        if i is not None:
            info["rule"] = "space-filling seed"
        else:
            cand = np.where(avail)[0]
            full_rank = len(measured_idx) * 3 >= L and np.linalg.matrix_rank(A) == L
            if index == "min_sv" and full_rank:
                M = A[None] + np.einsum("mkl,mkp->mlp", Js[cand], Js[cand])
                score = np.linalg.eigvalsh(M * np.outer(si, si))[:, 0]  # O3^2 as printed
                info["rule"] = "max min singular value"
            elif index == "v" and full_rank:
                # decrease of the mean prediction variance over the candidates, tr(W A^-1),
                # by adding c (Woodbury with the 3x3 block of c)
                Ainv = np.linalg.inv(A)
                B = np.einsum("lp,mkp->mlk", Ainv, Js[cand])  # (M, L, 3)
                S = np.eye(3)[None] + np.einsum("mkl,mlj->mkj", Js[cand], B)
                BWB = np.einsum("mlk,lp,mpj->mkj", B, W, B)
                score = np.trace(np.linalg.solve(S, BWB), axis1=1, axis2=2)
                info["rule"] = "min mean prediction variance (V-optimal)"
            else:
                Ainv = np.linalg.inv(A + eps * np.eye(L))
                S = np.eye(3)[None] + np.einsum("mkl,lp,mjp->mkj", Js[cand], Ainv, Js[cand])
                score = np.linalg.slogdet(S)[1]
                info["rule"] = "max O1 (D-optimal)"
            order = np.argsort(-score, kind="stable")
            i = _pick(reach, cand[order], info, rec, kind)
            info["score"] = float(score[cand == i][0])
        yield from _visit(i, pid, info, q_c, s_c, available, meas, measured_idx, on_choice, reach)


__all__ = [
    "ADAPTIVE_KINDS",
    "PlanStuck",
    "Reach",
    "candidate_poses",
    "identifiable_mask",
    "make_adaptive_plan",
    "maximin_indices",
    "plan_over_candidates",
    "pose_distance2",
]
