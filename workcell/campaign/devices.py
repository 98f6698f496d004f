"""Open the devices named on the command line: `sim`, `ur://HOST`, `serial://PORT`."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from workcell.campaign.envelope import Envelope, default_envelope, load_envelope
from workcell.campaign.run import CellSetup
from workcell.errors import UserError
from workcell.kinematics.robots import RobotSpec, robot_by_name
from workcell.recording.checks import SMR_OFFSET_MAX_M

if TYPE_CHECKING:
    import argparse

    from workcell.drivers.protocols import Robot, Tracker


def envelope_from_args(args: argparse.Namespace, spec: RobotSpec) -> Envelope:
    """`--envelope FILE` (checked for this arm) or the arm's default envelope."""
    path = getattr(args, "envelope", None)
    if path in (None, "", "default"):
        return default_envelope(spec)
    return load_envelope(path, spec)


DEFAULT_SMR_OFFSET_M = (0.0, 0.0, 0.06)


def parse_smr_offset(text: str | None, what: str = "--smr-offset") -> np.ndarray:
    """'X,Y,Z' in metres on the flange -> (3,); None or '' -> the default. Refuses a length
    over `SMR_OFFSET_MAX_M` (millimetres typed as metres) and anything not three finite
    numbers."""
    if text is None or str(text).strip() == "":
        return np.array(DEFAULT_SMR_OFFSET_M)
    try:
        v = np.array([float(x) for x in str(text).split(",")])
    except ValueError:
        v = np.array([])
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise UserError(f"{what} must be three numbers X,Y,Z in metres on the flange, got {text!r}")
    if math.hypot(*v) > SMR_OFFSET_MAX_M:  # hypot: no overflow warning on 1e300
        raise UserError(
            f"{what} {text!r} is {math.hypot(*v):g} m from the flange: the offset is in "
            "metres (109 mm is 0,0,0.109)"
        )
    return v


TIME_SCALE_RANGE = (0.01, 1000.0)  # a simulation 100x slower .. 1000x faster than real time


def check_time_scale_range(scale: float, opt: str = "--time-scale") -> None:
    """A time scale that is a finite number inside `TIME_SCALE_RANGE` (1e300 overflowed the
    recording's timestamps; 1e-320 stopped the simulated controller's clock)."""
    lo, hi = TIME_SCALE_RANGE
    if not (math.isfinite(scale) and lo <= scale <= hi):
        raise UserError(f"{opt} must be a number from {lo:g} to {hi:g} (e.g. 10), got {scale:g}")


PAYLOAD_COM_MAX_M = 0.5  # a centre of mass further from the flange is millimetres typed


def parse_payload(text: str, spec: RobotSpec, what: str = "--payload") -> tuple[float, tuple]:
    """'KG' or 'KG,CX,CY,CZ' (mass in kilograms, centre of mass in metres on the flange, as set
    on the teach pendant) -> (mass_kg, com_m). Refuses a negative or non-finite mass, one above
    the arm's rated payload (grams typed as kilograms), a centre of mass beyond
    `PAYLOAD_COM_MAX_M` (millimetres) and anything else."""
    try:
        v = [float(x) for x in str(text).split(",")]
    except ValueError:
        v = []
    if len(v) not in (1, 4) or not all(np.isfinite(v)):
        raise UserError(
            f"{what} must be KG or KG,CX,CY,CZ (kilograms; centre of mass in metres on the "
            f"flange), got {text!r}"
        )
    mass, com = v[0] + 0.0, tuple(v[1:]) if len(v) == 4 else (0.0, 0.0, 0.0)  # -0 is 0
    if mass < 0:
        raise UserError(f"{what}: the mass is negative ({mass:g} kg)")
    if mass > spec.max_payload_kg:
        hint = "; it looks like grams, give kilograms" if mass > 100 * spec.max_payload_kg else ""
        raise UserError(
            f"{what}: {mass:.10g} kg is above the {spec.model}'s rated payload "
            f"{spec.max_payload_kg:g} kg{hint}"
        )
    if math.hypot(*com) > PAYLOAD_COM_MAX_M:  # hypot: no overflow warning on 1e300
        raise UserError(
            f"{what}: the centre of mass is {math.hypot(*com):g} m from the flange: give it in "
            "metres (30 mm is 0.03)"
        )
    return float(mass), tuple(float(c) for c in com)


def check_device_pair(robot: str, tracker: str) -> None:
    """A simulated robot goes with a simulated tracker (one simulated world): refuse a mix."""
    if (robot == "sim") != (tracker == "sim"):
        raise UserError(
            "use --robot sim together with --tracker sim (one simulated world), "
            "or start `workcell sim` and give both real addresses"
        )


def open_cell(args: argparse.Namespace) -> tuple[CellSetup, Robot, Tracker, Envelope]:
    """-> (CellSetup, robot, tracker, envelope) from parsed CLI args (`envelope`: optional
    FILE; default: the arm's default envelope; `smr_offset`: optional 'X,Y,Z' m, the SMR on the
    flange as the operator declares it; a simulated cell keeps its own true SMR)."""
    declared = getattr(args, "smr_offset", None)
    tool_m = parse_smr_offset(declared)
    if args.robot == "sim" and args.tracker == "sim":
        from sim_devices.cell import sim_cell  # the simulator only when asked for

        _, robot, tracker, cell = sim_cell(
            args.model, args.effects, args.seed,
            noise_stream=int(getattr(args, "sim_noise_stream", 0) or 0),
        )  # fmt: skip
        if declared:  # else the simulated cell's own nominal SMR
            cell.tool_m = tool_m
        _declare_payload(cell, args)  # else the simulated arm's own
        return cell, robot, tracker, envelope_from_args(args, cell.spec)
    check_device_pair(args.robot, args.tracker)
    if not args.robot.startswith("ur://"):
        raise UserError(f"--robot {args.robot!r}: expected sim or ur://HOST")
    host = args.robot[len("ur://") :]
    if not host or "/" in host or (host.count(":") == 1 and not host.startswith("[")):
        raise UserError(
            f"--robot {args.robot!r}: expected ur://HOST (a name or an IP address, no port or "
            "path: the controller's RTDE and dashboard ports are fixed)"
        )
    if not args.tracker.startswith("serial://"):
        raise UserError(f"--tracker {args.tracker!r}: expected sim or serial:///dev/ttyX")
    try:
        from workcell.drivers.serial_tracker import SerialTracker
        from workcell.drivers.ur_robot import UrRobot
    except ModuleNotFoundError as e:
        raise UserError(f"real drivers not available in this build ({e.name})") from None
    spec = robot_by_name(args.model)
    env = envelope_from_args(args, spec)  # refused before any connection
    # the driver asks the controller which arm it is and refuses another family before any
    # motion: plans and envelope checks use `spec`'s kinematics; it also measures the
    # controller's clock and refuses a time scale faster than it (on a real arm,
    # --time-scale 50 would cut a 1 s settle to 20 ms)
    time_scale = getattr(args, "time_scale", None)
    robot = UrRobot(
        host, time_scale=1.0 if time_scale is None else float(time_scale), model=spec.model
    )
    port, link = parse_tracker_url(args.tracker)
    tracker = SerialTracker(port, **link)
    cell = CellSetup(
        spec=spec,
        tool_m=tool_m,
        base_in_tracker={"translation_m": [0.0, 0.0, 0.0], "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0]},
        tracker_model="GeoCOM tracker",
        payload_source="default",  # until --payload or the controller's setting (at connect)
    )
    _declare_payload(cell, args)
    return cell, robot, tracker, env


# serial://PORT?baud=9600&timeout=15&edm_wait=5&crc=1: the link settings an instrument needs
# (SerialTracker's defaults: 115200 baud, 2 s a reply, 1 s for the distance, no CRC)
TRACKER_URL_OPTIONS = {
    "baud": ("baudrate", int, 300, 921_600, "baud"),
    "timeout": ("timeout_s", float, 0.1, 120.0, "s"),
    "edm_wait": ("measure_wait_s", float, 0.0, 60.0, "s"),
    "crc": ("use_crc", int, 0, 1, ""),
}


def parse_tracker_url(url: str) -> tuple[str, dict]:
    """The serial port and `SerialTracker` keyword arguments of `serial://PORT[?opt=v&...]`
    (`TRACKER_URL_OPTIONS`); anything else is refused in one line."""
    from urllib.parse import unquote

    rest = url[len("serial://") :]
    port, _, query = rest.partition("?")
    if not port:
        raise UserError(f"--tracker {url!r}: no serial port (serial:///dev/ttyUSB0)")
    kw: dict = {}
    pairs = [item.partition("=")[::2] for item in query.split("&")] if query else []
    for key, value in ((unquote(k), unquote(v)) for k, v in pairs):
        if key not in TRACKER_URL_OPTIONS:
            raise UserError(
                f"--tracker {url!r}: unknown option {key!r}; known: "
                f"{', '.join(TRACKER_URL_OPTIONS)} (serial:///dev/ttyUSB0?baud=9600&timeout=15)"
            )
        name, kind, lo, hi, unit = TRACKER_URL_OPTIONS[key]
        try:
            v = kind(value)
        except ValueError:
            v = None
        if v is None or not (lo <= v <= hi) or (kind is float and not math.isfinite(v)):
            raise UserError(
                f"--tracker {url!r}: {key} must be a {'whole ' if kind is int else ''}number "
                f"in [{lo:g}, {hi:g}]{' ' + unit if unit else ''}, got {value!r}"
            )
        kw[name] = bool(v) if key == "crc" else v
    return port, kw


def _declare_payload(cell: CellSetup, args) -> None:
    """`--payload` as the operator declares it (the session and every sample record it)."""
    text = getattr(args, "payload", None)
    if text is None or str(text).strip() == "":
        return
    cell.payload_kg, cell.payload_com_m = parse_payload(text, cell.spec)
    cell.payload_source = "declared"
