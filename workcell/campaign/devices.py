"""Open the devices named on the command line: `sim`, `ur://HOST`, `serial://PORT`."""

from __future__ import annotations

import numpy as np

from workcell.campaign.envelope import default_envelope, load_envelope
from workcell.campaign.run import CellSetup, sim_cell
from workcell.errors import UserError
from workcell.kinematics.robots import robot_by_name


def envelope_from_args(args, spec):
    """`--envelope FILE` (checked for this arm) or the arm's default envelope."""
    path = getattr(args, "envelope", None)
    if path in (None, "", "default"):
        return default_envelope(spec)
    return load_envelope(path, spec)


def open_cell(args):
    """-> (CellSetup, robot, tracker, envelope) from parsed CLI args (`envelope`: optional
    FILE; default: the arm's default envelope)."""
    if args.robot == "sim" and args.tracker == "sim":
        _, robot, tracker, cell = sim_cell(args.model, args.effects, args.seed)
        return cell, robot, tracker, envelope_from_args(args, cell.spec)
    if args.robot == "sim" or args.tracker == "sim":
        raise UserError(
            "use --robot sim together with --tracker sim (one simulated world), "
            "or start `workcell sim` and give both real addresses"
        )
    if not args.robot.startswith("ur://"):
        raise UserError(f"--robot {args.robot!r}: expected sim or ur://HOST")
    if not args.tracker.startswith("serial://"):
        raise UserError(f"--tracker {args.tracker!r}: expected sim or serial:///dev/ttyX")
    try:
        from workcell.drivers.serial_tracker import SerialTracker
        from workcell.drivers.ur_robot import UrRobot
    except ModuleNotFoundError as e:
        raise UserError(f"real drivers not available in this build ({e.name})") from None
    spec = robot_by_name(args.model)
    env = envelope_from_args(args, spec)  # refused before any connection
    robot = UrRobot(args.robot[len("ur://") :], time_scale=getattr(args, "time_scale", 1.0))
    tracker = SerialTracker(args.tracker[len("serial://") :])
    cell = CellSetup(
        spec=spec,
        tool_m=np.array([0.0, 0.0, 0.06]),
        base_in_tracker={"translation_m": [0.0, 0.0, 0.0], "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0]},
        tracker_model="GeoCOM tracker",
    )
    return cell, robot, tracker, env
