"""`workcell export MODEL --format F --out PATH`: a correction the robot controller can use."""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from workcell import strict_json
from workcell.atomic import atomic_files
from workcell.errors import UserError, check_output_path, refuse_overwrite

FORMATS = ("table", "urscript", "ros-yaml", "targets")
# the targets CSV: comment lines (`# ...`: model, frame, units, coverage, 1-sigma basis), then
# one header row with each column's unit, then numbers
TARGETS_COLUMNS = (
    [f"{a}_m" for a in "xyz"]
    + [f"r{a}_rad" for a in "xyz"]
    + [f"{a}_cmd_m" for a in "xyz"]
    + [f"q{i}_cmd_rad" for i in range(1, 7)]
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", help="fitted model file (.json from `workcell fit`)")
    p.add_argument("--format", required=True, choices=FORMATS, help="what to write")
    p.add_argument("--out", required=True, help="output path")
    p.add_argument(
        "--volume",
        help="work volume x0,y0,z0,x1,y1,z1 in m (SMR in the robot base); default: a box in "
        "front of the robot scaled by its arm length",
    )
    p.add_argument(
        "--orientation",
        action="append",
        help="tool orientation rx,ry,rz (UR rotation vector, rad); repeatable; default 0,pi,0",
    )
    p.add_argument(
        "--interp-error", type=float, help="target max interpolation error, m (default 5e-6)"
    )
    p.add_argument("--spacing", type=float, help="fixed grid spacing in m (skips refinement)")
    p.add_argument(
        "--max-correction", type=float, help="refuse corrections above this, m (default 5e-3)"
    )
    p.add_argument(
        "--approach",
        help="approach sign per joint (the table's conditions; default 1,1,1,1,1,1)",
    )
    p.add_argument(
        "--payload",
        help="payload in kg the correction is for (models with compliance; default: the "
        "recording's)",
    )
    p.add_argument(
        "--joint-temperature",
        help="joint temperatures T1,..,T6 in degC the correction is for (models whose thermal "
        "drift follows the joint temperatures; default: the recording's mean)",
    )
    p.add_argument(
        "--elapsed",
        help="seconds after the campaign's start the correction is for (models whose thermal "
        "drift follows time; default: the recording's mean)",
    )
    p.add_argument("--recording", help="the model's recording (models without a nominal chain)")
    p.add_argument(
        "--in",
        dest="targets_in",
        help="targets: CSV with x,y,z[,rx,ry,rz][,q1..q6 seeds] (base; m, rad, or the unit in "
        "the name: x_mm, rx_deg) or q1..q6 only; also a targets CSV this command wrote (its "
        "desired x_m..rz_rad are corrected again, never its *_cmd_* columns)",
    )
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing output file that is not an earlier workcell export "
        "(never a recording or the command's inputs)",
    )


# The options each format uses; any other given is refused rather than silently ignored.
_CONDITIONS = ("--approach", "--payload", "--joint-temperature", "--elapsed")
_GRID = ("--volume", "--orientation", "--interp-error", "--spacing", "--max-correction")
_USES = {
    "table": {*_GRID, *_CONDITIONS, "--recording"},
    "urscript": {*_GRID, *_CONDITIONS, "--recording"},
    "targets": {"--in", "--max-correction", *_CONDITIONS, "--recording"},
    "ros-yaml": set(),
}
_WHY = {
    "table": "which builds a grid over --volume (--in is for --format targets)",
    "urscript": "which builds a grid over --volume (--in is for --format targets)",
    "targets": "which corrects the --in targets one by one (no grid)",
    "ros-yaml": "which carries the geometry only: no grid, no targets, and no condition changes it",
}


def check_unused_options(args: argparse.Namespace) -> None:
    """Refuse, in one line, options the chosen format would ignore."""
    given = [
        a
        for a in (*_GRID, *_CONDITIONS, "--recording", "--in")
        if getattr(args, "targets_in" if a == "--in" else a[2:].replace("-", "_")) is not None
        and a not in _USES[args.format]
    ]
    if given:
        raise UserError(
            f"{', '.join(given)}: not used by --format {args.format}, {_WHY[args.format]}; "
            f"leave {'it' if len(given) == 1 else 'them'} out"
        )


def run(args: argparse.Namespace) -> int:
    from workcell.estimation.models import load_model
    from workcell.export.build import (
        DEFAULT_INTERP_ERROR_M,
        DEFAULT_MAX_CORRECTION_M,
        conditions_note,
        make_table,
        parse_conditions,
        parse_vec,
    )
    from workcell.export.files import check_export_outputs, output_files, output_kinds
    from workcell.export.frame import frame_lines
    from workcell.export.table import is_warning

    check_unused_options(args)
    if args.interp_error is None:
        args.interp_error = DEFAULT_INTERP_ERROR_M
    if args.max_correction is None:
        args.max_correction = DEFAULT_MAX_CORRECTION_M

    for opt, path in (("--recording", args.recording), ("--in", args.targets_in)):
        if path is not None and not Path(path).is_file():
            raise UserError(f"{opt} {path} does not exist (or is not a file)")
    out = check_output_path(args.out, "output")
    refuse_overwrite(
        output_files(args.format, out), [args.model, args.recording, args.targets_in], "output"
    )
    check_export_outputs(
        output_files(args.format, out),
        args.force,
        (lambda m: None) if args.json else print,
        kinds=output_kinds(args.format),
        named=out,
    )
    cond = parse_conditions(
        args.approach or "1,1,1,1,1,1", args.payload, args.joint_temperature, args.elapsed
    )
    model = load_model(args.model)
    summary: dict = {"format": args.format, "model": args.model, "warnings": []}
    logged: list[str] = []  # what the table build logs: its warnings go in the JSON too

    def log(line: str) -> None:
        logged.append(line)
        if not args.json:
            print(line)

    if args.format == "ros-yaml":
        from workcell.export.build import model_recording
        from workcell.export.ros_yaml import export_ros_yaml

        rec, sha = model_recording(model)
        path, info = export_ros_yaml(
            model, out, meta={"model": args.model, "recording_sha256": sha}
        )
        summary["files"] = [str(path)]
        _copy_unexplained(info, summary)
        for key in ("base_ref", "base_correction"):
            summary[key] = info.get(key)
        log(info["base_correction_line"])
        return _report(args, summary)
    summary["conditions"] = conditions_note(model, cond, strict=True)
    if not args.json:
        for line in summary["conditions"]:
            print(f"conditions: {line}")
    from workcell.export.table import smr_hint

    if cause := smr_hint(model):  # corrections of that order follow, if the bound lets them
        log(f"  WARNING: {cause}")
    if args.format == "targets":
        return _targets(args, model, cond, summary, log, logged)
    volume = parse_vec(args.volume, 6, "--volume") if args.volume else None
    oris = (
        [parse_vec(o, 3, "--orientation") for o in args.orientation] if args.orientation else None
    )
    table, _ = make_table(
        model,
        model_path=args.model,
        volume=volume,
        orientations=oris,
        conditions=cond,
        target_error_m=args.interp_error,
        max_correction_m=args.max_correction,
        spacing_m=args.spacing,
        recording=args.recording,
        log=log,
    )
    log("  " + frame_lines(table.meta, "the table's nodes")[2])
    for key in ("base_ref", "base_correction"):
        summary[key] = table.meta.get(key)
    summary["grid"] = {"shape": list(table.shape), "spacing_m": table.spacing_m.tolist()}
    summary["max_interp_error_m"] = table.meta["max_interp_error_m"]
    summary["max_correction_m"] = table.meta["max_correction_m"]
    summary["interp_error_target_met"] = table.meta["interp_error_target_met"]
    summary["target_interp_error_m"] = table.meta["target_interp_error_m"]
    # the orientation tolerance, chosen so that the table's error stays within that stated error
    summary["orientation_tol_rad"] = table.orientation_tol_rad
    for key in ("orientation_change_at_tol_m", "orientation_error_at_tol_m"):
        summary[key] = table.meta.get(key)
    summary["joint_coverage"] = table.meta["joint_coverage"]
    if "nodes_std_exceeds_correction" in table.meta:
        summary["nodes_std_exceeds_correction"] = table.meta["nodes_std_exceeds_correction"]
    # the 1-sigma (None: the model carries no covariance) and what the model leaves out, as
    # printed and as the table's meta holds them
    summary["median_std_m"] = table.meta.get("median_std_m")
    summary["max_std_m"] = table.meta.get("max_std_m")
    summary["std_posterior"] = table.meta.get("std_posterior", False)
    _copy_unexplained(table.meta, summary)
    summary["warnings"] = [line.strip() for line in logged if is_warning(line)]
    if (w := _interp_warning(args, summary)) is not None:
        summary["warnings"].append(w)
    if args.format == "table":
        summary["files"] = [str(p) for p in table.save(out)]
    else:
        from workcell.export.urscript import size_warning, write_urscript

        script = out if out.suffix else out.with_suffix(".script")
        files = [str(write_urscript(table, script))]
        files += [str(p) for p in table.save(script)]  # X.script -> X.json, X.csv
        summary["files"] = files
        if (w := size_warning(script)) is not None:
            summary["warnings"].append(w)
            summary["script_size_warning"] = w
    return _report(args, summary)


def _copy_unexplained(meta: dict, summary: dict) -> None:
    """What the model leaves unexplained on its held-out poses (metres), as `meta` holds it."""
    for key in ("model_unexplained", "model_unexplained_without_outliers"):
        if meta.get(key) is not None:
            summary[key] = meta[key]


def _interp_warning(args, summary: dict) -> str | None:
    """The line saying the table's interpolation error target is not met, or None."""
    if summary.get("interp_error_target_met", True):
        return None
    why = (
        "with the --spacing given (a finer one lowers the error)"
        if args.spacing is not None
        else "(node limit reached); a smaller volume or fewer orientations give a finer grid"
    )
    return (
        f"warning: the interpolation error target {summary['target_interp_error_m'] * 1e6:.3g} "
        f"um is not met {why}; the table holds the error above"
    )


def _report(args, summary: dict) -> int:
    if args.json:
        print(strict_json.dumps(summary))
    else:
        for f in summary["files"]:
            print(f"wrote {f}")
        if summary.get("script_size_warning"):
            print(summary["script_size_warning"])
        if "max_interp_error_m" in summary:
            print(
                f"grid {summary['grid']['shape']}, max interpolation error "
                f"{summary['max_interp_error_m'] * 1e6:.2f} um, max correction "
                f"{summary['max_correction_m'] * 1e3:.3f} mm"
            )
            if (w := _interp_warning(args, summary)) is not None:
                print(w)
            if "orientation_tol_rad" in summary:
                c, e = summary["orientation_change_at_tol_m"], summary["orientation_error_at_tol_m"]
                at = (
                    "not measured"
                    if c is None or e is None
                    else f"the tilt changes the correction by up to {c * 1e6:.2f} um, the table "
                    f"is off by up to {e * 1e6:.2f} um"
                )
                print(
                    f"orientation tolerance {summary['orientation_tol_rad']:.3g} rad (there {at}); "
                    "a tool orientation further from the table's is refused"
                )
        elif "targets" in summary:
            print(
                f"{summary['targets']} targets, max correction "
                f"{summary['max_correction_m'] * 1e3:.3f} mm"
            )
    return 0


def _check_reach(src: Path, P: np.ndarray, nom, lines: list[int]) -> None:
    """Targets (SMR/TCP in base) must be within the arm's reach; refuse with its line in the file."""
    from workcell.export.build import reach_of
    from workcell.recording.checks import millimetre_hint

    r = reach_of(nom)
    with np.errstate(over="ignore"):  # 1e308: inf, still "beyond reach"
        dist = np.linalg.norm(P, axis=1)
    i = int(np.argmax(dist))
    if dist[i] > r:
        raise UserError(
            f"{src}: line {lines[i]}: target {dist[i]:.4g} m from the base, beyond the "
            f"{nom.robot}'s reach of {r:.3g} m: {millimetre_hint(dist[i], r, 'out of reach')}"
        )


def _check_joints(src: Path, q: np.ndarray, nom, lines: list[int], names=()) -> None:
    """Joint targets must be inside the arm's joint ranges; refuse with its line in the file."""
    from workcell.kinematics.robots import robot_by_name
    from workcell.recording.checks import joint_range_problem

    try:
        spec = robot_by_name(nom.robot)
    except ValueError:
        return  # unknown arm: its controller checks its own limits
    for i in range(len(q)):
        p = joint_range_problem(
            f"{src}: line {lines[i]}",
            "q",
            q[i],
            spec,
            label=lambda j: f"column {names[j] if names else f'q{j + 1}'}",
        )
        if p:
            raise UserError(p[0])


def _check_commanded(src: Path, q: np.ndarray, model, nom, lines: list[int]) -> str:
    """The commanded joints (what the controller will be sent) must lie in the envelope the
    model's recording ran in (the cell's configured one), or, without that recording, in the
    arm's joint ranges; refuse the first that does not with its line in the file. -> the line
    saying what they were checked against."""
    from workcell.campaign.envelope import envelope_of_session
    from workcell.export.build import model_session
    from workcell.kinematics.robots import robot_by_name

    names = [f"q{j}_cmd_rad" for j in range(1, 7)]
    _check_joints(src, q, nom, lines, names)  # the arm's own ranges first (degrees, 2 pi off)
    try:
        spec = robot_by_name(nom.robot)
    except ValueError:
        return "commanded joints: unknown arm, not checked (its controller checks its limits)"
    session, why = model_session(model)
    rec = (getattr(model, "info", {}) or {}).get("recording")
    env = envelope_of_session(session.get("campaign") or {}, spec, str(rec)) if session else None
    if env is None:
        return (
            "commanded joints checked against the arm's joint ranges only: "
            + (why or f"the model's recording {rec} records no envelope")
            + "; check them against the cell's envelope before sending them"
        )
    for i, v in enumerate(env.violations(spec, q, nom.tool_m)):
        if v is not None:
            raise UserError(
                f"{src}: line {lines[i]}: the corrected target's commanded joints "
                f"{np.round(q[i], 3).tolist()} rad leave the envelope the model's recording "
                f"{rec} ran in ({v}): check the target's frame and units, or leave it out"
            )
    return f"commanded joints inside the envelope the model's recording {rec} ran in"


JOINT_SWING_WARN_RAD = 0.05  # a correction of a millimetre moves a joint by ~0.001-0.01 rad


def joint_swing_line(
    q_cmd: np.ndarray, q_nominal: np.ndarray, corr_m: np.ndarray, lines: list[int]
) -> str | None:
    """A warning when a correction moves some joint by more than `JOINT_SWING_WARN_RAD` from
    the nominal solution for the same target: near a singularity (joint 5 near 0 or pi: the
    wrist) a correction of a millimetre swings joints 4 and 6, and an error of the model there
    moves the wrist as much. None when no target does."""
    dq = np.abs(np.angle(np.exp(1j * (np.asarray(q_cmd, float) - np.asarray(q_nominal, float)))))
    big = np.nanmax(dq, axis=1) > JOINT_SWING_WARN_RAD
    if not big.any():
        return None
    i = int(np.argmax(np.where(big, np.nanmax(dq, axis=1), -1.0)))
    j = int(np.nanargmax(dq[i]))
    q5 = float(np.asarray(q_cmd, float)[i, 4])
    wrist = (
        f", joint 5 at {q5:.3f} rad (the wrist singularity is at 0 and pi)"
        if abs(np.sin(q5)) < 0.1
        else ""
    )
    return (
        f"warning: {int(big.sum())} target(s) move a joint by more than {JOINT_SWING_WARN_RAD} rad "
        f"from the nominal solution for a correction of {corr_m[i] * 1e3:.3f} mm: line "
        f"{lines[i]} swings joint {j + 1} by {dq[i, j]:.3f} rad{wrist}; near a singularity a "
        "small model error moves the arm a lot: move those targets away from it, or command them "
        "with care"
    )


def _configuration_line(q: np.ndarray, nom) -> str:
    """The arm configurations (shoulder, elbow, wrist signs) the targets' corrections were solved
    on (`CONFIGURATION_BASIS`): the correction holds on that branch only."""
    from workcell.export.correction import configuration, configuration_dh

    c = configuration(q, configuration_dh(nom.theta))
    uniq, counts = np.unique(c, axis=0, return_counts=True)
    parts = "; ".join(
        f"shoulder {s:+d}, elbow {e:+d}, wrist {w:+d} ({n} target{'s' if n > 1 else ''})"
        for (s, e, w), n in zip(uniq.tolist(), counts.tolist(), strict=True)
    )
    return (
        f"arm configuration of the corrected joints q*_cmd_rad: {parts}; each correction holds "
        "on its configuration only: command the joints, or keep the arm on it"
    )


def _targets(args, model, cond, summary, log, logged: list[str]) -> int:
    from workcell.export.build import model_recording, nominal_for_model, note_unexplained
    from workcell.export.correction import Q_REF, Corrector, matrix_to_rotvec, rotvec_to_matrix
    from workcell.export.files import TARGETS_CSV_MARK
    from workcell.export.frame import frame_lines, frame_meta
    from workcell.export.table import (
        STD_BASIS,
        check_corrections,
        check_target_std,
        coverage_line,
        is_warning,
        joint_coverage,
        no_std_line,
        no_std_why,
        node_std,
        smr_hint,
        std_is_posterior,
        undetermined_line,
        unexplained_lines,
        weak_hint,
    )
    from workcell.export.targets_in import read_targets

    if not args.targets_in:
        raise UserError("--format targets needs --in CSV")
    src = Path(args.targets_in)
    if not src.exists():
        raise UserError(f"{src}: no such file")
    if not src.is_file():
        raise UserError(f"{src}: not a regular file; give a targets CSV file")
    tin = read_targets(src)  # one UserError line on anything it cannot use
    lines = tin.lines
    summary["input"] = {
        "file": str(src),
        "columns": tin.columns,
        "corrected_targets_csv": tin.corrected_csv,
        "notes": tin.notes,
    }
    for note in tin.notes:
        log(note)
    corr = Corrector(model, nominal_for_model(model, args.recording), cond)
    nom = corr.nominal
    if tin.P is not None:
        P = tin.P
        _check_reach(src, P, nom, lines)
        if tin.rotvec is not None:
            R = rotvec_to_matrix(tin.rotvec)
        else:
            R = np.broadcast_to(rotvec_to_matrix([0.0, np.pi, 0.0])[0], (len(P), 3, 3))
        seeds = np.broadcast_to(tin.q if tin.q is not None else Q_REF, (len(P), 6))
        if tin.q is not None:  # seeds in degrees would command far off
            _check_joints(src, seeds, nom, lines, tin.q_columns)
    else:  # joint targets: the nominal arm's pose there is the desired one
        seeds = tin.q
        _check_joints(src, seeds, nom, lines, tin.q_columns)
        P, R = nom.fk(seeds)
    c, q, _ = corr.correct_positions(P, R, seeds)
    bad = ~np.all(np.isfinite(c), axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise UserError(
            f"{src}: line {lines[i]}: no correction for the target at "
            f"{np.round(P[i], 4).tolist()} m with its orientation (IK did not converge: out of "
            f"reach or at a singularity){f'; and {bad.sum() - 1} more' if bad.sum() > 1 else ''}"
        )
    # finite: checked above
    check_corrections(
        c - P, P, args.max_correction, where="target", hint=weak_hint(model), cause=smr_hint(model)
    )
    log("  " + _check_commanded(src, q, model, nom, lines))
    q_nom = seeds if tin.P is None else nom.ik(P, R, seeds, iters=60)[0]
    if (line := joint_swing_line(q, q_nom, np.linalg.norm(c - P, axis=1), lines)) is not None:
        log(f"  {line}")
    rv = matrix_to_rotvec(R)
    mags = np.linalg.norm(c - P, axis=1)
    # as a table's export says them: extrapolated targets, the 1-sigma, what the model leaves out
    coverage = joint_coverage(corr, q, what="targets")
    log("  " + coverage_line(coverage, what="targets"))
    summary["joint_coverage"] = coverage
    sd = node_std(corr, q)  # (N, 3) or None: the model carries no covariance
    summary["median_std_m"] = summary["max_std_m"] = None
    summary["std_basis"] = f"none: {no_std_why(model)}"
    if sd is not None:
        s3 = np.linalg.norm(sd, axis=1)
        summary["median_std_m"], summary["max_std_m"] = float(np.median(s3)), float(s3.max())
        summary["std_basis"] = STD_BASIS
        summary["std_posterior"] = std_is_posterior(model)
        check_target_std(s3, args.max_correction, model, src, lines)
        summary["targets_std_exceeds_correction"] = int(np.sum(s3 > mags))
        log(
            f"  correction 1-sigma (model uncertainty, 3-D): median {np.median(s3) * 1e6:.1f} um, "
            f"max {s3.max() * 1e6:.1f} um"
        )
        if (line := undetermined_line(s3, mags, what="targets")) is not None:
            log(f"  {line}")
    else:
        log(f"  {no_std_line(model)}")
    note_unexplained(model, summary, log)
    summary.update(frame_meta(model, nom.base_ref, P))
    log("  " + frame_lines(summary, "these targets")[2])
    summary["warnings"] = [line.strip() for line in logged if is_warning(line)]
    rec_sha = model_recording(model)[1]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_files(out, newline="") as (f,):
        f.write(f"{TARGETS_CSV_MARK} (workcell export --format targets)\n")
        for line in (
            f"model: {args.model} ({getattr(model, 'method', '?')})",
            f"recording_sha256: {rec_sha}",
            f"robot: {nom.robot}",
            *frame_lines(summary, "these targets"),
            "columns: x_m..rz_rad the desired pose, *_cmd_* what to command (the nominal "
            "orientation is kept): commanded = desired + correction",
            "units: m, rad (UR rotation vectors)",
            f"TCP (SMR) in flange: {np.asarray(nom.tool_m).tolist()} m, the one the correction "
            "assumes: set this TCP in the controller",
            *(f"conditions: {x}" for x in summary["conditions"]),
            *(
                []
                if summary["conditions"]
                else [
                    f"conditions: approach {[int(x) for x in cond.approach_sign]} per joint as "
                    "computed; the model declares no payload-, approach- or thermal-dependent "
                    "term: the correction is the same under any"
                ]
            ),
            _configuration_line(q, nom),
            coverage_line(coverage, what="targets"),
            f"sx_m, sy_m, sz_m: {STD_BASIS}" if sd is not None else no_std_line(model),
            *unexplained_lines(summary),
        ):
            f.write(f"# {' '.join(line.split())}\n")
        w = csv.writer(f)
        w.writerow(TARGETS_COLUMNS + (["sx_m", "sy_m", "sz_m"] if sd is not None else []))
        for i in range(len(P)):
            row = (*P[i], *rv[i], *c[i], *q[i], *(() if sd is None else sd[i]))
            w.writerow([repr(float(v)) for v in row])
    summary["files"] = [str(out)]
    summary["targets"] = len(P)
    summary["max_correction_m"] = float(mags.max())
    return _report(args, summary)
