"""kill -9 in the middle of a campaign: the file keeps every completed pose; --resume measures
the rest into a chained file; no pose is measured twice."""

import os
import signal
import subprocess
import sys
import time

from workcell.recording.reader import read_recording


def _start_campaign(rec, poses: int, seed: int) -> subprocess.Popen:
    """`workcell campaign` against the simulated cell, in a child process."""
    cmd = [sys.executable, "-m", "workcell.cli", "campaign", "--robot", "sim", "--tracker", "sim"]
    cmd += ["--poses", str(poses), "--seed", str(seed), "--readings", "3", "--out", str(rec)]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for_samples(p: subprocess.Popen, rec, n: int, timeout_s: float = 120) -> None:
    """Until the recording holds n samples, the process ends or the time is up."""
    deadline = time.time() + timeout_s
    while time.time() < deadline and p.poll() is None:
        time.sleep(0.2)
        try:
            if rec.exists() and len(read_recording(rec).samples) >= n:
                return
        except Exception:  # noqa: BLE001 - the file may not hold its session yet
            pass


def test_kill9_then_resume(tmp_path):
    rec = tmp_path / "c.mcap"
    p = _start_campaign(rec, poses=40, seed=5)
    _wait_for_samples(p, rec, 8)
    assert p.poll() is None, "campaign finished before it could be killed; make it longer"
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    first = read_recording(rec)
    assert not first.closed_cleanly
    done = [s["pose_id"] for s in first.samples]
    assert len(done) >= 8 and len(set(done)) == len(done)
    r = subprocess.run(
        [sys.executable, "-m", "workcell.cli", "campaign", "--resume", str(rec)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    second_path = tmp_path / "c.resumed1.mcap"
    second = read_recording(second_path)
    assert second.closed_cleanly
    assert second.session["chained_from"]["samples"] == len(done)
    more = [s["pose_id"] for s in second.samples]
    skipped = sum(1 for e in first.events + second.events if e["kind"] in ("skip", "refused"))
    assert not set(done) & set(more), "a pose was measured twice"
    assert len(set(done) | set(more)) + skipped >= 40
    assert [s["index"] for s in second.samples][0] == len(done)
    assert any(e["kind"] == "resume_from" for e in second.events)


def test_ctrl_c_finishes_the_recording_cleanly(tmp_path):
    rec = tmp_path / "c.mcap"
    p = _start_campaign(rec, poses=60, seed=6)
    _wait_for_samples(p, rec, 5)
    assert p.poll() is None
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    r = read_recording(rec)
    assert r.closed_cleanly and not r.problems
    assert r.events[-1]["kind"] == "abort"
    assert 5 <= len(r.samples) < 60


def test_resume_refuses_a_recording_whose_plan_this_version_would_not_recreate(
    tmp_path, monkeypatch
):
    """Static plans resume by pose id: if the re-created plan puts a recorded pose id elsewhere
    (another version's planner, an edited seed), resuming would measure poses twice or miss some,
    so it is refused in one line; the plan of the same version is accepted."""
    import copy

    import numpy as np
    import pytest

    from workcell.campaign import plans
    from workcell.campaign.envelope import default_envelope
    from workcell.campaign.resume import check_same_plan, resume_plan
    from workcell.campaign.run import run_campaign, sim_cell
    from workcell.errors import UserError

    rec = tmp_path / "c.mcap"
    _, robot, tracker, cell = sim_cell("ur5e", "none", 3)
    run_campaign(robot, tracker, cell, rec, plan="random", poses=6, seed=3)
    info = resume_plan(str(rec))
    env = default_envelope(cell.spec)
    check_same_plan(info, cell.spec, env, cell.tool_m, "c.mcap")  # same version: accepted

    other = copy.deepcopy(info)
    other["campaign"]["seed"] = 4
    with pytest.raises(UserError, match="pose 0 was commanded"):
        check_same_plan(other, cell.spec, env, cell.tool_m, "c.mcap")

    real_order = plans.order_for_paths
    monkeypatch.setattr(
        plans,
        "order_for_paths",
        lambda *a: tuple(np.flip(x, 0) for x in real_order(*a)),  # a planner of another version
    )
    with pytest.raises(UserError, match="another workcell version"):
        check_same_plan(info, cell.spec, env, cell.tool_m, "c.mcap")
