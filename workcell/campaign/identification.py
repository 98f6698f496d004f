"""What a planned set of poses can identify, said before anything moves (the dry run of the
command line and of the TUI's Plan screen): Theorem 1's rank of the identification Jacobian at
the nominal chain against a rich random pose set, condition and O1, and warnings for parameters
the poses leave dependent or barely separate, and for too few poses to fit."""

from __future__ import annotations

import numpy as np

from workcell.campaign.envelope import Envelope
from workcell.kinematics.robots import RobotSpec

REFERENCE_POSES = 60  # random poses inside the envelope: what well-spread poses identify


def identification_lines(
    spec: RobotSpec, env: Envelope, q: np.ndarray, tool_m: np.ndarray
) -> list[str]:
    """The dry run's identification summary: one line, then a line per warning (each starts
    with 'warning:')."""
    from workcell.campaign.plans import random_configurations
    from workcell.estimation.fitting import MIN_TRAIN_POSES, min_poses_for_fit
    from workcell.estimation.identifiability import pose_set_report

    ref = random_configurations(spec, env, REFERENCE_POSES, np.random.default_rng(0), tool_m)
    r = pose_set_report(spec.dh, q, tool_m, reference_q=ref)
    lines = [
        f"identification (nominal chain, a point measured: 3 equations a pose): rank "
        f"{r['rank']} of the {r['rank_reference']} that well-spread poses give; condition "
        f"{r['condition']:.3g}, O1 {r['o1']:.3g}"
    ]
    if r["missing"]:
        need = -(-r["rank_reference"] // 3)
        why = (
            f"a point tracker needs at least {need} poses"
            if 3 * r["poses"] < r["rank_reference"]
            else "the poses are too alike: spread them over the joints"
        )
        lines.append(
            f"warning: these poses leave {len(r['missing'])} parameter(s) dependent, fixed at "
            f"nominal by the fit: {', '.join(r['missing'])} ({why})"
        )
    n_fit = min_poses_for_fit()
    if r["poses"] < n_fit:
        lines.append(
            f"warning: too few poses to fit ({r['poses']}): a fit needs at least "
            f"{MIN_TRAIN_POSES} training poses, {n_fit} poses with the default 25 % held out"
        )
    weak = r["weakly_identified"]
    for g in weak[:3]:
        lines.append(
            "warning: weakly identified on these poses: {" + ", ".join(g["parameters"]) + "}, "
            f"std {g['std_inflation']:.0f}x what it would be with the others known"
        )
    if len(weak) > 3:
        lines.append(f"warning: ... and {len(weak) - 3} more weakly identified groups")
    return lines
