"""`workcell diagnose REC.mcap [--json] [--report DIR] [--out MODEL]`: locate the mismatch between
the nominal model and a recording, name the physics left out, model it, show the fit improve.

See `workcell.estimation.discovery` for the method. Needs only the `/workcell/session` and
`/campaign/sample` channels, so it runs on recordings made by other tools too; the nominal base
pose in the session may be rough (the geometry registers the base itself).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from workcell import strict_json
from workcell.atomic import save_figure, write_text
from workcell.commands import prose
from workcell.commands.options import add_tracker_mpe, parse_tracker_mpe
from workcell.errors import UserError, check_output_path, replace_or_refuse
from workcell.estimation.models import interval_um
from workcell.recording.chain import add_chain_option


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "recording", help="an .mcap recording (needs /workcell/session + /campaign/sample)"
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument(
        "--report",
        metavar="DIR",
        help="write report.json, summary.txt, residual plots (PNG) and the models into DIR",
    )
    p.add_argument("--out", help="write the augmented model here (JSON); default: in --report DIR")
    p.add_argument("--holdout", type=float, default=0.25, help="held-out fraction (0.1-0.5)")
    p.add_argument(
        "--alpha",
        type=float,
        default=0.01,
        help="level of the likelihood-ratio test per selection step (Bonferroni over candidates)",
    )
    add_tracker_mpe(p)
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing model file (an earlier model of the same recording is "
        "replaced without it)",
    )
    p.add_argument("--no-np", action="store_true", help="skip the non-parametric residual check")
    add_chain_option(p)


REPORT_FILES = (
    "summary.txt",
    "report.json",
    "residuals_before_after.png",
    "heldout_rms_steps.png",
)


def _np_path(model_path: Path) -> Path:
    """Where the non-parametric residual model goes beside the augmented one."""
    p_np = model_path.with_name(model_path.name.replace(".json", ".np.json"))
    return model_path.with_suffix(".np.json") if p_np == model_path else p_np


def run(args: argparse.Namespace) -> int:
    from workcell.estimation.discovery import DiagnoseConfig, diagnose
    from workcell.estimation.models import check_model_output, save_model
    from workcell.recording.chain import file_sha256
    from workcell.recording.dataset import Dataset, read_warnings

    if not 0.1 <= args.holdout <= 0.5:
        raise UserError(f"--holdout must be in [0.1, 0.5], got {args.holdout}")
    if not 0.0 < args.alpha < 0.5:
        raise UserError(f"--alpha must be in (0, 0.5), got {args.alpha}")
    mpe = parse_tracker_mpe(args.tracker_mpe)
    ds = Dataset.from_recording(args.recording, chain_missing=args.chain_missing)
    log = lambda m: print(m, file=sys.stderr, flush=True)  # noqa: E731 - progress and warnings
    for line in read_warnings(ds):
        log(line)
    cfg = DiagnoseConfig(
        holdout=args.holdout, alpha=args.alpha, tracker_mpe=mpe, nonparametric=not args.no_np
    )
    if args.report:
        check_output_path(args.report, "report folder", folder=True)
    outdir = Path(args.report) if args.report else None
    model_path = (
        Path(args.out) if args.out else (outdir / "augmented.model.json" if outdir else None)
    )
    # every file this run writes: never the recording, never any MCAP (even with --force); a
    # model only over an earlier model of this recording (or with --force)
    # "replaced ..." is said once the files are written (it said "replacing" before the work,
    # and a failure or kill then left them as they were: a crash audit)
    replacing: dict[str, list[str]] = {}  # what is said once written: per model file, report

    def will_replace(key: str):
        return lambda line: replacing.setdefault(key, []).append(line)

    if model_path:
        for p in (model_path, _np_path(model_path)):
            check_output_path(p, "model file", inputs=[args.recording])
            check_model_output(p, args.recording, force=args.force, say=will_replace(str(p)))
    for name in REPORT_FILES if outdir else ():
        check_output_path(outdir / name, "report file", inputs=[args.recording])
    if outdir:
        check_report_folder(outdir, force=args.force, say=will_replace("report"))
    diag = diagnose(ds, cfg, progress=log)
    rep = diag.report
    rep["recording_problems"] = list(ds.read_problems)
    if outdir:
        outdir.mkdir(parents=True, exist_ok=True)
    if model_path:
        rep["model"] = str(save_model(diag.model, model_path))
        # the report names the model file by content too: the files are replaced one by one,
        # so after a crash between them report.json can be told from another run's model
        rep["model_sha256"] = file_sha256(model_path)
        if diag.model_np is not None:
            p_np = _np_path(model_path)
            rep["unexplained"].setdefault("np_model", {})["model"] = str(
                save_model(diag.model_np, p_np)
            )
    if outdir:
        rep["plots"] = write_plots(diag, outdir)
        write_text(outdir / REPORT_FILES[0], rep["summary"] + "\n")
        write_text(outdir / REPORT_FILES[1], strict_json.dumps(rep, indent=1))
    written = [str(model_path)] if model_path else []
    if model_path and diag.model_np is not None:  # none without the residual check (--no-np)
        written.append(str(_np_path(model_path)))
    for key in [*written, *(["report"] if outdir else [])]:
        for line in replacing.get(key, []):
            log(line.replace("replacing ", "replaced ", 1))
    if args.json:
        print(strict_json.dumps(rep))
    else:
        print_report(rep)
    return 0


def check_report_folder(outdir: Path, *, force: bool, say) -> None:
    """Write the report files over existing ones only when they are an earlier diagnose report
    (its report.json is one), else refuse unless `force`."""
    existing = [outdir / n for n in REPORT_FILES if (outdir / n).is_file()]
    if not existing:
        return
    try:
        d = json.loads((outdir / REPORT_FILES[1]).read_text(encoding="utf-8-sig"))
    except (OSError, ValueError, UnicodeDecodeError):
        d = None
    ours = isinstance(d, dict) and {"summary", "train_poses", "heldout_poses"} <= set(d)
    for p in existing:
        replace_or_refuse(
            "report file",
            p,
            "an earlier report" if ours else None,
            "not part of an earlier workcell diagnose report",
            force=force,
            say=say,
        )


def um(x) -> str:
    return "-" if x is None else f"{x * 1e6:.1f} um"


def print_report(r: dict) -> None:
    print(f"recording   {r['recording']}")
    if r.get("chain"):  # a resumed recording: diagnosed with every file it continues
        print(f"chain       {r['chain']}")
    print(
        f"poses       {r['train_poses']} train, {r['heldout_poses']} held out "
        f"({r['outliers_rejected']} outliers set aside)"
    )
    print()
    print(r["summary"])
    print()
    print(f"{'model':42s}{'held-out RMS':>14}{'max':>12}   95 % CI of the RMS")
    print(
        f"{'geometry (DH + offsets + base + SMR)':42s}{um(r['rms_before_m']):>14}"
        f"{um(r['max_before_m']):>12}   {interval_um(r.get('rms_before_ci95_m'), False)}"
    )
    for s in r["steps"]:
        print(
            f"{'  + ' + s['after']:42s}{um(s['heldout_rms_m']):>14}{um(s['heldout_max_m']):>12}"
            f"   {interval_um(s.get('heldout_rms_ci95_m'), False)}"
        )
    print(
        f"{'final (nonlinear joint refit)':42s}{um(r['rms_after_m']):>14}"
        f"{um(r['max_after_m']):>12}   {interval_um(r.get('rms_after_ci95_m'), False)}"
    )
    npm = r["unexplained"].get("np_model")
    if npm:
        ci = interval_um(npm.get("heldout_rms_ci95_m"), False)
        print(
            f"{'final + non-parametric residual (GP)':42s}{um(npm['heldout_rms_m']):>14}"
            f"{um(npm['heldout_max_m']):>12}   {ci + ' ' if ci else ''}(optimistic: see below)"
        )
    print(f"{'noise floor (expected)':42s}{um(r['noise_floor_m']):>14}   tracker + geometric fit")
    if r.get("tracker_noise_floor_m") is not None:
        print(f"{'  tracker alone (as `fit` states it)':42s}{um(r['tracker_noise_floor_m']):>14}")
    note = f"Held-out RMS and max: on the {r['heldout_poses']} held-out poses."
    if r["steps"]:
        note += (
            " The '+' rows are cumulative, in the order the selection accepted the effects: each "
            "adds one effect to those above it (linearised, fitted on the "
            f"{r['train_poses']} training poses), so a row's drop depends on that order and is "
            "not the effect's own held-out gain (leave-one-out, below)."
        )
    if npm:
        note += f" GP row: {npm.get('heldout_selection', GP_CAVEAT_FALLBACK)}."
    print(prose.fill(note, width=100))
    if (hs := r.get("heldout_model_std")) is not None:
        from workcell.commands.fit import heldout_std_text

        print(prose.fill("final " + heldout_std_text(hs), width=100, subsequent_indent="  "))
    if r["effects"]:
        print()
        print(effects_table(r))
    if r.get("model"):
        print(f"\nmodel       {r['model']}")
    if npm and npm.get("model"):
        print(f"GP model    {npm['model']}   (the augmented model + the residual GP)")
    if r.get("plots"):
        for p in r["plots"].values():
            print(f"plot        {p}")


GP_CAVEAT_FALLBACK = (
    "the residual GP was accepted on these held-out poses, so its held-out RMS is somewhat "
    "optimistic"
)


def _gain(g) -> str:
    return "-" if g is None else f"{g * 1e6:.1f} um"


def effects_table(r: dict) -> str:
    """Each accepted effect's own held-out test: the final model without it minus with it
    (leave-one-out, paired 95 % interval), and whether that confirms it."""
    lines = [
        "leave-one-out on the held-out poses: the final model without the effect, minus with it",
        f"{'effect':42s}{'gain':>14}   {'95 % CI of the gain':24s}held-out verdict",
    ]
    for e in r["effects"]:
        ev = e["evidence"]
        ci = ev.get("heldout_gain_ci95_m")
        cis = (
            f"{ci[0] * 1e6:.1f} to {ci[1] * 1e6:.1f} um"
            if ci is not None and all(np.isfinite(ci))
            else "-"
        )
        verdict = (
            "confirmed" if ev.get("heldout_confirms", True) else "NOT confirmed (kept in the model)"
        )
        lines.append(
            f"{'  ' + e['key']:42s}{_gain(ev.get('heldout_gain_m')):>14}   {cis:24s}{verdict}"
        )
    return "\n".join(lines)


def write_plots(diag, outdir: Path) -> dict:
    """Residual plots before/after (PNG): held-out residual norm over the workspace + histogram."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    P = diag.plots
    rep = diag.report
    p = P["p_te"]
    before = np.linalg.norm(P["res_before"], axis=1) * 1e6
    after = np.linalg.norm(P["res_after"], axis=1) * 1e6
    panels = [("geometry only", before), ("geometry + effects", after)]
    if "res_np" in P:
        panels.append(("+ non-parametric", np.linalg.norm(P["res_np"], axis=1) * 1e6))
    vmax = float(np.percentile(before, 98))
    fig, axes = plt.subplots(2, len(panels), figsize=(4.2 * len(panels), 7.2), squeeze=False)
    c = p - p.mean(0)
    for k, (title, e) in enumerate(panels):
        ax = axes[0, k]
        sc = ax.scatter(c[:, 0], c[:, 1], c=e, s=14, cmap="viridis", vmin=0, vmax=vmax)
        ax.set_title(f"{title}\nRMS {np.sqrt(np.mean(e**2)):.1f} um")
        ax.set_xlabel("x tracker - mean (m)")
        ax.set_ylabel("y tracker - mean (m)")
        ax.set_aspect("equal", adjustable="datalim")
        fig.colorbar(sc, ax=ax, label="held-out error (um)")
        ax = axes[1, k]
        bins = np.linspace(0, max(vmax, 1.0) * 1.2, 30)
        ax.hist(np.clip(e, 0, bins[-1]), bins=bins, color="C0" if k == 0 else "C2")
        over = int(np.sum(e > bins[-1]))
        ax.axvline(rep["noise_floor_m"] * 1e6, color="k", ls="--", lw=1, label="noise floor RMS")
        ax.set_xlabel(  # the errors beyond the axis are counted in the last bar: say so
            "held-out error (um)"
            + (
                f"\n{over} above {bins[-1]:.0f} um (up to {e.max():.0f}) in the last bar"
                if over
                else ""
            )
        )
        ax.set_ylabel("poses")
        ax.legend(fontsize=8)
    fig.suptitle(Path(rep["recording"]).name)
    fig.tight_layout()
    out = outdir / REPORT_FILES[2]
    save_figure(fig, out, dpi=110)
    plt.close(fig)
    # per-step bar chart
    fig, ax = plt.subplots(figsize=(6.5, 3.2))
    labels = ["geometry"] + [s["after"] for s in rep["steps"]]
    vals = [rep["rms_before_m"]] + [s["heldout_rms_m"] for s in rep["steps"]]
    ax.bar(range(len(vals)), np.array(vals) * 1e6, color="C0")
    ax.axhline(rep["noise_floor_m"] * 1e6, color="k", ls="--", lw=1, label="noise floor")
    ax.set_xticks(range(len(vals)), labels, rotation=20, ha="right", fontsize=8)
    ax.set_ylabel("held-out RMS (um)")
    ax.set_title(
        "held-out RMS, effects added cumulatively in acceptance order (not each one's own gain)",
        fontsize=8,
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    out2 = outdir / REPORT_FILES[3]
    save_figure(fig, out2, dpi=110)
    plt.close(fig)
    return {"residuals": str(out), "steps": str(out2)}
