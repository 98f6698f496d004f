"""Reader for recording format v1. Reads files without a summary (cut short by a crash): every
complete chunk before the cut is read, and `Recording.problems` says what could not be read.
"""

from __future__ import annotations

import json
import math
import os
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
            if rec.closed_cleanly and f.tell() < rec.size_bytes:
                rec.trailing_bytes = rec.size_bytes - f.tell()
                rec.problems.append(
                    f"{rec.trailing_bytes} bytes after the recording's end (byte {f.tell()}) "
                    "were ignored: something was appended to the file after it was closed; "
                    "the recording itself is intact"
                )
        except (McapError, EOFError, ValueError, OSError, MemoryError, KeyError) as e:
            rec.closed_cleanly = False
            rec.problems.append(
                f"file ends or is damaged after byte {good} of {rec.size_bytes} "
                f"({type(e).__name__}); read everything before it"
            )
        except Exception as e:  # noqa: BLE001 - a reader must never crash on a bad file
            rec.closed_cleanly = False
            rec.problems.append(f"unreadable data after byte {f.tell()} ({type(e).__name__}: {e})")
    if not rec.closed_cleanly and not any("ends" in x for x in rec.problems):
        rec.problems.append("no summary/footer: the writer did not finish (crash or still open)")
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
    # MCAP does not require a file's messages to be in time order (a merged or rewritten file
    # may not be): everything downstream (hold-out split, replay, drift tests) follows the order
    # of measurement, so put each stream in log-time order. Stable: equal times keep file order.
    for stream in (rec.samples, rec.events, rec.joint_states, rec.tracker_measurements):
        stream.sort(key=lambda m: m["_log_time_ns"])
    return rec


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
    except (ValueError, UnicodeDecodeError):
        rec.problems.append(f"{topic}: a message is not valid JSON (log time {t}); skipped")
        return
    if not isinstance(msg, dict):
        rec.problems.append(f"{topic}: a message is not a JSON object; skipped")
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


def _check_session(p: Path, s: dict) -> None:
    v = s.get("format_version")
    if v != S.FORMAT_VERSION:
        raise RecordingError(
            f"{p}: session format_version is {v!r}; this workcell reads version {S.FORMAT_VERSION}"
        )
    for key in ("robot", "tool", "tracker"):
        if not isinstance(s.get(key), dict):
            raise RecordingError(f"{p}: session has no '{key}' object; not a workcell recording")


def is_finite_list(v, n: int) -> bool:
    return (
        isinstance(v, list)
        and len(v) == n
        and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v
        )
    )
