"""`workcell tui [--robot sim|ur://HOST] [--tracker sim|serial://PORT] [--sim]`: the shop-floor
terminal UI (Textual). `--sim` starts the protocol-level simulators (UR controller + GeoCOM
tracker, `workcell sim`) and connects to them; `--robot sim --tracker sim` (the default) is the
in-process simulation."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from workcell.errors import UserError


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
    p.add_argument("--poses", type=int, default=50, help="default number of poses in the plan")
    p.add_argument("--out", default="campaign.mcap", help="default recording path")


def run(args: argparse.Namespace) -> int:
    from workcell.tui.app import make_app
    from workcell.tui.backend import PlanConfig

    scale = args.time_scale if args.time_scale is not None else (10.0 if args.sim else 1.0)
    if not (math.isfinite(scale) and scale > 0):
        raise UserError(f"--time-scale must be a finite number > 0 (e.g. 10), got {scale}")
    if args.poses <= 0:
        raise UserError(f"--poses must be positive, got {args.poses}")
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
        plan=PlanConfig(poses=args.poses, seed=args.seed, out=args.out),
    )
    app.run()
    return 0


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
        robot_by_name(args.model)
    except ValueError as e:
        raise UserError(f"--model: {e}") from None
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
