"""Run a whole campaign: open devices, write the session, execute the plan, close the recording."""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from workcell.campaign.envelope import Envelope, default_envelope
from workcell.campaign.executor import (
    ArmOutsideEnvelope,
    CampaignConfig,
    CampaignControl,
    CampaignResult,
    Executor,
)
from workcell.campaign.payload import CLI_HOW, settle_payload
from workcell.campaign.plans import (
    ADAPTIVE_KINDS,
    ArmPosture,
    PoseTarget,
    make_plan,
    with_reference,
)
from workcell.campaign.watch import MarginWatch
from workcell.drivers.protocols import DeviceError, Robot, Tracker, close_quietly
from workcell.errors import INTERRUPTED, UserError
from workcell.kinematics.robots import RobotSpec
from workcell.recording.writer import RecordingWriter


@dataclass
class CellSetup:
    """Everything the operator declares about the cell (what the session message records)."""

    spec: RobotSpec
    tool_m: np.ndarray
    base_in_tracker: dict  # {"translation_m", "quaternion_wxyz"} nominal (may be rough)
    tracker_model: str = "unknown"
    payload_kg: float = 0.0
    payload_com_m: tuple = (0.0, 0.0, 0.0)
    # where payload_kg/payload_com_m come from: "declared" (--payload, the TUI's field, a
    # simulated cell's setup), "recording" (a resume keeps the recorded one), "controller" (its
    # payload setting, read at connect: `payload.settle_payload`) or "default" (nobody stated
    # it and the controller did not say: the 0 kg above)
    payload_source: str = "declared"
    # what the controller reported at connect: {"mass_kg", "com_m"}, {"unavailable": reason},
    # or None (not asked: a robot that reports no payload setting)
    payload_controller: dict | None = None

    @property
    def payload_declared(self) -> bool:
        """Someone stated the payload (declared, recorded, or the controller's setting)."""
        return self.payload_source != "default"

    def session(self, campaign: dict) -> dict:
        payload = {
            "mass_kg": float(self.payload_kg),
            "com_m": list(self.payload_com_m),
            "source": self.payload_source,
        }
        if self.payload_controller is not None:
            payload["controller"] = dict(self.payload_controller)
        return {
            "robot": {
                "model": self.spec.model,
                "dh": self.spec.dh.to_dict(),
                "joint_limits_rad": self.spec.joint_limits_rad.tolist(),
            },
            "tool": {"smr_offset_m": np.asarray(self.tool_m, float).tolist()},
            "tracker": {"model": self.tracker_model, "base_in_tracker": self.base_in_tracker},
            "payload": payload,
            "campaign": campaign,
        }


def _first_target(plan, cell, env, poses, seed, cfg, plan_kwargs) -> PoseTarget:
    """The plan's first pose, re-created fresh (a resumed campaign skips it): the reference a
    `reference_every` campaign re-measures. An adaptive plan chose it from where the arm was
    then: a resume takes it from the recording (pose 0) when it is there."""
    history = (plan_kwargs or {}).get("history") or {}
    first = history.get(0)
    if plan in ADAPTIVE_KINDS and first is not None:
        q = np.asarray(first["q_commanded_rad"], float)
        sign = first.get("approach_sign")
        return PoseTarget(0, q, np.asarray(sign, float) if sign is not None else np.ones(len(q)))
    drop = ("history", "arm", "replace_skipped")
    kw = {k: v for k, v in (plan_kwargs or {}).items() if k not in drop}
    gen, _ = make_plan(
        plan, cell.spec, env, poses, seed=seed, tool_m=cell.tool_m,
        approach_rad=cfg.approach_rad, **kw,
    )  # fmt: skip
    try:
        return next(gen)
    finally:
        gen.close()


def tracker_identity(tracker: Tracker) -> dict:
    """What the connected tracker says it is, recorded in the session's `tracker` block and
    compared by a resume (`check_same_tracker`): `instrument_name` and `serial_number` of a GeoCOM
    instrument (CSV_GetInstrumentName, CSV_GetInstrumentNo); {} for a tracker that does not say
    (the in-process simulation). An instrument that does not answer the serial number query is
    recorded without one. The driver reads both on connect."""
    ident: dict = {}
    name = getattr(tracker, "instrument_name", None)
    if isinstance(name, str) and name.strip():
        ident["instrument_name"] = name.strip()
    sn = getattr(tracker, "serial_number", None)
    if isinstance(sn, int) and not isinstance(sn, bool):
        ident["serial_number"] = sn
    setup = getattr(tracker, "setup", None)  # station, prism constant, ppm (GeoCOM driver)
    if isinstance(setup, dict) and setup:
        ident["setup"] = dict(setup)
    lock = getattr(tracker, "lock", None)  # the target lock at connect
    if isinstance(lock, str) and lock:
        ident["lock"] = lock
    return ident


# the instrument's corrections a resume compares with the recording's (the station is absorbed
# by the fitted tracker_T_base, so it may differ): (tolerance, scale to the unit said, unit)
SETUP_TOLERANCES = {"prism_constant_m": (1e-6, 1e3, "mm"), "atm_ppm": (0.05, 1.0, "ppm")}


def setup_changed(recorded: object, now: object, key: str) -> str | None:
    """How one correction of the instrument (`SETUP_TOLERANCES`) differs between the recorded
    `setup` and the connected one's, in words; None when it does not or either is unknown."""
    if not isinstance(recorded, dict) or not isinstance(now, dict):
        return None
    tol, scale, unit = SETUP_TOLERANCES[key]
    a, b = recorded.get(key), now.get(key)
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and abs(a - b) > tol:
        name = "prism constant" if key == "prism_constant_m" else "atmospheric correction"
        return f"{name} is {b * scale:g} {unit} now, {a * scale:g} {unit} when recorded"
    return None


def _describe_tracker(ident: dict) -> str:
    name = ident.get("instrument_name")
    sn = ident.get("serial_number")
    if sn is None:
        return f"'{name}' (serial number unknown)" if name else "a tracker of unknown serial number"
    return f"serial number {sn}" + (f" ({name})" if name else "")


def check_same_tracker(same: dict, ident: dict, url: str | None) -> str | None:
    """A resume continues with the tracker its recording was made with (`same`: `source`, the
    recorded `url` and the recorded session's `serial_number` / `instrument_name`; `ident`:
    `tracker_identity` of the connected one at `url`). Another instrument is refused in one
    line, on any port. A new port (a re-plugged USB adapter: /dev/ttyUSB0 -> /dev/ttyUSB1) is
    accepted when the serial numbers agree, and the returned line says so; None: nothing to
    say. Simulators started for the recording (`simulated`) change ports each start and are not
    compared."""
    if same.get("simulated"):
        return None
    source = same.get("source", "the recording")
    rec_url = same.get("url")
    rec = {k: same.get(k) for k in ("serial_number", "instrument_name")}
    rec = {k: v for k, v in rec.items() if v is not None}
    moved = rec_url is not None and url is not None and rec_url != url
    if rec.get("serial_number") is not None and ident.get("serial_number") is not None:
        names = (rec.get("instrument_name"), ident.get("instrument_name"))
        if rec["serial_number"] != ident["serial_number"] or (
            None not in names and names[0] != names[1]
        ):
            raise UserError(
                f"{source} was recorded with the tracker {_describe_tracker(rec)}, the one "
                f"connected at {url} is {_describe_tracker(ident)}: a resume continues with the "
                "same instrument; connect that tracker, or start a new campaign"
            )
    changed = setup_changed(same.get("setup"), ident.get("setup"), "prism_constant_m")
    if changed is not None:  # the target's own offset: the same SMR measures alike
        raise UserError(
            f"the tracker's setup changed since {source} was recorded: its {changed} (it offsets "
            "every distance, and the fit would take the two parts for one campaign); set the "
            "SMR's constant back on the instrument, or start a new campaign"
        )
    if not moved:
        return None
    if rec.get("serial_number") is None:
        raise UserError(
            f"{source} was recorded with the tracker at {rec_url} and does not record the "
            f"tracker's serial number (an older recording), so a resume cannot tell that the "
            f"tracker at {url} is the same instrument: connect it at {rec_url} again (re-plug "
            "the adapter), or start a new campaign"
        )
    if ident.get("serial_number") is None:
        raise UserError(
            f"the tracker at {url} does not give its serial number, so a resume cannot tell "
            f"it is the instrument {source} was recorded with at {rec_url} "
            f"({_describe_tracker(rec)}): connect it at {rec_url} again, or start a new campaign"
        )
    return (
        f"the tracker's port changed: {rec_url} when {source} was recorded, {url} now; the "
        f"same instrument, {_describe_tracker(ident)}: the campaign continues"
    )


def chain_path(old: str | Path, out: str | Path) -> str:
    """How a resumed file names the file it continues (`chained_from.path`): relative to the
    new file's folder, so that the two stay linked when their folder is moved or read from
    another working directory."""
    try:
        return os.path.relpath(Path(old).resolve(), Path(out).resolve().parent)
    except ValueError:  # another drive (Windows): no relative path
        return str(Path(old).resolve())


def _start_clock(clock: dict | None, elapsed0_s: float) -> tuple[int, float]:
    """The new run's log time at its start and its elapsed time then. A resume (`clock`: the old
    file's last log time and campaign start, `resume.continuation`) starts after the old file's
    last record and counts the time the campaign was down in its elapsed time."""
    t0 = time.time_ns()
    if not clock:
        return t0, elapsed0_s
    t0 = max(t0, int(clock.get("last_ns") or 0) + 1)
    start = clock.get("start_ns")
    if start is not None:
        elapsed0_s = max(elapsed0_s, (t0 - int(start)) * 1e-9)
    return t0, elapsed0_s


def run_campaign(
    robot: Robot,
    tracker: Tracker,
    cell: CellSetup,
    out: str | Path,
    *,
    plan: str = "random",
    poses: int = 50,
    seed: int = 0,
    envelope: Envelope | None = None,
    config: CampaignConfig | None = None,
    control: CampaignControl | None = None,
    on_sample: Callable[[dict], None] | None = None,
    on_event: Callable[[dict], None] | None = None,
    extra_campaign: dict | None = None,
    skip_ids: set[int] | None = None,
    index0: int = 0,
    chained_from: dict | None = None,
    elapsed0_s: float = 0.0,
    clock: dict | None = None,
    plan_kwargs: dict | None = None,
    watch_history: list[dict] | None = None,
    reference_every: int = 0,
    same_tracker: dict | None = None,
    notes: list[dict] | None = None,
    payload_how: str = CLI_HOW,
) -> tuple[Path, CampaignResult]:
    """Plan, connect, record. With a non-zero kinematic margin, every sample
    also checks that the real SMR stays within the margin of the nominal one (`watch.MarginWatch`;
    `watch_history`: samples of the recording a resume continues) and the campaign stops when it
    does not. `reference_every` N > 0: the plan's first pose is measured again after every N
    poses and at the end (`plans.with_reference`), a drift record. The connected tracker's
    identity (`tracker_identity`) goes into the session; a resume (`same_tracker`, from
    `resume.continuation`) checks it is the recorded instrument before anything moves
    (`check_same_tracker`). `notes`: events ({level, kind, message}) recorded at the start, after what
    `payload.settle_payload` says about the controller's payload setting (`payload_how`: how
    the operator states a payload, in its notes)."""
    env = envelope or default_envelope(cell.spec)
    cfg = config or CampaignConfig(payload_kg=cell.payload_kg)
    # where the arm is, read by the executor before each choice of an adaptive plan
    arm = ArmPosture() if plan in ADAPTIVE_KINDS else None
    gen, _ = make_plan(
        plan,
        cell.spec,
        env,
        poses,
        seed=seed,
        tool_m=cell.tool_m,
        skip_ids=skip_ids,
        approach_rad=cfg.approach_rad,
        **({"arm": arm} if arm is not None else {}),
        **(plan_kwargs or {}),
    )
    if reference_every:
        gen = with_reference(
            gen,
            reference_every,
            _first_target(plan, cell, env, poses, seed, cfg, plan_kwargs)
            if skip_ids or (plan_kwargs or {}).get("history")
            else None,
        )
    campaign = {
        "plan": plan,
        "poses": poses,
        "seed": seed,
        "readings_per_pose": cfg.readings_per_pose,
        "settle_s": cfg.settle_s,
        "approach_rad": cfg.approach_rad,
        "warmup_s": cfg.warmup_s,
        "envelope": env.to_dict(),
        **(extra_campaign or {}),
    }
    if reference_every:
        campaign["reference_every"] = int(reference_every)
    session = cell.session(campaign)
    if chained_from:
        session["chained_from"] = {**chained_from, "path": chain_path(chained_from["path"], out)}
    if INTERRUPTED.is_set():
        # a Ctrl-C at the command line that Python dropped while planning (`errors.INTERRUPTED`):
        # stop here, nothing connected, nothing recorded. (A UI's abort runs through the executor.)
        raise KeyboardInterrupt
    watch = None
    if env.kinematic_margin_m > 0:
        watch = MarginWatch(cell.spec, cell.tool_m, env.kinematic_margin_m)
        if watch_history and (v := watch.extend(watch_history)) is not None and v.stop:
            raise UserError(
                f"the recording this continues already fails the margin check ({v.stop}); "
                "a resume keeps its SMR offset and envelope, so start a new campaign instead "
                "(nothing moved)"
            )
    robot.connect()
    try:
        tracker.connect()
        ident = tracker_identity(tracker)
        session["tracker"].update(ident)
        port_note = (
            check_same_tracker(same_tracker, ident, campaign.get("tracker_url"))
            if same_tracker is not None
            else None
        )
        # the controller's payload setting, where it reports one, against the stated payload
        notes = settle_payload(cell, robot, payload_how) + list(notes or [])
        session["payload"] = cell.session(campaign)["payload"]
    except BaseException:
        close_quietly(robot, tracker)
        raise
    cfg = replace(cfg, payload_kg=cell.payload_kg)
    if port_note:
        notes.append({"level": "info", "kind": "tracker_port", "message": port_note})
    if same_tracker is not None and (
        ppm := setup_changed(same_tracker.get("setup"), ident.get("setup"), "atm_ppm")
    ):  # right when the air changed since, a scale error when it did not: said, not refused
        notes.append({
            "level": "warning", "kind": "tracker_setup",
            "message": f"the tracker's {ppm}: right if the air changed "
            "since (temperature, pressure), else a scale error of the difference between the "
            "two parts of the campaign",
        })  # fmt: skip
    if ident.get("lock", "locked") != "locked":  # a GeoCOM instrument not following the SMR
        notes.append({
            "level": "warning", "kind": "tracker_lock",
            "message": f"tracker: {ident['lock']}; a pose it cannot see is a beam break",
        })  # fmt: skip
    t_wall0_ns, elapsed0_s = _start_clock(clock, elapsed0_s)
    ex = None
    try:
        with RecordingWriter(out, session, session_t_ns=t_wall0_ns) as w:
            ex = Executor(
                robot,
                tracker,
                cell.spec,
                env,
                w,
                tool_m=cell.tool_m,
                config=cfg,
                control=control,
                on_sample=on_sample,
                on_event=on_event,
                index0=index0,
                t_wall0_ns=t_wall0_ns,
                elapsed0_s=elapsed0_s,
                watch=watch,
                arm=arm,
            )
            if chained_from:
                ex.event(
                    "info",
                    "resume_from",
                    f"continues {chained_from.get('path')} ({chained_from.get('samples')} samples)",
                )
            for note in notes:
                ex.event(note["level"], note["kind"], note["message"])
            result = ex.run(gen)
    except (DeviceError, OSError) as e:
        if ex is not None:  # the recording was opened, is closed now and keeps what it has
            e.recording = (Path(out), ex.result.measured)
        raise
    except ArmOutsideEnvelope as e:
        if ex is not None and ex.result.measured == 0 and not ex.result.skipped:
            # found outside before its first motion: a session header and no sample, nothing
            # to keep or resume
            Path(out).unlink(missing_ok=True)
            raise ArmOutsideEnvelope(
                f"the arm is outside the envelope at the start ({e.reason}); the campaign will "
                "not move it from there: jog it inside, then start again (nothing was recorded)",
                e.reason,
            ) from None
        raise
    finally:
        close_quietly(robot, tracker)
    return Path(out), result


def progress(line: str) -> None:
    """A progress line on stderr, best effort: a closed pipe or terminal (`... 2>&1 | head`)
    must not stop a campaign; the recording is what counts."""
    try:
        print(line, file=sys.stderr, flush=True)
    except (OSError, ValueError):
        pass


def margin_stop(res: CampaignResult, path: str | Path) -> None:
    """A campaign the margin watch stopped is a user error (one line, non-zero exit), raised
    after its recording was closed with what it measured."""
    if res.stopped_by == "margin":
        raise UserError(
            f"the campaign stopped after {res.measured} poses: the envelope's kinematic margin "
            f"does not hold (the margin event above says why); {path} is closed and keeps them"
        )


def resume_hint(path: str | Path, measured: int) -> str:
    """The end of a line for a campaign that stopped with its recording closed."""
    return (
        f"{path} is closed and keeps {measured} poses: `workcell campaign --resume {path}` "
        "continues it"
    )


def stop_aftermath(res: CampaignResult, path: str | Path) -> str | None:
    """What `campaign_stop`'s line says after the engine's reason: where the arm is, what the
    recording keeps and how to continue it; None for a campaign that did not stop itself that
    way (finished, the operator's abort, the margin watch, an error)."""
    kept = f"{path} is closed and keeps {res.measured} poses"
    if res.stopped_by == "tracker":
        return (
            f"the arm is stopped and {kept}: fix the tracker, then "
            f"`workcell campaign --resume {path}`"
        )
    if res.stopped_by == "refused":
        return f"the arm is stopped and {kept}: `workcell campaign --resume {path}` continues it"
    if res.stopped_by in ("protective_stop", "safety_stop"):
        return f"{resume_hint(path, res.measured)} once it is fixed"
    if res.stopped_by == "unacknowledged":
        return f"the arm is left stopped; {resume_hint(path, res.measured)}"
    return None


def nothing_recorded(
    res: CampaignResult, path: str | Path, again: str = "with a new --out"
) -> tuple[str, str] | None:
    """A campaign that went through its plan recording no pose at all (every pose skipped):
    (why, what the recording keeps and what to do), the two halves of `campaign_stop`'s line
    (`again`: how to run it again); None for any other result."""
    if res.aborted or res.measured != 0 or res.skipped <= 0:
        return None
    return (
        f"no pose recorded: all {res.skipped} poses were skipped (the events above say why)",
        f"{path} is closed and keeps the events (`workcell info {path}`): fix the cause, "
        f"then run the campaign again {again}",
    )


def campaign_stop(res: CampaignResult, path: str | Path) -> None:
    """A campaign that stopped itself (the margin watch, `margin_stop`; a protective stop
    nobody acknowledged; protective stops, a tracker without readings or refused poses again
    and again, `executor.MAX_..._IN_A_ROW`; an adaptive plan with no reachable pose left), and
    one that went through its plan recording no pose at all, is one line and a non-zero exit
    (3; 2 for an unacknowledged protective stop), raised after its recording was closed with
    what it measured."""
    margin_stop(res, path)
    if (nothing := nothing_recorded(res, path)) is not None:
        raise UserError("; ".join(nothing), exit_code=3)
    after = stop_aftermath(res, path)
    if after is not None:
        code = 2 if res.stopped_by == "unacknowledged" else 3
        raise UserError(f"{res.stop_message}; {after}", exit_code=code)


@contextmanager
def device_errors_say_resume() -> Iterator[None]:
    """A device error that ended a campaign whose recording was open (`run_campaign` notes it
    on the error) says which file keeps the poses and how to continue it (one line, exit 3)."""
    try:
        yield
    except DeviceError as e:
        rec = getattr(e, "recording", None)
        if rec is None:
            raise
        raise UserError(f"{e}; {resume_hint(*rec)}", exit_code=3) from None


def summary(line: str, control: CampaignControl) -> None:
    """The closing line on stdout; best effort after SIGHUP (the terminal is gone: the
    recording is closed already, and the exit code says what happened)."""
    try:
        print(line, flush=True)
    except OSError:
        if not control.signum:
            raise


def abort_note(res: CampaignResult, path: str | Path) -> None:
    """After an operator's abort (Ctrl-C, SIGTERM, SIGHUP, the TUI's abort): one line on stderr
    saying what the recording keeps and how to continue it, as the other stops say."""
    if res.stopped_by == "operator":
        progress(f"aborted: {resume_hint(path, res.measured)}")


def exit_code(res: CampaignResult, control: CampaignControl) -> int:
    """0, or for an aborted campaign 128 + the signal that stopped it (130 Ctrl-C, 143
    SIGTERM, 129 SIGHUP; 130 for an abort without a signal), what a shell reports for a
    process a signal ended."""
    if not res.aborted:
        return 0
    return 128 + control.signum if control.signum else 130
