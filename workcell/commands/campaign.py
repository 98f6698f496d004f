"""`workcell campaign --robot sim|ur://HOST --tracker sim|serial://PORT --plan P --poses N --out REC`."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from workcell.campaign.devices import open_cell
from workcell.campaign.executor import CampaignConfig, CampaignControl
from workcell.campaign.plans import MAX_POSES, reference_line, reference_repeats
from workcell.campaign.run import (
    abort_note,
    campaign_stop,
    device_errors_say_resume,
    exit_code,
    progress,
    run_campaign,
    summary,
)
from workcell.errors import UserError, check_output_path, stop_if_interrupted
from workcell.recording.repeats import RepeatWatch

# Defaults of the options a resumed campaign takes from its recording instead. They default to
# None so that a resume can tell an option given from one left out, and refuse the former.
DEFAULTS = {
    "robot": "sim",
    "tracker": "sim",
    "plan": "random",
    "poses": 50,
    "seed": 0,
    "effects": "realistic",
    "model": "ur5e",
    "readings": 5,
    "settle": 1.0,
    "warmup": 0.0,
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", help="sim or ur://HOST (default sim)")
    p.add_argument("--tracker", help="sim or serial:///dev/ttyX (default sim)")
    p.add_argument(
        "--plan",
        help="grid, random (default), or an adaptive plan that picks each next pose from the "
        "measurements so far: vopt (V-optimal: least prediction variance over the envelope; "
        "the best measured on the real UR10 data), dopt (D-optimal: greedy O1), bo (GP-UCB as "
        "in seed 002; no better than random for identification, see the README)",
    )
    p.add_argument("--poses", type=int, help="number of poses to measure (default 50)")
    p.add_argument("--out", help="recording to write (.mcap); must not exist")
    p.add_argument("--seed", type=int, help="plan seed (and simulated truth seed; default 0)")
    p.add_argument(
        "--effects",
        help="simulated truth: none, realistic (default), all, or a comma list of effect kinds "
        "(pedestal_tilt, tracker_drift: forms outside the estimation library)",
    )
    p.add_argument("--model", help="robot model when not given by the device (default ur5e)")
    p.add_argument(
        "--smr-offset",
        metavar="X,Y,Z",
        help="the SMR's position on the flange in metres (default 0,0,0.06); the envelope and "
        "the margin watch use it",
    )
    p.add_argument(
        "--payload",
        metavar="KG[,CX,CY,CZ]",
        help="the payload at the flange as set on the teach pendant: mass in kg, centre of mass "
        "in m on the flange (recorded; the gravity-dependent terms use it). Default: the "
        "controller's payload setting (read over RTDE at connect; a warning when it differs "
        "from a given --payload); 0 kg with a warning when the controller does not report one",
    )
    p.add_argument("--readings", type=int, help="tracker readings per pose (default 5)")
    p.add_argument("--settle", type=float, help="settle time in seconds (default 1)")
    p.add_argument(
        "--warmup",
        type=float,
        help="exercise the arm this many seconds before measuring (default 0)",
    )
    p.add_argument(
        "--time-scale",
        type=float,
        help="with `workcell sim --time-scale X` and --robot ur://...: the same X (default 1, "
        "a real controller; checked against the controller's clock before anything moves)",
    )
    p.add_argument(
        "--envelope",
        metavar="FILE",
        help="safety envelope JSON (joint limits in rad, workspace box and floor in m, speed "
        "caps; `workcell envelope` writes the default to edit); default: the arm's default",
    )
    p.add_argument(
        "--reference-every",
        type=int,
        metavar="N",
        help="measure the plan's first pose again after every N poses and at the end, with the "
        "same approach: a record of drift during the campaign (`workcell info` reports it)",
    )
    p.add_argument("--dry-run", action="store_true", help="print and check the plan; do not move")
    p.add_argument(
        "--resume",
        help="continue this interrupted recording in a new chained file (the poses of every "
        "file it continues count as measured; the tracker may be on another serial port if it "
        "is the same instrument)",
    )
    p.add_argument(
        "--remeasure-missing",
        action="store_true",
        help="with --resume: when a file earlier in the chain is missing or has changed, "
        "measure the poses it held again instead of refusing",
    )
    p.add_argument("--online", choices=["ekf-ann"], help="feed samples to an online estimator")
    p.add_argument(
        "--on-protective-stop",
        choices=["ask", "resume", "stop"],
        default=None,
        help="after a protective stop: ask on the terminal before resuming (default "
        "when interactive; the end of input, e.g. < /dev/null, stops the campaign), stop the "
        "campaign with the arm left stopped (default without a terminal) or resume at once "
        "(3 protective stops in a row with no pose measured between them stop it)",
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


def _check_resume_options(args: argparse.Namespace) -> None:
    """A resume continues the recorded campaign: refuse options it would ignore, in one line."""
    given = [
        "--" + k.replace("_", "-")
        for k in (
            "plan",
            "poses",
            "seed",
            "effects",
            "model",
            "readings",
            "settle",
            "warmup",
            "reference_every",
        )  # fmt: skip
        if getattr(args, k) is not None
    ]
    if given:
        raise UserError(
            f"{', '.join(given)}: --resume continues the campaign as it was recorded (plan, "
            "poses, seed, simulated truth, arm, readings, settle, warm-up); leave "
            f"{'it' if len(given) == 1 else 'them'} out, or start a new campaign"
        )
    if args.dry_run:
        raise UserError(
            "--dry-run with --resume: `workcell info REC` shows what was measured; a resume "
            "checks every remaining pose against the recorded envelope before it moves"
        )
    if args.online:
        raise UserError(
            "--online with --resume: the filter's state is not recorded, so it cannot continue; "
            "replay the recordings through it with `workcell replay`"
        )


def _check_time_scale(args: argparse.Namespace) -> None:
    """--time-scale: a positive number, only for a controller (the in-process simulation runs on
    virtual time: it would ignore it); None becomes 1 (real time)."""
    args.time_scale_given = args.time_scale is not None  # a resume checks it on its robot
    if args.time_scale is None:
        args.time_scale = 1.0
        return
    from workcell.campaign.devices import check_time_scale_range

    check_time_scale_range(args.time_scale)
    if args.robot == "sim":  # None on a resume: the recorded robot (the driver checks it)
        raise UserError(
            f"--time-scale {args.time_scale:g} with --robot sim: the in-process simulation runs "
            "on virtual time, so it has no effect; leave it out (it is for a `workcell sim "
            "--time-scale X` controller, given with --robot ur://HOST)"
        )


def _control(args: argparse.Namespace) -> CampaignControl:
    """Ctrl-C, SIGTERM and SIGHUP abort cleanly; after a protective stop, ask on the terminal
    (default when interactive), stop the campaign (default without a terminal: nobody checks
    the cell before the arm moves again) or resume at once."""
    control = CampaignControl()
    control.install_sigint()
    mode = args.on_protective_stop or ("ask" if sys.stdin.isatty() else "stop")
    if mode in ("ask", "stop"):
        control.auto_resume_protective_stop = False
    if mode == "stop":
        control.stop_at_protective_stop = True
    if mode == "ask":
        _ask_on_protective_stop(control)
    return control


def run(args: argparse.Namespace) -> int:
    if getattr(args, "remeasure_missing", False) and not args.resume:
        raise UserError(
            "--remeasure-missing goes with --resume (it says what to do when a file the "
            "resumed recording continues is missing); leave it out"
        )
    if args.resume:
        from workcell.campaign.resume import resume_campaign

        _check_resume_options(args)
        _check_time_scale(args)
        for k in ("readings", "settle", "effects", "model"):
            setattr(args, k, DEFAULTS[k])  # for recordings that do not say (older ones)
        control = _control(args)
        with device_errors_say_resume():
            return resume_campaign(args, control)
    for k, v in DEFAULTS.items():
        if getattr(args, k) is None:
            setattr(args, k, v)
    if args.poses <= 0:
        raise UserError(f"--poses must be positive, got {args.poses}")
    if args.poses > MAX_POSES:
        raise UserError(
            f"--poses {args.poses} is more than a campaign can measure (limit {MAX_POSES}); "
            "split it into several recordings"
        )
    if args.readings <= 0:
        raise UserError(f"--readings must be positive, got {args.readings}")
    if args.reference_every is not None and args.reference_every <= 0:
        raise UserError(
            f"--reference-every must be a positive number of poses, got {args.reference_every}"
        )
    if args.seed < 0:
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    _check_time_scale(args)
    cell, robot, tracker, env = open_cell(args)
    cfg = CampaignConfig(
        readings_per_pose=args.readings,
        settle_s=args.settle,
        payload_kg=cell.payload_kg,
        warmup_s=args.warmup,
    )
    if args.dry_run:
        _say_planning(args)
        return dry_run(args, cell, env, cfg, start_posture(args, robot))
    if not args.out:
        raise UserError("--out REC.mcap is required (the recording to write)")
    if Path(args.out).exists():
        if Path(args.out).is_file() and Path(args.out).stat().st_size == 0:
            raise UserError(
                f"{args.out} already exists and is empty (0 bytes: a campaign that stopped "
                "before recording anything, on a full disk?); delete it or choose a new file"
            )
        if Path(args.out).is_dir():
            raise UserError(f"{args.out} is a folder; give the recording's file name (REC.mcap)")
        raise UserError(f"{args.out} already exists; choose a new file or use --resume")
    check_output_path(args.out, "recording")
    from workcell.campaign.identification import too_few_to_fit_notes

    # said (and recorded) once the devices answer, before the arm moves, as the dry run says it
    notes = too_few_to_fit_notes(args.poses)
    control = _control(args)
    n = [0]

    repeats = RepeatWatch()

    def on_sample(s: dict) -> None:
        r = repeats.update(s)
        if r is not None:  # the reference pose measured again (--reference-every)
            progress(
                f"pose {s['pose_id']:4d}  reference   elapsed {s['elapsed_s']:8.1f} s  "
                f"{r['displacement_m'] * 1e6:.1f} um from its first reading (scatter alone "
                f"~{r['noise_m'] * 1e6:.1f} um)"
            )
            return
        n[0] += 1
        progress(f"pose {s['pose_id']:4d}  {n[0]:4d}/{args.poses}  elapsed {s['elapsed_s']:8.1f} s")

    def on_event(e: dict) -> None:
        progress(f"  [{e['level']}] {e['kind']}: {e['message']}")

    online = None
    if args.online:
        from workcell.estimation.ekf_ann.live import LiveFilter  # EKF-ANN issue

        online = LiveFilter.for_cell(cell)
        prev = on_sample

        def on_sample(s: dict) -> None:  # noqa: F811
            prev(s)
            progress("  " + online.update(s))

    _say_planning(args)
    with device_errors_say_resume():
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
                "sim_seed": args.seed if args.robot == "sim" else None,
            },
            reference_every=args.reference_every or 0,
            notes=notes,
        )
    if online is not None:  # the filter's final estimate, or why there is none
        _online_report(online, path, control)
    again = f" (and the reference {res.measured - n[0]} more times)" if res.measured > n[0] else ""
    summary(
        f"recorded {n[0]} poses{again}, skipped {res.skipped}, events {res.events} -> {path}",
        control,
    )
    campaign_stop(res, path)
    abort_note(res, path)
    return exit_code(res, control)


def _online_report(online, path, control: CampaignControl) -> None:
    """The online filter's closing report on stdout (`replay.final_lines`): its estimate with
    groups, base frame and uncertainty, or one line saying it never started; best effort, the
    recording is closed already."""
    from workcell.commands.replay import final_lines

    try:
        lines = final_lines(online, str(path))
    except Exception as e:  # noqa: BLE001 - a report failure must not fail a recorded campaign
        progress(f"ekf-ann: no final estimate ({type(e).__name__}: {e})")
        return
    for line in lines:
        summary(line, control)


NOT_ACKNOWLEDGED = (
    "the protective stop was not acknowledged: standard input ended (no operator to press "
    "Enter; run on a terminal to be asked)"
)


def _ask_on_protective_stop(control: CampaignControl, stdin=None) -> None:
    """A thread that asks the operator on the terminal when the campaign waits to resume. Only
    an Enter typed after the question releases the stop: what was typed before (type-ahead)
    is flushed from a terminal first. The end of input (Ctrl-D, `< /dev/null`, a closed pipe)
    is no acknowledgement: the campaign stops (`control.stop_reason`), the arm left stopped."""
    import select
    import threading

    stream = sys.stdin if stdin is None else stdin
    try:
        fd = stream.fileno()
    except (AttributeError, OSError, ValueError):
        fd = None

    def flush_type_ahead() -> None:
        if fd is not None and os.isatty(fd):
            import termios

            try:
                termios.tcflush(fd, termios.TCIFLUSH)
            except (OSError, termios.error):
                pass

    def answer() -> bool | None:
        """True: a line (Enter); False: the end of input; None: the campaign was aborted."""
        if fd is None:
            return bool(stream.readline())
        while not control.abort.is_set():
            ready, _, _ = select.select([fd], [], [], 0.2)
            if ready:
                return bool(os.read(fd, 4096))  # unbuffered: nothing kept for the next stop
        return None

    def loop() -> None:
        while not control.abort.is_set():
            if control.waiting_for_resume.wait(0.2):
                flush_type_ahead()
                progress(
                    "protective stop: check the cell, then press Enter to resume (Ctrl-C aborts)"
                )
                try:
                    got = answer()
                except (OSError, ValueError):
                    got = False
                if got is None:
                    return
                if not got:
                    control.stop_reason = NOT_ACKNOWLEDGED
                    control.abort.set()
                    return
                control.resume.set()
                while control.waiting_for_resume.is_set():
                    control.abort.wait(0.05)

    threading.Thread(target=loop, name="pstop-prompt", daemon=True).start()


def start_posture(args, robot) -> np.ndarray | None:
    """The arm's posture when a campaign would start, when a dry run can know it without
    connecting: the in-process simulated arm's (`--robot sim`); None for a real controller."""
    if args.robot != "sim":
        return None
    try:
        return np.asarray(robot.state().q_rad, float)
    except Exception:  # noqa: BLE001 - a simulation that cannot say: checked when it starts
        return None


def start_line(start_q: np.ndarray | None, robot: str) -> str:
    """The dry run's line on where the first move is checked from."""
    from workcell.campaign.plans import fmt_q

    if start_q is not None:
        return (
            f"the first move is checked from the simulated arm's start posture q = "
            f"{fmt_q(start_q)} rad, where the campaign starts"
        )
    return (
        f"the first move is not checked here: a dry run does not connect to {robot}, so the "
        "campaign checks it when it starts, from wherever the arm is then (jog it inside the "
        "envelope, near the plan's first pose)"
    )


def dry_run(args, cell, env, cfg, start_q=None) -> int:
    from workcell.campaign.executor import PREVIEW_KINDS, dry_run_plan, preview_adaptive_plan

    targets, problems = dry_run_plan(
        args.plan, cell.spec, env, args.poses, seed=args.seed, tool_m=cell.tool_m, config=cfg,
        start_q=start_q,
    )  # fmt: skip
    if targets is None:
        print(
            f"plan {args.plan}: adaptive; each pose is chosen during the campaign inside the "
            f"envelope, among those the arm may move to from where it is; {args.poses} poses"
        )
        if args.plan not in PREVIEW_KINDS:
            return _dry_run_unlisted(args, cell, env, start_q)
        targets, problems = preview_adaptive_plan(
            args.plan, cell.spec, env, args.poses, seed=args.seed, tool_m=cell.tool_m,
            base_in_tracker=cell.base_in_tracker, config=cfg, start_q=start_q,
        )  # fmt: skip
        print(
            f"preview: the poses {args.plan} chooses if the arm is its nominal chain (the "
            "campaign's choice moves with what is measured):"
        )
    for t in targets:
        print(f"pose {t.pose_id:4d}  q = [" + ", ".join(f"{x:+.4f}" for x in t.q_rad) + "] rad")
    print(f"dry run: {len(targets)} poses, {len(problems)} problems; nothing moved")
    print(start_line(start_q, args.robot))
    if args.reference_every and targets:
        print(reference_line(targets[0].pose_id, len(targets), args.reference_every))
    for p in problems:
        print("  " + p)
    if targets:
        from workcell.campaign.identification import (
            identification_lines,
            plan_pose_count_line,
            reference_poses,
        )

        stop_if_interrupted()  # seconds to minutes of identification for thousands of poses
        q = np.array([t.q_rad for t in targets])
        ref = reference_poses(cell.spec, env, cell.tool_m)
        lines = identification_lines(
            cell.spec, env, q, cell.tool_m, cell.base_in_tracker, reference_q=ref
        )
        print("\n".join(lines))
        stop_if_interrupted()
        line = plan_pose_count_line(
            args.plan, cell.spec, env, seed=args.seed, tool_m=cell.tool_m,
            base_in_tracker=cell.base_in_tracker, approach_rad=cfg.approach_rad,
            previewed_q=q if args.plan in PREVIEW_KINDS else None, reference_q=ref,
        )  # fmt: skip
        if line:
            print(line)
    return 1 if problems else 0


def _dry_run_unlisted(args, cell, env, start_q=None) -> int:
    """The dry run of an adaptive plan with no preview (bo): why its poses are not listed, and
    what does not need them: where the first move is checked from, the reference pose, and the
    warnings that depend on the pose count alone."""
    from workcell.campaign.identification import pose_count_warnings

    print(
        f"{args.plan} chooses each pose from the position errors measured so far, which the "
        "nominal chain does not have, so its poses cannot be listed before the campaign; each "
        "move is checked against the envelope when it is made"
    )
    print(f"dry run: {args.poses} poses, chosen during the campaign; nothing moved")
    print(start_line(start_q, args.robot))
    if args.reference_every:
        # the live campaign's reference is the plan's first pose (`plans.with_reference`)
        print(
            f"reference: pose 0 (the first pose {args.plan} chooses) measured again after every "
            f"{args.reference_every} poses and at the end "
            f"({reference_repeats(args.poses, args.reference_every)} more measurements; each "
            "move to it is checked against the envelope when it is made)"
        )
    for line in pose_count_warnings(cell.spec, env, cell.tool_m, args.poses):
        print(line)
    return 0
