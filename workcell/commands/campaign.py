"""`workcell campaign --robot sim|ur://HOST --tracker sim|serial://PORT --plan P --poses N --out REC`."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from workcell.campaign.devices import open_cell
from workcell.campaign.executor import CampaignConfig, CampaignControl
from workcell.campaign.run import margin_stop, run_campaign
from workcell.errors import UserError, check_output_path

MAX_POSES = 100_000  # ~10 s a pose: eleven days at the tracker


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", default="sim", help="sim or ur://HOST")
    p.add_argument("--tracker", default="sim", help="sim or serial:///dev/ttyX")
    p.add_argument("--plan", default="random", help="grid, random, bo, dopt or vopt")
    p.add_argument("--poses", type=int, default=50, help="number of poses to measure")
    p.add_argument("--out", help="recording to write (.mcap); must not exist")
    p.add_argument("--seed", type=int, default=0, help="plan seed (and simulated truth seed)")
    p.add_argument(
        "--effects",
        default="realistic",
        help="simulated truth: none, realistic, all, or a comma list of effect kinds",
    )
    p.add_argument("--model", default="ur5e", help="robot model when not given by the device")
    p.add_argument(
        "--smr-offset",
        metavar="X,Y,Z",
        help="the SMR's position on the flange in metres (default 0,0,0.06); the envelope and "
        "the margin watch use it",
    )
    p.add_argument("--readings", type=int, default=5, help="tracker readings per pose")
    p.add_argument("--settle", type=float, default=1.0, help="settle time in seconds")
    p.add_argument(
        "--warmup",
        type=float,
        default=0.0,
        help="exercise the arm this many seconds before measuring",
    )
    p.add_argument("--time-scale", type=float, default=1.0, help="simulators: time scale")
    p.add_argument(
        "--envelope",
        metavar="FILE",
        help="safety envelope JSON (joint limits in rad, workspace box and floor in m, speed "
        "caps; `workcell envelope` writes the default to edit); default: the arm's default",
    )
    p.add_argument("--dry-run", action="store_true", help="print and check the plan; do not move")
    p.add_argument("--resume", help="continue this interrupted recording in a new chained file")
    p.add_argument("--online", choices=["ekf-ann"], help="feed samples to an online estimator")
    p.add_argument(
        "--on-protective-stop",
        choices=["ask", "resume"],
        default=None,
        help="after a protective stop: ask on the terminal before resuming (default "
        "when interactive) or resume at once",
    )


def _say_planning(args: argparse.Namespace) -> None:
    """A long plan is not a hang: say so before checking thousands of paths."""
    if args.poses >= 1000 and args.plan in ("random", "grid"):  # adaptive plans choose later
        print(
            f"planning {args.poses} poses and checking every path against the envelope "
            "(minutes for this many; Ctrl-C stops)",
            file=sys.stderr,
            flush=True,
        )


def run(args: argparse.Namespace) -> int:
    if args.resume:
        from workcell.campaign.resume import resume_campaign

        return resume_campaign(args)
    if args.poses <= 0:
        raise UserError(f"--poses must be positive, got {args.poses}")
    if args.poses > MAX_POSES:
        raise UserError(
            f"--poses {args.poses} is more than a campaign can measure (limit {MAX_POSES}); "
            "split it into several recordings"
        )
    if args.readings <= 0:
        raise UserError(f"--readings must be positive, got {args.readings}")
    if args.seed < 0:
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    if not (math.isfinite(args.time_scale) and args.time_scale > 0):
        raise UserError(f"--time-scale must be a positive number, got {args.time_scale}")
    cell, robot, tracker, env = open_cell(args)
    cfg = CampaignConfig(
        readings_per_pose=args.readings,
        settle_s=args.settle,
        payload_kg=cell.payload_kg,
        warmup_s=args.warmup,
    )
    if args.dry_run:
        _say_planning(args)
        return dry_run(args, cell, env, cfg)
    if not args.out:
        raise UserError("--out REC.mcap is required (the recording to write)")
    if Path(args.out).exists():
        raise UserError(f"{args.out} already exists; choose a new file or use --resume")
    check_output_path(args.out, "recording")
    control = CampaignControl()
    control.install_sigint()
    mode = args.on_protective_stop or ("ask" if sys.stdin.isatty() else "resume")
    if mode == "ask":
        control.auto_resume_protective_stop = False
        _ask_on_protective_stop(control)
    n = [0]

    def on_sample(s: dict) -> None:
        n[0] += 1
        print(
            f"pose {s['pose_id']:4d}  {n[0]:4d}/{args.poses}  elapsed {s['elapsed_s']:8.1f} s",
            file=sys.stderr,
            flush=True,
        )

    def on_event(e: dict) -> None:
        print(f"  [{e['level']}] {e['kind']}: {e['message']}", file=sys.stderr, flush=True)

    online = None
    if args.online:
        from workcell.estimation.ekf_ann.live import LiveFilter  # EKF-ANN issue

        online = LiveFilter.for_cell(cell)
        prev = on_sample

        def on_sample(s: dict) -> None:  # noqa: F811
            prev(s)
            print("  " + online.update(s), file=sys.stderr, flush=True)

    _say_planning(args)
    path, res = run_campaign(
        robot,
        tracker,
        cell,
        args.out,
        plan=args.plan,
        poses=args.poses,
        seed=args.seed,
        envelope=env,
        config=cfg,
        control=control,
        on_sample=on_sample,
        on_event=on_event,
        extra_campaign={
            "robot_url": args.robot,
            "tracker_url": args.tracker,
            "effects": args.effects if args.robot == "sim" else None,
        },
    )
    print(f"recorded {res.measured} poses, skipped {res.skipped}, events {res.events} -> {path}")
    margin_stop(res, path)
    return 130 if res.aborted else 0


def _ask_on_protective_stop(control: CampaignControl) -> None:
    """A thread that asks the operator on the terminal when the campaign waits to resume."""
    import threading

    def loop() -> None:
        while not control.abort.is_set():
            if control.waiting_for_resume.wait(0.2):
                print(
                    "protective stop: check the cell, then press Enter to resume (Ctrl-C aborts)",
                    file=sys.stderr,
                    flush=True,
                )
                try:
                    sys.stdin.readline()
                except (OSError, ValueError):
                    return
                control.resume.set()
                while control.waiting_for_resume.is_set():
                    control.abort.wait(0.05)

    threading.Thread(target=loop, name="pstop-prompt", daemon=True).start()


def dry_run(args, cell, env, cfg) -> int:
    from workcell.campaign.executor import dry_run_plan

    targets, problems = dry_run_plan(
        args.plan, cell.spec, env, args.poses, seed=args.seed, tool_m=cell.tool_m, config=cfg
    )
    if targets is None:
        print(
            f"plan {args.plan}: adaptive; each pose is chosen during the campaign inside the "
            f"envelope; {args.poses} poses"
        )
        return 0
    for t in targets:
        print(f"pose {t.pose_id:4d}  q = [" + ", ".join(f"{x:+.4f}" for x in t.q_rad) + "] rad")
    print(f"dry run: {len(targets)} poses, {len(problems)} problems; nothing moved")
    for p in problems:
        print("  " + p)
    return 1 if problems else 0
