"""`workcell envelope [--robot MODEL] [--out FILE] [--check FILE]`: write the arm's default safety
envelope as JSON to edit, or check a file and print it for review (joint limits also in degrees).

The file is what `campaign --envelope`, `validate --envelope` and the TUI's Plan screen take; the
recording keeps the envelope a campaign ran in, and `campaign --resume` reuses it."""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

from workcell.atomic import write_text
from workcell.errors import UserError, check_output_path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", default="ur5e", help="robot model (ur5e, ur10, ...)")
    p.add_argument("--out", metavar="FILE", help="write the default envelope here (JSON)")
    p.add_argument("--check", metavar="FILE", help="check this envelope file for --robot")
    p.add_argument(
        "--model",
        metavar="MODEL",
        help="a fitted model of this arm: measure how far it is from the nominal kinematics the "
        "checks use; with --check, say whether the margin covers it; with --out, write that margin",
    )


def run(args: argparse.Namespace) -> int:
    from workcell.campaign.envelope import default_envelope, load_envelope
    from workcell.kinematics.robots import robot_by_name

    try:
        spec = robot_by_name(args.robot)
    except ValueError as e:
        raise UserError(str(e)) from None
    if args.check and args.out:
        raise UserError("give --out (write the default) or --check FILE, not both")
    model = _load_model_for(args.model, spec) if args.model else None
    if args.check:
        env = load_envelope(args.check, spec)
        frac, n = reach_fraction(env, spec)
        if frac == 0.0:
            raise UserError(
                f"{args.check}: no pose fits: none of {n:,} random configurations in its joint "
                "ranges keeps the arm inside its box and above its floor (with the default SMR "
                "offset); a campaign would refuse it: widen the box or the joint ranges"
            )
        dev = _deviation(model, env, spec) if model is not None else None
        short = dev is not None and env.kinematic_margin_m < dev["suggested_margin_m"]
        # "ok" is the file's own checks; a margin the model says is too small is not ok
        status = f"its margin does not cover {args.model} (below)" if short else "ok"
        print(describe(env, spec, f"{args.check} ({spec.model})", status))
        print(
            f"  reach    {100 * frac:.3g} % of {n:,} random configurations in the joint ranges "
            "keep the arm inside (default SMR offset): what a random plan draws from"
        )
        width = np.ptp(np.asarray(env.joint_limits_rad, float), axis=1)
        if np.all(width < np.radians(5.0)):
            print(
                f"  WARNING: every joint range is narrower than 5 deg (widest "
                f"{np.degrees(width.max()):.3g} deg): the poses barely differ and a fit cannot "
                "tell the parameters apart; widen them"
            )
        if dev is not None:
            print(describe_deviation(dev, args.model))
            if short:
                say = (
                    f"margin {1e3 * env.kinematic_margin_m:g} mm is below the suggested "
                    f"{1e3 * dev['suggested_margin_m']:g} mm: raise kinematic_margin_m to "
                    f"{dev['suggested_margin_m']:g}"
                )
                print(f"  {say}")
                print(f"workcell envelope: error: {args.check}: {say}", file=sys.stderr)
                return 1
            print(f"  margin {1e3 * env.kinematic_margin_m:g} mm covers it")
        return 0
    env = default_envelope(spec)
    if model is not None:
        dev = _deviation(model, env, spec)
        if dev["suggested_margin_m"] > 0.1:
            raise UserError(
                f"the model is {1e3 * dev['max_m']:.1f} mm from the nominal kinematics; a margin "
                "above 100 mm is not an envelope, it is a wrong nominal model: check the robot "
                "model and the model's recording"
            )
        print(describe_deviation(dev, args.model))
        env.kinematic_margin_m = max(dev["suggested_margin_m"], 0.001)
    text = json.dumps(env.to_dict(), indent=2)
    if args.out:
        p = check_output_path(args.out, "envelope file")
        if p.exists():
            raise UserError(f"{p} already exists; choose a new file")
        p.parent.mkdir(parents=True, exist_ok=True)
        write_text(p, text + "\n")
        what = f"with the margin from {args.model}" if model is not None else ""
        print(
            f"wrote {p}: the default envelope of the {spec.model}{' ' + what if what else ''}; "
            f"edit it, then check it with `workcell envelope --robot {args.robot} --check {p}`"
        )
    else:
        print(text)
    return 0


def _load_model_for(path: str, spec):
    from workcell.estimation.models import load_model
    from workcell.export.build import nominal_for_model

    model = load_model(path)
    robot = nominal_for_model(model).robot  # wrapped models (augmented) name it through theirs
    if robot and str(robot).lower() != spec.model.lower():
        raise UserError(f"{path} is a model of a {robot}, not a {spec.model}; give --robot {robot}")
    return model


def _deviation(model, env, spec) -> dict:
    from workcell.export.margin import model_deviation

    try:
        return model_deviation(model, env, spec)
    except ValueError as e:
        raise UserError(f"envelope: {e}") from None


def _finite_pair(v) -> tuple[float, float] | None:
    """(low, high) from a model file's interval, or None when it is not two finite numbers."""
    try:
        lo, hi = (float(x) for x in v)
    except (TypeError, ValueError):
        return None
    return (lo, hi) if math.isfinite(lo) and math.isfinite(hi) else None


def describe_deviation(dev: dict, source: str) -> str:
    rms = dev["model_heldout_rms_m"]
    lines = [
        f"model {source}: how far its SMR is from the nominal kinematics the checks use, over "
        f"{dev['configurations']} configurations the envelope allows"
        + (
            f" (the model's own held-out RMS: {1e3 * rms:.3f} mm"
            + (
                f", 95 % CI {1e3 * ci[0]:.3f}-{1e3 * ci[1]:.3f} mm)"
                if (ci := _finite_pair(dev.get("model_heldout_rms_ci95_m")))
                else ")"
            )
            if rms
            else ""
        )
    ]
    for name, f in dev["frames"].items():
        lines.append(
            f"  in the {name} base frame: up to {1e3 * f['max_m']:.2f} mm (99 % within "
            f"{1e3 * f['p99_m']:.2f} mm, RMS {1e3 * f['rms_m']:.2f} mm)"
        )
    lines.append(f"  suggested margin {1e3 * dev['suggested_margin_m']:g} mm: {dev['basis']}")
    return "\n".join(lines)


def reach_fraction(env, spec, n: int = 20_000, seed: int = 0) -> tuple[float, int]:
    """Share of `n` seeded random configurations in the envelope's joint ranges that the
    envelope admits (box, floor, margin) with the default SMR offset."""
    from workcell.campaign.devices import DEFAULT_SMR_OFFSET_M

    lim = np.asarray(env.joint_limits_rad, float)
    q = np.random.default_rng(seed).uniform(lim[:, 0], lim[:, 1], size=(n, len(lim)))
    ok = [v is None for v in env.violations(spec, q, np.asarray(DEFAULT_SMR_OFFSET_M))]
    return float(np.mean(ok)), n


def describe(env, spec, title: str, status: str = "ok") -> str:
    lines = [f"envelope {title}: {status}"]
    arm = np.asarray(spec.joint_limits_rad)
    for j, (lo, hi) in enumerate(np.asarray(env.joint_limits_rad)):
        lines.append(
            f"  joint {j + 1}  [{lo:+.4f}, {hi:+.4f}] rad = [{np.degrees(lo):+7.1f}, "
            f"{np.degrees(hi):+7.1f}] deg   (arm [{np.degrees(arm[j, 0]):+.0f}, "
            f"{np.degrees(arm[j, 1]):+.0f}] deg)"
        )
    lo, hi = np.asarray(env.box_min_m), np.asarray(env.box_max_m)
    lines.append(f"  SMR box  {lo.round(3).tolist()} .. {hi.round(3).tolist()} m (base frame)")
    lines.append(f"  floor    every link frame above z = {env.floor_z_m:g} m (base frame)")
    lines.append(
        f"  margin   {1e3 * env.kinematic_margin_m:g} mm kept from the box and the floor (the "
        "checks use the nominal kinematics; the real arm is off by mm)"
    )
    lines.append(
        f"  caps     {env.max_speed_rad_s:g} rad/s, {env.max_accel_rad_s2:g} rad/s^2 per joint"
    )
    if getattr(env, "defaulted", ()):
        lines.append(
            f"  default  {', '.join(env.defaulted)}: not in the file, the value above is the "
            "default"
        )
    return "\n".join(lines)
