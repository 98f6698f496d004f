"""`workcell info REC`: what a recording holds and whether it was closed cleanly."""

from __future__ import annotations

import argparse
import json
import math
import os

import numpy as np

from workcell import strict_json
from workcell.recording import checks
from workcell.recording.checks import is_finite_list, is_finite_number
from workcell.recording.reader import Recording, read_recording
from workcell.recording.repeats import repeats_of


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", help="an .mcap recording")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def _get(d, key):
    return d.get(key) if isinstance(d, dict) else None


def value_problems(rec: Recording) -> tuple[list[str], list[str]]:
    """(what `Dataset.from_recording` would refuse in this file: wrong units, bad types, tracker
    positions that do not follow the arm; what it would set aside and use: gross readings,
    exact copies of samples)."""
    out = checks.problems_of(rec.session, rec.samples)
    if out or not rec.samples:
        return out, []
    from workcell.recording.chain import Chain, file_sha256
    from workcell.recording.dataset import Dataset
    from workcell.recording.reader import RecordingError

    try:  # this file's own values (`chain_summary` reports the files it continues)
        ds = Dataset.from_recording(Chain([rec], [file_sha256(rec.path)]))
    except RecordingError as e:
        msg = str(e)
        for where in (str(rec.path), os.path.abspath(rec.path)):
            msg = msg.removeprefix(f"{where}: ")
        return [msg], []
    return [], [n for n in ds.read_notes if "set aside" in n or "exact copies" in n]


def chain_summary(rec: Recording) -> dict | None:
    """What a fit of this resumed recording uses (`workcell.recording.chain.load_chain`): every
    file of its `chained_from` chain ({path, samples} oldest first) and their total, or why a fit
    refuses it (a link missing or changed); None for a recording that continues nothing."""
    if not rec.session.get("chained_from"):
        return None
    from workcell.errors import UserError
    from workcell.recording.chain import load_chain

    try:
        ch = load_chain(rec)
    except UserError as e:
        recs, notes, problem = [rec], [], str(e)
    else:
        recs, notes, problem = ch.recordings, ch.notes, None
    files = [{"path": str(r.path), "samples": len(r.samples)} for r in recs]
    return {
        "files": files,
        "samples": sum(f["samples"] for f in files),
        "problem": problem,
        "notes": notes,
    }


def summary(path: str) -> dict:
    rec = read_recording(path)
    s = rec.session
    kinds: dict[str, int] = {}
    for e in rec.events:
        kind = str(e.get("kind", "?"))
        kinds[kind] = kinds.get(kind, 0) + 1
    ids = [json.dumps(x.get("pose_id")) for x in rec.samples]
    return {
        "path": str(rec.path),
        "robot": _get(s.get("robot"), "model"),
        "tracker": _get(s.get("tracker"), "model"),
        "created_utc": s.get("created_utc"),
        "poses": len(rec.samples),
        "distinct_pose_ids": len(set(ids)),
        "duration_s": rec.duration_s,
        "channels": rec.channel_counts,
        "events": kinds,
        "closed_cleanly": rec.closed_cleanly,
        "trailing_bytes": rec.trailing_bytes,
        "problems": rec.problems,
        **dict(zip(("value_problems", "set_aside"), value_problems(rec), strict=True)),
        "plan": _get(s.get("campaign"), "plan"),
        "envelope": _get(s.get("campaign"), "envelope"),
        "payload": s.get("payload"),
        "chained_from": s.get("chained_from"),
        "chain": chain_summary(rec),
        "size_bytes": rec.size_bytes,
        "repeats": repeats_of(rec),
        "tracker_readings": tracker_readings(rec),
    }


def tracker_readings(rec: Recording) -> dict | None:
    """The raw tracker readings (`/tracker/measurement`): how many of each status, and how many
    carry the instrument's own time stamp (`instrument_time_s`) with the span it covers; None
    when the recording holds none (a file with only the two channels fits need)."""
    ms = rec.tracker_measurements
    if not ms:
        return None
    status: dict[str, int] = {}
    for m in ms:
        k = str(m.get("status", "?"))
        status[k] = status.get(k, 0) + 1
    t = [float(v) for m in ms if is_finite_number(v := m.get("instrument_time_s"))]
    return {
        "readings": len(ms),
        "status": status,
        "instrument_time_stamped": len(t),
        "instrument_time_span_s": (max(t) - min(t)) if t else None,
    }


def tracker_line(d: dict) -> str:
    """One line for `tracker_readings`'s result."""
    st = ", ".join(f"{v} {k}" for k, v in sorted(d["status"].items(), key=lambda kv: -kv[1]))
    n = d["instrument_time_stamped"]
    if n == 0:
        ts = "no instrument time stamps (the in-process simulated tracker, or a tool that keeps none)"
    else:
        ts = (
            f"{n} with the instrument's own time stamp, spanning "
            f"{d['instrument_time_span_s']:.1f} s of its clock"
        )
    return f"{d['readings']} raw readings ({st}); {ts}"


def run(args: argparse.Namespace) -> int:
    d = summary(args.recording)
    if args.json:
        print(strict_json.dumps(d))
        return 0
    print(f"recording   {d['path']} ({d['size_bytes']} bytes)")
    print(f"robot       {d['robot']}    tracker {d['tracker']}")
    print(f"created     {d['created_utc']}    plan {d['plan']}")
    print(f"poses       {d['poses']} samples ({d['distinct_pose_ids']} distinct pose ids)")
    print(f"duration    {d['duration_s']:.1f} s")
    print("channels    " + ", ".join(f"{k}: {v}" for k, v in d["channels"].items()))
    print("events      " + (", ".join(f"{k}: {v}" for k, v in d["events"].items()) or "none"))
    closed = "cleanly" if d["closed_cleanly"] else "NOT cleanly (crash or still open)"
    if d["trailing_bytes"]:
        closed += f", then {d['trailing_bytes']} bytes appended after its end (ignored)"
    print(f"closed      {closed}")
    if d["tracker_readings"] is not None:
        print(f"readings    {tracker_line(d['tracker_readings'])}")
    if d["envelope"] is not None:
        print(f"envelope    {envelope_line(d['envelope'])}")
    if (pl := payload_line(d["payload"])) is not None:
        print(f"payload     {pl}")
    if d["chained_from"]:
        print(f"continues   {_get(d['chained_from'], 'path')}")
    ch = d["chain"]
    if ch and ch["problem"]:
        print(f"chain       fits refuse this file: {ch['problem']}")
    elif ch:
        names = " + ".join(f"{f['samples']} ({os.path.basename(f['path'])})" for f in ch["files"])
        print(
            f"chain       {ch['samples']} samples in {len(ch['files'])} files, all used by fits: {names}"
        )
        for n in ch["notes"]:
            print(f"chain       {n}")
    from workcell.recording.repeats import repeat_line

    for r in d["repeats"][:3]:
        print(f"repeated    {repeat_line(r)}")
    if len(d["repeats"]) > 3:
        print(f"repeated    ... and {len(d['repeats']) - 3} more poses measured more than once")
    for p in d["problems"]:
        print(f"problem     {p}")
    for n in d["set_aside"]:
        print(f"set aside   {n}")
    vp = d["value_problems"]
    for p in vp[:20]:
        print(f"bad value   {p}")
    if len(vp) > 20:
        print(f"bad value   ... and {len(vp) - 20} more ({len(vp)} in all; --json lists every one)")
    if vp:
        print("            fits refuse this file until these values are repaired")
    return 0


_PAYLOAD_SOURCE = {
    "declared": "declared",
    "controller": "the controller's setting",
    "recording": "kept from the recording it continues",
    "default": "nothing stated it",
}


def _mass_com(d) -> str | None:
    """'0.5 kg at (0.0, 0.0, 30.0) mm' from {mass_kg, com_m}; None if not readable numbers."""
    m, com = _get(d, "mass_kg"), _get(d, "com_m")
    if isinstance(m, bool) or not isinstance(m, (int, float)) or not math.isfinite(m):
        return None
    text = f"{m:.4g} kg"
    if is_finite_list(com, 3) and max(map(abs, com)) < 1e6:
        text += " at (" + ", ".join(f"{c * 1e3:.1f}" for c in com) + ") mm"
    return text


def payload_line(d) -> str | None:
    """The recorded payload in one line: mass and centre of mass (flange, mm), where it came
    from and what the controller reported (None without a readable payload; the value checks
    say what is wrong with it)."""
    text = _mass_com(d)
    if text is None:
        return None
    src = _get(d, "source")
    if isinstance(src, str):
        text += f" ({_PAYLOAD_SOURCE.get(src, src[:40])})"
    else:  # an imported or older recording: the value without where it came from
        text += " (its source not recorded)"
    ctrl = _get(d, "controller")
    if isinstance(ctrl, dict):
        said = _mass_com(ctrl)
        if said is not None and src != "controller":
            text += f"; the controller was set to {said}"
        elif isinstance(ctrl.get("unavailable"), str):
            text += "; the controller's setting was not readable"
    return text


def envelope_line(d) -> str:
    """The recorded safety envelope in one line (joint limits in degrees for reading)."""
    from workcell.campaign.envelope import Envelope

    try:
        env = Envelope.from_dict(d, margin_if_absent_m=0.0)
    except ValueError as e:
        return f"unusable ({e})"
    lim = np.degrees(env.joint_limits_rad)
    joints = ", ".join(f"{lo:.0f}..{hi:.0f}" for lo, hi in lim)
    return (
        f"joints [{joints}] deg, SMR box {np.round(env.box_min_m, 3).tolist()}.."
        f"{np.round(env.box_max_m, 3).tolist()} m, floor {env.floor_z_m:g} m, "
        + (
            f"margin {1e3 * env.kinematic_margin_m:g} mm, "
            if isinstance(d, dict) and "kinematic_margin_m" in d
            else ""
        )
        + f"<= {env.max_speed_rad_s:g} rad/s"
    )
