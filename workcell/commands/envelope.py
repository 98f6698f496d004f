"""`workcell envelope [--robot MODEL] [--out FILE] [--check FILE]`: write the arm's default safety
envelope as JSON to edit, or check a file and print it for review (joint limits also in degrees).

The file is what `campaign --envelope`, `validate --envelope` and the TUI's Plan screen take; the
recording keeps the envelope a campaign ran in, and `campaign --resume` reuses it."""

from __future__ import annotations

import argparse
import json

import numpy as np

from workcell.errors import UserError, check_output_path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", default="ur5e", help="robot model (ur5e, ur10, ...)")
    p.add_argument("--out", metavar="FILE", help="write the default envelope here (JSON)")
    p.add_argument("--check", metavar="FILE", help="check this envelope file for --robot")


def run(args: argparse.Namespace) -> int:
    from workcell.campaign.envelope import default_envelope, load_envelope
    from workcell.kinematics.robots import robot_by_name

    try:
        spec = robot_by_name(args.robot)
    except ValueError as e:
        raise UserError(str(e)) from None
    if args.check and args.out:
        raise UserError("give --out (write the default) or --check FILE, not both")
    if args.check:
        env = load_envelope(args.check, spec)
        print(describe(env, spec, f"{args.check} ({spec.model})"))
        return 0
    env = default_envelope(spec)
    text = json.dumps(env.to_dict(), indent=2)
    if args.out:
        p = check_output_path(args.out, "envelope file")
        if p.exists():
            raise UserError(f"{p} already exists; choose a new file")
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text + "\n")
        print(
            f"wrote {p}: the default envelope of the {spec.model}; edit it, then check it with "
            f"`workcell envelope --robot {args.robot} --check {p}`"
        )
    else:
        print(text)
    return 0


def describe(env, spec, title: str) -> str:
    lines = [f"envelope {title}: ok"]
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
    return "\n".join(lines)
