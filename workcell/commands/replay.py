"""`workcell replay REC --online ekf-ann [--rate X] [--json]`: replay a recording's samples
through an online estimator, printing the same progress lines as a live campaign.

--rate X replays at X times real time (sample times from `elapsed_s`); 0 (default) = as fast
as possible. --json prints the final estimate as JSON (progress lines go to stderr).
--save MODEL writes the final estimate as a model file (`workcell-model/1`, method ekf-ann).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from workcell import strict_json
from workcell.commands import prose
from workcell.commands.options import say_replaced
from workcell.errors import UserError, check_output_path
from workcell.estimation.identifiability import GROUP_STAR_NOTE
from workcell.estimation.models import interval_um
from workcell.recording.chain import add_chain_option


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", help="recording (.mcap) to replay")
    p.add_argument("--online", required=True, choices=["ekf-ann"], help="online estimator")
    p.add_argument("--rate", type=float, default=0.0, help="X times real time (0: max speed)")
    p.add_argument("--json", action="store_true", help="print the final estimate as JSON")
    p.add_argument("--save", help="write the final estimate as a model file")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing file at --save (an earlier model of the same recording is "
        "replaced without it)",
    )
    p.add_argument(
        "--every",
        type=int,
        default=None,
        help="print every Nth progress line (default: about 50 lines in all; 1: every sample)",
    )
    add_chain_option(p)


def screened_samples(rec, name: str, chain_missing: str = "refuse"):
    """The fits' data on a replay: the samples of `rec` and of every file it continues (a
    resumed campaign's chain, `Dataset.from_recording`), screened as the fits screen them
    (`workcell.recording.consistency`): a recording whose tracker positions do not follow the
    arm is refused; exact copies of a sample and gross readings are skipped, with the warnings
    `fit` prints, so the filter sees what the fits see. -> (samples, the data set)."""
    from workcell.recording.chain import load_chain
    from workcell.recording.dataset import Dataset

    chain = load_chain(rec, missing=chain_missing)
    ds = Dataset.from_recording(chain)  # refuses a recording that does not follow the arm
    for note in ds.read_notes:
        if "set aside" in note or "exact copies" in note:
            print(f"warning: {name}: {note} (skipped by the replay too)", file=sys.stderr)
        elif note in chain.notes:
            print(f"warning: {name}: {note}", file=sys.stderr)
    samples = chain.samples
    return [samples[i] for i in ds.row], ds


def geometric_lines(est: dict) -> list[str]:
    """The text report of an initialised estimate's geometric states (`LiveFilter.estimate`).

    A state the data did not determine (`determined_by` "prior": its filter std stayed above
    `held_by_prior_ratio` of its starting std) is printed as held by its prior, not with a +-.
    """
    from workcell.commands.options import display_unit

    s0 = est.get("variance_factor", float("nan"))
    out = [
        f"geometric estimate at the last sample (variance factor s0^2 {s0:.3g}, "
        f"{'passes' if est.get('variance_test_ok') else 'fails'} the 95 % chi^2 test):"
    ]
    groups = est.get("unidentifiable") or []
    stands = {n for n, g in est["geometric"].items() if g.get("stands_for")}
    if groups:
        out += prose.wrap(
            f"not separately identifiable from the first {est.get('n_init', 'n_init')} samples "
            "(fixed at nominal; where the filter estimates one of a group, marked *, it carries "
            "the whole group's effect):",
            width=100,
        )
        out += ["   {" + ", ".join(f"{n}*" if n in stands else n for n in g) + "}" for g in groups]
    for n, g in est["geometric"].items():
        k, u = display_unit(g["unit"])
        name = f"{n}*" if n in stands else n
        head = f"  {name:>14} {g['value'] * k:12.4f}"
        if g.get("determined_by") != "prior":
            out.append(
                f"{head} +- {g['std'] * k:.3g} {u}   (filter alone +- {g['std_filter'] * k:.3g})"
            )
            continue
        cfg_name = "sigma_g0_rad" if g["unit"] == "rad" else "sigma_g0_m"
        out.append(
            f"{head} {u}   held by its prior ({cfg_name} = {g['std_prior'] * k:.3g} {u}), "
            "not measured"
        )
        why = (
            f"filter std {g['std_filter'] * k:.3g} {u} = {g['std_filter_over_prior']:.2f} of the "
            "prior"
        )
        partners = g.get("correlated_with") or {}
        if partners:
            why += "; the data measured only its combination with " + ", ".join(
                f"{m} (correlation {c:+.2f})" if len(partners) > 1 else f"{m}, correlation {c:+.2f}"
                for m, c in partners.items()
            )
        out.extend(prose.wrap(f"({why})", width=100, initial_indent=" " * 30,
                                 subsequent_indent=" " * 31))  # fmt: skip
    if stands:
        out += prose.wrap(GROUP_STAR_NOTE, width=100)
    out += base_lines(est)
    out += split_lines(est)
    out += prose.wrap(f"std: {est['geometric_std_basis']}", width=100)
    held = est.get("held_by_prior") or []
    if held:
        r = est.get("held_by_prior_ratio", 0.5)
        out += prose.wrap(
            f"held by its prior: {', '.join(held)} - not measured (std_filter / std_prior > "
            f"{r}); `workcell fit` on the recording says which combination is weakly identified",
            width=100,
        )
    return out


def base_lines(est: dict) -> list[str]:
    """The combined base and the frame of the base offsets (`LiveFilter.estimate`)."""
    T = est.get("tracker_T_base")
    if not T:
        return []
    t, q = T["translation_m"], T["quaternion_wxyz"]
    st, sr = T.get("translation_std_m"), T.get("rotation_std_rad")
    pm_t = f" +- ({', '.join(f'{x * 1e3:.3g}' for x in st)}) mm" if st else ""
    pm_r = f"  +- ({', '.join(f'{x * 1e3:.3g}' for x in sr)}) mrad about the tracker's x, y, z"
    n = est.get("n_init", "n_init")
    # the states the combined base is made of that the data did not determine: along them its
    # +- is the filter's prior, not a measurement (series D: +- 0.8 mm where `fit` has 27 mm)
    prior = [x for x in est.get("held_by_prior") or [] if x.startswith(("base_", "tool_"))]
    return [
        "base (combined, tracker_T_base: the one to compare with other models):",
        f"  translation ({', '.join(f'{x * 1e3:.4f}' for x in t)}) mm{pm_t}",
        f"  rotation quaternion wxyz ({', '.join(f'{x:.8f}' for x in q)})",
        *([pm_r] if sr else []),
        *(
            prose.wrap(
                f"not measured: {', '.join(prior)} held by their priors (above), so the +- "
                "of the combined base is the filter's prior along them, not what the data "
                "determine; compare a batch fit's std (`workcell fit`) before trusting it",
                width=100,
            )
            if prior and (st or sr)
            else []
        ),
        *prose.wrap(
            f"base_t*, base_r* above are offsets from base_ref, this filter's own registration "
            f"(the nominal chain fitted rigidly to its first {n} samples), which differs from "
            "`workcell fit`'s: compare the combined bases (tracker_T_base; a model file has "
            "it), not the offsets (the combined base too is part of the filter's split between "
            "geometry and network, below)",
            width=100,
        ),
    ]


def split_lines(est: dict) -> list[str]:
    """How the estimate splits the samples between geometry and network (`LiveFilter.estimate`,
    `geometry_split_basis`)."""
    if est.get("geometric_part_rms_m") is None:
        return []

    def ci(key: str) -> str:
        c = interval_um(est.get(key))
        return f" ({c})" if c else ""

    return prose.wrap(
        f"geometry vs network: the geometry alone (network off) fits the {est['fit_samples']} "
        f"samples at {est['geometric_part_rms_m'] * 1e6:.0f} um RMS"
        f"{ci('geometric_part_rms_ci95_m')}, geometry and network at "
        f"{est['rms_m'] * 1e6:.0f} um{ci('rms_ci95_m')} (in-sample, final state). The geometric parameters are the "
        "filter's split between geometry and network, which absorbs part of the geometry: not "
        "comparable one by one with `workcell fit --method dh`'s (compare its RMS with the "
        "geometry-alone figure); their stds are conditional on the network",
        width=100,
    )


def final_lines(lf, recording: str) -> list[str]:
    """The closing report of a live filter fed during a campaign: its estimate, or why there is
    none, and how to get and save one from the recording (commands on lines of their own, so a
    copy and paste gets them whole)."""
    est = lf.estimate()
    if not est.get("initialised"):
        from workcell.estimation.fitting import MIN_TRAIN_POSES

        return [
            f"ekf-ann: no estimate: the filter never started (it initialises on its first "
            f"{lf.n_init} samples and was given {lf.n})",
            f"  a batch estimate: workcell fit {recording}",
            f"    (it needs {MIN_TRAIN_POSES} training poses; --holdout 0 trains on all of them)",
            f"  the filter's: workcell replay {recording} --online ekf-ann",
            f"    (once the recording has {lf.n_init} samples or more)",
        ]
    out = ["ekf-ann estimate at the end of the campaign:"]
    out += geometric_lines(est) if est.get("geometric") else []
    return out + [
        f"save it: workcell replay {recording} --online ekf-ann --save MODEL",
        "  (feeds the recorded samples to the filter again, screened as `workcell fit` screens "
        "them)",
    ]


def run(args: argparse.Namespace) -> int:
    from workcell.estimation.ekf_ann.live import LiveFilter
    from workcell.recording import checks
    from workcell.recording.dataset import read_warnings
    from workcell.recording.reader import read_recording

    if not (args.rate == 0 or 1e-3 <= args.rate <= 1e6):
        raise UserError(
            f"--rate must be 0 (as fast as possible) or 0.001..1e6 times real time, got {args.rate}"
        )
    if args.every is not None and args.every < 1:
        raise UserError(f"--every must be >= 1, got {args.every}")
    replacing: list[str] = []
    if args.save:
        from workcell.estimation.models import check_model_output

        check_output_path(args.save, "model file", inputs=[args.recording])
        # said once the model is written, as `fit` does: a refusal of the recording found later
        # followed "replacing X: (--force)" and left X as it was (fuzz audit, 2026-11-29)
        check_model_output(args.save, args.recording, force=args.force, say=replacing.append)
    rec = read_recording(args.recording, streams=False)
    if not rec.samples and not rec.session.get("chained_from"):
        why = f" ({rec.problems[0]})" if rec.problems else ""
        raise UserError(f"{args.recording}: no /campaign/sample messages{why}; nothing to replay")
    problems = checks.problems_of(rec.session, rec.samples)
    if problems:
        raise UserError(f"{args.recording}: {checks.first_problem(problems)}")
    for line in read_warnings(rec):
        print(line, file=sys.stderr)
    n_own_problems = len(rec.problems)
    rec.samples, ds = screened_samples(rec, args.recording, args.chain_missing)
    for p in ds.read_problems[n_own_problems:]:  # of the files it continues
        print(f"warning: {args.recording}: {p}", file=sys.stderr)
    if ds.chain_line:  # a resumed recording: replayed with every file it continues
        print(f"recording {ds.chain_line}", file=sys.stderr)
    lf = LiveFilter.from_session(rec.session)
    out = sys.stderr if args.json else sys.stdout
    every = args.every
    if every is None:  # a line a sample flooded the screen: 704 for series D, ~1500 for B
        every = max(1, -(-len(rec.samples) // 50))  # at most 50, and the last
        if every > 1:
            print(
                f"  (every {every}th of {len(rec.samples)} samples and the last; --every 1 for "
                "all; s0^2 ok/REJECT: the running chi2 test of the innovations, not a sample "
                "discarded)",
                file=out,
            )
    t_wall0 = time.perf_counter()
    e0 = None
    for k, smp in enumerate(rec.samples):
        if args.rate > 0 and smp.get("elapsed_s") is not None:
            e0 = smp["elapsed_s"] if e0 is None else e0
            wait = (smp["elapsed_s"] - e0) / args.rate - (time.perf_counter() - t_wall0)
            if wait > 0:
                time.sleep(wait)
        try:
            line = lf.update(smp)
        except ValueError as e:
            raise UserError(f"{args.recording}: {e}") from None
        if k % every == 0 or k == len(rec.samples) - 1:
            print("  " + line, file=out, flush=True)
    dt = time.perf_counter() - t_wall0
    est = lf.estimate()
    est["replay_seconds"] = dt
    est["samples_per_s"] = len(rec.samples) / dt if dt > 0 else float("inf")
    if args.save:
        from workcell.estimation.models import save_model
        from workcell.recording.dataset import file_sha256

        try:
            model = lf.model()
            model.info.setdefault("recording", os.path.abspath(args.recording))
            model.info.setdefault("recording_sha256", file_sha256(args.recording))
            if ds.chain:  # a resumed recording: every file of its chain
                model.info.setdefault("recording_chain", [dict(f) for f in ds.chain])
            save_model(model, args.save)
        except ValueError as e:
            raise UserError(str(e)) from None
        say_replaced(replacing)
    if args.json:
        print(strict_json.dumps(est, indent=1))
    else:
        print(
            f"replayed {len(rec.samples)} samples in {dt:.1f} s "
            f"({est['samples_per_s']:.0f} samples/s)"
        )
        geo = est.get("geometric") or {}
        if not est.get("initialised"):
            print(
                f"no estimate: the filter starts after its first {lf.n_init} samples, and this "
                f"recording has {len(rec.samples)}"
            )
        elif geo:
            for line in geometric_lines(est):
                print(line)
    return 0
