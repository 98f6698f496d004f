"""Append-only MCAP writer for recording format v1. Flushes to disk at every pose and event.

Each `sample()` closes the current chunk and fsyncs, so a kill -9 loses at most the pose in
progress (its joint states and tracker readings, written before its sample).

While it writes, the writer holds an exclusive advisory lock (`flock`) on its file; the
operating system releases it when the file is closed or the process ends, however it ends.
`being_written` tells a resume that a file is still some campaign's (a resume of it would
measure the same poses again in another file).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mcap.writer import CompressionType, Writer

from workcell.recording import schema as S
from workcell.strict_json import finite

if TYPE_CHECKING:
    import numpy as np


def _now_ns() -> int:
    return time.time_ns()


try:
    import fcntl
except ImportError:  # not POSIX: no lock; a resume cannot tell a file still being written
    fcntl = None  # type: ignore[assignment]


def _lock(f) -> None:
    if fcntl is not None:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # a file system without locks (some network mounts): write unlocked
            pass


def being_written(path: str | os.PathLike) -> bool:
    """Whether a running campaign (this process or another on this machine) holds `path` open
    for writing (its `RecordingWriter` lock). False where locks are not available."""
    if fcntl is None:
        return False
    try:
        with open(path, "rb") as f:
            try:
                fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            except OSError:
                return False
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
    except OSError:
        return False
    return False


class RecordingWriter:
    """Write a campaign recording. Use as a context manager; `close()` writes the summary."""

    def __init__(
        self,
        path: str | os.PathLike,
        session: dict,
        *,
        compression: str = "zstd",
        session_t_ns: int | None = None,
    ):
        """`session_t_ns`: the session's log time (default now); a resume gives one after the
        old file's last record, so the continued campaign's log times never go back."""
        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"{self.path} already exists; refusing to overwrite a recording")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "xb")  # never over a file that appeared meanwhile
        _lock(self._f)  # released by close(), or by the end of the process
        try:
            self._start(session, compression, session_t_ns)
        except BaseException:
            # nothing measured yet (a full disk, an unwritable session): leave no header-only
            # file behind, which would block the same path and could not be resumed. Closing
            # flushes what is buffered, and on a full disk that fails too: remove it anyway
            try:
                self._f.close()
            except OSError:
                pass
            finally:
                self.path.unlink(missing_ok=True)
            raise

    def _start(self, session: dict, compression: str, session_t_ns: int | None) -> None:
        comp = {
            "zstd": CompressionType.ZSTD,
            "lz4": CompressionType.LZ4,
            "none": CompressionType.NONE,
        }[compression]
        self._w = Writer(self._f, chunk_size=4 * 1024 * 1024, compression=comp)
        self._w.start(profile="", library="workcell")
        self._ch: dict[str, int] = {}
        for topic in (S.SESSION, S.JOINT_STATE, S.TRACKER, S.SAMPLE, S.EVENT):
            name, data = S.schema_bytes(topic)
            sid = self._w.register_schema(name=name, encoding="jsonschema", data=data)
            self._ch[topic] = self._w.register_channel(
                topic=topic, message_encoding="json", schema_id=sid
            )
        self._seq = 0
        self.n_samples = 0
        self.closed = False
        sess = {
            "format_version": S.FORMAT_VERSION,
            "created_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            **session,
        }
        sess.setdefault("software", {"name": "workcell", "version": _version()})
        self._write(S.SESSION, sess, _now_ns() if session_t_ns is None else session_t_ns)
        self.flush()

    def _write(self, topic: str, msg: dict, t_ns: int) -> None:
        if self.closed:
            raise ValueError(f"recording {self.path} is closed")
        data = json.dumps(finite(msg), allow_nan=False).encode()
        self._w.add_message(
            channel_id=self._ch[topic],
            log_time=int(t_ns),
            publish_time=int(t_ns),
            data=data,
            sequence=self._seq,
        )
        self._seq += 1

    def flush(self) -> None:
        self._w.flush()  # closes the current chunk
        self._f.flush()
        os.fsync(self._f.fileno())

    def joint_state(
        self,
        t_ns: int,
        q_rad: np.ndarray | Sequence[float],
        qd_rad_s: np.ndarray | Sequence[float],
        torque_nm: np.ndarray | Sequence[float] | None = None,
        temperature_c: np.ndarray | Sequence[float] | None = None,
    ) -> None:
        self._write(
            S.JOINT_STATE,
            {
                "q_rad": q_rad,
                "qd_rad_s": qd_rad_s,
                "torque_nm": torque_nm,
                "temperature_c": temperature_c,
            },
            t_ns,
        )

    def tracker_measurement(
        self,
        t_ns: int,
        position_m: np.ndarray | Sequence[float | None],
        sigma_m: np.ndarray | Sequence[float | None],
        status: str,
        instrument_time_s: float | None = None,
    ) -> None:
        """One raw reading. A reading whose status is not `ok` read no position: its position and
        sigma are recorded as nulls whatever the device returned beside the status.
        `instrument_time_s`: the instrument's own time stamp of the measurement (GeoCOM's
        CoordTime, seconds on the instrument's clock, not the epoch), when it gives one."""
        if status != "ok":
            position_m = sigma_m = [None, None, None]
        msg: dict[str, Any] = {"position_m": position_m, "sigma_m": sigma_m, "status": status}
        if instrument_time_s is not None and math.isfinite(instrument_time_s):
            msg["instrument_time_s"] = float(instrument_time_s)
        self._write(S.TRACKER, msg, t_ns)

    def sample(self, t_ns: int, sample: dict, *, flush: bool = True) -> None:
        """Record one pose sample. `flush=False` (bulk import of a trajectory) skips the
        per-sample chunk close and fsync; the caller flushes or closes."""
        for k in ("q_measured_rad", "tracker_position_m"):
            if any(x is None or not math.isfinite(x) for x in finite(sample[k]) or [None]):
                raise ValueError(f"sample {sample.get('pose_id')}: non-finite {k}")
        self._write(S.SAMPLE, sample, t_ns)
        self.n_samples += 1
        if flush:
            self.flush()

    def event(self, t_ns: int, level: str, kind: str, message: str) -> None:
        self._write(S.EVENT, {"level": level, "kind": kind, "message": message}, t_ns)
        self.flush()

    def close(self) -> None:
        if self.closed:
            return
        try:
            self._w.finish()
            self._f.flush()
            os.fsync(self._f.fileno())
        finally:  # a failed summary (a full disk) still releases the file and its lock
            self._f.close()
            self.closed = True

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("workcell")
    except Exception:
        return "0+unknown"
