"""Coverage of the 95 % interval beside every held-out RMS (`models.rms_interval`), against the
bootstrap alone (`models._bootstrap_interval`), the study behind README "Beside every held-out
RMS". Run: `.venv/bin/python docs/rms_interval_coverage.py [--campaigns K]` (~3 min at K=40).

1. Synthetic per-pose 3-D errors: isotropic Gaussian (n = 8, 12 poses) and heteroscedastic
   (per-pose scale lognormal, sd 0.6; n = 10, 20), 400 draws each; the true RMS is known.
2. Simulated DH fits: a realistic UR5e cell (`sim_devices`, truth used only to score), N poses
   fitted with `fit_dataset` (25 % held out), the truth being the same model's RMS on 200 fresh
   poses of the same campaign; N = 40 (10 held out) and 80 (20 held out), K truth seeds each.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from workcell.estimation import models as M


def _both(e: np.ndarray) -> tuple[tuple[float, float], tuple[float, float]]:
    return M.rms_interval(e), M._bootstrap_interval((e,), M._rms, 0.95, 0)


def synthetic(trials: int = 400) -> None:
    for name, n in (("gaussian", 8), ("gaussian", 12), ("heteroscedastic", 10),
                    ("heteroscedastic", 20)):  # fmt: skip
        rng = np.random.default_rng(11)
        true = np.sqrt(3.0) * (np.exp(0.18) if name == "heteroscedastic" else 1.0)
        hit = np.zeros(2)
        for _ in range(trials):
            x = rng.normal(0.0, 1.0, (n, 3))
            if name == "heteroscedastic":
                x *= np.exp(rng.normal(0.0, 0.6, (n, 1)))
            for k, (lo, hi) in enumerate(_both(np.linalg.norm(x, axis=1))):
                hit[k] += lo <= true <= hi
        print(
            f"{name:16s} n={n:3d}: combined {hit[0] / trials:.3f}, bootstrap {hit[1] / trials:.3f}"
        )


def fits(n_poses: int, campaigns: int, tmp: Path) -> None:
    from sim_devices.truth import make_truth
    from workcell.bench.discovery import simulate_recording
    from workcell.estimation.fitting import fit_dataset
    from workcell.recording.dataset import Dataset

    hit, done = np.zeros(2), 0
    for seed in range(campaigns):
        p = tmp / f"c{n_poses}-{seed}.mcap"
        try:
            simulate_recording(make_truth("ur5e", "realistic", 300 + seed), n_poses + 200,
                               300 + seed, p, readings=3)  # fmt: skip
        except ValueError:  # the random plan found too few poses in the envelope: skip
            continue
        ds = Dataset.from_recording(p)
        perm = np.random.default_rng(seed).permutation(len(ds))
        sub, pop = ds.subset(np.sort(perm[:n_poses])), ds.subset(np.sort(perm[n_poses:]))
        model, _ = fit_dataset(sub, method="dh")
        e = np.linalg.norm(model.predict(pop.q) - pop.p_tracker, axis=1)
        true = float(np.sqrt(np.mean(e**2)))
        _, te = sub.holdout_split()
        eh = np.linalg.norm(model.predict(sub.q[te]) - sub.p_tracker[te], axis=1)
        for k, (lo, hi) in enumerate(_both(eh)):
            hit[k] += lo <= true <= hi
        done += 1
    if not done:
        print(f"dh fits, {n_poses} poses: no campaign ran")
        return
    print(
        f"dh fits, {n_poses} poses ({n_poses // 4} held out), {done} campaigns: "
        f"combined {hit[0] / done:.3f}, bootstrap {hit[1] / done:.3f}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--campaigns", type=int, default=40)
    a = ap.parse_args()
    synthetic()
    with tempfile.TemporaryDirectory() as d:
        for n in (40, 80):
            fits(n, a.campaigns, Path(d))


if __name__ == "__main__":
    main()
