"""`workcell bench dh [--json] [--poses N]`: speed of the geometric fit and of FK/Jacobians.

Simulated UR5e, DH errors + tracker noise only, in-process campaign (virtual time). Prints the
fit time (first call includes JIT compilation), the compiled fit time, FK and Jacobian
throughput; the compiled figures are the median of `--repeats` timed runs, with their range
(a shared 2-core machine moves single runs by tens of per cent).
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

from workcell.bench import check_ranges, environment
from workcell.errors import OneLineParser


def main(argv: list[str]) -> int:
    ap = OneLineParser(prog="workcell bench dh")
    ap.add_argument("--poses", type=int, default=500)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs of each compiled figure")
    a = ap.parse_args(argv)
    check_ranges(ap, [("--poses", a.poses, 12, 20_000), ("--repeats", a.repeats, 1, 100)])
    from sim_devices.cell import sim_cell
    from workcell.campaign.executor import CampaignConfig
    from workcell.campaign.run import run_campaign
    from workcell.estimation.dh import fit_dh
    from workcell.kinematics.chain import jac_params, p_tracker
    from workcell.recording.dataset import Dataset

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "b.mcap"
        _, robot, tracker, cell = sim_cell("ur5e", "none", 3)
        t0 = time.perf_counter()
        run_campaign(
            robot,
            tracker,
            cell,
            p,
            poses=a.poses,
            seed=3,
            config=CampaignConfig(readings_per_pose=3, payload_kg=cell.payload_kg),
        )
        camp_s = time.perf_counter() - t0
        ds = Dataset.from_recording(p)
    t0 = time.perf_counter()
    m = fit_dh(ds)
    first = time.perf_counter() - t0

    def timed(fn) -> float:
        t0 = time.perf_counter()
        fn()
        return time.perf_counter() - t0

    fits = [timed(lambda: fit_dh(ds)) for _ in range(a.repeats)]
    q = np.random.default_rng(0).uniform(-3, 3, (100_000, 6))
    np.asarray(p_tracker(m.theta, m.base_ref, q[:10]))
    fks = [
        len(q) / timed(lambda: np.asarray(p_tracker(m.theta, m.base_ref, q)))
        for _ in range(a.repeats)
    ]
    qj = q[:10_000]
    np.asarray(jac_params(m.theta, m.base_ref, qj[:10]))
    jacs = [
        len(qj) / timed(lambda: np.asarray(jac_params(m.theta, m.base_ref, qj)))
        for _ in range(a.repeats)
    ]
    second, fk, jac = (float(np.median(v)) for v in (fits, fks, jacs))
    out = {
        "poses": len(ds),
        "campaign_wall_s": camp_s,
        "fit_seconds_first": first,
        "fit_seconds_compiled": second,  # median of the runs
        "fit_seconds_compiled_runs": fits,
        "fk_points_per_s": fk,
        "fk_points_per_s_runs": fks,
        "jacobian_points_per_s": jac,
        "jacobian_points_per_s_runs": jacs,
        "repeats": a.repeats,
        "train_rms_m": m.info["train_rms_m"],
        "environment": environment(),
    }
    if a.json:
        print(json.dumps(out))
    else:
        n = f"median of {a.repeats}"
        print(
            f"DH fit, {out['poses']} poses: {first:.2f} s (first, incl. JIT), "
            f"{second:.2f} s (compiled; {n}, {min(fits):.2f}-{max(fits):.2f})"
        )
        print(f"simulated campaign of {out['poses']} poses: {camp_s:.1f} s wall (virtual time)")
        print(
            f"forward kinematics: {fk:,.0f} poses/s ({min(fks):,.0f}-{max(fks):,.0f}); parameter "
            f"Jacobian: {jac:,.0f} poses/s ({min(jacs):,.0f}-{max(jacs):,.0f}); {n}"
        )
    return 0
