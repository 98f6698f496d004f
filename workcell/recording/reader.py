"""Reader for recording format v1. Reads files without a summary (cut short by a crash): every
complete chunk before the cut is read, and `Recording.problems` says what could not be read.
"""

from __future__ import annotations

import json
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

from mcap.exceptions import McapError
from mcap.records import Channel, Chunk, DataEnd, Footer, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from workcell.errors import UserError
from workcell.recording import schema as S

MAGIC = b"\x89MCAP0\r\n"


class RecordingError(UserError):
    """The file is not a usable recording; the message says what and what to do."""


@dataclass
class Recording:
    path: Path
    session: dict
    samples: list[dict] = field(default_factory=list)
    events: list[dict] = field(default_factory=list)
    joint_states: list[dict] = field(default_factory=list)
    tracker_measurements: list[dict] = field(default_factory=list)
    channel_counts: dict[str, int] = field(default_factory=dict)
    closed_cleanly: bool = False
    trailing_bytes: int = 0  # bytes after the closing magic (appended later; ignored)
    problems: list[str] = field(default_factory=list)
    first_ns: int | None = None
    last_ns: int | None = None
    size_bytes: int = 0
    # why the session or samples cannot be read (their channel is not JSON); read_recording
    # refuses the file with it
    encoding_refusal: str = ""
    # reading state: problems said once per topic (schema, order, bad JSON counts)
    _said: set = field(default_factory=set, repr=False)
    _bad_json: dict = field(default_factory=dict, repr=False)

    @property
    def duration_s(self) -> float:
        if self.first_ns is None or self.last_ns is None:
            return 0.0
        return (self.last_ns - self.first_ns) * 1e-9


def read_recording(path: str | os.PathLike, *, streams: bool = True) -> Recording:
    """Read a recording. Raises RecordingError (one clear line) if it is unusable.

    `streams=False` skips decoding the joint-state and raw tracker streams (faster for fits).
    """
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"{p}: no such file; check the path")
    if p.is_dir():
        raise RecordingError(f"{p}: is a directory, expected an .mcap recording")
    if not p.is_file():  # reading a pipe would wait for a writer forever
        raise RecordingError(f"{p}: not a regular file (a pipe or device); give a recording file")
    with open(p, "rb") as f:
        head = f.read(len(MAGIC))
        if not head:
            raise RecordingError(
                f"{p}: is empty (0 bytes): nothing was recorded in it; give the recording file "
                "(or copy it again from where it was recorded)"
            )
        if head != MAGIC:
            raise RecordingError(f"{p}: not an MCAP file (bad magic bytes); expected a recording")
        f.seek(0)
        rec = Recording(path=p, session={}, size_bytes=p.stat().st_size)
        channels: dict[int, Channel] = {}
        schemas: dict[int, Schema] = {}
        reader = StreamReader(f, emit_chunks=True, record_size_limit=1 << 30)

        def handle(r) -> None:
            if isinstance(r, Schema):
                schemas[r.id] = r
            elif isinstance(r, Channel):
                channels[r.id] = r
            elif isinstance(r, Message):
                _message(rec, channels, schemas, r, streams)

        good = len(MAGIC)  # the end of the last record read whole
        try:
            for r in reader.records:
                good = f.tell()
                if isinstance(r, Chunk):
                    try:
                        inner = breakup_chunk(r, validate_crc=True)
                    except Exception as e:  # corrupt chunk: say so, keep going
                        rec.problems.append(f"a damaged chunk could not be read ({e})")
                        continue
                    for r2 in inner:
                        handle(r2)
                elif isinstance(r, DataEnd):
                    pass
                elif isinstance(r, Footer):
                    rec.closed_cleanly = True
                else:
                    handle(r)
            if rec.closed_cleanly and (why := _summary_unreachable(f)) is not None:
                rec.problems.append(
                    f"the footer does not lead to the summary ({why}): tools that seek through "
                    "the summary (Foxglove, the mcap library's seeking reader) cannot open the "
                    "file; workcell reads it from the start, whole"
                )
            if rec.closed_cleanly and f.tell() < rec.size_bytes:
                rec.trailing_bytes = rec.size_bytes - f.tell()
                rec.problems.append(
                    f"{rec.trailing_bytes} bytes after the recording's end (byte {f.tell()}) "
                    "were ignored: something was appended to the file after it was closed; "
                    "the recording itself is intact"
                )
        except (McapError, EOFError, ValueError, OSError, MemoryError, KeyError, struct.error) as e:
            rec.closed_cleanly = False
            why = "a record cut short" if isinstance(e, struct.error) else type(e).__name__
            rec.problems.append(
                f"file ends or is damaged after byte {good} of {rec.size_bytes} "
                f"({why}); read everything before it"
            )
        except Exception as e:  # noqa: BLE001 - a reader must never crash on a bad file
            rec.closed_cleanly = False
            rec.problems.append(f"unreadable data after byte {f.tell()} ({type(e).__name__}: {e})")
    if not rec.closed_cleanly and not any("ends" in x for x in rec.problems):
        rec.problems.append("no summary/footer: the writer did not finish (crash or still open)")
    for topic, n in rec._bad_json.items():
        rec.problems.append(
            f"{topic}: {n} message{'s are' if n > 1 else ' is'} not {'' if n > 1 else 'a '}valid "
            f"JSON object{'s' if n > 1 else ''}; skipped"
        )
    if rec.encoding_refusal:
        raise RecordingError(f"{p}: {rec.encoding_refusal}; write it with JSON messages")
    if not rec.session:
        if rec.problems and not rec.channel_counts:
            damage = rec.problems[0].split("; read everything")[0]
            raise RecordingError(
                f"{p}: {damage}, before its session (the first message) could be read; nothing "
                "in it is usable; copy it again from where it was recorded"
            )
        raise RecordingError(
            f"{p}: no {S.SESSION} message; a recording must start with its session"
        )
    _check_session(p, rec.session)
    rec.problems += _conformance_notes(rec)
    # MCAP does not require a file's messages to be in time order (a merged or rewritten file
    # may not be): everything downstream (hold-out split, replay, drift tests) follows the order
    # of measurement, so put each stream in log-time order. Stable: equal times keep file order.
    in_file_order = [id(m) for m in rec.samples]
    for stream in (rec.samples, rec.events, rec.joint_states, rec.tracker_measurements):
        stream.sort(key=lambda m: m["_log_time_ns"])
    idx = [m.get("index") for m in rec.samples]
    if all(isinstance(i, int) for i in idx) and any(
        b < a for a, b in zip(idx, idx[1:], strict=False)
    ):
        rec.problems.append(
            f"{S.SAMPLE}: the samples' index does not rise with their log times (format v1: "
            "both follow the order of measurement); read in log-time order"
        )
    if [id(m) for m in rec.samples] != in_file_order:
        rec.problems.append(
            f"{S.SAMPLE}: the samples are not in log-time order in the file; read in log-time "
            "order (the order of measurement the format defines), not in file order"
        )
    return rec


# required sample fields whose absence nothing else reports (pose_id, q_measured_rad and
# tracker_position_m are refused as values; a data set says what it assumes for the others)
_UNSAID_FIELDS = {
    "index": "the order of measurement is taken from the log times",
    "n_readings": "the readings behind each mean are not known",
    "q_commanded_rad": "commanded and measured joints cannot be compared",
    "joint_temperature_c": "thermal effects cannot be tested on those samples",
}
EPOCH_2001_NS = 10**18  # log times below this are before 2001-09-09: not Unix-epoch nanoseconds


def _conformance_notes(rec: Recording) -> list[str]:
    """What a readable file does not do as format v1 says, each said once: required fields
    left out (counted), log times that are not Unix-epoch nanoseconds."""
    out: list[str] = []
    missing = [k for k in S.SCHEMAS[S.SESSION][1]["required"] if k not in rec.session]
    if missing:
        out.append(
            f"{S.SESSION}: the session lacks required field(s) {', '.join(missing)} (format v1); "
            "read without them"
        )
    n = len(rec.samples)
    for key, means in _UNSAID_FIELDS.items():
        lacking = sum(1 for m in rec.samples if key not in m)
        if lacking:
            out.append(
                f"{S.SAMPLE}: {lacking} of {n} samples lack the required field {key} "
                f"(format v1; null where unknown): {means}"
            )
    if rec.first_ns is not None and rec.first_ns < EPOCH_2001_NS:
        out.append(
            f"log times start at {rec.first_ns} ns, before 2001: not nanoseconds since the Unix "
            "epoch as format v1 requires (milliseconds or seconds since start?); the order of "
            "the messages is kept, dates and rates from them are wrong"
        )
    return out


def _say_once(rec: Recording, key: str, text: str) -> None:
    if key not in rec._said:
        rec._said.add(key)
        rec.problems.append(text)


def _message(rec: Recording, channels, schemas, m: Message, streams: bool) -> None:
    ch = channels.get(m.channel_id)
    if ch is None:
        rec.problems.append(f"message on unknown channel id {m.channel_id} skipped")
        return
    topic = ch.topic
    rec.channel_counts[topic] = rec.channel_counts.get(topic, 0) + 1
    t = m.log_time
    rec.first_ns = t if rec.first_ns is None else min(rec.first_ns, t)
    rec.last_ns = t if rec.last_ns is None else max(rec.last_ns, t)
    if topic not in (S.SESSION, S.SAMPLE, S.EVENT) and not streams:
        return
    if topic not in S.SCHEMAS:
        return  # extension channels are allowed
    name = S.SCHEMAS[topic][0]
    sch = schemas.get(ch.schema_id)
    if sch is None or sch.name != name or sch.encoding != "jsonschema":
        got = (
            "no schema" if sch is None else f"schema {sch.name!r} ({sch.encoding or 'no'} encoding)"
        )
        _say_once(
            rec,
            "schema " + topic,
            f"channel {topic} declares {got}, not {name!r} (jsonschema) as format v1 requires; "
            "its messages were read as the format's",
        )
    if topic != S.SESSION and not rec.session:
        _say_once(
            rec,
            "order",
            f"a {topic} message comes before the session, which format v1 requires to be the "
            "first message",
        )
    if ch.message_encoding != "json":
        # the format's messages are JSON; a stream in another encoding cannot be read. Without
        # the session or the samples nothing is usable (refused after the pass, naming the
        # encoding); another stream is skipped with one note
        what = f"channel {topic} uses encoding {ch.message_encoding!r}; format v1 requires json"
        if topic in (S.SESSION, S.SAMPLE):
            rec.encoding_refusal = rec.encoding_refusal or what
        elif not any(x.startswith(what) for x in rec.problems):
            rec.problems.append(f"{what}: its messages were skipped")
        return
    try:
        msg = json.loads(m.data)
    except (ValueError, UnicodeDecodeError, RecursionError):  # one bad message, not the file
        msg = None
    if not isinstance(msg, dict):
        rec._bad_json[topic] = rec._bad_json.get(topic, 0) + 1
        return
    msg["_log_time_ns"] = t
    if topic == S.SESSION:
        if rec.session:
            rec.problems.append("more than one session message; kept the first")
        else:
            rec.session = msg
    elif topic == S.SAMPLE:
        rec.samples.append(msg)
    elif topic == S.EVENT:
        rec.events.append(msg)
    elif topic == S.JOINT_STATE:
        rec.joint_states.append(msg)
    elif topic == S.TRACKER:
        rec.tracker_measurements.append(msg)


def _summary_unreachable(f) -> str | None:
    """Why the mcap library's seeking reader cannot read the summary the footer points at (a
    damaged footer offset), or None; the file position is kept. (A flipped bit in
    summary_start: `info` said "closed cleanly" and Foxglove could not open the file.)"""
    from mcap.reader import SeekingReader

    here = f.tell()
    try:
        f.seek(0)  # the seeking reader reads the magic where the file stands
        SeekingReader(f).get_summary()
    except Exception as e:  # noqa: BLE001 - any failure of the seeking path is the finding
        return f"{type(e).__name__}: {e}"[:120]
    finally:
        f.seek(here)
    return None


def _check_session(p: Path, s: dict) -> None:
    v = s.get("format_version")
    # the integer itself: `true` and 1.0 equal 1 in Python and passed, where "1" was refused
    if type(v) is not int or v != S.FORMAT_VERSION:
        got = "missing" if "format_version" not in s else f"{json.dumps(v)}"
        raise RecordingError(
            f"{p}: session format_version is {got}; this workcell reads version "
            f"{S.FORMAT_VERSION} (the integer)"
        )
    for key in ("robot", "tool", "tracker"):
        if not isinstance(s.get(key), dict):
            raise RecordingError(f"{p}: session has no '{key}' object; not a workcell recording")
