"""`workcell campaign --resume OLD.mcap`: continue a campaign whose process died.

Reads what survived in OLD (a file cut short by a crash is fine), re-creates the same plan from
the session's `campaign` block (plan, poses, seed, devices, readings, settle), skips every pose
already measured (by `pose_id`) and records the rest into a new file whose session carries
`chained_from` {path, sha256, samples}. The old file is never modified. When OLD is itself a
resume, its `chained_from` chain is followed back (`read_chain`, over
`workcell.recording.chain.follow_chain`, which the fits use too: each path relative to the file
that names it, each sha256 checked) and the poses of every file of the chain count as measured;
a link missing or changed is refused in one line unless `remeasure_missing`. Sample `index`
continues from the chain's count; `elapsed_s` continues from its last value plus the time the
campaign was down (on the old files' log-time scale), and every log time comes after the
chain's last. The tracker may be on another port (a re-plugged adapter) if it is the same
instrument by serial number (`run.check_same_tracker`).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import glob
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from workcell.campaign.devices import open_cell
from workcell.campaign.envelope import Envelope, envelope_of_session
from workcell.campaign.executor import CampaignConfig, CampaignControl
from workcell.campaign.run import (
    abort_note,
    campaign_stop,
    exit_code,
    progress,
    run_campaign,
    summary,
)
from workcell.drivers.protocols import DeviceUnreachable
from workcell.errors import UserError, check_output_path
from workcell.recording import checks
from workcell.recording.chain import file_sha256, follow_chain, link_candidates
from workcell.recording.reader import RecordingError, read_recording
from workcell.recording.repeats import RepeatWatch
from workcell.recording.writer import being_written

if TYPE_CHECKING:
    from workcell.kinematics.robots import RobotSpec


def _read_for_resume(old: str):
    """The old recording, or one line for a file with nothing to resume: empty (0 bytes), or
    an MCAP header with no session after it (a campaign that stopped before recording
    anything: a full disk, a crash at its start)."""
    from workcell.errors import MCAP_MAGIC
    from workcell.recording import schema as S
    from workcell.recording.reader import RecordingError

    p = Path(old)
    earlier = _earlier_in_series(p)
    again = (
        f"delete {old} and resume the file its resume continued again (`workcell campaign "
        f"--resume {earlier[-1]}` if it was that one)"
        if earlier
        else f"delete {old} and start the campaign again"
    )
    nothing = (
        "a campaign that stopped before recording anything (a full disk, a crash at its "
        f"start?); there is nothing to resume in it: {again}"
    )
    if p.is_file() and p.stat().st_size == 0:
        raise UserError(f"{old} is empty (0 bytes): {nothing}")
    try:
        return read_recording(old)
    except RecordingError as e:
        try:
            with open(p, "rb") as f:
                head = f.read(len(MCAP_MAGIC))
        except OSError:
            raise e from None
        if head == MCAP_MAGIC and (
            "before its session" in str(e) or f"no {S.SESSION} message" in str(e)
        ):
            raise UserError(
                f"{old} holds no campaign session ({p.stat().st_size} bytes): {nothing}"
            ) from None
        raise


REMEASURE_OPTION = "--remeasure-missing"


def read_chain(old: str, *, remeasure_missing: bool = False) -> tuple[list, list[dict]]:
    """The recordings of a resume chain, oldest first, ending with `old`, and the notes
    (events) to record: `old`'s `chained_from`, then that file's, and so on. A link missing or
    changed is refused in one line (its poses would be measured twice, or a changed file's
    counted as this campaign's), unless `remeasure_missing`: the chain then stops there, the
    poses it held are measured again and a warning says so."""
    if being_written(old):
        raise UserError(
            f"{old} is still being written by a running campaign (a `workcell campaign` or a "
            "TUI on this computer has it open); a resume now would measure the same poses "
            "again: let that campaign end, or stop it (Ctrl-C), then resume"
        )
    newest = _read_for_resume(old)
    _refuse_continued(Path(old))
    chain, why, _ = follow_chain(newest)
    notes = []
    if why:
        if not remeasure_missing:
            raise UserError(
                f"{why}: put the original back there and resume again, or measure the "
                f"poses it held again with `workcell campaign --resume {old} "
                f"{REMEASURE_OPTION}` (from a terminal; the TUI has no such option)"
            )
        note = f"{why}; its poses (and any before it in the chain) are measured again"
        notes.append({"level": "warning", "kind": "chain", "message": note})
    for r in chain:  # damage inside a file (not a crash's cut end): its poses are measured again
        for p in r.problems:
            if "damaged chunk" in p:
                notes.append({
                    "level": "warning", "kind": "damaged",
                    "message": f"{r.path.name}: {p}; the poses in it are measured again",
                })  # fmt: skip
    return chain, notes


def resume_plan(old: str, *, remeasure_missing: bool = False) -> dict:
    """What a resume needs from the old recording and the files it continues (`read_chain`)."""
    chain, notes = read_chain(old, remeasure_missing=remeasure_missing)
    rec = chain[-1]
    camp = rec.session.get("campaign") or {}
    if not isinstance(camp, dict):
        raise UserError(f"{old}: session campaign block is not an object; cannot resume it")
    for key in ("plan", "poses", "seed"):
        if key not in camp:
            raise UserError(
                f"{old}: session campaign block has no {key!r}; cannot re-create the plan"
            )
    if (why := campaign_block_problem(camp, rec.session)) is not None:
        raise UserError(f"{old}: session campaign block: {why}; cannot resume it")
    for r in chain:
        problems = checks.problems_of(r.session, r.samples)
        if problems:
            raise UserError(f"{r.path}: {checks.first_problem(problems)}; cannot resume it")
        rc = r.session.get("campaign")
        if r is not rec and (
            not isinstance(rc, dict) or any(rc.get(k) != camp[k] for k in ("plan", "poses", "seed"))
        ):
            raise UserError(
                f"{old} continues {r.path}, which records another campaign (plan, poses or seed "
                "differ); cannot tell which poses were measured: resume the file of that campaign"
            )
    samples = [s for r in chain for s in r.samples]
    history: dict[int, dict] = {}
    for s in samples:  # a reference pose measured again keeps its first sample
        history.setdefault(int(s["pose_id"]), s)
    done = set(history)
    skipped_events = [e for r in chain for e in r.events if e.get("kind") in ("skip", "refused")]
    return {
        "recording": rec,
        "chain": chain,
        "notes": notes,
        "campaign": camp,
        "done": done,
        "history": history,
        "samples": samples,
        "n_samples": len(rec.samples),
        "index0": len(samples),
        "last_elapsed": max((float(s.get("elapsed_s") or 0.0) for s in samples), default=0.0),
        "clock": _recorded_clock(chain),
        "skipped_events": len(skipped_events),
    }


def chain_line(info: dict) -> str:
    """'20 poses measured (12 in a.mcap, 8 in a.resumed1.mcap)': what a chain holds."""
    chain = info.get("chain") or [info["recording"]]
    n = len(info["done"])
    if len(chain) < 2:
        return f"{n} poses measured"
    per = ", ".join(f"{len({s['pose_id'] for s in r.samples})} in {r.path.name}" for r in chain)
    return f"{n} poses measured ({per})"


def _recorded_clock(chain) -> dict:
    """The old files' clock: the log time of the chain's last record, and the campaign's start
    on the log-time scale (a sample's log time less its `elapsed_s`), so that the new file's log
    times come after the old ones' and its `elapsed_s` counts the time the campaign was down.
    `chain`: the recordings, or one recording."""
    recs = chain if isinstance(chain, list) else [chain]
    timed = [
        (s["_log_time_ns"], float(s["elapsed_s"]))
        for rec in recs
        for s in rec.samples
        if isinstance(s.get("elapsed_s"), int | float)
        and not isinstance(s["elapsed_s"], bool)
        and np.isfinite(s["elapsed_s"])
    ]
    start = None
    if timed:
        t_ns, e = max(timed, key=lambda x: x[1])
        start = t_ns - int(round(e * 1e9))
    return {"last_ns": max((rec.last_ns or 0 for rec in recs), default=0), "start_ns": start}


def campaign_block_problem(camp: dict, session: dict) -> str | None:
    """What in a recorded campaign block (edited by hand, or written by another tool) a resume
    could not use, or None: the plan, its size and seed, the measurement settings, the simulated
    truth, the arm's model."""
    import math

    from workcell.campaign.plans import MAX_POSES, PLAN_KINDS

    def whole(v) -> bool:
        return isinstance(v, int) and not isinstance(v, bool)

    def number(v) -> bool:
        return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)

    if camp["plan"] not in PLAN_KINDS:
        return f"plan {camp['plan']!r} is not one of {sorted(PLAN_KINDS)}"
    for key, lo in (("poses", 1), ("seed", 0)):
        if not whole(camp[key]) or camp[key] < lo:
            return f"{key} {camp[key]!r} is not a whole number >= {lo}"
    if camp["poses"] > MAX_POSES:
        return f"poses {camp['poses']} is more than a campaign can measure ({MAX_POSES})"
    optional = (
        ("readings_per_pose", whole, 1),
        ("settle_s", number, 0),
        ("approach_rad", number, 0),
        ("warmup_s", number, 0),
        ("sim_seed", whole, 0),
        ("reference_every", whole, 0),
    )
    for key, kind, lo in optional:
        v = camp.get(key)
        if v is not None and (not kind(v) or v < lo):
            return f"{key} {v!r} is not a {'whole ' if kind is whole else ''}number >= {lo}"
    for key in ("effects", "robot_url", "tracker_url"):
        v = camp.get(key)
        if v is not None and not isinstance(v, str):
            return f"{key} {v!r} is not text"
    model = (session.get("robot") or {}).get("model") if isinstance(session, dict) else None
    if model is not None and not isinstance(model, str):
        return f"robot model {model!r} is not text"
    return None


def plan_continuation(kind: str, info: dict) -> dict:
    """run_campaign arguments that continue the old plan: static plans skip the measured pose
    ids (and so measure the skipped ones again); adaptive plans (bo, dopt, vopt) are fed the
    recorded samples to rebuild their state, and choose a new pose (new pose ids after the
    plan's last) for each one the old run skipped (`adaptive.make_adaptive_plan`)."""
    from workcell.campaign.plans import ADAPTIVE_KINDS

    if kind in ADAPTIVE_KINDS:
        return {"plan_kwargs": {"history": info["history"], "replace_skipped": True}}
    return {"skip_ids": info["done"]}


def to_go_line(info: dict) -> str:
    """'7 to go': the poses the resume offers (the campaign's count less those measured); for an
    adaptive plan that skipped poses, that it chooses new ones in their place."""
    from workcell.campaign.plans import ADAPTIVE_KINDS

    camp, done = info["campaign"], info["done"]
    remaining = int(camp["poses"]) - len(done)
    line = f"{remaining} to go"
    if camp["plan"] in ADAPTIVE_KINDS and done:
        skipped = max(done) + 1 - len(done)  # pose ids up to the last recorded, not recorded
        if skipped > 0:
            k, first = min(skipped, remaining), max(max(done) + 1, int(camp["poses"]))
            ids = f"pose id {first}" if k == 1 else f"pose ids {first} on"
            line += (
                f" ({camp['plan']} chooses {k} new pose{'' if k == 1 else 's'} in place of "
                f"skipped ones, {ids})"
            )
    return line


def continuation(info: dict, old: str | Path) -> dict:
    """Every run_campaign argument that makes a new run continue the recording `info`
    (`resume_plan`) was read from: the plan's state, sample index and elapsed time carried on,
    the chain to the old file, the margin watch's history and the reference interval. The
    command line and the terminal UI resume through this one function."""
    camp = info["campaign"]
    tracker = info["recording"].session.get("tracker")
    tracker = tracker if isinstance(tracker, dict) else {}
    return {
        **plan_continuation(camp["plan"], info),
        "index0": info.get("index0", info["n_samples"]),
        "chained_from": {
            "path": str(old),
            "sha256": file_sha256(old),
            "samples": info["n_samples"],
        },
        "elapsed0_s": info["last_elapsed"],
        "clock": info["clock"],
        "watch_history": info.get("samples", info["recording"].samples),
        "reference_every": recorded_reference_every(camp, str(old)),
        "same_tracker": {
            "source": str(old),
            "url": camp.get("tracker_url"),
            "simulated": camp.get("effects") is not None,
            "serial_number": tracker.get("serial_number"),
            "instrument_name": tracker.get("instrument_name"),
            "setup": tracker.get("setup"),
        },
        "notes": list(info.get("notes") or []),
    }


def recorded_config(camp: dict, payload_kg: float, defaults: CampaignConfig) -> CampaignConfig:
    """The measurement settings the old campaign recorded (readings, settle time, approach,
    warm-up: the arm is warmed up again as the campaign was); `defaults` for a recording that
    lacks one."""

    def get(key: str):
        v = camp.get(key)
        return getattr(defaults, key) if v is None else v

    return dataclasses.replace(
        defaults,
        readings_per_pose=int(get("readings_per_pose")),
        settle_s=float(get("settle_s")),
        approach_rad=float(get("approach_rad")),
        warmup_s=float(get("warmup_s")),
        payload_kg=payload_kg,
    )


def check_same_plan(
    info: dict, spec: RobotSpec, env: Envelope, tool_m: np.ndarray, source: str
) -> None:
    """A grid or random plan is resumed by pose id, so the re-created plan must put every
    recorded sample's pose id at the configuration that was commanded for it; else (a recording made by
    a version that planned differently, another tool, an edited session) poses would be measured
    twice or missed. Refuses with one line. Adaptive plans check themselves on their history."""
    import numpy as np

    from workcell.campaign.plans import STATIC_KINDS, make_plan

    camp = info["campaign"]
    if camp["plan"] not in STATIC_KINDS:
        return
    try:
        _, q = make_plan(
            camp["plan"],
            spec,
            env,
            int(camp["poses"]),
            seed=int(camp["seed"]),
            tool_m=tool_m,
            approach_rad=float(0.02 if camp.get("approach_rad") is None else camp["approach_rad"]),
        )
    except ValueError as e:
        raise UserError(f"{source}: cannot re-create its plan ({e})") from None
    # every sample, not one per pose id: 60 samples all with pose id 0 (a file another tool
    # wrote) passed on their first and 59 more poses were measured (fuzz audit, 2026-11-29)
    samples = info.get("samples") or list(info["history"].values())
    for sample in samples:
        pid = int(sample["pose_id"])
        q_rec = np.asarray(sample.get("q_commanded_rad", []), float)
        if not (0 <= pid < len(q) and q_rec.shape == q[pid].shape) or not np.allclose(
            q_rec, q[pid], rtol=0.0, atol=1e-9
        ):
            raise UserError(
                f"{source}: pose {pid} was commanded at a configuration this version's "
                f"{camp['plan']} plan (seed {camp['seed']}) does not put there (recorded by "
                "another workcell version?); resuming would measure poses twice or miss some. "
                "Start a new campaign, or fit what is recorded"
            )


def recorded_envelope(
    camp: dict,
    spec: RobotSpec,
    source: str,
    default: Envelope,
    say: Callable[[str], None] | None = None,
) -> Envelope:
    """The envelope the old campaign ran in: its poses were planned inside it and every motion of
    the continuation must stay inside it. A recording without one gets `default`, and `say`
    (default: stderr) is told so."""
    env = envelope_of_session(camp, spec, source)
    if env is None:
        msg = f"{source}: no recorded envelope; resuming inside the arm's default envelope"
        (say or (lambda m: print(m, file=sys.stderr)))(msg)
        return default
    return env


def recorded_tool(session: dict) -> list[float]:
    """The SMR offset (m) the old campaign declared (checked by `resume_plan`); its poses were
    planned with it."""
    return [float(v) for v in session["tool"]["smr_offset_m"]]


def recorded_reference_every(camp: dict, source: str) -> int:
    """The recorded reference interval (0: none); a hand-edited one is refused in one line."""
    v = camp.get("reference_every", 0)
    if v in (None, 0):
        return 0
    if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
        raise UserError(
            f"{source}: campaign reference_every {v!r} is not a positive whole number of poses; "
            "cannot resume it"
        )
    return v


def recorded_sim_seed(camp: dict) -> int | None:
    """The seed of the simulated truth a campaign ran against: `sim_seed` where recorded (the
    terminal UI sets it apart from the plan's seed), else the plan's `seed`, which the command
    line uses for both; None when neither is recorded."""
    v = camp.get("sim_seed")
    v = camp.get("seed") if v is None else v
    return None if v is None else int(v)


def check_same_cell(camp: dict, source: str, *, robot_url: str, tracker_url: str,
                    effects: str | None, sim_seed: int | None) -> None:  # fmt: skip
    """A resume continues on the cell the campaign was recorded on: refuse (one line) a
    simulated truth other than the recorded one (`effects` None: the connected cell is not a
    simulation this program runs), or other device addresses for a real cell; a tracker on
    another serial port is let through here: `run.check_same_tracker` compares the instrument's
    serial number once it is connected. Addresses of simulators started for the recording are
    not compared (their ports change each start)."""
    rec_effects = camp.get("effects")
    if rec_effects is not None or effects is not None:
        if effects is None:
            raise UserError(
                f"{source} was recorded on a simulated cell ({rec_effects} effects); a resume "
                "continues on the same cell: connect that simulation"
            )
        if rec_effects is None:
            raise UserError(
                f"{source} was recorded on {camp.get('robot_url', 'a real cell')}; a resume "
                "continues on the same cell, not on a simulation"
            )
        rec_seed = recorded_sim_seed(camp)
        if (rec_effects, rec_seed) != (effects, sim_seed):
            raise UserError(
                f"{source} was recorded against the simulated truth '{rec_effects}', seed "
                f"{rec_seed}; the connected simulation is '{effects}', seed {sim_seed}: a resume "
                "continues on the same cell (set them on the Devices screen and reconnect)"
            )
        return
    for what, given in (("robot", robot_url), ("tracker", tracker_url)):
        recorded = camp.get(f"{what}_url")
        if what == "tracker" and new_serial_port(recorded, given):
            continue
        if recorded is not None and recorded != given:
            raise UserError(
                f"{source} was recorded with the {what} at {recorded}, the connected one is "
                f"{given}: a resume continues on the same cell"
            )


def new_serial_port(recorded: object, given: object) -> bool:
    """Both addresses name a serial port, and not the same address: the tracker may have been
    re-plugged (`run.check_same_tracker` decides once it is connected)."""
    return (
        isinstance(recorded, str)
        and isinstance(given, str)
        and recorded.startswith("serial://")
        and given.startswith("serial://")
        and recorded != given
    )


def with_recorded_link(recorded: str, given: str) -> str:
    """The tracker address a resume on a re-plugged port connects to: the port given, with the
    recorded link settings (`?baud=...`) when the given address names none (typed as the
    refusal suggests, it dropped them, and the instrument stayed silent at the defaults)."""
    query = recorded.partition("?")[2]
    return given if "?" in given or not query else f"{given}?{query}"


def _series(old: Path) -> tuple[str, int]:
    """(X, k) for X.resumedk.mcap, (X, 0) for X.mcap: the names `default_out` gives."""
    m = re.fullmatch(r"(.+)\.resumed(\d+)", old.stem)
    return (m.group(1), int(m.group(2))) if m else (old.stem, 0)


def _earlier_in_series(old: Path) -> list[Path]:
    """The files beside `old` that a resume could have continued into `old`'s name: X.mcap,
    X.resumed1.mcap, ... below `old`'s number, those that exist (none for X.mcap itself)."""
    base, k = _series(old)
    names = [f"{base}{old.suffix}"] + [f"{base}.resumed{j}{old.suffix}" for j in range(1, k)]
    return [old.with_name(n) for n in names if k > 0 and old.with_name(n).is_file()]


def _refuse_continued(old: Path) -> None:
    """Refuse a resume of `old` when a file beside it, named as a resume of it would be
    (X.resumedk.mcap), already continues it with poses measured: resuming `old` again would
    measure those poses again in another file and leave that one out of every later chain (an
    operator typing the same command after a resume that was itself interrupted). A
    continuation with no pose (stopped at its start) is no loss and does not refuse."""
    base, _ = _series(old)
    me = old.resolve()
    pattern = re.compile(re.escape(base) + r"\.resumed\d+" + re.escape(old.suffix))
    for p in sorted(old.parent.glob(f"{glob.escape(base)}.resumed*{old.suffix}")):
        if not pattern.fullmatch(p.name) or p.resolve() == me or not p.is_file():
            continue
        try:
            rec = read_recording(p, streams=False)
        except (RecordingError, OSError):
            continue  # not a readable recording: it holds no pose a resume would lose
        link = rec.session.get("chained_from")
        if not rec.samples or not isinstance(link, dict) or not isinstance(link.get("path"), str):
            continue
        if any(c.exists() and c.resolve() == me for c in link_candidates(link["path"], p)):
            n = len(rec.samples)
            raise UserError(
                f"{p} already continues {old} ({n} pose{'' if n == 1 else 's'} measured there): "
                f"resume that file instead (`workcell campaign --resume {p}`); resuming {old} "
                f"again would measure them again and leave {p.name} out of the campaign (to do "
                f"that on purpose, move {p.name} out of this folder)"
            )


def default_out(old: Path) -> Path:
    """Beside `old`: X.resumed1.mcap for X.mcap, X.resumed2.mcap for X.resumed1.mcap, ... (the
    first free number after `old`'s)."""
    base, k = _series(old)
    k += 1
    while True:
        p = old.with_name(f"{base}.resumed{k}{old.suffix}")
        if not p.exists():
            return p
        k += 1


def resume_campaign(args: argparse.Namespace, control: CampaignControl) -> int:
    """Continue `args.resume` in a new chained file. `--robot`/`--tracker` are needed only for
    recordings that do not name their devices; given otherwise, they must name the same ones."""
    old = Path(args.resume)
    if getattr(args, "smr_offset", None):
        raise UserError(
            "--resume keeps the SMR offset the campaign was recorded with; leave --smr-offset out"
        )
    if getattr(args, "envelope", None) not in (None, "", "default"):
        raise UserError(
            "--resume keeps the envelope the campaign was recorded with (its poses were planned "
            "inside it); leave --envelope out"
        )
    if getattr(args, "payload", None):
        raise UserError(
            "--resume keeps the payload the campaign was recorded with (one campaign, one "
            "payload); leave --payload out"
        )
    info = resume_plan(str(old), remeasure_missing=bool(getattr(args, "remeasure_missing", False)))
    camp = info["campaign"]
    remaining = int(camp["poses"]) - len(info["done"])
    out = Path(args.out) if args.out else default_out(old)
    if out.exists():
        raise UserError(f"{out} already exists; choose a new file with --out")
    try:
        check_output_path(out, "recording", inputs=[old])
    except UserError as e:
        if args.out:
            raise
        raise UserError(
            f"{e} (by default the continuation goes beside {old}; `--out DIR/NEW.mcap` writes "
            "it elsewhere)"
        ) from None
    if remaining <= 0:
        for note in info["notes"]:
            progress(f"warning: {note['message']}")
        print(f"{old}: all {camp['poses']} poses already measured; nothing to resume")
        return 0
    ns = copy.copy(args)
    for opt in ("robot", "tracker"):
        given, recorded = getattr(args, opt), camp.get(f"{opt}_url")
        if opt == "tracker" and new_serial_port(recorded, given):
            # a re-plugged adapter: `run.check_same_tracker` compares the serial numbers
            setattr(ns, opt, with_recorded_link(recorded, given))
            continue
        if given is not None and recorded is not None and given != recorded:
            raise UserError(
                f"--{opt} {given}: {old} was recorded with --{opt} {recorded}, and a resume "
                f"continues on the same cell; leave --{opt} out"
            )
        setattr(ns, opt, recorded or given or "sim")
    if ns.robot == "sim" and getattr(args, "time_scale_given", False):
        raise UserError(
            f"--time-scale {args.time_scale:g}: {old} was recorded with the in-process simulation, "
            "which runs on virtual time, so it has no effect; leave it out"
        )
    if camp.get("effects") is not None:
        ns.effects = camp["effects"]
    ns.seed = recorded_sim_seed(camp)
    ns.model = (info["recording"].session.get("robot") or {}).get("model") or args.model
    ns.envelope = None
    ns.sim_noise_stream = len(info["chain"])  # a simulated cell: new noise, same truth
    cell, robot, tracker, env = open_cell(ns)
    cell.tool_m = np.asarray(recorded_tool(info["recording"].session))
    pay = info["recording"].session.get("payload") or {}
    if pay.get("mass_kg") is not None:  # the recorded payload, declared or the default
        cell.payload_kg = float(pay["mass_kg"])
        cell.payload_com_m = tuple(float(c) for c in (pay.get("com_m") or (0.0, 0.0, 0.0)))
        cell.payload_source = "recording"
    env = recorded_envelope(camp, cell.spec, str(old), default=env)
    check_same_plan(info, cell.spec, env, cell.tool_m, str(old))
    cfg = recorded_config(
        camp, cell.payload_kg, CampaignConfig(readings_per_pose=args.readings, settle_s=args.settle)
    )
    print(f"resuming {old}: {chain_line(info)}, {to_go_line(info)} -> {out}", file=sys.stderr)
    extra = {
        k: v
        for k, v in camp.items()
        if k
        not in (
            "plan",
            "poses",
            "seed",
            "envelope",
            "readings_per_pose",
            "settle_s",
            "approach_rad",
            "warmup_s",
            "reference_every",
        )
    }
    if "tracker_url" in extra:  # the port it is on now (a re-plugged adapter)
        extra["tracker_url"] = ns.tracker
    watch, repeats = RepeatWatch(info["history"]), [0]

    measured = [0]

    def count_repeats(sample: dict) -> None:  # and a progress line per pose, as a first run
        r = watch.update(sample)
        if r is not None:
            repeats[0] += 1
            progress(
                f"pose {sample['pose_id']:4d}  reference   elapsed {sample['elapsed_s']:8.1f} s  "
                f"{r['displacement_m'] * 1e6:.1f} um from its first reading"
            )
            return
        measured[0] += 1
        progress(
            f"pose {sample['pose_id']:4d}  {measured[0]:4d}/{remaining} more  "
            f"elapsed {sample['elapsed_s']:8.1f} s"
        )

    try:
        _, res = run_campaign(
            robot,
            tracker,
            cell,
            out,
            plan=camp["plan"],
            poses=int(camp["poses"]),
            seed=int(camp["seed"]),
            envelope=env,
            config=cfg,
            control=control,
            extra_campaign=extra,
            **continuation(info, old),
            on_event=lambda e: progress(f"  [{e['level']}] {e['kind']}: {e['message']}"),
            on_sample=count_repeats,
        )
    except DeviceUnreachable as e:
        if getattr(e, "recording", None) is not None or args.tracker is not None:
            raise
        if not str(ns.tracker).startswith("serial://") or not str(e).startswith("tracker port"):
            raise
        raise UserError(
            f"{e}; a re-plugged USB adapter may have another name: give it with --tracker "
            "serial:///dev/ttyUSBn (the resume checks it is the same tracker by its serial "
            "number, and keeps the recorded link settings)",
            exit_code=3,
        ) from None
    again = f" (and the reference {repeats[0]} more times)" if repeats[0] else ""
    summary(
        f"recorded {res.measured - repeats[0]} more poses{again}, skipped {res.skipped} -> {out}",
        control,
    )
    campaign_stop(res, out)
    abort_note(res, out)
    return exit_code(res, control)
