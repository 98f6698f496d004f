"""`workcell demo`: a simulated campaign end to end: record, fit, evaluate on held-out poses.

The simulated truth is used only to score (the noise floor and the correction check); the fits see
only the recording.
"""

from __future__ import annotations

import argparse
import sys
import time

from workcell import strict_json
from workcell.bench.scoring import noise_floor
from workcell.errors import UserError, check_output_path
from workcell.estimation.models import interval_um


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--poses", type=int, default=150, help="poses to measure (default 150)")
    p.add_argument(
        "--effects",
        default="realistic",
        help="simulated physics: none (DH errors + noise), realistic, all, or a list",
    )
    p.add_argument("--seed", type=int, default=1, help="seed of the simulated truth and plan")
    p.add_argument("--model", default="ur5e", help="robot model (ur5e, ur10)")
    p.add_argument(
        "--methods",
        default="dh,lddmm,gp,augmented",
        help="fits to run (comma list; augmented = geometry + the effects that "
        "`workcell diagnose` names)",
    )
    p.add_argument("--out", default="out/demo", help="directory for the recording and models")
    p.add_argument(
        "--warmup",
        type=float,
        default=2700.0,
        help="simulated warm-up before measuring, seconds (default 45 min)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--no-correction", action="store_true", help="skip the correction check")


def run(args: argparse.Namespace) -> int:
    from sim_devices.cell import sim_cell
    from workcell.campaign.run import margin_stop, run_campaign
    from workcell.estimation.fitting import fit_dataset, keep_in_model
    from workcell.estimation.models import save_model
    from workcell.recording.dataset import Dataset

    if not 20 <= args.poses <= 5000:
        raise UserError(
            f"--poses must be 20..5000 (a fit needs 20; a demo is not a long campaign), got "
            f"{args.poses}"
        )
    if args.seed < 0:
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    from workcell.estimation.fitting import FIT_METHODS

    known = (*FIT_METHODS, "augmented")
    unknown = [m.strip() for m in args.methods.split(",") if m.strip() and m.strip() not in known]
    if unknown or not args.methods.strip():
        raise UserError(
            f"--methods: unknown {unknown or args.methods!r}; choose from {', '.join(known)}"
        )
    log = (lambda m: print(m, file=sys.stderr, flush=True)) if args.json else print
    out = check_output_path(args.out, "output folder", folder=True)
    out.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    rec_path = out / f"demo-{args.model}-{args.effects.replace(',', '+')}-s{args.seed}-{stamp}.mcap"
    world, robot, tracker, cell = sim_cell(args.model, args.effects, args.seed)
    log(f"simulated {args.model}, effects: {args.effects}, seed {args.seed}")
    log(f"campaign: {args.poses} random poses -> {rec_path}")
    t0 = time.perf_counter()
    from workcell.campaign.executor import CampaignConfig

    cfg = CampaignConfig(payload_kg=cell.payload_kg, warmup_s=args.warmup)
    _, res = run_campaign(
        robot,
        tracker,
        cell,
        rec_path,
        plan="random",
        poses=args.poses,
        seed=args.seed,
        config=cfg,
        extra_campaign={"effects": args.effects, "warmup_s": args.warmup},
        on_event=lambda e: log(f"  {e['kind']}: {e['message']}") if e["kind"] == "margin" else None,
    )
    margin_stop(res, rec_path)
    if res.aborted:  # Ctrl-C during the campaign: stop there, do not fit a partial demo
        print(
            f"workcell demo: interrupted after {res.measured} poses; {rec_path} is closed and "
            "keeps them",
            file=sys.stderr,
        )
        return 130
    camp_s = time.perf_counter() - t0
    log(
        f"  measured {res.measured}, skipped {res.skipped}, {res.events} events "
        f"({world.clock.now() / 60:.1f} simulated minutes, {camp_s:.1f} s wall)"
    )
    ds = Dataset.from_recording(rec_path)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    results, models = {}, {}
    for m in methods:
        if m == "augmented":
            continue
        try:
            model, rep = fit_dataset(ds, method=m, holdout=0.25)
        except UserError as e:
            log(f"  fit {m}: skipped ({e})")
            continue
        models[m] = model
        keep_in_model(model, ds, rep)  # recording and held-out figures, as `fit --out` keeps
        save_model(model, out / f"{rec_path.stem}.{m}.json")
        results[m] = rep
        log(
            f"  fit {m:6s}: held-out RMS {rep['heldout_rms_m'] * 1e6:8.1f} um  "
            f"max {rep['heldout_max_m'] * 1e6:8.1f} um  ({rep['fit_seconds']:.1f} s)"
        )
    if "dh" not in results:
        raise UserError("the DH fit failed; nothing to report")
    diagnosis = None
    if "augmented" in methods:
        from workcell.estimation.discovery import diagnose

        t1 = time.perf_counter()
        diagnosis = diagnose(ds)
        r = diagnosis.report
        models["augmented"] = diagnosis.model
        save_model(diagnosis.model, out / f"{rec_path.stem}.augmented.json")
        results["augmented"] = {
            "heldout_rms_m": r["rms_after_m"],
            "heldout_rms_ci95_m": r.get("rms_after_ci95_m"),
            "heldout_max_m": r["max_after_m"],
            "fit_seconds": time.perf_counter() - t1,
            "heldout_poses": r.get("heldout_poses"),
        }
        log(
            f"  diagnose      : held-out RMS {r['rms_after_m'] * 1e6:8.1f} um  "
            f"max {r['max_after_m'] * 1e6:8.1f} um  ({results['augmented']['fit_seconds']:.1f} s)"
        )
        for e in r["effects"]:
            log(f"     named: {e['kind']} joint {e['joint']}")
    dh = results["dh"]
    floor = noise_floor(ds, models["dh"], world.truth.noise)
    train, test = ds.holdout_split(0.25)
    summary = {
        "robot": args.model,
        "effects": args.effects,
        "seed": args.seed,
        "poses": int(len(ds)),
        "skipped_poses": int(res.skipped),
        "heldout_poses": int(dh["heldout_poses"]),
        "noise_floor_m": floor,
        "noise_floor_basis": NOISE_FLOOR_BASIS,
        "nominal_rms_m": dh["nominal_rms_m"],
        "nominal_rms_ci95_m": dh.get("nominal_rms_ci95_m"),
        "rms_interval_basis": dh.get("rms_interval_basis"),
        "calibrated_rms_m": {m: r["heldout_rms_m"] for m, r in results.items()},
        "calibrated_rms_ci95_m": {m: r.get("heldout_rms_ci95_m") for m, r in results.items()},
        "calibrated_max_m": {m: r["heldout_max_m"] for m, r in results.items()},
        "fit_seconds": {m: r["fit_seconds"] for m, r in results.items()},
        "unidentifiable": dh["unidentifiable"],
        "recording": str(rec_path),
        "models": {m: str(out / f"{rec_path.stem}.{m}.json") for m in results},
    }
    if diagnosis is not None:
        summary["diagnosis"] = {
            "effects": [
                {"kind": e["kind"], "joint": e["joint"]} for e in diagnosis.report["effects"]
            ],
            "summary": diagnosis.report["summary"],
            "noise_floor_m": diagnosis.report["noise_floor_m"],
        }
    if not args.no_correction:
        try:
            from workcell.export.demo_step import correction_step  # export issue
        except ModuleNotFoundError:
            pass
        else:
            best = min(results, key=lambda m: results[m]["heldout_rms_m"])
            summary["correction"] = correction_step(world, cell, models[best], best, out, log)
            summary["correction"]["model_heldout_rms_m"] = results[best]["heldout_rms_m"]
    if args.json:
        print(strict_json.dumps(summary))
        return 0
    print()
    print(f"{'':24}{'held-out RMS':>14}{'max':>12}   95 % CI of the RMS")
    ci = interval_um(dh.get("nominal_rms_ci95_m"), label=False)
    print(
        f"{'nominal model':24}{um(dh['nominal_rms_m']):>14}{um(dh['nominal_max_m']):>12}"
        + (f"   {ci}" if ci else "")
    )
    for m, r in results.items():
        ci = interval_um(r.get("heldout_rms_ci95_m"), label=False)
        print(
            f"{'calibrated: ' + m:24}{um(r['heldout_rms_m']):>14}{um(r['heldout_max_m']):>12}"
            + (f"   {ci}" if ci else "")
        )
    print(f"{'noise floor (sim noise)':24}{um(floor):>14}")
    if diagnosis is not None:  # the floor the tool states without the truth
        print(f"{'noise floor (diagnose)':24}{um(diagnosis.report['noise_floor_m']):>14}")
    print(f"  (noise floor: {NOISE_FLOOR_BASIS})")
    best = min(results.values(), key=lambda r: r["heldout_rms_m"])
    print(
        f"\nimprovement nominal/calibrated: {dh['nominal_rms_m'] / best['heldout_rms_m']:.0f}x; "
        f"calibrated/noise floor: {best['heldout_rms_m'] / floor:.2f}"
    )
    print(f"poses: {len(train)} train, {len(test)} held out; recording {rec_path}")
    if diagnosis is not None:
        print("\ndiagnosis: " + diagnosis.report["summary"].split("\n")[0])
        print(
            "  (diagnose's floor comes from the recording alone: per-pose sigma max(recorded, "
            "tracker MPE/4), plus its geometry's estimation uncertainty; the table's floor is the "
            "simulator's own noise)"
        )
    if "correction" in summary:
        c = summary["correction"]
        print(
            f"correction ({c['targets']} targets): RMS {um(c['before_rms_m'])} -> "
            f"{um(c['after_rms_m'])}"
            + (f" ({ci})" if (ci := interval_um(c.get("after", {}).get("rms_ci95_m"))) else "")
        )
    return 0


NOISE_FLOOR_BASIS = (
    "expected held-out RMS from the simulator's tracker noise alone (truth, used only to score), "
    "with the noise's effect on the fitted geometry"
)


def um(x: float) -> str:
    return f"{x * 1e6:.1f} um"
