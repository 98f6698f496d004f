"""What a planned set of poses can identify, said before anything moves (the dry run of the
command line and of the TUI's Plan screen): Theorem 1's rank of the identification Jacobian at
the nominal chain against a rich random pose set, condition and O1, and warnings for parameters
the poses leave dependent or barely separate, and for too few poses to fit."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from workcell.campaign.envelope import Envelope
from workcell.kinematics.robots import RobotSpec
from workcell.recording.tracker_spec import TRACKER_MPE_M, tracker_spec_sigma

REFERENCE_POSES = 60  # random poses inside the envelope: what well-spread poses identify
HOLDOUT = 0.25  # the fits' default held-out share


def reference_poses(spec: RobotSpec, env: Envelope, tool_m: np.ndarray) -> np.ndarray:
    """`REFERENCE_POSES` random poses inside the envelope (seeded): what well-spread poses
    identify, and where the expected figures are taken. A dry run draws them once and passes
    them to `identification_lines` and `plan_pose_count_line`."""
    from workcell.campaign.plans import random_configurations

    return random_configurations(spec, env, REFERENCE_POSES, np.random.default_rng(0), tool_m)


def nominal_smr_in_tracker(
    spec: RobotSpec, q: np.ndarray, tool_m: np.ndarray, base_in_tracker: dict | None
) -> np.ndarray:
    """The nominal chain's SMR positions (N, 3) in the tracker frame at joints q (N, n), with
    the base at the declared `base_in_tracker` (identity when not declared)."""
    from workcell.kinematics.chain import p_tracker, pack
    from workcell.kinematics.frames import matrix_from_quat_wxyz, transform_from

    T = np.eye(4)
    if isinstance(base_in_tracker, dict):
        T = transform_from(
            matrix_from_quat_wxyz(np.asarray(base_in_tracker["quaternion_wxyz"], float)),
            np.asarray(base_in_tracker["translation_m"], float),
        )
    theta = pack(spec.dh, tool=np.asarray(tool_m, float))
    return np.asarray(p_tracker(theta, T, np.atleast_2d(np.asarray(q, float))))


def tracker_sigma_m(
    spec: RobotSpec,
    q: np.ndarray,
    tool_m: np.ndarray,
    base_in_tracker: dict | None,
    mpe: tuple[float, float] = TRACKER_MPE_M,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis 1-sigma (N,) a tracker meeting its MPE (A + B x range) measures the SMR with at
    joints q (N, n), the floor the fits weight by (MPE / 4), and the ranges (N,) in metres from
    the tracker at the declared `base_in_tracker` (identity when not declared)."""
    p = nominal_smr_in_tracker(spec, q, tool_m, base_in_tracker)
    return tracker_spec_sigma(p, mpe), np.linalg.norm(p, axis=1)


def expected_after_fit(
    spec: RobotSpec,
    env: Envelope,
    q: np.ndarray,
    tool_m: np.ndarray,
    base_in_tracker: dict | None = None,
    reference_q: np.ndarray | None = None,
) -> dict | None:
    """What a DH fit of the poses q (N, n) should reach if the geometry is the whole error and
    the tracker meets its MPE: `expected_prediction_sigma` over `reference_q` (default:
    `REFERENCE_POSES` random poses inside the envelope) of the fit's training poses (the fits'
    deterministic split), plus `train_poses`, `pose_sigma_m` and `range_m` of the planned poses.
    None with too few training poses, or when they leave a parameter dependent."""
    from workcell.estimation.fitting import MIN_TRAIN_POSES
    from workcell.estimation.identifiability import pose_set_report
    from workcell.recording.dataset import holdout_indices

    q = np.atleast_2d(np.asarray(q, float))
    if reference_q is None:
        reference_q = reference_poses(spec, env, tool_m)
    train, _ = holdout_indices(len(q), HOLDOUT)
    if len(train) < MIN_TRAIN_POSES:
        return None
    sig, rng = tracker_sigma_m(spec, q, tool_m, base_in_tracker)
    sig_ref, _ = tracker_sigma_m(spec, reference_q, tool_m, base_in_tracker)
    e = pose_set_report(
        spec.dh,
        q[train],
        tool_m,
        reference_q=reference_q,
        sigma_m=sig[train],
        reference_sigma_m=sig_ref,
    )["expected_prediction"]
    if e is None:
        return None
    m = len(q) - len(train)
    out = {**e, "train_poses": int(len(train)), "pose_sigma_m": sig, "range_m": rng}
    out["heldout_poses"] = int(m)
    if m > 0:
        # the spread of a held-out RMS over m poses from sampling alone: 3 m squared errors of
        # the expected size, a scaled chi-square with 3 m degrees of freedom
        from scipy.stats import chi2

        lo, hi = chi2.ppf([0.025, 0.975], 3 * m) / (3 * m)
        out["heldout_rms_range95_m"] = [
            float(e["heldout_rms_m"] * np.sqrt(lo)),
            float(e["heldout_rms_m"] * np.sqrt(hi)),
        ]
    return out


def identification_lines(
    spec: RobotSpec,
    env: Envelope,
    q: np.ndarray,
    tool_m: np.ndarray,
    base_in_tracker: dict | None = None,
    reference_q: np.ndarray | None = None,
) -> list[str]:
    """The dry run's identification summary: one line, then what a DH fit of these poses
    should reach if the geometric model holds, then a line per warning (each starts with
    'warning:'). `reference_q`: `reference_poses`, drawn here if not given."""
    from workcell.estimation.identifiability import pose_set_report

    q = np.atleast_2d(np.asarray(q, float))
    ref = reference_poses(spec, env, tool_m) if reference_q is None else reference_q
    r = pose_set_report(spec.dh, q, tool_m, reference_q=ref)
    lines = [
        f"identification (nominal chain, a point measured: 3 equations a pose): rank "
        f"{r['rank']} of the {r['rank_reference']} that well-spread poses give; condition "
        f"{r['condition']:.3g}, O1 {r['o1']:.3g}"
    ]
    e = expected_after_fit(spec, env, q, tool_m, base_in_tracker, reference_q=ref)
    if e is not None:
        sig, rng, um = e["pose_sigma_m"], e["range_m"], 1e6
        t = (base_in_tracker or {}).get("translation_m")
        where = "" if t is not None and np.any(np.asarray(t, float)) else ", from the robot base"
        lines.append(
            f"expected after a DH fit of the {e['train_poses']} training poses, if the geometry "
            f"is the whole error and the tracker meets its MPE (1-sigma {sig.min() * um:.1f}-"
            f"{sig.max() * um:.1f} um an axis at {rng.min():.2f}-{rng.max():.2f} m{where}): the "
            f"model's 1-sigma over the envelope {e['rms_m'] * um:.1f} um RMS (max "
            f"{e['max_m'] * um:.1f} um); held-out RMS about {e['heldout_rms_m'] * um:.1f} um"
            + (
                f" (95 % range {rr[0] * um:.1f}-{rr[1] * um:.1f} um on {e['heldout_poses']} "
                "held-out poses, from their sampling alone)"
                if (rr := e.get("heldout_rms_range95_m"))
                else ""
            )
            + ", "
            f"{e['heldout_rms_m'] / e['floor_m']:.2f}x the noise floor of "
            f"{e['floor_m'] * um:.1f} um"
        )
    if r["missing"]:
        need = -(-r["rank_reference"] // 3)
        why = (
            f"a point tracker needs at least {need} poses"
            if 3 * r["poses"] < r["rank_reference"]
            else "the poses are too alike: spread them over the joints"
        )
        lines.append(
            f"warning: these poses leave {len(r['missing'])} parameter(s) dependent, fixed at "
            f"nominal by the fit: {', '.join(r['missing'])} ({why})"
        )
    lines += too_few_to_fit(r["poses"])
    weak = r["weakly_identified"]
    for g in weak[:3]:
        lines.append(
            "warning: weakly identified on these poses: {" + ", ".join(g["parameters"]) + "}, "
            f"std {g['std_inflation']:.0f}x what it would be with the others known"
        )
    if len(weak) > 3:
        lines.append(f"warning: ... and {len(weak) - 3} more weakly identified groups")
    return lines


POSE_COUNTS = (16, 20, 25, 30, 40, 50, 60, 80, 100, 125, 150, 200, 250, 300)
STOP_RATIO = 1.1  # the pose-count curve stops once the held-out RMS is this close to the floor


def pose_count_curve(
    spec: RobotSpec,
    env: Envelope,
    q_for: Callable[[int], np.ndarray | None],
    tool_m: np.ndarray,
    base_in_tracker: dict | None = None,
    *,
    counts: Sequence[int] = POSE_COUNTS,
    stop_ratio: float = STOP_RATIO,
    reference_q: np.ndarray | None = None,
) -> dict[int, float]:
    """{n: expected held-out RMS / noise floor} of a DH fit of the plan's first n poses
    `q_for(n)` (None: the plan has no n poses), by `expected_after_fit`, for the `counts` a fit
    accepts, in order, until the ratio is within `stop_ratio`."""
    from workcell.estimation.fitting import min_poses_for_fit

    ref = reference_poses(spec, env, tool_m) if reference_q is None else reference_q
    curve: dict[int, float] = {}
    for n in sorted(c for c in counts if c >= min_poses_for_fit(HOLDOUT)):
        q = q_for(n)
        if q is None:
            break
        e = expected_after_fit(spec, env, q, tool_m, base_in_tracker, reference_q=ref)
        if e is None:
            continue
        curve[n] = float(e["heldout_rms_m"] / e["floor_m"])
        if curve[n] <= stop_ratio:
            break
    return curve


def pose_count_line(curve: dict[int, float], plan: str) -> str | None:
    """The dry run's line from `pose_count_curve`; None when no count could be assessed."""
    if not curve:
        return None
    pts = [f"{r:.2f}x at {n}" for n, r in curve.items()]
    return (
        f"expected held-out RMS / noise floor of a DH fit of n poses planned the same way "
        f"({plan}; the geometry the whole error, the tracker at its MPE): " + ", ".join(pts)
    )


def plan_pose_count_line(
    kind: str,
    spec: RobotSpec,
    env: Envelope,
    *,
    seed: int,
    tool_m: np.ndarray,
    base_in_tracker: dict | None = None,
    approach_rad: float = 0.02,
    previewed_q: np.ndarray | None = None,
    reference_q: np.ndarray | None = None,
) -> str | None:
    """The dry run's pose-count line for a plan: a grid or random plan re-planned (same seed)
    with each count; an adaptive plan's preview `previewed_q` (its choice at the nominal
    chain, greedy, so its first n poses are the n-pose plan's) cut at each count up to its
    length. None for an adaptive plan without a preview."""
    from workcell.campaign.plans import STATIC_KINDS, make_plan

    if kind in STATIC_KINDS:

        def q_for(n: int) -> np.ndarray | None:
            try:
                return make_plan(
                    kind, spec, env, n, seed=seed, tool_m=tool_m, approach_rad=approach_rad
                )[1]
            except ValueError:  # the envelope does not hold n such poses
                return None

    elif previewed_q is not None:
        qp = np.atleast_2d(np.asarray(previewed_q, float))

        def q_for(n: int) -> np.ndarray | None:
            return qp[:n] if n <= len(qp) else None

    else:
        return None
    curve = pose_count_curve(spec, env, q_for, tool_m, base_in_tracker, reference_q=reference_q)
    return pose_count_line(curve, kind)


def too_few_to_fit(poses: int) -> list[str]:
    """The warning for a pose count too small to fit (empty when it is enough)."""
    from workcell.estimation.fitting import MIN_TRAIN_POSES, min_poses_for_fit

    n_fit = min_poses_for_fit()
    if poses >= n_fit:
        return []
    return [
        f"warning: too few poses to fit ({poses}): a fit needs at least {MIN_TRAIN_POSES} "
        f"training poses, {n_fit} poses with the default 25 % held out"
    ]


def too_few_to_fit_notes(poses: int) -> list[dict]:
    """`too_few_to_fit` as campaign events ({level, kind, message}) a campaign records and says
    once its devices answer, before the first motion (`run_campaign(notes=...)`)."""
    return [
        {
            "level": "warning",
            "kind": "too_few_to_fit",
            "message": line.removeprefix("warning: ")
            + "; ask for more poses to fit this recording alone",
        }
        for line in too_few_to_fit(poses)
    ]


def pose_count_warnings(
    spec: RobotSpec, env: Envelope, tool_m: np.ndarray, poses: int
) -> list[str]:
    """The dry run's warnings that need only the number of poses (a plan whose poses cannot be
    listed before the campaign, bo): too few for a point tracker to identify what well-spread
    poses do (3 equations a pose), and too few to fit (`too_few_to_fit`)."""
    from workcell.estimation.identifiability import pose_set_report
    from workcell.kinematics.chain import param_names

    lines = []
    if 3 * poses < len(param_names(len(spec.dh.a))):
        ref = reference_poses(spec, env, tool_m)
        full = pose_set_report(spec.dh, ref, tool_m)["rank"]
        if 3 * poses < full:
            lines.append(
                f"warning: {poses} poses leave at least {full - 3 * poses} of the {full} "
                "parameters that well-spread poses give dependent, fixed at nominal by the fit "
                f"(a point tracker needs at least {-(-full // 3)} poses)"
            )
    return lines + too_few_to_fit(poses)
