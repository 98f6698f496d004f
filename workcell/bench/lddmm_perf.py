"""`workcell bench lddmm [--json]`: LDDMM performance against the issue's targets.

1. pendulum fit time: the `lddmm-pendulum` link-length scenario (169 grid points, width CV,
   L-BFGS max_iter 100, 10 RK4 steps), cold (includes JAX compilation) and warm (target <= 5 s).
2. 6-joint fit time for 500 poses: a simulated UR5e recording (joint compliance + transmission
   error, 500 poses, all used for training) fitted with `fit --method lddmm --on dh` (DH fit,
   linearised CV of widths and sigma, L-BFGS shooting, Jacobian check, evaluation tuning)
   (target <= 60 s). The recording itself is simulated first and not timed.
3. evaluation throughput of that fitted model: `predict` on random configurations in the
   training box (warm, after one call per bucket; the median of 3 timed runs), with the reference evaluation (the fit's RK4
   steps, float64) and with the tuned one (fewest steps / float32 / frozen Jacobian, within 10 nm
   of the reference
   on the training poses and random configurations); the max deviation between the two on
   the throughput points is reported (target >= 100,000 points/s).
Times are wall-clock on this machine; the 1-minute load average is reported with them.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from workcell.bench import check_ranges, environment
from workcell.errors import OneLineParser

TARGETS = {"pendulum_fit_s": 5.0, "fit_500_s": 60.0, "eval_points_per_s": 100_000.0}
EVAL_RUNS = 3  # timed evaluations of all the points; the figure is their median


def _load() -> float:
    try:
        return float(os.getloadavg()[0])
    except OSError:
        return float("nan")


def bench_pendulum() -> dict:
    from workcell.bench.lddmm_pendulum import SCENARIOS, datasets, k0
    from workcell.estimation.lddmm import fit_lddmm

    X, _ = datasets()
    Y = SCENARIOS["link_lengths"](X)
    out = {}
    for tag in ("cold", "warm"):
        t0 = time.perf_counter()
        m = fit_lddmm(k0, X, Y, sigma=0.1, n_steps=10, max_iter=100)
        out[f"fit_{tag}_s"] = time.perf_counter() - t0
    out["lbfgs_iterations"] = m.info.n_iter
    out["load_avg_1min"] = _load()
    return out


def _recording(poses: int, seed: int, tmp: str):
    from sim_devices.cell import sim_cell
    from workcell.campaign.run import run_campaign
    from workcell.recording.dataset import Dataset

    p = Path(tmp) / f"ur5e_{poses}.mcap"
    _, robot, tracker, cell = sim_cell("ur5e", "joint_compliance,transmission_error", seed)
    run_campaign(robot, tracker, cell, p, poses=poses, seed=seed)
    return Dataset.from_recording(p)


def bench_6dof(poses: int = 500, n_eval: int = 100_000, seed: int = 5) -> dict:
    from workcell.estimation.fitting import fit_dataset
    from workcell.estimation.lddmm.model import PREDICT_BATCH

    with tempfile.TemporaryDirectory() as tmp:
        ds = _recording(poses, seed, tmp)
    t0 = time.perf_counter()
    model, rep = fit_dataset(ds, method="lddmm", holdout=0.0, on="dh")
    fit_s = time.perf_counter() - t0
    load_fit = _load()
    e = rep["extra"]
    lm = model.lddmm
    rng = np.random.default_rng(1)
    q = rng.uniform(ds.q.min(0), ds.q.max(0), size=(n_eval, 6))
    res = {
        "poses": int(len(ds)),
        "fit_s": fit_s,
        "fit_lddmm_only_s": e["lddmm_fit_seconds"],
        "fit_load_avg_1min": load_fit,
        "train_rms_before_m": e["train_rms_before_m"],
        "train_rms_after_m": e["train_rms_after_m"],
        "sigma_v_rad": e["sigma_v_rad"],
        "sigma_w_m": e["sigma_w_m"],
        "sigma": e["sigma"],
        "min_jacobian_det": min(e["min_jacobian_det_phi"], e["min_jacobian_det_psi"]),
        "evaluation": e["evaluation"],
    }
    tuned = (lm.eval_steps, lm.eval_float32, lm.eval_frozen_jacobian)
    preds = {}
    b = PREDICT_BATCH
    for tag, cfg in (("reference", (None, False, False)), ("tuned", tuned)):
        lm.set_evaluation(*cfg)
        lm.predict(q[:b])  # compile the full bucket
        lm.predict(q[: n_eval % b or b])  # and the tail bucket
        rates = []
        for _ in range(EVAL_RUNS):
            t0 = time.perf_counter()
            preds[tag] = model.predict(q)
            rates.append(n_eval / (time.perf_counter() - t0))
        res[f"eval_{tag}_points_per_s"] = float(np.median(rates))
        res[f"eval_{tag}_points_per_s_runs"] = rates
        res[f"eval_{tag}_steps"] = lm.eval_steps
        res[f"eval_{tag}_float32"] = lm.eval_float32
        res[f"eval_{tag}_frozen_jacobian"] = lm.eval_frozen_jacobian
    res["eval_load_avg_1min"] = _load()
    res["eval_points"] = n_eval
    res["eval_tuned_max_dev_m"] = float(
        np.max(np.linalg.norm(preds["tuned"] - preds["reference"], axis=1))
    )
    return res


def main(argv: list[str]) -> int:
    ap = OneLineParser(prog="workcell bench lddmm", description=__doc__.split("\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    ap.add_argument("--poses", type=int, default=500, help="poses of the 6-joint recording")
    ap.add_argument("--eval-points", type=int, default=100_000, help="points for the throughput")
    ap.add_argument("--skip-pendulum", action="store_true")
    args = ap.parse_args(argv)
    check_ranges(
        ap, [("--poses", args.poses, 12, 20_000), ("--eval-points", args.eval_points, 1, 10**8)]
    )
    doc: dict = {"targets": TARGETS, "cpu_count": os.cpu_count()}
    if not args.skip_pendulum:
        doc["pendulum"] = bench_pendulum()
    doc["six_joint"] = bench_6dof(args.poses, args.eval_points)
    s = doc["six_joint"]
    met = {
        "fit_500_s": s["fit_s"] <= TARGETS["fit_500_s"],
        "eval_points_per_s": s["eval_tuned_points_per_s"] >= TARGETS["eval_points_per_s"],
    }
    if "pendulum" in doc:
        met["pendulum_fit_s"] = doc["pendulum"]["fit_warm_s"] <= TARGETS["pendulum_fit_s"]
    doc["met"] = met
    doc["environment"] = environment()
    if args.json:
        json.dump(doc, sys.stdout)
        sys.stdout.write("\n")
        return 0
    if "pendulum" in doc:
        p = doc["pendulum"]
        print(
            f"pendulum fit (169 pts): cold {p['fit_cold_s']:.2f} s, warm {p['fit_warm_s']:.2f} s"
            f" (target <= 5 s; load {p['load_avg_1min']:.1f})"
        )
    print(
        f"6-joint fit ({s['poses']} poses, --on dh): {s['fit_s']:.1f} s, of which LDDMM shooting"
        f" {s['fit_lddmm_only_s']:.1f} s (target <= 60 s; load {s['fit_load_avg_1min']:.1f});"
        f" train RMS {s['train_rms_before_m'] * 1e6:.1f} -> {s['train_rms_after_m'] * 1e6:.1f} um"
    )
    print(
        f"evaluation ({s['eval_points']} pts): reference ({s['eval_reference_steps']} RK4 steps,"
        f" float64) {s['eval_reference_points_per_s']:,.0f} pts/s; tuned"
        f" ({s['eval_tuned_steps']} steps, float32={s['eval_tuned_float32']},"
        f" frozen Jacobian={s['eval_tuned_frozen_jacobian']})"
        f" {s['eval_tuned_points_per_s']:,.0f} pts/s (median of"
        f" {', '.join(f'{r:,.0f}' for r in s['eval_tuned_points_per_s_runs'])}), max deviation"
        f" {s['eval_tuned_max_dev_m'] * 1e9:.2f} nm (target >= 100,000 pts/s;"
        f" load {s['eval_load_avg_1min']:.1f})"
    )
    print("targets met:", ", ".join(f"{k}={v}" for k, v in met.items()))
    return 0
