"""`workcell tui [--robot sim|ur://HOST] [--tracker sim|serial://PORT] [--sim]`: the shop-floor
terminal UI (Textual). `--sim` starts the protocol-level simulators (UR controller + GeoCOM
tracker, `workcell sim`) and connects to them; `--robot sim --tracker sim` (the default) is the
in-process simulation. SIGTERM, SIGHUP and SIGINT abort a running campaign cleanly, as on the
command line (arm stopped, recording closed), then quit with exit code 128 + the signal."""

from __future__ import annotations

import argparse
import signal
import threading
import time
from pathlib import Path

from workcell.errors import UserError, console_command, hard_exit


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", default="sim", help="sim (in-process) or ur://HOST")
    p.add_argument("--tracker", default="sim", help="sim (in-process) or serial:///dev/ttyX")
    p.add_argument(
        "--sim",
        action="store_true",
        help="start the protocol simulators (UR controller + GeoCOM tracker) and connect",
    )
    p.add_argument("--model", default="ur5e", help="robot model (ur5e, ur10)")
    p.add_argument("--effects", default="realistic", help="simulated physics (simulators only)")
    p.add_argument("--seed", type=int, default=0, help="simulated truth seed / plan seed")
    p.add_argument(
        "--time-scale",
        type=float,
        default=None,
        help="simulators run this many times faster (default 10 with --sim, else 1)",
    )
    p.add_argument("--sim-host", default="127.0.0.2", help="loopback address for --sim")
    p.add_argument(
        "--smr-offset",
        metavar="X,Y,Z",
        default="",
        help="the SMR's position on the flange in metres (default 0,0,0.06)",
    )
    p.add_argument(
        "--payload",
        metavar="KG[,CX,CY,CZ]",
        default="",
        help="the payload at the flange as set on the teach pendant (kg; centre of mass in m); "
        "default: the simulated arm's, or the controller's payload setting (0 kg with a warning "
        "when it does not report one)",
    )
    p.add_argument("--poses", type=int, default=50, help="default number of poses in the plan")
    p.add_argument("--out", default="campaign.mcap", help="default recording path")


def run(args: argparse.Namespace) -> int:
    from workcell.tui.app import make_app
    from workcell.tui.backend import PlanConfig
    from workcell.tui.screens.devices import check_time_scale

    scale = args.time_scale if args.time_scale is not None else (10.0 if args.sim else 1.0)
    from workcell.campaign.plans import MAX_POSES

    # the Devices screen's rules: 0.01..1000, and 1 with the in-process simulation (virtual time)
    check_time_scale(scale, args.robot, args.sim, opt="--time-scale", robot_opt="--robot")
    if not 0 < args.poses <= MAX_POSES:
        raise UserError(f"--poses must be 1..{MAX_POSES}, got {args.poses}")
    check_args(args)
    app = make_app(
        args.robot,
        args.tracker,
        sim=args.sim,
        model=args.model,
        effects=args.effects,
        seed=args.seed,
        time_scale=scale,
        sim_host=args.sim_host,
        smr_offset=getattr(args, "smr_offset", ""),
        payload=getattr(args, "payload", "") or "",
        plan=PlanConfig(poses=args.poses, seed=args.seed, out=args.out),
    )
    console = console_command()  # not a test calling run()
    old = install_abort_signals(app, hard_exit=console)
    try:
        app.run()
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    code = int(app.return_code or 0)
    if app.exit_signal and console:
        # ended by a signal, the campaign aborted and its recording closed, the devices closed:
        # end the process now, as the command line does after Ctrl-C (`cli.main`): JAX's exit
        # clean-up would wait for an estimate still compiling in the EKF-ANN thread (tens of
        # seconds), and whoever sent the signal would find the process still there
        hard_exit(code)
    return code


def install_abort_signals(app, *, hard_exit: bool = False) -> dict:
    """SIGINT, SIGTERM and SIGHUP (`ABORT_SIGNALS`: `kill`, `timeout`, a closed terminal) abort
    a running campaign cleanly, as on the command line: its `control.abort` is set at once (the
    arm stopped after the current step, the `abort` event written, the recording closed, even if
    the UI can no longer draw), and the app quits once the campaign has ended; with none running
    it quits at once, devices closed (`WorkcellApp.abort_signal`, handed to the event loop).

    `hard_exit` (the console command): a watchdog then ends the process if the UI has not ended
    it `EXIT_GRACE_S` after the campaign's worker finished (a closed terminal leaves Textual
    blocked restoring it). Returns the handlers it replaced, by signal."""
    from workcell.campaign.executor import ABORT_SIGNALS

    watching: list[threading.Thread] = []

    def handler(signum, frame) -> None:
        loop = getattr(app, "_loop", None)
        if loop is None or loop.is_closed():  # the UI is not running (yet, or any more)
            raise KeyboardInterrupt
        control = app.control
        if control is not None:
            control.abort.set()
        loop.call_soon_threadsafe(app.abort_signal, signum)
        if hard_exit and not watching:
            t = threading.Thread(
                target=_exit_watchdog, args=(app, 128 + signum), name="exit-watchdog", daemon=True
            )
            watching.append(t)
            t.start()

    return {sig: signal.signal(sig, handler) for sig in ABORT_SIGNALS}


EXIT_GRACE_S = 5.0


def _exit_watchdog(app, code: int) -> None:
    """After an abort signal: once the campaign's worker has ended (its recording closed), give
    the UI `EXIT_GRACE_S` to quit by itself, then close what is still open and end the process
    (the terminal may be gone: nothing left to show)."""
    app.campaign_idle.wait()
    time.sleep(EXIT_GRACE_S)
    dev = app.devices
    if dev is not None:
        if app.validating:  # the closed-loop check has no pause: stop the arm where it is
            try:
                dev.robot.stop()
            except Exception:  # noqa: BLE001 - best effort, the process is ending
                pass
        try:
            dev.close()
        except Exception:  # noqa: BLE001
            pass
    hard_exit(code)


def _port_in_use(host: str) -> int | None:
    """The first of the simulated controller's ports (dashboard, script, RTDE) already bound on
    `host`, else None: its child process would print "Address already in use" over the UI."""
    import socket

    from sim_devices.ur_controller import DASHBOARD_PORT, RTDE_PORT, SCRIPT_PORT

    for port in (DASHBOARD_PORT, SCRIPT_PORT, RTDE_PORT):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            # as the simulator binds (a closed one's TIME_WAIT does not count; a listener does)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((host, port))
            except OSError:
                return port
    return None


def check_args(args: argparse.Namespace) -> None:
    """What the TUI would only find out on its Devices or Campaign screen, refused before it
    starts: one line each."""
    from workcell.errors import check_output_path
    from workcell.kinematics.robots import robot_by_name

    if args.seed < 0:
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    from workcell.campaign.devices import check_device_pair, parse_smr_offset

    parse_smr_offset(getattr(args, "smr_offset", ""))
    if args.robot != "sim" and not args.robot.startswith("ur://"):
        raise UserError(f"--robot {args.robot!r}: expected sim or ur://HOST")
    if args.tracker != "sim" and not args.tracker.startswith("serial://"):
        raise UserError(f"--tracker {args.tracker!r}: expected sim or serial:///dev/ttyX")
    try:
        spec = robot_by_name(args.model)
    except ValueError as e:
        raise UserError(f"--model: {e}") from None
    if getattr(args, "payload", ""):
        from workcell.campaign.devices import parse_payload

        parse_payload(args.payload, spec)
    if args.sim and (args.robot != "sim" or args.tracker != "sim"):
        raise UserError(
            "--sim starts its own simulated devices: --robot and --tracker are not used with it "
            "(leave them out, or drop --sim to connect to those devices)"
        )
    if not args.sim:
        check_device_pair(args.robot, args.tracker)
    if args.sim and not args.sim_host.startswith("127."):
        raise UserError(
            f"--sim-host {args.sim_host}: the simulator only listens on loopback (127.x.y.z)"
        )
    if args.sim and (busy := _port_in_use(args.sim_host)) is not None:
        raise UserError(
            f"--sim-host {args.sim_host}: port {busy} is already in use there (another "
            "simulator or a test?); give another --sim-host, e.g. 127.0.0.3"
        )
    if args.sim or args.robot == "sim":
        from sim_devices.truth import parse_effects

        try:
            parse_effects(args.effects)
        except ValueError as e:
            raise UserError(f"--effects: {e}") from None
    if not Path(args.out).exists():  # an existing one: the Campaign screen asks for a new name
        check_output_path(args.out, "recording")
