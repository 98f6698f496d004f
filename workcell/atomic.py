"""Outputs written whole or not at all: each file goes to a fresh temporary name beside it,
is flushed to disk, and only then renamed over the target (`os.replace`, atomic on POSIX). A
failure on the way (a full disk, Ctrl-C, an error while formatting) leaves the earlier output
as it was and no partial file behind. A kill (SIGKILL, a power cut) can leave the temporary
file (`.NAME.PID.XXXXXXXX.tmp`); the next write of the same output removes those whose process
is gone."""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_files(
    *paths: str | os.PathLike, newline: str | None = None, binary: bool = False
) -> Iterator[list]:
    """Open a temporary file (UTF-8 text whatever the locale, or bytes when `binary`) beside
    each of `paths`; yields the open files. When the block ends without an error, every file is flushed and synced, then all
    are renamed into place (in the order given); otherwise the temporaries are removed and
    nothing is replaced."""
    targets = [Path(p) for p in paths]
    tmps: list[str] = []
    files = []
    try:
        for p in targets:
            p.parent.mkdir(parents=True, exist_ok=True)
            # the name cut short: a target name near the file system's limit (255 bytes) still
            # gets a temporary one within it
            _remove_orphans(p)
            fd, tmp = tempfile.mkstemp(
                prefix=f"{_tmp_prefix(p)}{os.getpid()}.", suffix=".tmp", dir=p.parent
            )
            tmps.append(tmp)
            files.append(
                os.fdopen(fd, "wb")
                if binary
                else os.fdopen(fd, "w", encoding="utf-8", newline=newline)
            )
        yield files
        umask = os.umask(0)
        os.umask(umask)
        for f, tmp in zip(files, tmps, strict=True):
            f.flush()
            os.fsync(f.fileno())
            f.close()
            os.chmod(tmp, 0o666 & ~umask)  # as an ordinary new file (mkstemp makes it 0600)
        for tmp, p in zip(tmps, targets, strict=True):
            os.replace(tmp, p)
    finally:
        for f in files:
            with contextlib.suppress(OSError):
                f.close()
        for tmp in tmps:
            Path(tmp).unlink(missing_ok=True)  # gone already once renamed


def _tmp_prefix(p: Path) -> str:
    return f".{p.name[:48]}."


_ORPHAN_AGE_S = 60.0  # and not touched for a minute (a writer on another host has other pids)


def _remove_orphans(p: Path) -> None:
    """Remove the temporaries of earlier writes of `p` whose process no longer runs (a kill
    between mkstemp and the rename); a live writer's, and any other file, are left alone."""
    pattern = re.compile(re.escape(_tmp_prefix(p)) + r"(\d+)\.[A-Za-z0-9_]{8}\.tmp")
    with contextlib.suppress(OSError):
        for q in p.parent.iterdir():
            m = pattern.fullmatch(q.name)
            if m is None or _alive(int(m[1])):
                continue
            with contextlib.suppress(OSError):
                if q.is_file() and time.time() - q.stat().st_mtime > _ORPHAN_AGE_S:
                    q.unlink()


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True  # another user's, or not a pid at all: not ours to remove
    return True


def write_text(path: str | os.PathLike, text: str) -> Path:
    """`Path.write_text`, whole or not at all."""
    with atomic_files(path) as (f,):
        f.write(text)
    return Path(path)


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """`Path.write_bytes`, whole or not at all."""
    with atomic_files(path, binary=True) as (f,):
        f.write(data)
    return Path(path)


def save_figure(fig, path: str | os.PathLike, **kw) -> Path:
    """`fig.savefig(path, **kw)` (a matplotlib figure), whole or not at all: the image is made
    in memory (its format from the name's suffix), then written by `write_bytes`."""
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format=Path(path).suffix.lstrip(".") or "png", **kw)
    return write_bytes(path, buf.getvalue())
