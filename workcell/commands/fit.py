"""`workcell fit REC --method dh|lddmm|gp [--holdout F] [--out MODEL] [--json]`."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from workcell import strict_json
from workcell.commands import prose
from workcell.commands.options import (
    add_tracker_mpe,
    display_unit,
    parse_tracker_mpe,
    say_replaced,
)
from workcell.errors import UserError, check_output_path
from workcell.estimation.fitting import FIT_METHODS, fit_recording
from workcell.estimation.identifiability import GROUP_STAR_NOTE
from workcell.estimation.models import (
    check_model_output,
    default_model_out,
    evaluated_figure,
    interval_um,
    unexplained_text,
)
from workcell.recording.chain import add_chain_option
from workcell.recording.tracker_spec import TRACKER_MPE_M

DEFAULT_HOLDOUT = 0.25  # `--holdout`; the SMR note's command gives it only when it differs


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "recording", help="an .mcap recording (needs /workcell/session + /campaign/sample)"
    )
    p.add_argument("--method", default="dh", help=f"one of: {', '.join(FIT_METHODS)}")
    p.add_argument(
        "--holdout",
        type=float,
        default=DEFAULT_HOLDOUT,
        help="fraction of poses held out for evaluation (deterministic split)",
    )
    p.add_argument(
        "--out", help="write the fitted model here (JSON); default next to the recording"
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing file at --out (an earlier model of the same recording is "
        "replaced without it)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument(
        "--on",
        default="auto",
        help="lddmm: base model (dh, nominal or auto); gp: dh or auto (it models the DH fit's "
        "residual)",
    )
    p.add_argument(
        "--bounds",
        help="dh: parameter bounds file (JSON, SI units: m, rad), 'default' or 'none' (bounded "
        "QP; default bounds the DH corrections to +-5 mm, +-10 mrad, base and SMR offset "
        "unbounded; none: the QP without bounds; leave --bounds out for the unbounded fit)",
    )
    p.add_argument(
        "--smr-offset",
        metavar="X,Y,Z",
        help="dh, lddmm, gp: the SMR offset on the flange in m (the controller's TCP) for this "
        "fit, in place of the one the recording declares (e.g. the fitted one a note below "
        "suggests); the model and its exports are for a controller with this TCP",
    )
    add_tracker_mpe(p)
    add_chain_option(p)


# the report's `extra` keys as the text report names them ("on dh" read as a stray line)
EXTRA_LABELS = {
    "on": "base model",
    "qp_iterations": "QP iterations",
}

HELDOUT_P = 0.05  # below this, the held-out errors are not what the 1-sigma and noise say


def extra_text(key: str, v: object) -> str:
    """A report's `extra` value as text: numbers to 4 significant digits, lengths (`_m` keys)
    in um, nested dictionaries and lists spelled out (lddmm's text printed raw Python
    dictionaries with 16-digit floats: metrology audit, 2026-11-29)."""

    def scaled(k: str, x: float) -> str:
        if k.endswith("_m"):
            return f"{x * 1e6:.4g} um"
        if k.endswith("_rad"):
            return f"{x:.4g} rad"
        if k.endswith(("_s", "_seconds")):
            return f"{x:.3g} s"
        return f"{x:.4g}"

    def one(k: str, x: object) -> str:
        if isinstance(x, bool) or not isinstance(x, int | float | list | tuple | dict):
            return str(x)
        if isinstance(x, int):
            return str(x)
        if isinstance(x, float):
            return scaled(k, x)
        if isinstance(x, dict):
            return "; ".join(
                f"{k2} {one(k2 if k2.endswith(('_m', '_rad', '_s')) else k, x2)}"
                for k2, x2 in x.items()
            )
        return "[" + ", ".join(one(k, y) for y in x) + "]"

    return one(key, v)


def heldout_std_text(hs: dict) -> str:
    """The fit's line on its 1-sigma at the held-out poses (`fitting.heldout_std_check`): the
    mean of the normalised errors and the share inside the 95 % ellipsoid, each with its chance
    if the 1-sigma and the tracker's noise held them (a file from before 2026-11-29 has no
    chances: judged by the mean alone, as then)."""
    k = hs["z2_mean_over_3"]
    p_mean, p_in = hs.get("p_mean"), hs.get("p_inside")
    if p_mean is None or p_in is None:
        high, few = k > 1.5, False
        chances = ""
    else:
        high, few = p_mean < HELDOUT_P, p_in < HELDOUT_P
        chances = f" (p = {p_mean:.2g} if they held)"
    if high:
        verdict = (
            f"about {math.sqrt(k):.1f}x what the 1-sigma and the tracker's noise say: what the "
            "model leaves out (above), or a 1-sigma stated too small; read the parameters' stds "
            "as too small by as much"
        )
    elif few:
        verdict = (
            "more errors outside the 95 % ellipsoid than the 1-sigma and the tracker's noise "
            "allow: a 1-sigma stated too small where the errors are largest, or what the model "
            "leaves out"
        )
    else:
        n = hs.get("poses")
        verdict = "no evidence against the 1-sigma and the tracker's noise" + (
            f" (a test of {n} poses: where the tracker's noise is the larger, a 1-sigma stated "
            "too small passes it; the unexplained part above says what the model leaves out)"
            if n
            else ""
        )
    inside = f"{hs['inside_95']:.0%} inside the 95 % ellipsoid"
    if p_in is not None:
        inside += f" (p = {p_in:.2g})"
    return (
        f"model 1-sigma   {hs['median_m'] * 1e6:.1f} um median, {hs['max_m'] * 1e6:.1f} um max "
        "(3-D, its "
        f"covariance) at the held-out poses; their errors: e'(C + s^2)^-1 e / 3 = {k:.2f}"
        f"{chances}, {inside}: {verdict}"
    )


def run(args: argparse.Namespace) -> int:
    if args.method not in FIT_METHODS:
        raise UserError(f"unknown method {args.method!r}; choose from {', '.join(FIT_METHODS)}")
    if not 0.0 <= args.holdout < 0.9:
        raise UserError(f"--holdout must be in [0, 0.9), got {args.holdout}")
    if args.bounds and args.method != "dh":
        raise UserError(f"--bounds applies to --method dh only (the bounded QP), not {args.method}")
    if args.on not in ("auto", "dh", "nominal"):
        raise UserError(f"--on must be dh, nominal or auto, got {args.on!r}")
    if args.on != "auto" and args.method == "dh":
        raise UserError("--on chooses the base model of lddmm and gp; --method dh has none")
    mpe = parse_tracker_mpe(args.tracker_mpe)
    smr = None
    if getattr(args, "smr_offset", None) is not None:
        from workcell.campaign.devices import parse_smr_offset

        smr = parse_smr_offset(args.smr_offset)  # typed empty: refused by the CLI, one place
    if args.out:
        out = Path(args.out)
    else:
        out, moved = default_model_out(args.recording, f".{args.method}.json")
        if moved:
            print(f"{moved} (--out chooses)", file=sys.stderr)
    check_output_path(out, "model file", inputs=[args.recording, args.bounds])
    # said once the model is written: a refusal found later (a bounds file, the recording)
    # followed "replacing m.json" and left m.json as it was
    replacing: list[str] = []
    check_model_output(out, args.recording, force=args.force, say=replacing.append)
    report = fit_recording(
        args.recording,
        method=args.method,
        holdout=args.holdout,
        out=out,
        on=args.on,
        bounds=args.bounds,
        tracker_mpe=mpe,
        progress=None if args.json else lambda m: print(m, file=sys.stderr),
        warn=lambda m: print(m, file=sys.stderr),
        chain_missing=args.chain_missing,
        smr_offset_m=smr,
    )
    say_replaced(replacing)
    if args.json:
        print(strict_json.dumps(report))
    else:
        print_report(report, refit=lambda smr_m: refit_command(args, out, smr_m))
    return 0


def refit_command(args: argparse.Namespace, out: Path, smr_m) -> str:
    """The `workcell fit` that the SMR note suggests: this fit's options (method, hold-out,
    base model, bounds, tracker MPE, chain), the fitted SMR offset declared, and the model
    written beside this one (`-smr` added to its name) rather than over it."""
    import shlex

    parts = ["workcell", "fit", args.recording]
    if args.method != "dh":
        parts += ["--method", args.method]
    if args.holdout != DEFAULT_HOLDOUT:
        parts += ["--holdout", f"{args.holdout:g}"]
    if args.on != "auto":
        parts += ["--on", args.on]
    if args.bounds:
        parts += ["--bounds", args.bounds]
    if args.tracker_mpe and parse_tracker_mpe(args.tracker_mpe) != tuple(TRACKER_MPE_M):
        parts += ["--tracker-mpe", args.tracker_mpe]
    if getattr(args, "chain_missing", None) not in (None, "refuse"):
        parts += ["--chain-missing", args.chain_missing]
    parts += ["--smr-offset=" + ",".join(f"{x:.4f}" for x in smr_m)]
    parts += ["--out", str(out.with_name(out.stem + "-smr" + out.suffix))]
    return shlex.join(parts)


def _vec_m(v) -> str:
    return "(" + ", ".join(f"{x:.4f}" for x in v) + ") m"


def um(x: float) -> str:
    return f"{x * 1e6:9.1f} um"


def identification_line(i: dict) -> str:
    """Rank, condition (labelled by its basis) and the observability indices O1 and O3 of a
    fit's `identifiability` report, each figure with the Jacobian it is of."""
    cond = f"condition {i['condition']:.3g} ({i.get('condition_label') or 'unit-norm columns'}"
    cu = i.get("condition_unweighted")
    if cu is not None:
        cond += f"; {cu:.3g} unweighted, the dry run's definition"
    cond += ")"
    line = f"identification  rank {i['rank']}/{i['n_parameters']}, {cond}"
    if i.get("o1") is not None:
        line += (
            f"; O1 {i['o1']:.3g}, O3 {i['min_singular_value']:.3g} (SI Jacobian, 1 rad = 1 m, "
            f"over the {i.get('observability_parameters')} parameters the chain can identify)"
        )
    return line


def base_text(tb: dict) -> str:
    """'base            tracker_T_base: translation [..] m +- [..] mm, ...' (fit's output)."""
    t = ", ".join(f"{x:.6f}" for x in tb["translation_m"])
    qt = ", ".join(f"{x:.8f}" for x in tb["quaternion_wxyz"])
    txt = f"base            tracker_T_base (base_ref with the fitted base offsets): translation [{t}] m"
    if "translation_std_m" in tb:
        ts = ", ".join(f"{x * 1e3:.3f}" for x in tb["translation_std_m"])
        rs = ", ".join(f"{x * 1e3:.3f}" for x in tb["rotation_std_rad"])
        txt += (
            f" (1-sigma along the tracker's x, y, z [{ts}] mm), quaternion wxyz [{qt}] (1-sigma "
            f"about the tracker's x, y, z [{rs}] mrad)"
        )
    else:
        txt += f", quaternion wxyz [{qt}] (no covariance: no 1-sigma)"
    return txt + "; compare this, not the base offsets, with another model's base"


def print_report(r: dict, refit=None) -> None:
    print(f"method          {r['method']}")
    print(f"recording       {r['recording']}")
    if r.get("chain"):  # a resumed recording: fitted with every file it continues
        print(f"chain           {r['chain']}")
    sd = r.get("smr_declared") or {}
    if sd.get("by") == "--smr-offset":
        print(
            f"SMR offset      {_vec_m(sd['offset_m'])} on the flange, by --smr-offset (the "
            f"recording declares {_vec_m(sd['recording_m'])})"
        )
    print(f"poses           {r['train_poses']} train, {r['heldout_poses']} held out ({r['split']})")
    on = "held-out RMS" if r["heldout_poses"] else "train RMS   "  # --holdout 0: no held-out
    nci = interval_um(r.get("nominal_rms_ci95_m"))
    print(
        f"nominal         {on} {um(r['nominal_rms_m'])}   (nominal chain, base registered"
        + (f"; {nci}" if nci else "")
        + ")"
    )
    ci = interval_um(evaluated_figure(r, "rms_ci95_m"))
    print(
        f"calibrated      {on} {um(evaluated_figure(r, 'rms_m'))}   max "
        f"{um(evaluated_figure(r, 'max_m'))}"
        + (f"   ({ci}, from the spread over these poses)" if ci else "")
    )
    if r.get("stated_noise_floor_m"):
        print(
            f"noise floor     {um(r['stated_noise_floor_m'])}   repeatability: the recorded "
            "sigmas of the means"
        )
    if r.get("tracker_noise_floor_m"):
        print(
            f"                {um(r['tracker_noise_floor_m'])}   with the tracker's accuracy "
            f"(MPE {r['tracker_mpe']['a_m'] * 1e6:g} um + {r['tracker_mpe']['b_m_per_m'] * 1e6:g} "
            "um/m, "
            "sigma = MPE/4)"
        )
    if r.get("unexplained"):
        print(
            f"unexplained     {unexplained_text(r['unexplained'])}: what the model leaves out "
            "beyond the tracker's noise, in neither the parameters' std nor the model 1-sigma: "
            "add it in quadrature to the model 1-sigma for a target's uncertainty"
        )
    if (hs := r.get("heldout_model_std")) is not None:
        print(prose.fill(heldout_std_text(hs), width=100, subsequent_indent=" " * 16))
    ho = r.get("heldout_outliers")
    if ho:
        poses = ", ".join(
            f"pose {i} ({e * 1e3:.2f} mm)"
            for i, e in zip(ho["pose_ids"], ho["errors_m"], strict=True)
        )
        print(
            f"held-out outliers {len(ho['pose_ids'])} pose(s), {ho['rule']}: {poses}; without "
            f"them: held-out RMS {ho['heldout_rms_m'] * 1e6:.1f} um "
            f"({interval_um(ho['heldout_rms_ci95_m'])}), unexplained "
            f"{unexplained_text(ho['unexplained'])}"
        )
    tb = r.get("tracker_T_base")
    if tb:
        print(prose.fill(base_text(tb), width=100, subsequent_indent=" " * 16))
    print(f"fit time        {r['fit_seconds']:.2f} s")
    if r.get("unidentifiable"):
        print(
            "not separately identifiable (fixed at nominal; where one of a group is kept free, "
            "marked *, it carries the whole group's effect):"
        )
        kept = {
            n: k for k, v in (r.get("parameters") or {}).items() for n in v.get("stands_for") or ()
        }
        for g in r["unidentifiable"]:
            print("   {" + ", ".join(f"{n}*" if kept.get(n) == n else n for n in g) + "}")
    if r.get("identifiability"):
        i = r["identifiability"]
        print(prose.fill(identification_line(i), width=100, subsequent_indent=" " * 16))
        weak = i.get("weakly_identified") or []
        if weak:
            print(
                "weakly identified: the poses barely tell each group's parameters apart (only "
                "their combination is meaningful; add poses that separate them):"
            )
            for g in weak:
                rho = g.get("correlation")
                corr = f", correlation {rho:+.4f}" if rho is not None else ""
                print(
                    "   {" + ", ".join(g["parameters"]) + "}: std "
                    f"{g['std_inflation']:.0f}x what it would be with the others known{corr}"
                )
        pairs = i.get("correlated_pairs") or []
        if pairs:
            shown_pairs = ", ".join(
                f"{'/'.join(c['parameters'])} {c['correlation']:+.3f}" for c in pairs[:8]
            )
            more = f" and {len(pairs) - 8} more (--json)" if len(pairs) > 8 else ""
            print(
                prose.fill(
                    f"correlated      {len(pairs)} pair(s) with |r| >= 0.9, whose +- are not "
                    f"independent (the model file holds the covariance): {shown_pairs}{more}",
                    width=100,
                    subsequent_indent=" " * 16,
                )
            )
    params = r.get("parameters") or {}
    shown = [(k, v) for k, v in params.items() if v.get("estimated", True)]
    if shown:
        print(
            f"{'parameter':>16} {'value m|rad':>14} {'- nominal':>12} {'std':>10}  "
            "unit of '- nominal' and std"
        )
        for k, v in shown:
            d = v["value"] - v.get("nominal", v["value"]) if "nominal" in v else float("nan")
            scale, unit = display_unit(v["unit"])
            std = v.get("std")
            if std is not None:
                std_s = f"{std * scale:10.4f}"
            else:  # a bound was hit, or a discrete (cross-validated) choice: no Gaussian std
                why = (
                    (f"x/ {v['factor_95']:.3g}" if v["factor_95"] < 1e3 else "x/ >1000")
                    if v.get("factor_95")
                    else "fixed"
                    if v.get("fixed_by_bound")
                    else "at bound"
                    if v.get("at_bound")
                    else "CV grid"
                    if v.get("chosen_by")
                    else "no peak"
                    if v.get("no_std")
                    else "-"
                )
                std_s = f"{why:>10}"
            d_s = f"{d * scale:12.4f}" if "nominal" in v else " " * 12
            name = f"{k}*" if v.get("stands_for") else k
            val = v["value"]  # a value below 1e-3 (a GP's noise std) keeps its digits
            val_s = f"{val:14.4e}" if 0 < abs(val) < 1e-3 else f"{val:14.6f}"
            # the unit is that of '- nominal' and of a std; a factor or a status has none
            unit = unit if std is not None or "nominal" in v else ""
            print(f"{name:>16} {val_s} {d_s} {std_s}  {unit}".rstrip())
        if any(v.get("std") is None and v.get("factor_95") for _, v in shown):
            print(
                prose.fill(
                    "x/ F: 95 % range from value / F to value x F (the uncertainty is Gaussian "
                    "in the log of the value; a +- std beyond half the value would say nothing)",
                    width=100,
                )
            )
        if any(v.get("stands_for") for _, v in shown):
            print(prose.fill(GROUP_STAR_NOTE, width=100))
        if r.get("parameter_std_basis"):
            print(prose.fill(f"std: {r['parameter_std_basis']}", width=100))
    smr = r.get("smr_change")
    if smr is not None:
        to = smr.get("suggested_m") or smr["fitted_m"]
        cmd = (
            refit(to)
            if refit is not None
            else f"workcell fit {r['recording']} --smr-offset=" + ",".join(f"{x:.4f}" for x in to)
        )
        side = smr.get("sideways_kept_m")
        print(
            prose.fill(
                f"note: the fitted SMR is {smr['change_m'] * 1e3:.1f} mm (std "
                f"{smr['std_m'] * 1e3:.2f} mm) from the offset the recording declares "
                f"{_vec_m(smr['declared_m'])}: a controller with the declared TCP needs "
                "corrections of that order. Declare the fitted offset and fit again (the base "
                "registered with the declared one absorbs part of the difference), and set the "
                "controller's TCP to it"
                + (
                    ""
                    if side is None
                    else f" (its sideways components, {side * 1e3:.2f} mm from the declared"
                    + (
                        f" (std {smr['sideways_std_m'] * 1e3:.2f} mm)"
                        if smr.get("sideways_std_m") is not None
                        else ""
                    )
                    + ", "
                    "stay as declared: so small a sideways offset makes the wrist's parameters "
                    "look separately identifiable while the poses barely tell them apart)"
                )
                + ":",
                width=100,
            )
        )
        print(f"  {cmd}")  # on its own line, unwrapped: a command to paste
    for k, v in (r.get("extra") or {}).items():
        if k.startswith("gp_") and isinstance(v, (int, float, list)):
            continue  # the GP's hyperparameters: in the table above, with their std
        print(f"{EXTRA_LABELS.get(k, k):>16} {extra_text(k, v)}")
    b = r.get("bounds")
    if b:
        print(prose.fill(b["line"], width=100))
    if (r.get("extra") or {}).get("converged") is False:
        if r.get("method") == "dh":
            print(
                prose.fill(
                    "warning: the bounded QP stopped after "
                    f"{r['extra'].get('qp_iterations')} iterations before its step fell below "
                    "its tolerance; the parameters may be short of the bounded optimum: compare "
                    "with the fit without --bounds, or loosen the bounds that hold",
                    width=100,
                )
            )
        else:
            print(
                "warning: the LDDMM optimiser stopped before its convergence test held "
                f"({r['extra'].get('optimizer_message')}); the deformation may be short of its "
                "optimum: compare train_rms_after_m with train_rms_linear_m"
            )
    print(f"model           {r['model']}")
