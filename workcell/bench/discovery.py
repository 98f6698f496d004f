"""`workcell bench discovery [--json] [--draws N] [--poses N] [--quick] [--seed S]`.

Proof of discrepancy discovery on simulated recordings where the effect is concealed:
- the simulated truth (sim_devices) always has geometric errors and realistic tracker noise
  (per-pose systematic + random parts, beam breaks, outliers); a fresh random seed per case;
- one recording per effect kind and per joint where it makes sense (compliance of joints 2-5,
  deflection of links 2 and 3, transmission error of joints 1-5 at a random harmonic order 1-3,
  backlash of joints 1-5, thermal drift), pairs of effects of different kinds, and clean
  recordings (geometry only);
- each effect is scaled so that the geometry-only residual it leaves is 2-10x the noise floor
  (target ratio drawn log-uniformly per case): the harness computes, from the truth, the part of
  the effect's signature that a geometric calibration cannot absorb on this case's poses, and
  scales the effect's parameters to reach the target;
- 300 random poses (random approach direction per joint), a random warm-up of 0-15 min;
- recordings are written as MCAP and read back like any recording; diagnosis sees only the file.
Extra reported cases (not in the accuracy): `tracker_scale` (not identifiable with a point-only
tracker; the correct answer is "absorbed, not claimed"), `unknown` (an effect outside the
library: joint 3's angle shifted by A sin(2 q2), a cross-coupling) and `pedestal_tilt` (the
simulator's pedestal yielding to the arm's overturning moment, also outside the library): they
should be reported as unexplained, located, and reduced by the non-parametric model; library
terms that stand in for them are flagged (a sign the physics excludes, or a final model whose
held-out RMS interval stays above the noise floor).

Scoring: a single case is right when the named non-geometric effects are exactly the true one
(kind and joint); a pair is right when both true effects are named (extra claims make it wrong);
a clean case is a false alarm when any non-geometric effect is claimed. The truth is used only to
build and score the cases.
"""

from __future__ import annotations

import copy
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from workcell.atomic import write_text
from workcell.bench import check_bench_outputs, environment
from workcell.errors import OneLineParser, UserError, check_output_path
from workcell.kinematics.chain import jac_params, pack

SINGLE_CASES: list[tuple[str, int | None]] = (
    [("joint_compliance", j) for j in (2, 3, 4, 5)]
    + [("link_deflection", link) for link in (2, 3)]
    + [("transmission_error", j) for j in (1, 2, 3, 4, 5)]
    + [("backlash", j) for j in (1, 2, 3, 4, 5)]
    + [("thermal_drift", None)]
)


def unit_effect(kind: str, joint: int | None, rng: np.random.Generator) -> dict:
    """The effect's parameters at a nominal size (scaled later), in the simulator's format."""
    if kind == "joint_compliance":
        c = [0.0] * 6
        c[joint - 1] = 1e-5
        return {"c_rad_per_nm": c}
    if kind == "link_deflection":
        f = [0.0, 0.0]
        f[joint - 2] = 3e-7
        return {"flex_m_per_n": f}
    if kind == "transmission_error":
        k = int(rng.integers(1, 4))
        return {"harmonics": {joint - 1: [(k, 30e-6, float(rng.uniform(-np.pi, np.pi)))]}}
    if kind == "backlash":
        b = [0.0] * 6
        b[joint - 1] = 60e-6
        return {"b_rad": b}
    if kind == "thermal_drift":
        return {"alpha_per_k": 23e-6, "warmup_k": [6.0, 8.0, 7.0, 4.0, 4.0, 3.0], "tau_s": 1200.0}
    if kind == "tracker_scale":
        return {"scale": 15e-6}
    if kind == "pedestal_tilt":
        return {"k_rad_per_nm": 1e-6, "pivot_below_m": 0.5}
    raise ValueError(kind)


def scale_effect(kind: str, params: dict, s: float) -> dict:
    p = copy.deepcopy(params)
    if kind == "joint_compliance":
        p["c_rad_per_nm"] = [s * x for x in p["c_rad_per_nm"]]
    elif kind == "link_deflection":
        p["flex_m_per_n"] = [s * x for x in p["flex_m_per_n"]]
    elif kind == "transmission_error":
        p["harmonics"] = {j: [(k, s * a, ph) for k, a, ph in h] for j, h in p["harmonics"].items()}
    elif kind == "backlash":
        p["b_rad"] = [s * x for x in p["b_rad"]]
    elif kind == "thermal_drift":
        p["alpha_per_k"] = s * p["alpha_per_k"]
    elif kind == "tracker_scale":
        p["scale"] = s * p["scale"]
    elif kind == "pedestal_tilt":
        p["k_rad_per_nm"] = s * p["k_rad_per_nm"]
    elif kind == "unknown":
        p["amp_rad"] = s * p["amp_rad"]
    return p


# ----------------------------------------------------------------------------- simulation
def _unknown_truth(truth, amp_rad: float):
    """A truth with an effect outside the library: joint 3 shifted by amp * sin(2 q2)."""
    base_cls = type(truth)

    class _Coupled(base_cls):  # type: ignore[misc, valid-type]
        def link_angles(self, q_enc, approach_sign):
            q = super().link_angles(q_enc, approach_sign)
            q = np.array(q, float)
            q[2] += self._amp * np.sin(2.0 * np.asarray(q_enc, float)[1])
            return q

    t = copy.copy(truth)
    t.__class__ = _Coupled
    t._amp = amp_rad
    return t


def plan_targets(spec, n: int, seed: int):
    from sim_devices.truth import NOMINAL_SMR_M
    from workcell.campaign.envelope import default_envelope
    from workcell.campaign.plans import make_plan

    gen, _ = make_plan(
        "random",
        spec,
        default_envelope(spec),
        n,
        seed=seed,
        tool_m=NOMINAL_SMR_M,
        approach_rad=0.02,
    )
    return list(gen)


def simulate_recording(
    truth,
    n_poses: int,
    seed: int,
    out: str | Path,
    *,
    warmup_s: float = 0.0,
    targets=None,
    readings: int = 5,
) -> Path:
    """Drive a SimWorld through a random plan (pre-pose approach, settle, 5 readings) and write
    an MCAP recording in the shared format. Like the campaign executor, without its per-state
    gravity-torque polling (which dominates its run time in virtual time)."""
    from sim_devices.cell import declared_cell
    from sim_devices.world import SimWorld
    from workcell.campaign.executor import CampaignConfig, reject_outliers
    from workcell.recording.writer import RecordingWriter

    cfg = CampaignConfig()
    world = SimWorld(truth, seed=seed)
    rng = np.random.default_rng(seed + 5)
    cell = declared_cell(truth, seed)
    targets = plan_targets(truth.nominal, n_poses, seed) if targets is None else targets
    session = cell.session(
        {
            "plan": "random",
            "poses": n_poses,
            "seed": seed,
            "warmup_s": warmup_s,
            "generator": "workcell bench discovery",
        }
    )
    world.clock.advance(warmup_s)
    with RecordingWriter(out, session) as w:
        t0_ns = time.time_ns()  # the campaign starts now, after its session; virtual time on
        k = 0  # samples written: `index` is the order of measurement (a skipped pose has none)
        for t in targets:
            pre = t.q_rad - np.sign(t.approach_sign) * 0.02
            for q in (pre, t.q_rad):
                world.clock.advance(world.command_move(q, cfg.speed_rad_s, cfg.accel_rad_s2))
            world.clock.advance(cfg.settle_s)
            good = []
            fails = 0
            while len(good) < readings and fails <= cfg.max_beam_retries:
                p, status = world.read_tracker()
                world.clock.advance(0.1)
                if status != "ok":
                    fails += 1
                    world.clock.advance(cfg.beam_retry_wait_s)
                    continue
                good.append((p, world.stated_sigma_m(p)))
            # as the campaign executor: at least half the readings (two when more than one)
            if len(good) < (max(2, (readings + 1) // 2) if readings > 1 else 1):
                continue
            P = np.array([g[0] for g in good])
            S = np.array([g[1] for g in good])
            keep = reject_outliers(P, S, cfg.outlier_k)
            P, S = P[keep], S[keep]
            if len(P) > 1:
                sig = np.maximum(P.std(0, ddof=1), S.mean(0) / 4) / np.sqrt(len(P))
            else:
                sig = S[0]
            q_meas = t.q_rad + rng.normal(0.0, 2e-6, (len(good), 6)).mean(0)
            e = world.clock.now() - warmup_s
            w.sample(
                t0_ns + int(e * 1e9),
                {
                    "index": k,
                    "pose_id": int(t.pose_id),
                    "q_commanded_rad": np.asarray(t.q_rad, float).tolist(),
                    "q_measured_rad": q_meas.tolist(),
                    "approach_sign": [int(s) for s in np.sign(t.approach_sign)],
                    "tracker_position_m": P.mean(0).tolist(),
                    "tracker_sigma_m": sig.tolist(),
                    "n_readings": int(len(P)),
                    "joint_temperature_c": world.joint_temperatures_c().tolist(),
                    "ambient_temperature_c": None,
                    "elapsed_s": float(e),
                    "payload_kg": float(truth.declared_payload_kg),
                },
            )
            k += 1
    return Path(out)


def concealed_rms(truth, effects: dict, targets, warmup_s: float, unknown_amp=None) -> float:
    """RMS of the part of the effects' signature a geometric calibration cannot absorb, on these
    poses (noise-free, from the truth), in metres."""
    n = len(targets)
    q = np.array([t.q_rad for t in targets])
    sg = np.array([np.sign(t.approach_sign) for t in targets])
    tt = warmup_s + 6.0 * np.arange(n)  # about 6 s per pose
    t_on = copy.deepcopy(truth)
    t_on.effects = effects
    if unknown_amp is not None:
        t_on = _unknown_truth(t_on, unknown_amp)
    t_off = copy.deepcopy(truth)
    t_off.effects = {}
    d = np.array(
        [
            t_on.smr_in_tracker(q[i], sg[i], tt[i]) - t_off.smr_in_tracker(q[i], sg[i], tt[i])
            for i in range(n)
        ]
    )
    th = pack(truth.nominal.dh, tool=truth.smr_flange_m)
    J = np.asarray(jac_params(th, truth.tracker_T_base, q)).reshape(3 * n, -1)
    J = J / (np.linalg.norm(J, axis=0) + 1e-300)
    x, *_ = np.linalg.lstsq(J, d.ravel(), rcond=1e-10)
    r = d.ravel() - J @ x
    return float(np.sqrt(np.sum(r**2) / n))


def floor_estimate(truth, targets) -> float:
    """Noise floor of a held-out RMS for this cell (3-D, per pose mean of 5 readings)."""
    from sim_devices.truth import NOMINAL_SMR_M  # noqa: F401

    q = np.array([t.q_rad for t in targets])
    th = pack(truth.nominal.dh, tool=truth.smr_flange_m)
    from workcell.kinematics.chain import p_tracker

    rng_m = np.linalg.norm(np.asarray(p_tracker(th, truth.tracker_T_base, q)), axis=1)
    s = np.array([truth.noise.sigma_of_mean(r, 5) for r in rng_m])
    return float(np.sqrt(np.mean(3 * s**2)) * 1.05)


# ----------------------------------------------------------------------------- cases
def make_case(
    kinds: list[tuple[str, int | None]],
    seed: int,
    n_poses: int,
    ratio: float,
    out_dir: Path,
    rng: np.random.Generator,
    *,
    warmup_s: float | None = None,
) -> dict:
    """Build one simulated recording with the given concealed effects at a target ratio."""
    from sim_devices.truth import make_truth

    truth = make_truth("ur5e", {}, seed)
    targets = plan_targets(truth.nominal, n_poses, seed)
    warm = float(rng.uniform(0, 900)) if warmup_s is None else warmup_s
    floor = floor_estimate(truth, targets)
    effects: dict = {}
    unknown_amp = None
    sizes = {}
    for kind, joint in kinds:
        target = floor * np.sqrt(max(ratio**2 - 1.0, 0.0)) / np.sqrt(len(kinds))
        if kind == "unknown":
            base = 30e-6
            r1 = concealed_rms(truth, {}, targets, warm, unknown_amp=base)
            unknown_amp = base * target / max(r1, 1e-15)
            sizes["unknown"] = unknown_amp
            continue
        p1 = unit_effect(kind, joint, rng)
        if kind == "tracker_scale":
            effects[kind] = scale_effect(kind, p1, 20.0)  # 300 ppm: large, yet absorbed
            continue
        r1 = concealed_rms(truth, {kind: p1}, targets, warm)
        s = target / max(r1, 1e-15)
        if kind in effects:  # same kind twice (pairs avoid this)
            raise ValueError("pairs must be of different kinds")
        effects[kind] = scale_effect(kind, p1, s)
        sizes[f"{kind}/{joint}"] = s
    truth.effects = effects
    if unknown_amp is not None:
        truth = _unknown_truth(truth, unknown_amp)
    path = out_dir / f"case-s{seed}-{'+'.join(k for k, _ in kinds) or 'clean'}.mcap"
    simulate_recording(truth, n_poses, seed, path, warmup_s=warm, targets=targets)
    return {"path": path, "truth": truth, "warmup_s": warm, "floor_est": floor, "scales": sizes}


def named_of(report: dict) -> list[tuple[str, int | None]]:
    return sorted({(e["kind"], e["joint"]) for e in report["effects"]}, key=str)


def true_floor(ds, truth, diag) -> float:
    """Noise floor with the simulator's true noise model (for scoring only)."""
    from workcell.bench.scoring import noise_floor

    return noise_floor(ds, diag.dh_model, truth.noise)


def _lbl(kinds, sep: str = "+", empty: str = "clean") -> str:
    return sep.join(k if j is None else f"{k}{j}" for k, j in kinds) or empty


def run_case(kinds, seed, n_poses, ratio, tmp: Path, rng, log, np_check: bool = True) -> dict:
    from workcell.estimation.discovery import DiagnoseConfig, diagnose
    from workcell.recording.dataset import Dataset

    t0 = time.perf_counter()
    case = make_case(kinds, seed, n_poses, ratio, tmp, rng)
    ds = Dataset.from_recording(case["path"])
    diag = diagnose(ds, DiagnoseConfig(seed=seed, nonparametric=np_check))
    r = diag.report
    floor = true_floor(ds, case["truth"], diag)
    named = named_of(r)
    out = {
        "seed": seed,
        "true": [list(k) for k in kinds],
        "named": [list(k) for k in named],
        "ratio_target": ratio,
        "rms_before_m": r["rms_before_m"],
        "rms_after_m": r["rms_after_m"],
        "noise_floor_true_m": floor,
        "noise_floor_reported_m": r["noise_floor_m"],
        "before_over_floor": r["rms_before_m"] / floor,
        "after_over_floor": r["rms_after_m"] / floor,
        "floor_reached": r.get("floor_reached"),
        "set_aside_sign": [
            st["candidate"] for st in r["selection"] if st["action"] == "set aside (sign)"
        ],
        "unexplained": {
            "structured": r["unexplained"].get("structured", False),
            "where": r["unexplained"].get("where", []),
            "np": r["unexplained"].get("np_test", {}).get("heldout_rms_with_m"),
        },
        "seconds": time.perf_counter() - t0,
    }
    log(
        f"  {_lbl(kinds):40s} "
        f"seed {seed:>10d}  before {out['before_over_floor']:5.2f}x  after "
        f"{out['after_over_floor']:5.2f}x floor  named: "
        f"{_lbl(named, ', ', '-')}"
        f"{'  [unexplained structure]' if out['unexplained']['structured'] else ''}"
        f"  ({out['seconds']:.0f} s)"
    )
    try:
        case["path"].unlink()
    except OSError:
        pass
    return out


def main(argv: list[str]) -> int:
    ap = OneLineParser(prog="workcell bench discovery", description=__doc__.split("\n")[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--draws", type=int, default=1, help="repetitions of the single-effect set")
    ap.add_argument("--pairs", type=int, default=10, help="pair cases per draw")
    ap.add_argument("--clean", type=int, default=20, help="clean cases per draw")
    ap.add_argument("--poses", type=int, default=300)
    ap.add_argument("--seed", type=int, default=None, help="master seed (default: random)")
    ap.add_argument("--quick", action="store_true", help="a few cases only (smoke test)")
    ap.add_argument("--out", help="write the JSON result here too")
    ap.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --out file that is not an earlier result of this bench",
    )
    ap.add_argument(
        "--np-all",
        action="store_true",
        help="run the non-parametric residual check in every case (default: extra cases only; "
        "it does not change which effects are named)",
    )
    a = ap.parse_args(argv)
    for opt, v, lo, hi in (
        ("--draws", a.draws, 1, 100),
        ("--pairs", a.pairs, 0, 1000),
        ("--clean", a.clean, 0, 1000),
        ("--poses", a.poses, 40, 5000),
    ):
        if not lo <= v <= hi:
            raise UserError(f"{opt} must be {lo}..{hi}, got {v}")
    if a.seed is not None and not 0 <= a.seed < 2**63:
        raise UserError(f"--seed must be 0..2^63-1, got {a.seed}")
    log = (
        (lambda m: print(m, file=sys.stderr, flush=True))
        if a.json
        else (lambda m: print(m, flush=True))
    )
    if a.out:  # before minutes of work: never over a recording, a device, an input or a file
        # that is not an earlier result of this bench (unless --force)
        check_output_path(a.out, "bench result")
        check_bench_outputs([a.out], "discovery", a.out, force=a.force, say=log)
    master = int(np.random.SeedSequence().entropy % (2**31)) if a.seed is None else a.seed
    rng = np.random.default_rng(master)
    log(f"bench discovery: master seed {master}, {a.poses} poses per recording")
    singles = SINGLE_CASES * a.draws
    n_pairs, n_clean = a.pairs * a.draws, a.clean * a.draws
    if a.quick:
        pick = rng.choice(len(SINGLE_CASES), 4, replace=False)
        singles = [SINGLE_CASES[i] for i in pick]
        n_pairs, n_clean = 2, 3

    def new_seed() -> int:
        return int(rng.integers(1, 2**31 - 1))

    def ratio() -> float:
        return float(np.exp(rng.uniform(np.log(2.0), np.log(10.0))))

    res: dict = {"single": [], "pairs": [], "clean": [], "extra": []}
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="wc-discovery-") as td:
        tmp = Path(td)
        log("single effects:")
        for kind, joint in singles:
            res["single"].append(
                run_case([(kind, joint)], new_seed(), a.poses, ratio(), tmp, rng, log, a.np_all)
            )
        log("pairs:")
        for _ in range(n_pairs):
            i, j = rng.choice(len(SINGLE_CASES), 2, replace=False)
            while SINGLE_CASES[i][0] == SINGLE_CASES[j][0]:
                i, j = rng.choice(len(SINGLE_CASES), 2, replace=False)
            kinds = [SINGLE_CASES[i], SINGLE_CASES[j]]
            res["pairs"].append(
                run_case(kinds, new_seed(), a.poses, ratio(), tmp, rng, log, a.np_all)
            )
        log("clean recordings:")
        for _ in range(n_clean):
            res["clean"].append(run_case([], new_seed(), a.poses, 1.0, tmp, rng, log, a.np_all))
        log("extra cases (not in the accuracy):")
        res["extra"].append(
            run_case([("tracker_scale", None)], new_seed(), a.poses, 1.0, tmp, rng, log)
        )
        res["extra"].append(run_case([("unknown", 3)], new_seed(), a.poses, 5.0, tmp, rng, log))
        res["extra"].append(
            run_case([("pedestal_tilt", None)], new_seed(), a.poses, 5.0, tmp, rng, log)
        )
    summary = {"bench": "discovery", **score(res)}
    summary["master_seed"] = master
    summary["poses"] = a.poses
    summary["seconds"] = time.perf_counter() - t_all
    summary["cases"] = res
    summary["environment"] = environment()
    if a.out:
        write_text(a.out, json.dumps(summary, indent=1, default=float))
    if a.json:
        print(json.dumps(summary, default=float))
    else:
        print_table(summary)
    return 0


def _key(k) -> str:
    kind, joint = k
    return kind if joint is None else f"{kind}/{joint}"


def score(res: dict) -> dict:
    def norm(lst):
        return sorted((k, j) for k, j in lst)

    single_ok = [norm(c["named"]) == norm(c["true"]) for c in res["single"]]
    pair_ok = [norm(c["named"]) == norm(c["true"]) for c in res["pairs"]]
    pair_both = [set(map(tuple, c["true"])) <= set(map(tuple, c["named"])) for c in res["pairs"]]
    fa = [len(c["named"]) > 0 for c in res["clean"]]
    confusion: dict[str, dict[str, int]] = {}
    for c in res["single"] + res["pairs"] + res["clean"] + res["extra"]:
        trues = [_key(k) for k in c["true"]] or ["none"]
        nameds = [_key(k) for k in c["named"]] or ["none"]
        for t in trues:
            row = confusion.setdefault(t, {})
            # a named effect counts for the true effect of the same kind, else for every true one
            for n in nameds:
                if len(trues) > 1 and n != "none" and n in trues and n != t:
                    continue
                row[n] = row.get(n, 0) + 1
    named_cases = [c for c in res["single"] + res["pairs"] if c["named"]]
    right = [c for c in named_cases if norm(c["named"]) == norm(c["true"])]
    ratios = [c["after_over_floor"] for c in right]
    extra = {}
    for c in res["extra"]:
        extra[_key(c["true"][0])] = {
            "named": [_key(k) for k in c["named"]],
            "before_over_floor": c["before_over_floor"],
            "after_over_floor": c["after_over_floor"],
            "unexplained_structured": c["unexplained"]["structured"],
            "where": c["unexplained"]["where"],
            "np_heldout_rms_m": c["unexplained"]["np"],
            "rms_after_m": c["rms_after_m"],
            "floor_reached": c.get("floor_reached"),
            "set_aside_sign": c.get("set_aside_sign", []),
        }
    return {
        "single": {
            "cases": len(single_ok),
            "accuracy": _mean(single_ok),
            "accuracy_ci95": _ci(single_ok),
        },
        "pairs": {
            "cases": len(pair_ok),
            "accuracy": _mean(pair_both),
            "accuracy_ci95": _ci(pair_both),
            "exact_accuracy": _mean(pair_ok),
            "exact_accuracy_ci95": _ci(pair_ok),
        },
        "clean": {
            "cases": len(fa),
            "false_alarm_rate": _mean(fa),
            "false_alarm_rate_ci95": _ci(fa),
        },
        "rate_interval_basis": "Wilson score interval, 95 %, over the cases",
        "rms_after_over_floor": {
            "median": float(np.median(ratios)) if ratios else float("nan"),
            "max": float(np.max(ratios)) if ratios else float("nan"),
            "cases": len(ratios),
        },
        # how often the "named effects do not reach the floor" caveat is printed where every
        # named effect is right, and how often a term was set aside for its sign there
        "caveats_when_right": {
            "floor_not_reached": sum(1 for c in right if c.get("floor_reached") is False),
            "set_aside_sign": sum(1 for c in right if c.get("set_aside_sign")),
            "cases": len(right),
        },
        "confusion": confusion,
        "extra": extra,
    }


def _mean(x) -> float:
    return float(np.mean(x)) if len(x) else float("nan")


def _ci(x) -> list[float] | None:
    """95 % Wilson interval of a rate over len(x) yes/no cases (None without cases)."""
    from scipy.stats import binomtest

    if not len(x):
        return None
    ci = binomtest(int(np.sum(x)), len(x)).proportion_ci(0.95, method="wilson")
    return [float(ci.low), float(ci.high)]


def _pct(rate: float, ci) -> str:
    return f"{rate:.0%}" + (f" (95 % CI {ci[0]:.0%}-{ci[1]:.0%})" if ci else "")


def print_table(s: dict) -> None:
    print()
    si, pa, cl = s["single"], s["pairs"], s["clean"]
    print(
        f"single effects: {si['cases']} cases, accuracy "
        f"{_pct(si['accuracy'], si.get('accuracy_ci95'))}"
    )
    print(
        f"pairs:          {pa['cases']} cases, both named "
        f"{_pct(pa['accuracy'], pa.get('accuracy_ci95'))} (exactly: "
        f"{_pct(pa['exact_accuracy'], pa.get('exact_accuracy_ci95'))})"
    )
    print(
        f"clean:          {cl['cases']} cases, false alarms "
        f"{_pct(cl['false_alarm_rate'], cl.get('false_alarm_rate_ci95'))}"
    )
    r = s["rms_after_over_floor"]
    print(
        f"held-out RMS after / noise floor (correctly named): median {r['median']:.2f}, max {r['max']:.2f}"
    )
    cw = s["caveats_when_right"]
    print(
        f"correctly named cases still said not to reach the floor: {cw['floor_not_reached']} of "
        f"{cw['cases']}; with a term set aside for its sign: {cw['set_aside_sign']}"
    )
    print("\nconfusion (true -> named: count)")
    for t, row in sorted(s["confusion"].items()):
        cells = ", ".join(f"{n}: {c}" for n, c in sorted(row.items(), key=lambda x: -x[1]))
        print(f"  {t:28s} -> {cells}")
    for k, v in s["extra"].items():
        print(
            f"\n{k}: named {v['named'] or 'nothing'}; before {v['before_over_floor']:.2f}x, after "
            f"{v['after_over_floor']:.2f}x floor; unexplained structure: "
            f"{v['unexplained_structured']} {'; '.join(v['where'])}"
        )
        print(
            f"   floor reached: {v['floor_reached']}; set aside for their sign: "
            f"{', '.join(v['set_aside_sign']) or 'none'}"
        )
        if v["np_heldout_rms_m"]:
            print(
                f"   non-parametric model: held-out RMS {v['rms_after_m'] * 1e6:.1f} -> "
                f"{v['np_heldout_rms_m'] * 1e6:.1f} um"
            )
    print(f"\n{s['seconds']:.0f} s, master seed {s['master_seed']}")
