"""`workcell sim`: start the protocol-level simulators and print one JSON line.

One process hosts the simulated true cell, the UR controller (RTDE 30004, dashboard 29999,
script 30003 on a loopback address) and a GeoCOM tracker on a pseudo-terminal that measures the
robot the controller moves. Prints `{"ur_host": ..., "tracker_port": "/dev/pts/N", "pid": ...}`
and runs until interrupted (Ctrl-C / SIGTERM). Point a campaign at it exactly as at hardware:

    workcell campaign --robot ur://127.0.0.2 --tracker serial:///dev/pts/N --time-scale X ...
"""

from __future__ import annotations

import argparse
import json
import sys

from workcell.errors import UserError

FAULT_PRESETS = {
    "none": {},
    "default": {
        "tracker": {"beam_break_rate": 0.05, "garbage_rate": 0.01},
        "robot": {"rtde_drop_at_move": [10, 30, 50]},
    },
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.2", help="loopback address for the UR controller")
    p.add_argument("--robot", default="ur5e", help="robot model (ur5e, ur10)")
    p.add_argument(
        "--effects",
        default="realistic",
        help="simulated physics: none, realistic, all, or a comma list",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated truth")
    p.add_argument(
        "--time-scale",
        type=float,
        default=1.0,
        help="run X times faster than real time (pass the same to the campaign)",
    )
    p.add_argument(
        "--faults", default="none", help='none, default, or JSON {"robot": {...}, "tracker": {...}}'
    )
    p.add_argument("--no-tracker", action="store_true", help="only the UR controller")


def parse_faults(text: str) -> tuple[dict, dict]:
    if text in FAULT_PRESETS:
        d = FAULT_PRESETS[text]
    else:
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise UserError(
                f"--faults: not a preset ({', '.join(FAULT_PRESETS)}) and not valid JSON ({e.msg})"
            ) from None
        if not isinstance(d, dict) or set(d) - {"robot", "tracker"}:
            raise UserError('--faults JSON must look like {"robot": {...}, "tracker": {...}}')
        for dev in ("robot", "tracker"):
            block = d.get(dev)
            if block is not None and not isinstance(block, dict):
                raise UserError(
                    f'--faults "{dev}" must be an object of fault settings, got {block!r}'
                )
            for k, v in (block or {}).items():
                if (dev, k) == ("tracker", "garbage_mode") and isinstance(v, str):
                    continue  # "before" / "instead" / "mixed", checked by the simulator
                if (dev, k) == ("robot", "restart_power_off"):
                    if not isinstance(v, bool):
                        raise UserError(
                            f"--faults robot.restart_power_off must be true or false, got {v!r}"
                        )
                    continue
                items = v if isinstance(v, list) else [v]
                if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in items):
                    raise UserError(
                        f"--faults {dev}.{k} must be a number or a list of numbers, got {v!r}"
                    )
    return dict(d.get("robot") or {}), dict(d.get("tracker") or {})


def run(args: argparse.Namespace) -> int:
    from workcell.campaign.devices import check_time_scale_range

    check_time_scale_range(args.time_scale)
    if args.seed is not None and not 0 <= args.seed < 2**63:
        raise UserError(f"--seed must be 0..2^63-1, got {args.seed}")
    if not args.host.startswith("127."):
        raise UserError(f"--host {args.host}: the simulator only listens on loopback (127.x.y.z)")
    robot_faults, tracker_faults = parse_faults(args.faults)
    from sim_devices.ur_process import run_sim

    def announce(info: dict) -> None:
        print(json.dumps({k: info[k] for k in ("ur_host", "tracker_port", "pid")}), flush=True)
        print(
            f"simulators running ({args.robot}, effects {args.effects}, seed {args.seed}, "
            f"time scale {args.time_scale}); Ctrl-C to stop",
            file=sys.stderr,
            flush=True,
        )

    try:
        return run_sim(
            args.host,
            args.seed,
            args.effects,
            args.time_scale,
            robot_faults or None,
            not args.no_tracker,
            robot=args.robot,
            ready=announce,
            tracker_faults=tracker_faults or None,
        )
    except OSError as e:
        raise UserError(
            f"cannot start the simulators on {args.host}: {e.strerror or e}; is "
            "another simulator using that address?"
        ) from None
