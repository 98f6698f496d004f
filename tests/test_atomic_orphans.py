"""A kill during a write leaves its temporary file; the next write of the same output removes
the temporaries of processes that are gone, and nothing else."""

from __future__ import annotations

import os
import subprocess
import sys
import time

from workcell.atomic import write_text


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _aged(path, seconds: float = 3600.0):
    path.write_text("partial")
    t = time.time() - seconds
    os.utime(path, (t, t))
    return path


def test_next_write_removes_a_dead_writers_temporary(tmp_path):
    dead = _dead_pid()
    orphan = _aged(tmp_path / f".model.json.{dead}.abcd_123.tmp")
    live = _aged(tmp_path / f".model.json.{os.getpid()}.zzzzzzzz.tmp")  # a writer still running
    fresh = tmp_path / f".model.json.{dead}.yyyyyyyy.tmp"  # just written: may be another host's
    fresh.write_text("partial")
    other = _aged(tmp_path / f".report.json.{dead}.abcd_123.tmp")  # another output's
    longer = _aged(tmp_path / f".model.json.x.{dead}.abcd_123.tmp")  # model.json.x's
    mine = _aged(tmp_path / "notes.tmp")
    write_text(tmp_path / "model.json", "{}")
    assert (tmp_path / "model.json").read_text() == "{}"
    assert not orphan.exists()
    for kept in (live, fresh, other, longer, mine):
        assert kept.exists(), kept.name


def test_a_killed_write_is_cleaned_by_the_next(tmp_path):
    out = tmp_path / "table.csv"
    code = (
        "import os, sys\n"
        "from workcell.atomic import atomic_files\n"
        "with atomic_files(sys.argv[1]) as (f,):\n"
        "    f.write('half'); f.flush(); os.kill(os.getpid(), 9)\n"
    )
    subprocess.run([sys.executable, "-c", code, str(out)], check=False)
    left = [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    assert len(left) == 1 and not out.exists()
    t = time.time() - 3600
    os.utime(left[0], (t, t))
    write_text(out, "whole")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]
