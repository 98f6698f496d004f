"""kill -9 in the middle of a campaign: the file keeps every completed pose; --resume measures
the rest into a chained file; no pose is measured twice."""

import os
import re
import signal
import subprocess
import sys
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

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
    # one clock across the chain: the new file's records come after the old file's, and a
    # sample's log time less its elapsed time is the campaign's start in both files
    assert min(s["_log_time_ns"] for s in second.samples) > first.last_ns
    # every record, the session included (it was stamped with the wall clock, 272 s before the
    # old file's last record in a time-scaled simulation)
    assert second.first_ns > first.last_ns
    starts = [s["_log_time_ns"] - s["elapsed_s"] * 1e9 for s in first.samples + second.samples]
    assert max(starts) - min(starts) < 1e6, (min(starts), max(starts))


def test_a_resume_counts_the_time_the_campaign_was_down():
    """`elapsed_s` is the time since the campaign started: a resume an hour after the old file's
    last record continues an hour later (it used to continue from the last value, as if the
    arm had not cooled meanwhile), and starts after that record however the clocks stand."""
    from workcell.campaign.run import _start_clock

    now = time.time_ns()
    hour = 3600 * 10**9
    t0, e0 = _start_clock({"last_ns": now - hour, "start_ns": now - hour - 100 * 10**9}, 100.0)
    assert t0 >= now and 3700 <= e0 < 3700 + (t0 - now) * 1e-9 + 1
    # an old file whose log times run ahead of this clock (a time-scaled simulation): after it
    t0, e0 = _start_clock({"last_ns": now + hour, "start_ns": now + hour - 50 * 10**9}, 50.0)
    assert t0 == now + hour + 1 and abs(e0 - 50.0) < 1e-6
    assert _start_clock(None, 0.0)[1] == 0.0


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

    from sim_devices.cell import sim_cell
    from workcell.campaign import plans
    from workcell.campaign.envelope import default_envelope
    from workcell.campaign.resume import check_same_plan, resume_plan
    from workcell.campaign.run import run_campaign
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
    # every sample is checked, not one per pose id: all six recorded as pose 0 (another tool's
    # file) passed on the first, and five more poses were measured (fuzz audit, 2026-11-29)
    same_id = copy.deepcopy(info)
    for smp in same_id["samples"]:
        smp["pose_id"] = 0
    same_id["history"] = {0: same_id["samples"][0]}
    with pytest.raises(UserError, match="pose 0 was commanded"):
        check_same_plan(same_id, cell.spec, env, cell.tool_m, "c.mcap")

    real_order = plans.order_for_paths
    monkeypatch.setattr(
        plans,
        "order_for_paths",
        lambda *a: tuple(np.flip(x, 0) for x in real_order(*a)),  # a planner of another version
    )
    with pytest.raises(UserError, match="another workcell version"):
        check_same_plan(info, cell.spec, env, cell.tool_m, "c.mcap")


def test_tui_resume_continues_on_the_same_simulated_cell_only(tmp_path, monkeypatch):
    """The terminal UI resumes on the devices it has connected: a simulated truth other than the
    recorded one (effects, or the Devices screen's seed, which the UI keeps apart from the
    plan's) is refused in one line, as the command line adopts the recorded one. The recording
    keeps the simulation's seed (`sim_seed`) and the warm-up, which `validate --robot sim` and
    the resume then use."""
    import sim_devices.cell as cell_mod
    from workcell.campaign.executor import CampaignControl
    from workcell.cli import main
    from workcell.errors import UserError
    from workcell.tui import backend

    monkeypatch.chdir(tmp_path)
    plan = backend.PlanConfig(poses=18, seed=5, readings_per_pose=2, settle_s=0.2, out="a.mcap")

    def start(effects="none", seed=2, control=None, resume_from=None, on_sample=lambda s: None):
        dev = backend.open_devices(backend.DeviceConfig(effects=effects, seed=seed))
        try:
            return backend.start_campaign(
                dev, plan, control=control or CampaignControl(), on_sample=on_sample,
                on_event=lambda e: None, resume_from=resume_from,
            )  # fmt: skip
        finally:
            dev.close()

    control = CampaignControl()
    start(control=control, on_sample=lambda s: s["index"] >= 12 and control.abort.set())
    camp = read_recording(tmp_path / "a.mcap").session["campaign"]
    assert (camp["seed"], camp["sim_seed"], camp["effects"], camp["warmup_s"]) == (5, 2, "none", 0)
    with pytest.raises(UserError, match="simulated truth 'none', seed 2; the connected simulation"):
        start(seed=3, resume_from="a.mcap")
    with pytest.raises(UserError, match="is 'realistic', seed 2"):
        start(effects="realistic", resume_from="a.mcap")
    path, res = start(resume_from="a.mcap")
    assert not res.aborted
    assert read_recording(path).session["campaign"]["sim_seed"] == 2
    # validate rebuilds the simulated arm the recording was made on: seed 2, not the plan's 5
    seeds = []
    real = cell_mod.sim_cell

    def spy(model, effects, seed, **kw):
        seeds.append(seed)
        return real(model, effects, seed, **kw)

    monkeypatch.setattr(cell_mod, "sim_cell", spy)
    assert main(["fit", "a.mcap", "--holdout", "0", "--out", "m.json"]) == 0
    assert main(["validate", "m.json", "--targets", "2", "--json"]) == 0
    assert seeds == [2]


@pytest.mark.parametrize(
    ("recorded", "connected", "refused"),
    [
        # a real cell: the addresses must match
        ({"robot_url": "ur://10.0.0.5", "tracker_url": "serial:///dev/ttyUSB0"},
         ("ur://10.0.0.5", "serial:///dev/ttyUSB0", None, None), None),
        ({"robot_url": "ur://10.0.0.5", "tracker_url": "serial:///dev/ttyUSB0"},
         ("ur://10.0.0.6", "serial:///dev/ttyUSB0", None, None), "robot at ur://10.0.0.5"),
        ({"robot_url": "ur://10.0.0.5", "tracker_url": "serial:///dev/ttyUSB0"},
         ("sim", "sim", "none", 0), "not on a simulation"),
        # simulators the UI started: their ports change each start, the truth must not
        ({"robot_url": "ur://127.0.0.2", "tracker_url": "serial:///dev/pts/4",
          "effects": "realistic", "sim_seed": 7},
         ("ur://127.0.0.2", "serial:///dev/pts/9", "realistic", 7), None),
        ({"robot_url": "sim", "tracker_url": "sim", "effects": "realistic", "sim_seed": 7},
         ("ur://10.0.0.5", "serial:///dev/ttyUSB0", None, None), "connect that simulation"),
        # a command-line recording: its seed is the truth's
        ({"robot_url": "sim", "tracker_url": "sim", "effects": "none", "sim_seed": None},
         ("sim", "sim", "none", 3), "seed 0"),
    ],
)  # fmt: skip
def test_check_same_cell(recorded, connected, refused):
    from workcell.campaign.resume import check_same_cell
    from workcell.errors import UserError

    camp = {"plan": "random", "poses": 10, "seed": 0, **recorded}
    robot_url, tracker_url, effects, sim_seed = connected
    kw = dict(robot_url=robot_url, tracker_url=tracker_url, effects=effects, sim_seed=sim_seed)
    if refused is None:
        check_same_cell(camp, "x.mcap", **kw)
    else:
        with pytest.raises(UserError, match=re.escape(refused)):
            check_same_cell(camp, "x.mcap", **kw)


def test_a_resume_measures_with_the_recorded_settings():
    """Readings, settle time, approach and warm-up come from the recording (the arm is warmed
    up again as the campaign was); a recording without one gets the caller's default."""
    from workcell.campaign.executor import CampaignConfig
    from workcell.campaign.resume import recorded_config

    camp = {"readings_per_pose": 7, "settle_s": 2.5, "approach_rad": 0.03, "warmup_s": 600.0}
    cfg = recorded_config(camp, 1.5, CampaignConfig(readings_per_pose=3, settle_s=1.0))
    assert (cfg.readings_per_pose, cfg.settle_s, cfg.approach_rad, cfg.warmup_s) == (
        7, 2.5, 0.03, 600.0
    )  # fmt: skip
    assert cfg.payload_kg == 1.5
    old = recorded_config({}, 0.0, CampaignConfig(readings_per_pose=3, settle_s=1.0))
    assert (old.readings_per_pose, old.settle_s, old.approach_rad, old.warmup_s) == (
        3, 1.0, 0.02, 0.0
    )  # fmt: skip


@pytest.fixture(scope="module")
def interrupted(tmp_path_factory):
    """A 6-pose simulated campaign aborted after 2 poses: (session, samples)."""
    from sim_devices.cell import sim_cell
    from workcell.campaign.executor import CampaignConfig, CampaignControl
    from workcell.campaign.run import run_campaign

    _, robot, tracker, cell = sim_cell("ur5e", "none", 1, beam_break_prob=0.0)
    path = tmp_path_factory.mktemp("interrupted") / "i.mcap"
    control = CampaignControl()
    run_campaign(
        robot, tracker, cell, path, poses=6, seed=1,
        config=CampaignConfig(readings_per_pose=1, settle_s=0.1), control=control,
        on_sample=lambda s: s["index"] >= 1 and control.abort.set(),
        extra_campaign={"robot_url": "sim", "tracker_url": "sim", "effects": "none"},
    )  # fmt: skip
    rec = read_recording(path)
    return rec.session, rec.samples


JSON_VALUES = st.one_of(
    st.none(), st.booleans(), st.integers(-3, 40), st.just(10**9), st.floats(allow_nan=True),
    st.text("abcnoe", max_size=6), st.lists(st.integers(0, 3), max_size=2),
    st.dictionaries(st.text("ab", max_size=2), st.integers(), max_size=1),
)  # fmt: skip
CAMPAIGN_KEYS = (
    "plan", "poses", "seed", "readings_per_pose", "settle_s", "approach_rad", "warmup_s",
    "sim_seed", "effects", "robot_url", "tracker_url", "reference_every",
)  # fmt: skip


@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(where=st.sampled_from([*CAMPAIGN_KEYS, "robot.model", "elapsed_s", "campaign"]),
       value=JSON_VALUES)  # fmt: skip
def test_a_hand_edited_campaign_block_resumes_or_is_one_line(interrupted, tmp_path, capsys,
                                                              where, value):  # fmt: skip
    """`campaign --resume` of a recording whose campaign block (or a sample's elapsed time, or
    the arm's model) was edited by hand or written by another tool: it resumes, or says in one
    line what it cannot use (before, a null settle time, a list as the seed, a text as the pose
    count... ended in a traceback)."""
    import copy
    import uuid

    from workcell.cli import main
    from workcell.recording.schema import SAMPLE
    from workcell.recording.writer import RecordingWriter

    session, samples = copy.deepcopy(interrupted)
    if where == "campaign":
        session["campaign"] = value
    elif where == "robot.model":
        session["robot"]["model"] = value
    elif where == "elapsed_s":
        samples[-1]["elapsed_s"] = value
    else:
        session["campaign"][where] = value
    path = tmp_path / f"{uuid.uuid4().hex}.mcap"
    with RecordingWriter(path, session) as w:
        for i, s in enumerate(samples):  # past the writer's own checks, as another tool would
            w._write(SAMPLE, s, 10**9 * (i + 1))
    capsys.readouterr()
    rc = main(["campaign", "--resume", str(path), "--on-protective-stop", "resume"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc in (0, 2), (rc, err)
    assert not any("Traceback" in x for x in err), err
    if rc == 2:  # progress lines may come first (a resume that started); one error line
        errors = [x for x in err if x.startswith("workcell campaign: error:")]
        assert len(errors) == 1 and err[-1] == errors[0], err
