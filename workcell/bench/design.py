"""`workcell bench design [--json]`: how many tracker poses does each plan need? (seed 002)

Setting: a simulated UR5e whose geometry differs from nominal (the simulator's DH, base and SMR
errors: sigma 0.3 mm lengths, 0.5 mrad twists, 1 mrad joint offsets, 0.3 mm Hayati tilts of
joints 2-3; `sim_devices.truth.make_truth(effects="none")`), measured by the simulated tracker
(per-axis sigma (15 um + 6 um/m * range)/4 per reading, 80 % of it systematic per pose; a pose
is the mean of 5 readings). One true cell per seed.

Plans (all from `workcell.campaign.plans.make_plan`, the code `workcell campaign --plan` runs):
``random`` (uniform in the envelope), ``dopt`` (greedy O1 / D-optimal), ``vopt`` (greedy
V-optimal: least mean prediction variance over the candidate poses) and ``bo`` (GP-UCB on
S3 x R3, the paper's Algorithm 1). Each plan is driven for up to ``--max-poses`` poses by a fast
in-process measurement loop (the true cell's SMR position plus the tracker noise of a 5-reading
pose mean, fed back to the plan as a sample dict exactly as the campaign executor does).

Held-out set: per seed, ``--holdout`` (default 100) independent random configurations inside the
envelope, measured once in the same simulated cell (its own noise draws): extra poses, on top of
the ones each plan chooses, used only to score the fits; a real campaign would need them too.
Noise floor: the RMS of the measurement error alone on that set,
``floor = sqrt(mean_i 3 sigma_i^2)`` with ``sigma_i`` the simulator's per-axis sigma of a
5-reading mean at that pose's range: the held-out RMS a perfect model would show.
Fitted model: the DH fit on the first n poses (`fit_dh_bounded(bounds=None)`, which is the
unbounded nonlinear fit: identical to `workcell.estimation.dh.fit_dh`, see
tests/test_design_bounded.py; the padded-shape version avoids recompiling per n).
Poses to target: first passage, the smallest n on the schedule (every pose from ceil(L/3), L =
number of identifiable parameters, the rank bound of Theorem 1) whose held-out RMS is <= 2 x
floor (`--target-factor`). The held-out RMS is not monotone in n, so the plan then runs
``AFTER`` (2) more poses, fitted and scored the same way, only to say whether the run stayed
at or below the target (`stayed_below_after`: True, False, or None when --max-poses left no
room); the count is still the first passage. A run that does not reach the target within
--max-poses counts as max-poses + 1 and is reported under `censored`.
`ratio_best_to_random` = mean poses of the best of the adaptive plans run (dopt, vopt, bo) over
mean poses of random (`ratios_to_random`: each plan's);
`best_possible_ratio` = the rank bound ceil(L/3) over mean poses of random (no plan can beat it).

`--envelope compact` restricts the joints to +-30 deg (`--half-width-deg`) around the home pose
(0, -90, 90, -90, -90, 0) deg (wam7: (0, 0, 0, 90, 0, 0, 0) deg), a cell where the tracker's line
of sight or fixtures confine the arm; random poses are then much less informative and the design
matters more.

`--robot wam7`: the paper's own simulated setting (section V-A): a 7-joint Barrett-WAM-like arm
(`workcell.kinematics.robots.WAM7`) whose true DH parameters carry the paper's four errors
(theta7 offset +1.3 rad, alpha2 +0.4 rad, a3 +10 mm, d3 +150 mm;
`sim_devices.truth.make_paper_wam_truth`), with `--small-errors` also the UR cell's small random
DH errors. The SMR sits 50 mm off the flange axis (as on the paper's scoop), measured by the same
simulated tracker: position only (the paper's camera measured full pose). The plans and the fit
are the same code as for the UR5e; the fit starts from the nominal chain, far from the truth.
Envelope: the WAM's joint limits less 5 deg, links above z = -0.25 m (its mounting plate sits
0.35 m below the shoulder), SMR inside a 1.1 m box.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import numpy as np

from workcell.bench import check_ranges, environment
from workcell.errors import OneLineParser

PLANS = ("random", "dopt", "vopt", "bo")
AFTER = 2  # poses run past the first passage to check the held-out RMS stays at the target


ROBOTS = ("ur5e", "wam7")
HOME_RAD = {
    "ur5e": np.deg2rad([0.0, -90.0, 90.0, -90.0, -90.0, 0.0]),
    "wam7": np.deg2rad([0.0, 0.0, 0.0, 90.0, 0.0, 0.0, 0.0]),
}


def wam_envelope(spec):
    """The WAM bench's envelope: joint limits less 5 deg, links above its mounting plate."""
    from workcell.campaign.envelope import Envelope

    lim = spec.joint_limits_rad + np.deg2rad(5.0) * np.array([1.0, -1.0])
    return Envelope(
        joint_limits_rad=lim,
        box_min_m=np.array([-1.1, -1.1, -0.25]),
        box_max_m=np.array([1.1, 1.1, 1.1]),
        floor_z_m=-0.25,
    )


def _cell(
    seed: int,
    envelope: str = "default",
    half_width_deg: float = 30.0,
    robot: str = "ur5e",
    small_errors: bool = False,
):
    from sim_devices.truth import (
        NOMINAL_SMR_M,
        WAM_SMR_M,
        TrackerNoise,
        make_paper_wam_truth,
        make_truth,
    )
    from workcell.campaign.envelope import default_envelope

    noise = TrackerNoise(beam_break_prob=0.0, outlier_prob=0.0)
    if robot == "ur5e":
        truth = make_truth("ur5e", "none", seed, noise=noise)
        env, tool = default_envelope(truth.nominal), NOMINAL_SMR_M.copy()
    elif robot == "wam7":
        truth = make_paper_wam_truth(seed, small_errors=small_errors, noise=noise)
        env, tool = wam_envelope(truth.nominal), WAM_SMR_M.copy()
    else:
        raise ValueError(f"robot must be one of {', '.join(ROBOTS)}, got {robot!r}")
    if envelope == "compact":
        h = np.deg2rad(half_width_deg)
        lim = env.joint_limits_rad
        home = HOME_RAD[robot]
        env.joint_limits_rad = np.column_stack(
            [np.maximum(lim[:, 0], home - h), np.minimum(lim[:, 1], home + h)]
        )
    elif envelope != "default":
        raise ValueError(f"envelope must be 'default' or 'compact', got {envelope!r}")
    return truth, env, tool


def measure(truth, q: np.ndarray, sign: np.ndarray, rng: np.random.Generator, n_read: int = 5):
    """One pose: (noisy SMR position in the tracker frame (3,), per-axis sigma (3,))."""
    p = truth.smr_in_tracker(np.asarray(q, float), np.asarray(sign, float), 0.0)
    sig = truth.noise.sigma_of_mean(float(np.linalg.norm(p)), n_read)
    return p + rng.normal(0.0, sig, 3), np.full(3, sig)


def drive_plan(gen, truth, rng: np.random.Generator, stop=None) -> list[dict]:
    """Run a plan generator against the true cell; returns the sample dicts in order.

    `stop(samples) -> bool` is asked after every sample; True ends the plan early."""
    samples: list[dict] = []
    try:
        t = next(gen)
        while True:
            p, sig = measure(truth, t.q_rad, t.approach_sign, rng)
            s = {
                "index": len(samples),
                "pose_id": int(t.pose_id),
                "q_commanded_rad": np.asarray(t.q_rad, float).tolist(),
                "q_measured_rad": np.asarray(t.q_rad, float).tolist(),
                "approach_sign": [int(x) for x in np.sign(t.approach_sign)],
                "tracker_position_m": p.tolist(),
                "tracker_sigma_m": sig.tolist(),
            }
            samples.append(s)
            if stop is not None and stop(samples):
                gen.close()
                break
            t = gen.send(s)
    except StopIteration:
        pass
    return samples


def dataset_of(samples: list[dict], truth, tool_m):
    from workcell.recording.dataset import Dataset

    return Dataset(
        robot=truth.nominal,
        tool_offset_m=np.asarray(tool_m, float),
        tracker_T_base_nominal=np.eye(4),
        q=np.array([s["q_measured_rad"] for s in samples]),
        p_tracker=np.array([s["tracker_position_m"] for s in samples]),
        sigma_m=np.array([s["tracker_sigma_m"] for s in samples]),
    )


def one_run(
    plan: str,
    seed: int,
    max_poses: int,
    n_holdout: int,
    log=None,
    target_factor: float = 2.0,
    envelope: str = "default",
    half_width_deg: float = 30.0,
    robot: str = "ur5e",
    small_errors: bool = False,
) -> dict:
    from workcell.campaign.adaptive import identifiable_mask
    from workcell.campaign.plans import make_plan, random_configurations
    from workcell.estimation.bounded import fit_dh_bounded, jacobian_padded, predict_padded
    from workcell.kinematics.chain import pack

    truth, env, tool = _cell(seed, envelope, half_width_deg, robot, small_errors)
    spec = truth.nominal
    # held-out set: independent configurations and noise draws (seed-specific)
    rng_v = np.random.default_rng(10_000 + seed)
    q_v = random_configurations(spec, env, n_holdout, rng_v, tool)
    meas_v = [measure(truth, q, np.ones(spec.n_joints), rng_v) for q in q_v]
    p_v = np.array([m[0] for m in meas_v])
    floor = float(np.sqrt(np.mean([3.0 * m[1][0] ** 2 for m in meas_v])))
    free = identifiable_mask(spec, jacobian_padded(pack(spec.dh, tool=tool), np.eye(4), q_v))
    n_min = int(math.ceil(free.sum() / 3))  # Theorem 1: 3 n >= L
    curve: list[tuple[int, float]] = []
    target = target_factor * floor
    passage: list[int] = []  # the first n at the target
    after: list[bool] = []  # the next poses' fits at or below the target (a failed fit: False)

    def reached(samples: list[dict]) -> bool:
        n = len(samples)
        if n < n_min:
            return False
        ds = dataset_of(samples, truth, tool)
        try:
            m = fit_dh_bounded(ds, bounds=None, min_poses=n_min)
        except (ValueError, np.linalg.LinAlgError):
            m = None
        if m is not None:
            err = predict_padded(m.theta, m.base_ref, q_v) - p_v
            curve.append((n, float(np.sqrt(np.mean(np.sum(err**2, axis=1))))))
        ok = m is not None and curve[-1][1] <= target
        if passage:
            after.append(ok)
        elif ok:
            passage.append(n)
        return bool(passage) and (len(after) >= AFTER or not all(after))

    t0 = time.perf_counter()
    # the plans' own refits unbounded, as the scoring fit: the paper's WAM errors (d3 +150 mm,
    # alpha2 +0.4 rad) lie far outside the default bounds of a manufacturing tolerance
    kw = {} if plan == "random" else {"refit_bounds": None}
    gen, _ = make_plan(plan, spec, env, max_poses, seed=seed, tool_m=tool, **kw)
    drive_plan(gen, truth, np.random.default_rng(20_000 + seed), stop=reached)
    seconds = time.perf_counter() - t0
    first = passage[0] if passage else None
    stayed = None if first is None or (all(after) and len(after) < AFTER) else all(after)
    out = {
        "plan": plan,
        "seed": seed,
        "poses_to_target": first if first is not None else max_poses + 1,
        "censored": first is None,
        "stayed_below_after": stayed,
        "noise_floor_m": floor,
        "rank_bound_poses": n_min,
        "curve": curve,
        "seconds": seconds,
    }
    if log:
        log(
            f"  {plan:6s} seed {seed:2d}: {out['poses_to_target']:3d} poses"
            f"{' (not reached)' if first is None else ''}; floor {floor * 1e6:.1f} um, "
            f"last RMS {curve[-1][1] * 1e6 if curve else float('nan'):.1f} um"
            f"{'' if stayed is None else ' (stayed)' if stayed else ' (went above again)'} "
            f"({seconds:.1f} s)"
        )
    return out


def poses_summary(rs: list[dict]) -> dict:
    """Mean, spread, median and runs of `poses_to_target` over one plan's runs."""
    v = np.array([r["poses_to_target"] for r in rs], float)
    return {
        "mean": float(v.mean()),
        "std": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
        "median": float(np.median(v)),
        "runs": [int(x) for x in v],
        "censored": int(sum(r["censored"] for r in rs)),
    }


def best_vs_random(summary: dict) -> tuple[str | None, float | None]:
    """(the non-random plan needing the fewest poses on average, its mean over random's)."""
    if "random" not in summary or len(summary) < 2:
        return None, None
    best = min((p for p in summary if p != "random"), key=lambda p: summary[p]["mean"])
    return best, summary[best]["mean"] / summary["random"]["mean"]


RATIO_CI_BASIS = (
    "95 % interval of a plan's mean poses over random's: paired bootstrap over the seeds (each "
    "seed is one simulated cell both plans ran on; BCa, percentile when BCa is degenerate)"
)


def ratio_intervals(summary: dict) -> dict[str, list[float]]:
    """Each non-random plan's 95 % interval of mean(poses) / mean(random's poses), paired over
    the seeds (`RATIO_CI_BASIS`); {} without random or with fewer than 3 seeds."""
    from workcell.estimation.models import mean_ratio_interval

    if "random" not in summary:
        return {}
    base = np.asarray(summary["random"]["runs"], float)
    out = {}
    for p, s in summary.items():
        v = np.asarray(s["runs"], float)
        if p != "random" and len(v) == len(base):
            lo, hi = mean_ratio_interval(v, base)
            if np.isfinite(lo) and np.isfinite(hi):
                out[p] = [lo, hi]
    return out


def ratio_line(out: dict, best: str, bound_text: str) -> str:
    """'ratio best (dopt) / random: 0.85 (95 % CI 0.78-0.93; dopt 0.85 ..., ...); no design
    can do better than 0.85 here (rank bound 9 poses)' from a bench's JSON."""
    cis = out.get("ratios_to_random_ci95") or {}

    def ci(p: str) -> str:
        c = cis.get(p)
        return f" (95 % CI {c[0]:.2f}-{c[1]:.2f})" if c else ""

    each = ", ".join(f"{p} {v:.2f}{ci(p)}" for p, v in out["ratios_to_random"].items())
    return (
        f"ratio best ({best}) / random: {out['ratio_best_to_random']:.2f} ({each}; intervals "
        f"paired over the seeds); no design can do better than {out['best_possible_ratio']:.2f} "
        f"here ({bound_text})"
    )


def ratios_to_random(summary: dict) -> dict[str, float]:
    """Each non-random plan's mean poses over random's ({} without random)."""
    if "random" not in summary:
        return {}
    return {p: s["mean"] / summary["random"]["mean"] for p, s in summary.items() if p != "random"}


def summarise(runs: dict[str, list[dict]]) -> dict:
    res = {}
    for plan, rs in runs.items():
        res[plan] = poses_summary(rs)
        # the held-out RMS / floor with the fewest poses any plan can use (the rank bound):
        # how good each plan's first identifiable set is, beyond the count
        first = [r["curve"][0][1] / r["noise_floor_m"] for r in rs if r["curve"]]
        if first:
            res[plan]["rms_over_floor_at_rank_bound"] = {
                "median": float(np.median(first)),
                "max": float(np.max(first)),
            }
        st = [r.get("stayed_below_after") for r in rs]
        res[plan]["stayed_below_after"] = {
            "poses": AFTER,
            "stayed": sum(x is True for x in st),
            "checked": sum(x is not None for x in st),
        }
    return res


HALF_WIDTH_DEG = 30.0  # the compact envelope's default half-width


def _holdout_count(text: str) -> int:
    """`--holdout`: a number of poses (`fit --holdout` takes a fraction: say which is meant)."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        frac = float(text)
    except ValueError:
        frac = None
    what = (
        "a fraction, as `workcell fit --holdout` takes"
        if frac is not None and 0 < frac < 1
        else "not a whole number"
    )
    raise argparse.ArgumentTypeError(
        f"{text!r} is {what}; here it is the number of held-out poses per simulated cell, a "
        "whole number >= 10 (e.g. --holdout 100)"
    )


def main(argv: list[str]) -> int:
    ap = OneLineParser(prog="workcell bench design", description=__doc__.split("\n")[0])
    ap.add_argument(
        "--seeds",
        type=int,
        default=10,
        help="number of simulated cells (>= 1; default: %(default)s)",
    )
    ap.add_argument("--seed0", type=int, default=0, help="first seed (>= 0; default: %(default)s)")
    ap.add_argument(
        "--max-poses",
        type=int,
        default=80,
        help="poses per run at most (>= 12; default: %(default)s)",
    )
    ap.add_argument(
        "--holdout",
        type=_holdout_count,
        default=100,
        metavar="N",
        help="held-out poses per simulated cell: N extra random poses that score the fits, a "
        "count (>= 10), not a fraction as in `workcell fit --holdout` (default: %(default)s)",
    )
    ap.add_argument(
        "--plans",
        default=",".join(PLANS),
        help=f"comma list of {','.join(PLANS)}, each at most once (default: %(default)s)",
    )
    ap.add_argument(
        "--target-factor",
        type=float,
        default=2.0,
        help="target: held-out RMS <= this x floor (default: %(default)s)",
    )
    ap.add_argument(
        "--envelope",
        choices=["default", "compact"],
        default="default",
        help="default: the campaign's default envelope; compact: joints within "
        "+-HALF_WIDTH of the home pose (0,-90,90,-90,-90,0) deg (default: %(default)s)",
    )
    ap.add_argument(
        "--half-width-deg",
        type=float,
        metavar="DEG",
        default=None,  # None: not given (refused without --envelope compact)
        help=f"with --envelope compact: the joints' half-width around the home pose in deg "
        f"(default: {HALF_WIDTH_DEG:g})",
    )
    ap.add_argument(
        "--robot",
        choices=ROBOTS,
        default="ur5e",
        help="ur5e (default) or wam7: the paper's 7-joint setting with its four DH errors",
    )
    ap.add_argument(
        "--small-errors",
        action="store_true",
        help="with --robot wam7: add the UR cell's small random DH errors to the paper's four",
    )
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--runs", action="store_true", help="include per-run curves in the JSON")
    a = ap.parse_args(argv)
    if not (math.isfinite(a.target_factor) and a.target_factor > 0):
        ap.error(f"--target-factor must be a positive number, got {a.target_factor:g}")
    if a.half_width_deg is None:
        a.half_width_deg = HALF_WIDTH_DEG
    elif a.envelope != "compact":
        ap.error(
            "--half-width-deg goes with --envelope compact (the default envelope has no "
            "half-width); add --envelope compact or leave it out"
        )
    if not (math.isfinite(a.half_width_deg) and 0 < a.half_width_deg <= 180):
        ap.error(f"--half-width-deg must be in (0, 180], got {a.half_width_deg:g}")
    if a.small_errors and a.robot != "wam7":
        ap.error(
            f"--small-errors goes with --robot wam7 (the {a.robot} cell has small random DH "
            "errors already); add --robot wam7 or leave it out"
        )
    check_ranges(
        ap,
        [
            ("--seed0", a.seed0, 0, 2**32 - 1),
            ("--seeds", a.seeds, 1, 1000),
            ("--max-poses", a.max_poses, 12, 5000),
            ("--holdout", a.holdout, 10, 100_000),
            ("--target-factor", a.target_factor, 1e-3, 1e3),
        ],
    )
    plans = [p.strip() for p in a.plans.split(",") if p.strip()]
    if not plans:
        ap.error(f"--plans {a.plans!r} names no plan; give at least one of {','.join(PLANS)}")
    for p in plans:
        if p not in PLANS:
            ap.error(f"unknown plan {p!r}; choose from {', '.join(PLANS)}")
    twice = sorted({p for p in plans if plans.count(p) > 1}, key=plans.index)
    if twice:
        ap.error(f"--plans names {', '.join(twice)} more than once; give each plan once")
    log = (lambda m: print(m, file=sys.stderr, flush=True)) if a.json else print
    t0 = time.perf_counter()
    runs: dict[str, list[dict]] = {p: [] for p in plans}
    for s in range(a.seed0, a.seed0 + a.seeds):
        for p in plans:
            runs[p].append(
                one_run(
                    p,
                    s,
                    a.max_poses,
                    a.holdout,
                    log,
                    a.target_factor,
                    a.envelope,
                    a.half_width_deg,
                    a.robot,
                    a.small_errors,
                )  # fmt: skip
            )
    summary = summarise(runs)
    best, r = best_vs_random(summary)
    ratio = {"plan": best, "ratio": r} if best else None
    floors = [r["noise_floor_m"] for rs in runs.values() for r in rs]
    # No plan can reach the target with fewer poses than Theorem 1's rank bound ceil(L / 3):
    # the best ratio any design could show against this random baseline.
    bound = float(np.mean([r["rank_bound_poses"] for rs in runs.values() for r in rs]))
    out = {
        "robot": a.robot,
        "effects": "none (DH, base and SMR errors only)"
        if a.robot == "ur5e"
        else "none; DH errors of seed 002 section V-A (theta7 +1.3 rad, alpha2 +0.4 rad, "
        "a3 +10 mm, d3 +150 mm)" + (" plus small random DH errors" if a.small_errors else ""),
        "seeds": list(range(a.seed0, a.seed0 + a.seeds)),
        "max_poses": a.max_poses,
        "heldout_poses": a.holdout,
        "envelope": a.envelope
        if a.envelope == "default"
        else f"compact (+-{a.half_width_deg:g} deg around home)",
        "target": f"held-out RMS <= {a.target_factor:g} x noise floor",
        "scoring": f"each cell's fits are scored on {a.holdout} extra held-out poses (measured "
        "on top of the plan's poses); poses_to_target is the first pose count whose held-out "
        f"RMS is <= the target (first passage); stayed_below_after: runs whose next {AFTER} "
        "poses' fits stayed at or below it",
        "noise_floor_m": {
            "mean": float(np.mean(floors)),
            "min": float(np.min(floors)),
            "max": float(np.max(floors)),
        },
        "poses_to_target": summary,
        "ratio_best_to_random": ratio["ratio"] if ratio else None,
        "ratio_best_to_random_ci95": ratio_intervals(summary).get(best) if best else None,
        "ratios_to_random": ratios_to_random(summary),
        "ratios_to_random_ci95": ratio_intervals(summary),
        "ratio_ci_basis": RATIO_CI_BASIS,
        "rank_bound_poses": bound,
        "best_possible_ratio": bound / summary["random"]["mean"] if "random" in summary else None,
        "best_plan": ratio["plan"] if ratio else None,
        "wall_seconds": time.perf_counter() - t0,
    }
    if a.runs:
        out["runs"] = runs
    out["environment"] = environment()
    if a.json:
        print(json.dumps(out))
        return 0
    print()
    print(
        f"poses to target: the first pose count whose held-out RMS (on {a.holdout} extra "
        "held-out poses per cell) is <= the target; the runs then go on for "
        f"{AFTER} poses to see if it stays there"
    )
    print(f"{'plan':8}{'mean':>8}{'std':>8}{'median':>8}  runs (poses to target)")
    for p, r in summary.items():
        cens = f"  [{r['censored']} not reached]" if r["censored"] else ""
        rb = r.get("rms_over_floor_at_rank_bound")
        at = (
            f"  at the rank bound RMS/floor median {rb['median']:.2f}, max {rb['max']:.2f}"
            if rb
            else ""
        )
        sb = r["stayed_below_after"]
        stay = f"  stayed at the target {sb['stayed']}/{sb['checked']}" if sb["checked"] else ""
        print(
            f"{p:8}{r['mean']:8.1f}{r['std']:8.1f}{r['median']:8.1f}  {r['runs']}{cens}{at}{stay}"
        )
    fl = out["noise_floor_m"]
    print(
        f"noise floor {fl['mean'] * 1e6:.1f} um (mean over cells); target {a.target_factor:g}x "
        f"floor; envelope {out['envelope']}"
    )
    if ratio:
        print(ratio_line(out, ratio["plan"], f"rank bound {bound:g} poses"))
    print(f"wall {out['wall_seconds']:.0f} s")
    return 0
