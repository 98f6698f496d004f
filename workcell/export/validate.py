"""Closed-loop validation of an exported correction table.

N random targets (SMR positions in base, one of the table's tool orientations) inside the volume
are each visited twice: uncorrected (the controller is asked for the target itself) and corrected
through the table (the same trilinear interpolation the URScript does). "The controller" is
emulated: the commanded pose goes through the nominal IK (branch of the seed), the joints are
approached from the table's declared approach direction (pre-pose q - sign * approach_rad) and the
SMR is measured. Errors are distances to the target mapped to the tracker with the model's
registered base. Reported per ISO 9283 style (one cycle per target): mean, RMS, max of the
position error, plus the mean error vector (the accuracy bias, in base_ref axes).

In simulation the measurement is the simulated truth (noise-free SMR position of the true robot);
on a real cell it is the tracker (mean of several readings).

Closure: at the end the first target is visited again (corrected, from the same approach) and
measured: how far it moved is what the cell itself moved during the validation (tracker stand,
base, temperature), plus the arm's repeatability and the tracker's noise. Beyond the tracker's
noise (chi-square, 99 %, as `diagnose` judges a reference pose) and larger than the corrected RMS,
the after figure carries that drift, and a warning says so.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from workcell.campaign.envelope import AT_SENT_TOL_RAD, Guard
from workcell.errors import UserError
from workcell.estimation.models import (
    interval_um,
    model_fingerprint,
    rms_interval,
    rms_ratio_interval,
)
from workcell.export.correction import Q_REF, Nominal, rotvec_to_matrix
from workcell.export.table import CorrectionTable

if TYPE_CHECKING:
    from workcell.campaign.envelope import Envelope
    from workcell.drivers.protocols import Robot, Tracker
    from workcell.estimation.models import FittedModel
    from workcell.kinematics.robots import RobotSpec


def random_targets(
    table: CorrectionTable, n: int, seed: int = 0, margin: float = 0.02
) -> tuple[np.ndarray, np.ndarray]:
    """n random positions (N, 3) inside the volume (shrunk by `margin` of each side) and their
    orientation indices (N,)."""
    if n < 1:
        raise UserError(f"--targets must be at least 1, got {n}")
    rng = np.random.default_rng(seed)
    span = table.hi_m - table.lo_m
    P = rng.uniform(table.lo_m + margin * span, table.hi_m - margin * span, (n, 3))
    k = rng.integers(0, len(table.orientations_rotvec), n)
    return P, k


def accuracy_stats(err_vec: np.ndarray) -> dict:
    """Mean, RMS (with its 95 % interval over the targets), max and mean vector of the position
    errors (N, 3), reached minus desired, given in base_ref axes (the table's frame, the model's
    registered base: `error_vectors_base`); `bias_base_m` is their mean in those axes."""
    e = np.linalg.norm(err_vec, axis=1)
    n = len(err_vec)
    sem = err_vec.std(0, ddof=1) / np.sqrt(n) if n >= 2 else np.full(3, np.nan)
    return {
        "mean_m": float(e.mean()),
        "rms_m": float(np.sqrt(np.mean(e**2))),
        "rms_ci95_m": list(rms_interval(e)),
        "max_m": float(e.max()),
        "bias_base_m": err_vec.mean(0).tolist(),
        # standard error of that mean over the targets (nan with one target)
        "bias_base_std_m": sem.tolist(),
    }


def error_vectors_base(
    nominal: Nominal, reached_tracker: npt.ArrayLike, goal_tracker: npt.ArrayLike
) -> np.ndarray:
    """Reached minus desired SMR positions (N, 3), both measured in the tracker frame, as vectors
    in base_ref axes (the table's frame): rotated by tracker_T_base's rotation, not translated.
    Their lengths are those of the tracker-frame errors."""
    ev = np.asarray(reached_tracker, float) - np.asarray(goal_tracker, float)
    return ev @ np.asarray(nominal.base_ref, float)[:3, :3]


def commanded_joints(
    nominal: Nominal, table: CorrectionTable, P: np.ndarray, k: np.ndarray, corrected: bool
) -> np.ndarray:
    """Joints the (emulated) controller goes to when asked for P (or its table correction)."""
    q = np.full((len(P), 6), np.nan)
    for kk in np.unique(k):
        sel = k == kk
        R = rotvec_to_matrix(table.orientations_rotvec[kk])[0]
        seeds = table.seed_for(P[sel], int(kk)) if table.q_nodes is not None else Q_REF
        target = P[sel]
        if corrected:
            target = target + table.interpolate(target, int(kk))
        qq, r = nominal.ik(target, R, seeds, iters=100)
        qq[r > 1e-9] = np.nan
        q[sel] = qq
    return q


# the closed-loop check's defaults and limits, shared by `workcell validate` and the TUI
DEFAULT_TARGETS = 50
DEFAULT_READINGS = 5  # tracker readings per visit (a real or protocol-simulated tracker)
MAX_TARGETS = 10_000  # ~10 s a target: more than a day at the tracker
MAX_READINGS = 1000


def run_validation(
    nominal: Nominal,
    table: CorrectionTable,
    move: Callable[[np.ndarray], None],
    measure: Callable[[], np.ndarray],
    *,
    n: int = 50,
    seed: int = 0,
    approach_rad: float = 0.02,
    guard: Guard | None = None,
    q_start: np.ndarray | Callable[[], np.ndarray] | None = None,
    log: Callable[[str], None] | None = None,
    clock: Callable[[], float] | None = None,
) -> dict:
    """Measure n targets uncorrected and corrected. `move(q)` moves the robot (blocking, along
    the joint-space straight line), `measure()` returns the SMR position in the tracker frame.

    With a `guard` (the envelope) every motion is checked before the arm moves: each target and
    pre-pose, the approach (pre-pose -> target) and the transit from where the arm is (`q_start`
    at first) to the pre-pose, direct or via the upright posture. A target any of whose four
    moves would leave the envelope is skipped, with the reason, before its first motion.
    `q_start` may be a callable: it is then read after the targets are solved, just before the
    first move is checked (the arm may have been jogged while they were), and again before
    every move, as a campaign does: an arm not where it was last sent (moved by someone since,
    beyond `AT_SENT_TOL_RAD`) goes on from where it is, along a path checked from there
    (direct or via the upright posture), or, when none stays inside, nothing is sent and
    `UserError` says so.

    `clock()` (s; the controller's time) dates the closure measurement (module docstring);
    `measure` may carry `sigma_m` (per-axis 1-sigma of its last result) and `exact` (truth)."""
    log = log or (lambda m: None)
    if guard is not None and q_start is None:
        raise ValueError("run_validation: a guard needs q_start, the arm's joints now")
    P, k = random_targets(table, n, seed)
    sign = np.sign(
        np.asarray((table.meta.get("conditions") or {}).get("approach_sign") or [1.0] * 6)
    )
    q_u = commanded_joints(nominal, table, P, k, corrected=False)
    q_c = commanded_joints(nominal, table, P, k, corrected=True)
    where = q_start if callable(q_start) else None
    if callable(q_start):
        q_start = q_start()
    start_outside = False  # beyond the joint ranges: the first transit comes back in
    if guard is not None:
        why = guard.pose(q_start)
        if why is not None:
            # beyond the joint ranges only: come back in along a path checked for box and floor
            if guard.with_arm_joint_ranges().pose(q_start) is not None:
                raise UserError(
                    f"the arm is outside the envelope before validation ({why}); jog it inside, "
                    "then run again"
                )
            start_outside = True
            log(f"  the arm starts outside the envelope's joint ranges ({why}); moves checked")
    p_goal = nominal.to_tracker(P)
    keep = np.all(np.isfinite(q_u), 1) & np.all(np.isfinite(q_c), 1)
    skipped = []
    if guard is not None:
        for i in range(len(P)):
            if not keep[i]:
                continue
            for q in (q_u[i], q_c[i], q_u[i] - sign * approach_rad, q_c[i] - sign * approach_rad):
                why = guard.pose(q)
                if why:
                    keep[i] = False
                    skipped.append(f"target {i}: {why}")
                    break
    if not keep.any():
        raise UserError("no target could be reached inside the envelope; check the volume")
    if guard is not None and where is not None:
        move = _from_where_the_arm_is(move, where, guard, q_start, log)
    meas = {"before": [], "after": []}
    t_after = []  # when each corrected target was measured (s; visit order without a clock)
    q_at = None if q_start is None else np.asarray(q_start, float)
    n_via = 0
    first = None  # the first corrected visit: (target, joints, position, sigma, time)
    for i in np.where(keep)[0]:
        legs = []  # (waypoints to the pre-pose, target) for the uncorrected and corrected visit
        why = None
        for q in (q_u[i], q_c[i]):
            pre = q - sign * approach_rad
            if guard is None:
                legs.append(([pre], q))
                continue
            if start_outside and not legs and not any(meas.values()):
                wps, why = guard.route_back_in(q_at, pre)
            else:
                wps, why = guard.route(q_at if not legs else legs[-1][1], pre)
            if why is None and (v := guard.direct(pre, q)) is not None:
                why = f"approach: {v}"
            if why is not None:
                break
            legs.append((wps, q))
        if why is not None:
            keep[i] = False
            skipped.append(f"target {i}: {why}")
            continue
        for key, (wps, q) in zip(("before", "after"), legs, strict=True):
            n_via += len(wps) - 1
            for w in wps:
                move(w)
            move(q)
            meas[key].append(measure())
            if key == "before" and len(meas["before"]) == 1:  # the first target only
                _check_registration(table, meas[key][-1], p_goal[i], P[i], int(k[i]))
            if key == "after":
                t_after.append(clock() if clock else float(len(t_after)))
            q_at = q
            if key == "after" and first is None:
                first = (int(i), q, meas[key][-1], _sigma(measure), clock() if clock else None)
    if not keep.any():
        raise UserError(
            "no target could be reached along paths inside the envelope; check the volume"
        )
    out = {"targets": int(keep.sum()), "skipped": skipped, "via_upright_moves": n_via}
    norms = {}
    for key in ("before", "after"):
        # measured in the tracker frame; the bias is stated in base_ref axes, the table's
        ev = error_vectors_base(nominal, meas[key], p_goal[keep])
        norms[key] = np.linalg.norm(ev, axis=1)
        st = accuracy_stats(ev)
        out[key] = st
        if key == "after":
            ev_after = ev
    trend = drift_trend(ev_after, np.asarray(t_after, float), "s" if clock else "target")
    if trend is not None:
        out["drift"] = trend
    if first is not None and out["targets"] >= 2:
        out["closure"] = _closure(
            nominal, first, q_at, move, measure, guard, sign, approach_rad, clock
        )
    # the table's own 1-sigma at the targets (model uncertainty only): in simulation, scored
    # against the truth, the corrected error should be of that size plus the interpolation error
    # and what the model leaves out; much larger means the stated uncertainty is optimistic
    sd = [table.interpolate_std(P[i][None], int(k[i])) for i in np.where(keep)[0]]
    if sd and sd[0] is not None:
        s3 = np.linalg.norm(np.concatenate(sd), axis=1)
        out["after"]["predicted_rms_std_m"] = float(np.sqrt(np.mean(s3**2)))
    out["before_rms_m"] = out["before"]["rms_m"]
    out["after_rms_m"] = out["after"]["rms_m"]
    out["improvement"] = out["before_rms_m"] / max(out["after_rms_m"], 1e-15)
    out["improvement_ci95"] = list(rms_ratio_interval(norms["before"], norms["after"]))
    if (rej := getattr(measure, "rejected", None)) is not None:
        out["rejected_readings"] = int(rej)
        if rej:
            log(f"  {rej} tracker reading(s) rejected (farther than 5 robust sigmas from their "
                "target's median)")  # fmt: skip
    if skipped:
        log(f"  {len(skipped)} target(s) skipped before any motion; first: {skipped[0]}")
    log(
        f"  validation on {out['targets']} targets: RMS {out['before_rms_m'] * 1e6:.1f} um -> "
        f"{out['after_rms_m'] * 1e6:.1f} um ({out['improvement']:.1f}x), max "
        f"{out['before']['max_m'] * 1e6:.1f} -> {out['after']['max_m'] * 1e6:.1f} um"
        + (f"; after: {ci}" if (ci := interval_um(out["after"]["rms_ci95_m"])) else "")
    )
    if (c := out.get("closure")) is not None:
        log(f"  {closure_line(c)}")
        if (w := closure_warning(c, out["after_rms_m"])) is not None:
            c["warning"] = w
            log(f"warning: {w}")
    if (d := out.get("drift")) is not None:
        log(f"  {drift_line(d)}")
        if (w := drift_warning(d)) is not None:
            d["warning"] = w
            log(f"warning: {w}")
    if "predicted_rms_std_m" in out["after"]:
        log(
            f"  the table's own 1-sigma at these targets (model uncertainty): RMS "
            f"{out['after']['predicted_rms_std_m'] * 1e6:.1f} um; max interpolation error "
            f"{(table.meta.get('max_interp_error_m') or float('nan')) * 1e6:.1f} um"
        )
    return out


def _from_where_the_arm_is(
    move: Callable[[np.ndarray], None],
    where: Callable[[], np.ndarray],
    guard: Guard,
    q_start: np.ndarray,
    log: Callable[[str], None],
) -> Callable[[np.ndarray], None]:
    """`move`, with the arm's posture read again before each move: the last line of defence.
    `run_validation` checks each path from where it sent the arm last; an arm moved since (a jog
    on the pendant between two moves) would follow a path nobody checked. Then the move goes
    from where the arm is, direct or via the upright posture, each leg checked; when neither
    stays inside, nothing is sent (`UserError`)."""
    from workcell.campaign.plans import fmt_q

    sent = {"q": np.asarray(q_start, float)}

    def guarded(q: np.ndarray) -> None:
        q = np.asarray(q, float)
        q_now = np.asarray(where(), float)
        last = sent["q"]
        if not (np.all(np.isfinite(q_now)) and np.max(np.abs(q_now - last)) < AT_SENT_TOL_RAD):
            legs, why = guard.route(q_now, q)
            if why is not None:
                raise UserError(
                    f"the arm was moved during the validation (it is at q = {fmt_q(q_now)} rad, "
                    f"not where it was sent) and the path from there {why}, also via the "
                    "upright posture; nothing sent: jog it back inside the envelope, then run "
                    "again"
                )
            log(
                f"  the arm was moved during the validation (q = {fmt_q(q_now)} rad): the next "
                "move goes from where it is"
                + (", via the upright posture" if len(legs) > 1 else "")
            )
            if len(legs) > 1:  # to the upright posture, then on from where the arm is then
                move(legs[0])
                sent["q"] = np.asarray(legs[0], float)
                guarded(q)
                return
        move(q)
        sent["q"] = q

    return guarded


# an uncorrected target misses by about the table's correction there (the errors the model
# found, up to a few mm on an arm of this class) plus what the model leaves out; this much more
# is no calibration error: the tracker was moved since the fitting campaign, or the model is of
# another cell
REGISTRATION_GROSS_M = 0.02


def _check_registration(table, p_tracker, p_goal_tracker, p_base, k: int) -> None:
    """Refuse a validation whose first uncorrected target is far beyond any calibration error:
    the model's tracker_T_base does not hold for this tracker setup (nothing else measured).
    Checked on the first target only: a later one off (a bumped SMR, another reflector) is
    one target's error in the results, not a reason to discard the others."""
    miss = float(np.linalg.norm(np.asarray(p_tracker, float) - p_goal_tracker))
    corr = float(np.linalg.norm(table.interpolate(np.asarray(p_base)[None], k)[0]))
    if np.isfinite(miss) and miss <= corr + REGISTRATION_GROSS_M:
        return
    raise UserError(
        f"the first uncorrected target was measured {miss * 1e3:.1f} mm from where the model "
        f"puts it (its correction there is {corr * 1e3:.2f} mm): the tracker is not where it "
        "was when the model was fitted (moved, or the model is of another cell), so every "
        "figure would measure the tracker's move; measure a campaign with the tracker where it "
        "stands now (`workcell campaign`, `workcell fit`) and validate that model"
    )


def _sigma(measure) -> np.ndarray | None:
    """The per-axis 1-sigma of `measure`'s last result: zeros for the simulated truth, what the
    tracker stated (None: unknown) otherwise."""
    if getattr(measure, "exact", False):
        return np.zeros(3)
    s = getattr(measure, "sigma_m", None)
    return None if s is None else np.asarray(s, float)


def _closure(nominal, first, q_at, move, measure, guard, sign, approach_rad, clock) -> dict:
    """Visit the first corrected target again (along a checked path) and measure it: the
    `closure` entry of `run_validation` (module docstring)."""
    from workcell.recording.repeats import reading_sigma, repeat_beyond_noise

    i, q, p0, s0, t0 = first
    pre = q - sign * approach_rad
    wps, why = ([pre], None) if guard is None else guard.route(q_at, pre)
    if why is None and guard is not None and (v := guard.direct(pre, q)) is not None:
        why = f"approach: {v}"
    if why is not None:
        return {"target": i, "skipped": why}
    for w in wps:
        move(w)
    move(q)
    p1, s1 = measure(), _sigma(measure)
    t1 = clock() if clock else None
    d = error_vectors_base(nominal, [p1], [p0])[0]
    if s0 is not None and s1 is not None and not (s0.any() or s1.any()):
        noise = 0.0  # the simulated truth: no measurement noise
    else:  # what the tracker states, at least its MPE / 4 (as the fits weight readings)
        nan3 = np.full(3, np.nan)
        s0 = reading_sigma(nan3 if s0 is None else s0, p0)
        s1 = reading_sigma(nan3 if s1 is None else s1, p1)
        noise = float(np.sqrt(np.sum(s0**2 + s1**2)))
    dist = float(np.linalg.norm(d))
    beyond = (
        dist > 0
        if noise == 0
        else repeat_beyond_noise({"measurements": 2, "rms_m": dist, "noise_m": noise})
    )
    return {
        "target": i,
        "displacement_m": dist,
        "displacement_base_m": d.tolist(),
        "elapsed_s": None if t0 is None or t1 is None else float(t1 - t0),
        "noise_m": noise,
        "beyond_noise": bool(beyond),
    }


DRIFT_ALPHA = 0.01  # a trend of the corrected errors in time is warned about below this p


def drift_trend(ev: np.ndarray, t: np.ndarray, unit: str = "s") -> dict | None:
    """A linear trend in time of the corrected error vectors ev (N, 3) measured at t (N,):
    e = a + b (t - mean t) + noise, least squares per axis, the noise's 3 x 3 covariance S
    estimated from the residuals (each axis its own variance, and their correlation: a tracker
    measures range and angles differently); Hotelling's T^2 test of b = 0, F(3, N - 4); the change
    the trend makes over the validation's span, its length with the 1-sigma along it. The targets
    are visited in random order over the volume, so their position-dependent errors are noise to
    it; a drift of the cell (warm-up, temperature, a tracker stand settling) is not. None for
    fewer than 6 targets or no span."""
    from scipy import stats

    ev = np.asarray(ev, float)
    t = np.asarray(t, float)
    n = len(t)
    if n < 6 or ev.shape != (n, 3) or not np.all(np.isfinite(t)) or np.ptp(t) <= 0:
        return None
    tc = t - t.mean()
    sxx = float(tc @ tc)
    b = tc @ (ev - ev.mean(0)) / sxx  # (3,) m per unit
    res = ev - ev.mean(0) - np.outer(tc, b)
    S = res.T @ res / (n - 2)
    try:
        t2 = float(sxx * b @ np.linalg.solve(S, b))
    except np.linalg.LinAlgError:
        return None  # errors along a line or a point: no test
    f = (n - 4) / (3 * (n - 2)) * t2
    span = float(np.ptp(t))
    change = b * span
    size = float(np.linalg.norm(change))
    u = change / size if size > 0 else np.array([1.0, 0.0, 0.0])
    return {
        "unit": unit,
        "span": span,
        "rate_base_m": b.tolist(),  # per `unit`, base_ref axes
        "rate_std_m": np.sqrt(np.diag(S) / sxx).tolist(),  # each axis's 1-sigma
        "change_m": size,
        "change_std_m": float(np.sqrt(u @ S @ u / sxx) * span),  # along the change
        "p_value": float(stats.f.sf(f, 3, n - 4)),
        "targets": n,
        "basis": "least-squares trend of the corrected error vectors in time, the residuals' "
        "3 x 3 covariance; Hotelling's T^2 test of no trend, F(3, N - 4). change_m is a length: "
        "with no drift it is about 1.6 times change_std_m, not 0",
    }


def drift_line(d: dict) -> str:
    """One line for `drift_trend`'s result."""
    over = f"its {d['span'] / 60:.1f} min" if d["unit"] == "s" else f"its {d['targets']} targets"
    return (
        f"drift: the corrected error changes by {d['change_m'] * 1e6:.1f} +- "
        f"{d['change_std_m'] * 1e6:.1f} um (1-sigma) over {over} (linear trend; p = "
        f"{d['p_value']:.2g} for none)"
    )


def validation_warnings(res: dict) -> list[str]:
    """The warnings `run_validation` put in its result (closure, drift), for `warnings` lists."""
    return [w for k in ("closure", "drift") if (w := (res.get(k) or {}).get("warning"))]


def drift_warning(d: dict) -> str | None:
    """A warning when the corrected errors trend in time (p < DRIFT_ALPHA)."""
    if not d["p_value"] < DRIFT_ALPHA:
        return None
    return (
        f"the corrected error drifted during the validation ({d['change_m'] * 1e6:.1f} +- "
        f"{d['change_std_m'] * 1e6:.1f} um, p = {d['p_value']:.1g}): the after figure carries "
        "that drift (warm-up, temperature, the tracker's stand); let the cell settle and "
        "validate again"
    )


def closure_line(c: dict) -> str:
    """One line for `run_validation`'s `closure` entry."""
    if "skipped" in c:
        return f"closure: target {c['target']} not measured again ({c['skipped']})"
    el = c.get("elapsed_s")
    when = f", {el / 60:.1f} min later" if el is not None else ""
    noise = (
        "measured by the simulated truth: no noise"
        if c["noise_m"] == 0
        else f"the tracker alone gives ~{c['noise_m'] * 1e6:.1f} um, the arm's repeatability "
        "comes on top"
    )
    return (
        f"closure: target {c['target']} measured again at the end{when}: "
        f"{c['displacement_m'] * 1e6:.1f} um from its first reading (base_ref "
        f"{np.round(np.asarray(c['displacement_base_m']) * 1e6, 1).tolist()} um; {noise})"
    )


def closure_warning(c: dict, after_rms_m: float) -> str | None:
    """A warning when the closure moved beyond the tracker's noise and by more than the
    corrected RMS: the after figure then carries the cell's drift, not the table's error alone."""
    if "skipped" in c or not c["beyond_noise"] or not c["displacement_m"] > after_rms_m:
        return None
    return (
        f"the cell moved {c['displacement_m'] * 1e6:.1f} um during the validation (target "
        f"{c['target']} measured again at the end), more than the corrected RMS "
        f"{after_rms_m * 1e6:.1f} um: the after figure carries that drift (tracker stand, base, "
        "temperature); let the cell settle, check the tracker's set-up, and validate again"
    )


class _TruthMeasure:
    """Simulated truth: the true SMR position at the robot's current joints and approach."""

    exact = True

    def __init__(self, world) -> None:
        self.world = world

    def __call__(self) -> np.ndarray:
        return np.asarray(self.world.true_smr_tracker(), float)


def sim_measure(world: Any) -> Callable[[], np.ndarray]:
    """Simulated truth: the true SMR position at the robot's current joints and approach."""
    return _TruthMeasure(world)


class _TrackerMeasure:
    """The mean of `readings` good readings, less outliers as a campaign rejects them
    (`reject_outliers`: farther from the median than 5 robust sigmas, the stated sigma at
    least); two readings that disagree by more than that get a third, so that the median can
    tell which one is off. `sigma_m`: the stated 1-sigma of the last mean; `rejected`: readings
    rejected so far."""

    def __init__(self, tracker, readings: int, max_failures: int) -> None:
        self.tracker, self.readings, self.max_failures = tracker, readings, max_failures
        self.sigma_m: np.ndarray | None = None
        self.rejected = 0

    def __call__(self) -> np.ndarray:
        from workcell.campaign.executor import OUTLIER_K, readings_disagree, reject_outliers

        good, sig, fails = [], [], 0
        need = self.readings
        while len(good) < need:
            r = self.tracker.measure()
            if r.status == "ok" and np.all(np.isfinite(r.position_m)):
                good.append(np.asarray(r.position_m, float))
                sig.append(np.asarray(r.sigma_m, float))
            else:
                fails += 1
                if fails > self.max_failures:
                    raise UserError(f"tracker: {fails} failed readings at one target ({r.status})")
            if len(good) == need == 2 and readings_disagree(
                list(zip(good, sig, strict=True)), OUTLIER_K
            ):
                need = 3  # two that disagree: a third to take the median of
        P, S = np.array(good), np.array(sig)
        keep = reject_outliers(P, S, OUTLIER_K)
        self.rejected += int((~keep).sum())
        P, S = P[keep], S[keep]
        self.sigma_m = S.mean(axis=0) / np.sqrt(len(S))
        return P.mean(axis=0)


def tracker_measure(
    tracker: Tracker, readings: int = 5, max_failures: int = 10
) -> Callable[[], np.ndarray]:
    """The tracker's mean of `readings` good readings at a target (UserError after more than
    `max_failures` failed ones)."""
    return _TrackerMeasure(tracker, readings, max_failures)


def robot_mover(
    robot: Robot, speed: float = 0.5, accel: float = 1.0, settle_s: float = 0.5
) -> Callable[[np.ndarray], None]:
    def move(q: np.ndarray) -> None:
        try:
            robot.move_joints(np.asarray(q, float), speed, accel)
        except BaseException:  # Ctrl-C, SIGTERM, a fault: the arm is stopped before it is said
            try:
                robot.stop()
            except Exception:  # noqa: BLE001 - a lost connection stops the controller's program
                pass
            raise
        robot.sleep(settle_s)

    return move


TABLE_MATCH_RTOL = 1e-9  # base_ref / tcp_m: a table written from the model carries them exactly


def table_model_mismatch(
    table: CorrectionTable,
    nominal: Nominal,
    recording_sha256: str | None = None,
    *,
    model: FittedModel | None = None,
    ui: bool = False,
) -> str | None:
    """One line when a given table was not built from the model being validated, else None.

    Compared, where both the table's meta (`build_table`, `make_table`) and the model give
    them: the recording the model was fitted on (`recording_sha256`), the arm (`robot`), the
    registered base the table corrects in (`base_ref`) and the SMR/TCP on the flange (`tcp_m`),
    the last two within `TABLE_MATCH_RTOL` of their largest entry, and, given the `model`, the
    model itself (`model_fingerprint`: another fit of the same recording, another method). A
    table of another model would move the arm by another model's corrections and report that
    model's 1-sigma. The remedy is said for the command line, or with `ui` for the terminal
    UI's Export screen."""
    meta = table.meta if isinstance(table.meta, dict) else {}
    remedy = (
        "export the table from this model on the Export screen"
        if ui
        else "build the table from this model with `workcell export MODEL --format table` (or "
        "leave --table out: validate then builds it)"
    )
    if not any(meta.get(k) for k in ("model_fingerprint", "recording_sha256")):
        return (
            "the table names neither the model nor the recording it was built from (meta "
            "model_fingerprint, recording_sha256), so it cannot be told it belongs to this "
            f"model; {remedy}"
        )
    sha = meta.get("recording_sha256")
    if sha and recording_sha256 and sha != recording_sha256:
        return (
            f"the table was built from a model of another recording (recording_sha256 "
            f"{str(sha)[:12]}..., this model's {str(recording_sha256)[:12]}...); {remedy}"
        )
    fp = meta.get("model_fingerprint")
    mine = model_fingerprint(model) if fp and model is not None else None
    if mine is not None and fp != mine:
        return (
            f"the table was built from another model of this recording ("
            f"{meta.get('method', '?')} model, fingerprint {str(fp)[:12]}..., this "
            f"{getattr(model, 'method', '?')} model's {mine[:12]}...); {remedy}"
        )
    robot = meta.get("robot")
    if robot and nominal.robot and robot != nominal.robot:
        return f"the table was built for a {robot!r} arm, this model is of a {nominal.robot!r}; {remedy}"
    for key, mine, what in (
        ("base_ref", nominal.base_ref, "the registered base it corrects in"),
        ("tcp_m", nominal.tool_m, "the SMR/TCP on the flange"),
    ):
        if meta.get(key) is None:
            continue
        mine = np.asarray(mine, float)
        try:
            theirs = np.asarray(meta[key], float)
        except (TypeError, ValueError):
            theirs = None
        if theirs is None or theirs.shape != mine.shape or not np.all(np.isfinite(theirs)):
            return f"the table's meta {key} is not a {mine.shape} array of numbers; {remedy}"
        scale = max(float(np.abs(mine).max()), float(np.abs(theirs).max()))
        diff = float(np.abs(theirs - mine).max())
        if diff > TABLE_MATCH_RTOL * scale:
            return (
                f"the table's {key} ({what}) differs from this model's by {diff:.3g} "
                f"({diff / scale:.2g} relative): it was built from another model; {remedy}"
            )
    return None


THERMAL_MISMATCH_K = 2.0


def thermal_mismatch(
    model: FittedModel, table: CorrectionTable, temps_c: npt.ArrayLike | None, *, ui: bool = False
) -> str | None:
    """One line when a given table was built for another thermal state than the arm's now (a
    model whose thermal drift follows the joint temperatures), else None. The remedy is said
    for the command line, or with `ui` for the terminal UI (whose Export screen builds tables
    for the recording's thermal state)."""
    from workcell.estimation.effects import thermal_signal

    fs = getattr(model, "features_spec", None)
    accepted = getattr(model, "accepted", None) or []
    if fs is None or fs.thermal_source != "joint" or temps_c is None:
        return None
    if not any(c.kind == "thermal_drift" for c in accepted):
        return None
    now = np.asarray(temps_c, float).reshape(1, 6)
    if not np.all(np.isfinite(now)):
        return None
    t_table = (table.meta.get("conditions") or {}).get("joint_temperature_c")
    if t_table is None:
        link_table, what = np.asarray(fs.thermal_ref, float), "the recording's mean"
    else:
        link_table = thermal_signal(
            "joint", np.asarray(t_table, float).reshape(1, 6), None, None, 1
        )[0]
        what = "the temperatures it was exported for"
    link_now = thermal_signal("joint", now, None, None, 1)[0]
    d = float(np.abs(link_now - link_table).max())
    # what the mismatch costs: the model's thermal drift between the two states over the joint
    # range it was fitted on, against the table's own median 1-sigma (a drift larger than what
    # the table says it knows is worth a warning at any K); without either, the 2 K rule
    shift = thermal_shift_rms_m(model, t_table, now[0])
    std = table_median_std(table.meta)
    if shift is not None and std is not None:
        if shift <= std:
            return None
        cost = (
            f", and the model's thermal drift between the two moves the SMR by "
            f"{shift * 1e6:.1f} um RMS over its fitted joint range, more than the table's median "
            f"1-sigma {std * 1e6:.1f} um"
        )
    elif d <= THERMAL_MISMATCH_K:
        return None
    else:
        cost = ", and the model's thermal drift differs by that"
    temps = ",".join(f"{t:.1f}" for t in now[0])
    remedy = (
        f"export it for now on the command line (`workcell export MODEL --joint-temperature "
        f"{temps}`) or let `workcell validate` build it"
        if ui
        else f"export the table again with --joint-temperature {temps}, or leave --table out to "
        "build it for now"
    )
    return (
        f"the table is for {what} (link temperatures {np.round(link_table, 1).tolist()} degC); "
        f"the arm is now at {np.round(link_now, 1).tolist()} degC ({d:.1f} K apart){cost}: "
        f"{remedy}"
    )


def table_median_std(meta: dict | None) -> float | None:
    """A table's own median 1-sigma (`meta.median_std_m`) when it states a usable one (finite,
    positive), else None: what the thermal and payload checks weigh a model's shift against."""
    std = (meta or {}).get("median_std_m")
    ok = isinstance(std, int | float) and np.isfinite(std) and std > 0
    return float(std) if ok else None


def fitted_range_configurations(model: FittedModel, n: int = 64) -> np.ndarray | None:
    """(n, 6) seeded joint configurations drawn uniformly in the model's fitted joint range
    (`info.joint_range_rad`); None when the model records none usable."""
    jr = (getattr(model, "info", {}) or {}).get("joint_range_rad")
    try:
        jr = np.asarray(jr, float)
    except (TypeError, ValueError):
        return None
    if jr.shape != (6, 2) or not np.all(np.isfinite(jr)):
        return None
    return np.random.default_rng(0).uniform(jr[:, 0], jr[:, 1], size=(n, 6))


def thermal_shift_rms_m(
    model, t_table_c: npt.ArrayLike | None, t_now_c: npt.ArrayLike, n: int = 64
) -> float | None:
    """RMS over `n` seeded configurations in the model's fitted joint range of how far its
    prediction moves between joint temperatures `t_table_c` (None: the recording's mean, the
    model's reference) and `t_now_c` (m); None without a recorded joint range."""
    q = fitted_range_configurations(model, n)
    if q is None:
        return None
    now = np.tile(np.asarray(t_now_c, float), (n, 1))
    p_now = model.predict_parametric(q, joint_temperature_c=now)
    if t_table_c is None:
        p_tab = model.predict_parametric(q)  # no temperatures: the reference state
    else:
        p_tab = model.predict_parametric(
            q, joint_temperature_c=np.tile(np.asarray(t_table_c, float), (n, 1))
        )
    return float(np.sqrt(np.mean(np.sum((p_now - p_tab) ** 2, axis=1))))


PAYLOAD_MATCH_KG = 1e-3  # payloads this close are the same setting


def payload_mismatch(
    model: FittedModel, table: CorrectionTable, payload_kg: float | None, *, ui: bool = False
) -> str | None:
    """One line when a given table was built for another payload than the arm carries now (a
    model with payload-dependent terms: joint compliance, link deflection), else None. A
    payload whose compliance shift over the model's fitted joint range is within the table's
    median 1-sigma is not a mismatch. The remedy is said for the command line, or with `ui` for
    the terminal UI. (The approach the table was built for needs no comparison: the validation
    approaches every target as the table declares.)"""
    from workcell.export.build import COMPLIANCE_KINDS

    fs = getattr(model, "features_spec", None)
    accepted = getattr(model, "accepted", None) or []
    if fs is None or payload_kg is None or not any(c.kind in COMPLIANCE_KINDS for c in accepted):
        return None
    meta = table.meta if isinstance(table.meta, dict) else {}
    t_pay = (meta.get("conditions") or {}).get("payload_kg")
    if t_pay is None:
        t_pay, what = float(fs.payload_kg_default), "the recording's"
    else:
        t_pay, what = float(t_pay), "given at export"
    now = float(payload_kg)
    if abs(t_pay - now) <= PAYLOAD_MATCH_KG:
        return None
    shift = payload_shift_rms_m(model, t_pay, now)
    std = table_median_std(meta)
    if shift is not None and std is not None:
        if shift <= std:
            return None
        cost = (
            f": the model's compliance terms move the SMR by {shift * 1e6:.1f} um RMS between "
            f"the two over its fitted joint range, more than the table's median 1-sigma "
            f"{std * 1e6:.1f} um"
        )
    elif shift is not None:
        cost = (
            f": the model's compliance terms move the SMR by {shift * 1e6:.1f} um RMS between "
            "the two over its fitted joint range"
        )
    else:
        cost = ", and the model's compliance terms depend on it"
    remedy = (
        f"export it for {now:g} kg on the command line (`workcell export MODEL --payload "
        f"{now:g}`) or let `workcell validate` build it"
        if ui
        else f"export the table again with --payload {now:g}, or leave --table out to build it "
        "for this payload"
    )
    return (
        f"the table is for a payload of {t_pay:g} kg ({what}); the arm carries {now:g} kg{cost}; "
        f"{remedy}"
    )


PAYLOAD_ORIGIN = {
    "declared": "the payload as declared",
    "controller": "the payload as the controller is set",
    "recording": "the recorded payload",
    "default": "no payload stated and the controller's setting unread, so 0 kg",
}


def payload_check(
    model: FittedModel,
    table: CorrectionTable,
    payload_kg: float | None,
    *,
    simulated: bool,
    ui: bool = False,
    source: str = "declared",
) -> str | None:
    """`payload_mismatch` as `validate` acts on it: on a simulated arm (its payload known) a
    UserError naming the table's problem; on a controller the warning line to give, saying where
    the payload it compared came from (`source`, a `CellSetup.payload_source`); None when the
    payloads match."""
    from workcell.errors import UserError

    why = payload_mismatch(model, table, payload_kg, ui=ui)
    if why is None:
        return None
    if simulated:
        raise UserError(why)
    origin = PAYLOAD_ORIGIN.get(source, PAYLOAD_ORIGIN["declared"])
    return f"{why} ({origin}; if the arm carries the table's, disregard this)"


def payload_shift_rms_m(model: FittedModel, kg_a: float, kg_b: float, n: int = 64) -> float | None:
    """RMS over `n` seeded configurations in the model's fitted joint range of how far its
    prediction moves between payloads `kg_a` and `kg_b` (m); None without a recorded joint
    range or a finite prediction."""
    q = fitted_range_configurations(model, n)
    if q is None:
        return None
    f = getattr(model, "predict_parametric", None) or model.predict
    d = f(q, payload_kg=np.full(n, kg_b)) - f(q, payload_kg=np.full(n, kg_a))
    r = float(np.sqrt(np.mean(np.sum(np.asarray(d, float) ** 2, axis=1))))
    return r if np.isfinite(r) else None


def real_cell(session: dict) -> str | None:
    """What says the recording of `session` was made on a real cell, not a simulation this
    program runs (None when it does not say so): a campaign on devices that recorded no
    simulated truth (`effects`, which the in-process and the protocol simulators record), or
    measurements imported from another system. A simulator has another arm than such a
    recording's, so a simulated validation of its model scores a model of one arm on another."""
    camp = (session or {}).get("campaign")
    if not isinstance(camp, dict) or camp.get("effects") is not None:
        return None
    if camp.get("sim_seed") is not None:
        return None
    url = camp.get("robot_url")
    if isinstance(url, str) and url and url != "sim":
        return f"robot {url}"
    if camp.get("plan") == "imported" or camp.get("source") is not None:
        return f"measurements imported from {camp.get('source') or 'another system'}"
    return None


def validation_envelope(
    given: Envelope | None,
    session: dict,
    spec: RobotSpec,
    source: str,
    default: Envelope | None = None,
) -> tuple[Envelope, str]:
    """The envelope a closed-loop validation moves in -> (envelope, what it is): the one
    `given` (chosen by the user), else the one the model's campaign recorded (the cell's, as
    it was calibrated in), else `default` (the arm's default envelope), said so."""
    from workcell.campaign.envelope import default_envelope, envelope_of_session

    if given is not None:
        return given, "the envelope given"
    env = envelope_of_session((session or {}).get("campaign") or {}, spec, source)
    if env is not None:
        return env, f"the envelope recorded with the model's campaign ({source})"
    return (
        default if default is not None else default_envelope(spec),
        "the arm's default envelope: the model's recording gives none (give the cell's "
        "envelope file)",
    )
