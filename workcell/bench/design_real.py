"""`workcell bench design-real [--recording PATH] [--json]`: does the choice of poses save tracker
time on a real robot? Experiment design (seed 002) replayed over the poses of a real recording.

Setting: a recording of a real arm measured by a tracker; default the UR10 + Leica series B of
`../shared/data/ur10-leica` (1495 joint configurations spread over the workspace). Nobody on
this project made these numbers.

Split: the project's held-out split (`Dataset.holdout_split`, seeded, 25 % held out, the split
`workcell fit` uses). The other poses are the candidate pool. Each plan chooses poses one at a
time from the pool and "measures" a pose by reading its recorded tracker position:
``random`` (a seeded random order of the pool), ``dopt``, ``vopt`` and ``bo`` (the campaign plans' code,
`workcell.campaign.adaptive.plan_over_candidates`, fed the recorded samples as a campaign would).

Fitted model: the DH fit (`fit_dh_bounded(bounds=None)`, as `workcell bench design`) on the
poses chosen so far, evaluated on the held-out poses. On real data the held-out RMS does not
go down to the tracker noise: effects a DH model cannot express remain (joint compliance,
transmission error...). The reference is therefore the DH fit on the *whole pool*, R_pool, what
this model reaches with all the data; the target is a held-out RMS <= (1 + tolerance) R_pool
(`--tolerance`, default 0.10). Poses to target is the smallest n (from the rank bound
ceil(L / 3) on; every n up to 40, then every 5th) that reaches it; a run that does not within `--max-poses` counts as
max-poses + 1 (`censored`). `ratio_best_to_random` = mean poses of the best adaptive plan over
random's (`ratios_to_random`: each plan's); `best_possible_ratio` = rank bound over random's mean.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from workcell.bench import check_ranges, environment
from workcell.errors import OneLineParser

PLANS = ("random", "dopt", "vopt", "bo")
DENSE_UNTIL, COARSE_STEP = 40, 5  # evaluate after every pose up to 40, then every 5th
DEFAULT_RECORDING = (
    Path(__file__).resolve().parents[3]
    / "shared"
    / "data"
    / "ur10-leica"
    / "series_B_joint_configurations.mcap"
)


def _heldout_rms(model, ds_test) -> float:
    from workcell.estimation.bounded import predict_padded

    err = predict_padded(model.theta, model.base_ref, ds_test.q) - ds_test.p_tracker
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


# the seeds here are orders of one recording's poses, not simulated cells (design.RATIO_CI_BASIS)
RATIO_CI_BASIS_REAL = (
    "95 % interval of a plan's mean poses over random's: paired bootstrap over the seeds (each "
    "seed is one random order of this recording's poses and one seed of each plan; BCa, "
    "percentile when BCa is degenerate). It is the spread over those orders on this one cell "
    "and its one set of measurements, not over cells"
)


def one_run(plan: str, seed: int, pool, test, n_min: int, target_m: float, max_poses: int) -> dict:
    """Poses one plan needs from `pool` (Dataset) until the held-out RMS on `test` <= target."""
    from workcell.campaign.adaptive import plan_over_candidates
    from workcell.estimation.bounded import fit_dh_bounded

    chosen: list[int] = []
    curve: list[tuple[int, float]] = []

    def reached() -> bool:
        n = len(chosen)
        if n < n_min or (n > DENSE_UNTIL and n % COARSE_STEP):
            return False
        try:
            m = fit_dh_bounded(pool.subset(np.array(chosen)), bounds=None, min_poses=n_min)
        except (ValueError, np.linalg.LinAlgError):
            return False
        curve.append((len(chosen), _heldout_rms(m, test)))
        return curve[-1][1] <= target_m

    t0 = time.perf_counter()
    done = False
    if plan == "random":
        for i in np.random.default_rng(seed).permutation(len(pool))[:max_poses]:
            chosen.append(int(i))
            if reached():
                done = True
                break
    else:
        picks: list[int] = []
        gen = plan_over_candidates(
            plan, pool.robot, pool.q, np.zeros_like(pool.q), pool.tool_offset_m,
            list(range(max_poses)), seed=seed, on_choice=lambda c: picks.append(c["candidate"]),
        )  # fmt: skip
        try:
            next(gen)
            while True:
                i = picks[-1]
                chosen.append(i)
                if reached():
                    done = True
                    gen.close()
                    break
                sample = {
                    "q_measured_rad": pool.q[i].tolist(),
                    "tracker_position_m": pool.p_tracker[i].tolist(),
                    "tracker_sigma_m": pool.sigma_m[i].tolist(),
                }
                gen.send(sample)
        except StopIteration:
            pass
    return {
        "plan": plan,
        "seed": seed,
        "poses_to_target": len(chosen) if done else max_poses + 1,
        "censored": not done,
        "curve": curve,
        "seconds": time.perf_counter() - t0,
    }


def main(argv: list[str]) -> int:
    ap = OneLineParser(prog="workcell bench design-real", description=__doc__.split("\n")[0])
    ap.add_argument(
        "--recording",
        default=str(DEFAULT_RECORDING),
        help="real recording (.mcap); default: the UR10 series B in ../shared beside a source "
        f"checkout ({DEFAULT_RECORDING})",
    )
    ap.add_argument("--seeds", type=int, default=10, help="random orders / plan seeds (>= 1)")
    ap.add_argument("--max-poses", type=int, default=150, help="poses per run at most")
    ap.add_argument("--tolerance", type=float, default=0.10, help="target: <= (1 + this) R_pool")
    ap.add_argument("--plans", default=",".join(PLANS), help=f"comma list of {','.join(PLANS)}")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    a = ap.parse_args(argv)
    plans = [p.strip() for p in a.plans.split(",") if p.strip()]
    for p in plans:
        if p not in PLANS:
            ap.error(f"unknown plan {p!r}; choose from {', '.join(PLANS)}")
    if not math.isfinite(a.tolerance):
        ap.error(f"--tolerance must be a number, got {a.tolerance}")
    check_ranges(
        ap,
        [
            ("--seeds", a.seeds, 1, 1000),
            ("--max-poses", a.max_poses, 12, 100_000),
            ("--tolerance", a.tolerance, 1e-6, 10.0),
        ],
    )
    path = Path(a.recording)
    if not path.is_file():
        what = (
            "is a folder, not a recording file"
            if path.is_dir()
            else "is not a regular file (a pipe or device)"
            if path.exists()
            else "not found"
        )
        print(
            f"workcell bench design-real: recording {path} {what} "
            "(give --recording PATH; the default is the UR10 series B in ../shared beside a "
            "source checkout, which an installed package does not have)",
            file=sys.stderr,
        )
        return 2
    from workcell.bench.design import (
        best_vs_random,
        poses_summary,
        ratio_intervals,
        ratio_line,
        ratios_to_random,
    )
    from workcell.campaign.adaptive import identifiable_mask
    from workcell.estimation.bounded import fit_dh_bounded, jacobian_padded
    from workcell.kinematics.chain import pack
    from workcell.recording.dataset import Dataset
    from workcell.recording.reader import RecordingError

    try:
        ds = Dataset.from_recording(path)
    except RecordingError as e:
        print(f"workcell bench design-real: {e}", file=sys.stderr)
        return 2
    log = (lambda m: print(m, file=sys.stderr, flush=True)) if a.json else print
    t0 = time.perf_counter()
    train, test_idx = ds.holdout_split(0.25)
    pool, test = ds.subset(train), ds.subset(test_idx)
    ref = fit_dh_bounded(pool, bounds=None)
    r_pool = _heldout_rms(ref, test)
    th = pack(ds.robot.dh, tool=ds.tool_offset_m)
    L = int(identifiable_mask(ds.robot, jacobian_padded(th, np.eye(4), pool.q)).sum())
    n_min = int(math.ceil(L / 3))
    target = (1.0 + a.tolerance) * r_pool
    log(
        f"{path.name}: {len(pool)} candidate poses, {len(test)} held out; DH fit on the whole "
        f"pool: held-out RMS {r_pool * 1e6:.1f} um; target <= {target * 1e6:.1f} um; "
        f"rank bound {n_min} poses ({L} parameters)"
    )
    runs: dict[str, list[dict]] = {p: [] for p in plans}
    for s in range(a.seeds):
        for p in plans:
            r = one_run(p, s, pool, test, n_min, target, a.max_poses)
            runs[p].append(r)
            last = r["curve"][-1][1] * 1e6 if r["curve"] else float("nan")
            log(
                f"  {p:6s} seed {s:2d}: {r['poses_to_target']:3d} poses"
                f"{' (not reached)' if r['censored'] else ''}; last held-out RMS {last:.1f} um "
                f"({r['seconds']:.1f} s)"
            )
    summary = {p: poses_summary(rs) for p, rs in runs.items()}
    best, ratio = best_vs_random(summary)
    out = {
        "recording": str(path),
        "candidate_poses": len(pool),
        "heldout_poses": len(test),
        "pool_fit_heldout_rms_m": r_pool,
        "target": f"held-out RMS <= {1 + a.tolerance:g} x the whole-pool DH fit's",
        "target_m": target,
        "rank_bound_poses": n_min,
        "poses_to_target": summary,
        "ratio_best_to_random": ratio,
        "ratio_best_to_random_ci95": ratio_intervals(summary).get(best) if best else None,
        "ratios_to_random": ratios_to_random(summary),
        "ratios_to_random_ci95": ratio_intervals(summary),
        "ratio_ci_basis": RATIO_CI_BASIS_REAL,
        "best_plan": best,
        "best_possible_ratio": n_min / summary["random"]["mean"] if "random" in summary else None,
        "wall_seconds": time.perf_counter() - t0,
        "environment": environment(),
    }
    if a.json:
        print(json.dumps(out))
        return 0
    print()
    print(f"{'plan':8}{'mean':>8}{'std':>8}{'median':>8}  runs (poses to target)")
    for p, r in summary.items():
        cens = f"  [{r['censored']} not reached]" if r["censored"] else ""
        print(f"{p:8}{r['mean']:8.1f}{r['std']:8.1f}{r['median']:8.1f}  {r['runs']}{cens}")
    if ratio is not None:
        print(ratio_line(out, best, f"rank bound {n_min} poses"))
    print(f"wall {out['wall_seconds']:.0f} s")
    return 0
