"""`workcell validate MODEL --robot sim|ur://HOST --tracker sim|serial://...`: closed-loop check
of the exported correction table (before/after position accuracy on random targets)."""

from __future__ import annotations

import argparse
import signal
import threading

import numpy as np

from workcell import strict_json
from workcell.commands import prose
from workcell.drivers.protocols import DeviceError
from workcell.errors import UserError
from workcell.export.validate import DEFAULT_READINGS, DEFAULT_TARGETS, MAX_READINGS, MAX_TARGETS


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", help="fitted model file")
    p.add_argument("--robot", default="sim", help="sim or ur://HOST")
    p.add_argument("--tracker", default="sim", help="sim or serial:///dev/ttyX")
    p.add_argument("--targets", type=int, default=DEFAULT_TARGETS, help="random targets to measure")
    p.add_argument("--table", help="exported table (.json); default: build it from the model")
    p.add_argument("--volume", help="x0,y0,z0,x1,y1,z1 in m (when building the table)")
    p.add_argument(
        "--envelope",
        metavar="FILE",
        help="safety envelope JSON; default: the one recorded with the model's campaign, else "
        "the arm's default",
    )
    p.add_argument(
        "--max-correction",
        type=float,
        help="refuse corrections above this, m (default 5e-3; when building the table)",
    )
    p.add_argument("--seed", type=int, default=12345, help="seed of the random targets")
    p.add_argument("--sim-seed", type=int, help="simulated truth seed (default: the recording's)")
    p.add_argument("--effects", help="simulated effects (default: the recording's)")
    p.add_argument(
        "--model-name", dest="robot_model", help="robot model for real cells (default: the model's)"
    )
    p.add_argument(
        "--readings", type=int, help="tracker readings per target (real tracker; default 5)"
    )
    p.add_argument(
        "--payload",
        metavar="KG[,CX,CY,CZ]",
        help="real cell: the payload at the flange as set on the teach pendant (kg; centre of "
        "mass in m), which a --table is checked against (default: the controller's payload "
        "setting; 0 kg if it does not report one)",
    )
    p.add_argument(
        "--time-scale",
        type=float,
        help="with `workcell sim --time-scale X` and --robot ur://...: the same X (default 1, "
        "a real controller; checked against the controller's clock before anything moves)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")


def check_options(args: argparse.Namespace) -> None:
    """Refuse out-of-range options before loading anything or connecting."""
    if not 1 <= args.targets <= MAX_TARGETS:
        raise UserError(f"--targets must be 1..{MAX_TARGETS}, got {args.targets}")
    for name in ("seed", "sim_seed"):
        v = getattr(args, name)
        if v is not None and v < 0:
            raise UserError(f"--{name.replace('_', '-')} must be a non-negative integer, got {v}")
    if args.readings is not None and not 1 <= args.readings <= MAX_READINGS:
        raise UserError(f"--readings must be 1..{MAX_READINGS}, got {args.readings}")
    if args.table and args.volume:
        raise UserError(
            "--volume: not used with --table, whose volume is the table's own grid (it is for "
            "the table validate builds from the model); leave one of them out"
        )
    if args.table and getattr(args, "max_correction", None) is not None:
        raise UserError(
            "--max-correction: not used with --table, which was built with its own bound (it is "
            "for the table validate builds from the model); leave one of them out"
        )
    sim = args.robot == "sim" and args.tracker == "sim"
    if getattr(args, "time_scale", None) is not None:
        from workcell.campaign.devices import check_time_scale_range

        check_time_scale_range(args.time_scale)
    real_only = (
        ("--readings", args.readings),
        ("--time-scale", getattr(args, "time_scale", None)),
        ("--model-name", args.robot_model),
        ("--payload", getattr(args, "payload", None)),
    )
    if sim and any(v is not None and v != "" for _, v in real_only):
        given = [o for o, v in real_only if v is not None and v != ""]
        raise UserError(
            f"{' and '.join(given)} {'is' if len(given) == 1 else 'are'} for a real cell; the "
            "simulation rebuilds the model's robot and scores against its true positions "
            "(leave them out, or give --robot ur://HOST --tracker serial://PORT)"
        )


def check_robot_model(args: argparse.Namespace, arm: str) -> None:
    """Refuse, before any device, a --model-name other than the arm the model is of: validate
    would command that arm with the model's kinematics (its IK and corrections)."""
    given = getattr(args, "robot_model", None)
    if not given or not arm or arm == "unknown" or given.strip().lower() == arm.lower():
        return
    raise UserError(
        f"--model-name {given}: the model {args.model} is of a {arm} (its nominal chain gives "
        f"the IK and the corrections validate commands); on a {given} it would move the arm "
        f"with the {arm}'s kinematics; validate it on the {arm} it was fitted on (leave "
        f"--model-name out), or fit a model on the {given} (`workcell campaign`, `workcell fit`)"
    )


def wrong_arm(e: Exception, args: argparse.Namespace, arm: str) -> Exception:
    """The driver's refusal of a controller that is another arm than the model's, said for
    validate (whose arm is the model's, not an option to change), else `e` itself."""
    import re

    if type(e).__name__ != "WrongRobotModel":
        return e
    m = re.search(r"says it is an? (\S+?) but|so the arm is an? (.+?), but", str(e))
    said = next((g for g in m.groups() if g), None) if m else None
    return UserError(
        f"{args.robot}: the controller's arm is {'a ' + said if said else 'another arm'}, not "
        f"the {arm} the model {args.model} is of: validate would command it with the {arm}'s "
        f"kinematics (nothing moved); validate the model on the {arm} it was fitted on, or fit "
        f"a model on this arm (`workcell campaign`, `workcell fit`)"
    )


def print_table(res: dict, interval_um) -> None:
    """The before/after table: columns as wide as their widest number, one space at least
    between them (a 3 m error no longer runs into the next column)."""
    keys = ("mean_m", "rms_m", "max_m")
    vals = [f"{res[k][c] * 1e6:.1f}" for k in ("before", "after") for c in keys]
    w = max(9, 1 + max(len(v) for v in vals))
    print(
        f"{'':10}{'mean':>{w + 3}}{'RMS':>{w + 3}}{'max':>{w + 3}}   95 % CI of the RMS   "
        f"({res['targets']} targets, truth: {res['truth']})"
    )
    for key in ("before", "after"):
        s = res[key]
        cells = "".join(f"{s[c] * 1e6:>{w}.1f} um" for c in keys)
        print(f"{key:10}{cells}   {interval_um(s.get('rms_ci95_m'), label=False)}")


def recorded_end_s(rec: str | None) -> float | None:
    """The last sample's elapsed_s in the recording (s), None when unreadable or absent."""
    if not rec:
        return None
    try:
        from workcell.recording.reader import read_recording

        e = [s.get("elapsed_s") for s in read_recording(rec, streams=False).samples]
    except Exception:  # noqa: BLE001 - the recording is optional here
        return None
    e = [float(x) for x in e if isinstance(x, int | float) and not isinstance(x, bool)]
    e = [x for x in e if np.isfinite(x) and x >= 0]
    return max(e) if e else None


def _interrupt_on_abort_signals() -> dict:
    """SIGTERM and SIGHUP (`kill`, `timeout`, a closed terminal) interrupt the validation as
    Ctrl-C does: the move under way is stopped (`robot_mover`) and the devices closed; by
    default they ended the process with the arm still moving. Main thread only (signals are
    delivered there); returns the handlers replaced, by signal."""
    if threading.current_thread() is not threading.main_thread():
        return {}

    def interrupt(signum: int, _frame: object) -> None:
        raise KeyboardInterrupt

    from workcell.campaign.executor import ABORT_SIGNALS

    # the campaign's abort signals; SIGINT is Ctrl-C's own KeyboardInterrupt already (cli.py)
    sigs = [sig for sig in ABORT_SIGNALS if sig != signal.SIGINT]
    return {sig: signal.signal(sig, interrupt) for sig in sigs}


def run(args: argparse.Namespace) -> int:
    from workcell.campaign.devices import envelope_from_args
    from workcell.campaign.envelope import Guard
    from workcell.campaign.payload import settle_payload
    from workcell.campaign.resume import recorded_sim_seed
    from workcell.drivers.protocols import close_quietly
    from workcell.estimation.models import RMS_INTERVAL_BASIS, interval_um, load_model
    from workcell.export.build import (
        make_table,
        model_recording,
        model_session,
        nominal_for_model,
        parse_vec,
    )
    from workcell.export.correction import Conditions
    from workcell.export.table import load_table
    from workcell.export.validate import (
        payload_check,
        real_cell,
        robot_mover,
        run_validation,
        sim_measure,
        table_model_mismatch,
        thermal_mismatch,
        tracker_measure,
        validation_envelope,
        validation_warnings,
    )

    check_options(args)
    model = load_model(args.model)
    log = (lambda m: None) if args.json else print
    rec, sha = model_recording(model)
    table = vol = None
    if args.table:  # a table of another model, or in other units, is refused before any device
        table = load_table(args.table)
    elif args.volume:
        vol = parse_vec(args.volume, 6, "--volume")
    # the arm the model's nominal chain (the IK validate commands with) is of
    nominal = nominal_for_model(model)
    check_robot_model(args, nominal.robot)
    if table is not None and (why := table_model_mismatch(table, nominal, sha, model=model)):
        raise UserError(f"{args.table}: {why}")
    session, missing = model_session(model)
    camp = session.get("campaign", {}) or {}
    if args.robot == "sim" and args.tracker == "sim":
        from sim_devices.cell import sim_cell

        if (where := real_cell(session)) is not None:
            raise UserError(
                f"{args.model} was fitted on a real cell ({rec or 'its recording'}: {where}): "
                "a simulator has "
                "another arm; validate it on that cell: --robot ur://HOST --tracker "
                "serial://PORT"
            )
        if not session and (args.sim_seed is None or args.effects is None):
            why = missing or "the model names no recording"
            raise UserError(
                f"simulation: {why}; put the recording beside the model, or, for a model "
                "fitted on a simulated cell whose recording moved, pass --sim-seed and --effects "
                "(they must match the recording's campaign)"
            )
        seed = args.sim_seed if args.sim_seed is not None else recorded_sim_seed(camp)
        effects = args.effects or camp.get("effects")
        if seed is None or effects is None:
            raise UserError(
                f"simulation: the model's recording {rec} does not say which simulated cell it "
                "was made on (seed and effects); if it was a simulation, pass --sim-seed and "
                "--effects as its campaign ran, else validate on the real cell: --robot "
                "ur://HOST --tracker serial://PORT"
            )
        robot_name = (session.get("robot") or {}).get("model") or getattr(
            model, "robot_model", "ur5e"
        )
        world, robot, tracker, cell = sim_cell(robot_name, effects, int(seed))
        # the simulated arm is as warm as at the recording's last sample (its clock started
        # with the campaign, warm-up included)
        end_s = recorded_end_s(rec)
        if end_s is None:
            end_s = float(camp.get("warmup_s") or 0.0) + 3600.0
            log(
                f"simulated clock set to {end_s:.0f} s (warm-up + 1 h: the recording's sample "
                "times are not readable)"
            )
        else:
            log(f"simulated clock set to {end_s:.1f} s, the recording's last sample")
        world.clock.advance(end_s)
        measure = sim_measure(world)
        spec = cell.spec
    else:
        from workcell.campaign.devices import open_cell

        ns = argparse.Namespace(
            robot=args.robot,
            tracker=args.tracker,
            model=args.robot_model or nominal.robot,
            effects=None,
            seed=0,
            payload=getattr(args, "payload", None),
            time_scale=getattr(args, "time_scale", None),
        )
        cell, robot, tracker, _ = open_cell(ns)
        measure = tracker_measure(tracker, args.readings or DEFAULT_READINGS)
        spec = cell.spec
    env, env_what = validation_envelope(  # before connecting
        envelope_from_args(args, spec) if args.envelope else None, session, spec, str(rec)
    )
    log(f"moves checked against {env_what}")
    warnings: list[str] = []
    simulated = args.robot == "sim"

    def check_payload() -> None:
        try:
            w = payload_check(
                model, table, cell.payload_kg, simulated=simulated, source=cell.payload_source
            )
        except UserError as e:
            raise UserError(f"{args.table}: {e}") from None
        if w is not None:
            log(f"warning: {w}")
            warnings.append(w)

    if table is not None and simulated:  # refused before anything connects
        check_payload()
    try:
        robot.connect()
    except DeviceError as e:
        raise wrong_arm(e, args, nominal.robot) from None
    old_handlers = _interrupt_on_abort_signals()  # the arm is stopped before the process ends
    try:
        tracker.connect()
        if not simulated:  # the controller's payload setting against --payload
            for note in settle_payload(cell, robot):
                log(f"{note['level']}: {note['message']}")
                if note["level"] == "warning":
                    warnings.append(note["message"])
            if table is not None:
                check_payload()
        # the arm's joint temperatures now (the controller reports them; None if it does not)
        temps = robot.state().temperature_c
        if table is not None:
            if (w := thermal_mismatch(model, table, temps)) is not None:
                log(f"warning: {w}")
                warnings.append(w)
        else:
            cond = Conditions(
                approach_sign=np.ones(6),
                joint_temperature_c=None if temps is None else np.asarray(temps, float),
                payload_kg=float(cell.payload_kg),
            )
            table, corr = make_table(
                model,
                model_path=args.model,
                volume=vol,
                conditions=cond,
                nominal=nominal,
                # not handed to a controller: the guard checks each of validate's moves and
                # skips a target outside the envelope (`run_validation`)
                check_envelope=False,
                log=log,
                **(
                    {}
                    if getattr(args, "max_correction", None) is None
                    else {"max_correction_m": args.max_correction}
                ),
            )
            nominal = corr.nominal
        res = run_validation(
            nominal,
            table,
            robot_mover(robot, *env.cap(0.5, 1.0)),  # speeds capped by the envelope
            measure,
            n=args.targets,
            seed=args.seed,
            guard=Guard(env, spec, nominal.tool_m),  # the SMR the campaign declared
            q_start=lambda: np.asarray(robot.state().q_rad, float),
            log=log,
            clock=lambda: float(robot.state().t_s),  # the controller's time
        )
    finally:
        close_quietly(robot, tracker)
        for sig, handler in old_handlers.items():
            signal.signal(sig, handler)
    res["truth"] = "simulated robot" if args.robot == "sim" else "tracker"
    res["envelope"] = env_what
    res["warnings"] = warnings + validation_warnings(res)
    res["rms_interval_basis"] = RMS_INTERVAL_BASIS
    if args.json:
        print(strict_json.dumps(res))
        return 0
    print_table(res, interval_um)
    if res.get("skipped"):
        print(
            f"skipped   {len(res['skipped'])} target(s) before any motion; first: {res['skipped'][0]}"
        )
    ci = res.get("improvement_ci95") or []
    print(
        f"improvement (RMS): {res['improvement']:.1f}x"
        + (
            f" (95 % CI {ci[0]:.1f}-{ci[1]:.1f}x, paired bootstrap over the targets)"
            if len(ci) == 2 and all(np.isfinite(ci))
            else f" (no interval: {res['targets']} target(s) measured; one needs at least 3"
            + (", --targets)" if not res.get("skipped") else "; the envelope skipped the others)")
            if res["targets"] < 3
            else ""
        )
    )
    b, bs = res["after"].get("bias_base_m"), res["after"].get("bias_base_std_m")
    if b is not None and bs is not None and all(np.isfinite(bs)):
        cells = ", ".join(f"{x * 1e6:.1f} +- {e * 1e6:.1f}" for x, e in zip(b, bs, strict=True))
        print(
            f"bias after (mean error vector, reached - desired, base_ref x, y, z): {cells} um "
            "(+- its standard error over the targets)"
        )
    if res["targets"] >= 3:
        print(prose.fill(f"CI: {RMS_INTERVAL_BASIS} (here the targets)", width=100))
    return 0
