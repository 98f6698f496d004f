"""`campaign --reference-every N`: the plan's first pose measured again during the campaign, a
drift record read without any model (`recording.repeats`), kept on one side of the hold-out
split, and continued by a resume."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from workcell.campaign.plans import PoseTarget, with_reference
from workcell.recording.dataset import holdout_indices


def _plan(n: int, sent: list):
    """A plan of n targets that records what the executor sends back to it."""
    for i in range(n):
        s = yield PoseTarget(pose_id=i, q_rad=np.full(6, float(i)), approach_sign=np.ones(6))
        sent.append(None if s is None else s["pose_id"])


def _drive(plan, skip: set[int] = frozenset()):
    """Run a plan the way the executor does: measure each target (or skip it) and send back."""
    order = []
    try:
        t = next(plan)
        while True:
            order.append(t.pose_id)
            sample = (
                None
                if (t.pose_id in skip and order.count(t.pose_id) == 1)
                else {"pose_id": t.pose_id}
            )
            t = plan.send(sample)
    except StopIteration:
        return order


def test_the_reference_is_measured_after_every_n_poses_and_at_the_end():
    sent: list = []
    order = _drive(with_reference(_plan(7, sent), 3))
    assert order == [0, 1, 2, 0, 3, 4, 5, 0, 6, 0]
    assert sent == [0, 1, 2, 3, 4, 5, 6]  # the plan sees each of its own poses once
    # a campaign ending right after a reference measures it once, not twice
    assert _drive(with_reference(_plan(6, []), 3)) == [0, 1, 2, 0, 3, 4, 5, 0]
    # skipped poses do not count towards the interval
    assert _drive(with_reference(_plan(5, []), 2), skip={1}) == [0, 1, 2, 0, 3, 4, 0]
    # a given reference (a resume: the plan's first pose is already measured)
    ref = PoseTarget(pose_id=0, q_rad=np.zeros(6), approach_sign=np.ones(6))
    rest = (t for t in [PoseTarget(5, np.ones(6), np.ones(6))])
    assert _drive(with_reference(rest, 4, ref)) == [5, 0]
    with pytest.raises(ValueError, match="positive"):
        next(with_reference(_plan(3, []), 0))


@settings(max_examples=200, deadline=None)
@given(
    n=st.integers(1, 80),
    frac=st.sampled_from([0.0, 0.1, 0.25, 0.5]),
    reps=st.lists(st.integers(0, 79), max_size=30),
)
def test_a_pose_measured_again_stays_on_one_side_of_the_split(n, frac, reps):
    """Samples of one group (one pose measured again) are never split between training and
    held-out, and are trained on while singly measured poses can fill the held-out share;
    without repeats the split is the ungrouped one, sample for sample."""
    groups = list(range(n)) + [r % n for r in reps]
    m = len(groups)
    tr, te = holdout_indices(m, frac, np.array(groups))
    assert sorted(np.r_[tr, te].tolist()) == list(range(m))
    side = {}
    for i in te:
        side.setdefault(groups[i], "test")
        assert side[groups[i]] == "test"
    for i in tr:
        assert side.get(groups[i], "train") == "train"
    size = {k: groups.count(k) for k in set(groups)}
    singles = sum(1 for k in groups if size[k] == 1)
    n_test = int(round(frac * m))
    if singles >= n_test:
        assert len(te) == n_test and all(size[groups[i]] == 1 for i in te)
    else:
        assert len(te) >= n_test
    if not reps:
        tr0, te0 = holdout_indices(n, frac)
        assert np.array_equal(tr, tr0) and np.array_equal(te, te0)


def test_a_campaign_with_a_reference_records_its_drift(tmp_path, capsys):
    """Simulated UR5e with its realistic effects (thermal drift from a cold start), 12 poses,
    the reference every 5: pose 0 is measured 4 times (start, after 5, after 10, at the end);
    `info` reports how far it moved against the readings' own scatter, fits keep the repeats on
    one side of the split, and a fit runs on the recording."""
    from sim_devices.cell import sim_cell
    from workcell.campaign.executor import CampaignConfig
    from workcell.campaign.run import run_campaign
    from workcell.cli import main
    from workcell.recording.dataset import Dataset
    from workcell.recording.reader import read_recording

    _, robot, tracker, cell = sim_cell("ur5e", "realistic", 2, beam_break_prob=0.0)
    path = tmp_path / "ref.mcap"
    cfg = CampaignConfig(readings_per_pose=2, settle_s=0.2)
    _, res = run_campaign(
        robot, tracker, cell, path, poses=12, seed=2, config=cfg, reference_every=5
    )
    rec = read_recording(path)
    ids = [s["pose_id"] for s in rec.samples]
    assert len(ids) == 15 and [i for i, p in enumerate(ids) if p == 0] == [0, 5, 11, 14], ids
    assert rec.session["campaign"]["reference_every"] == 5
    q0 = [s["q_commanded_rad"] for s in rec.samples if s["pose_id"] == 0]
    assert all(np.allclose(q, q0[0], atol=1e-12) for q in q0)
    ds = Dataset.from_recording(path)
    tr, te = ds.holdout_split(0.25)
    assert set(np.flatnonzero(ds.pose_id == 0).tolist()) <= set(tr.tolist())  # trained on
    assert len(te) == round(0.25 * 15) and len(set(ds.pose_id[te].tolist())) == len(te)
    assert main(["info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    (r,) = info["repeats"]
    assert r["pose_id"] == 0 and r["measurements"] == 4
    assert r["displacement_m"][0] == 0.0 and r["max_m"] > 0.0 and r["noise_m"] > 0.0
    assert r["span_s"] == pytest.approx(r["elapsed_s"][-1] - r["elapsed_s"][0])
    # the live comparison (campaign output, TUI event log) gives the same displacements
    from workcell.recording.repeats import RepeatWatch, repeat_event_line

    watch = RepeatWatch()
    live = [x for x in map(watch.update, rec.samples) if x is not None]
    assert [x["pose_id"] for x in live] == [0, 0, 0]
    assert [x["displacement_m"] for x in live] == pytest.approx(r["displacement_m"][1:], abs=1e-12)
    assert "um from its first reading" in repeat_event_line(live[0])
    assert main(["info", str(path)]) == 0
    assert "repeated    pose 0 measured 4 times" in capsys.readouterr().out


def test_a_resumed_campaign_goes_on_measuring_the_reference(tmp_path, capsys):
    """Aborted after 6 samples, resumed from the command line: the continuation records the
    interval again, re-measures the plan's first pose (not the first pose it measures itself),
    and together the two files hold each plan pose once plus the references."""
    from sim_devices.cell import sim_cell
    from workcell.campaign.executor import CampaignConfig, CampaignControl
    from workcell.campaign.run import run_campaign
    from workcell.cli import main
    from workcell.recording.reader import read_recording

    _, robot, tracker, cell = sim_cell("ur5e", "realistic", 0, beam_break_prob=0.0)
    path = tmp_path / "c.mcap"
    control = CampaignControl()
    n = [0]

    def on_sample(s):
        n[0] += 1
        if n[0] >= 6:
            control.abort.set()

    cfg = CampaignConfig(readings_per_pose=2, settle_s=0.2)
    run_campaign(
        robot, tracker, cell, path, poses=14, seed=0, config=cfg, control=control,
        on_sample=on_sample, reference_every=4,
        extra_campaign={"robot_url": "sim", "tracker_url": "sim", "effects": "realistic"},
    )  # fmt: skip
    first = read_recording(path)
    assert [s["pose_id"] for s in first.samples][:6] == [0, 1, 2, 3, 0, 4]
    capsys.readouterr()
    assert main(["campaign", "--resume", str(path)]) == 0
    second = read_recording(tmp_path / "c.resumed1.mcap")
    assert second.session["campaign"]["reference_every"] == 4
    more = [s["pose_id"] for s in second.samples]
    out = capsys.readouterr().out
    assert f"recorded {len(more) - more.count(0)} more poses (and the reference " in out
    assert f"{more.count(0)} more times)" in out
    assert more.count(0) >= 2 and 0 not in more[:1]
    own = [p for p in more if p != 0]
    assert len(own) == len(set(own)) and not set(own) & {1, 2, 3, 4}
    assert set(own) | {0, 1, 2, 3, 4} == set(range(14))


@pytest.mark.parametrize("bad", ["5", 2.5, -1, True, [3]])
def test_a_hand_edited_reference_interval_is_refused_in_one_line(bad):
    from workcell.campaign.resume import recorded_reference_every as _reference_every
    from workcell.errors import UserError

    assert _reference_every({}, "x.mcap") == 0 and _reference_every({"reference_every": 4}, "") == 4
    with pytest.raises(UserError, match="not a positive whole number"):
        _reference_every({"reference_every": bad}, "x.mcap")


def test_the_command_line_refuses_a_non_positive_interval(capsys):
    from workcell.cli import main

    argv = ["campaign", "--robot", "sim", "--tracker", "sim", "--dry-run", "--poses", "20"]
    assert main([*argv, "--reference-every", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--reference-every must be a positive number" in err[0]
    assert main([*argv, "--reference-every", "8"]) == 0
    assert "reference: pose 0 measured again after every 8 poses and at the end (3 more" in (
        capsys.readouterr().out
    )


def test_a_cell_without_drift_is_not_called_drifting_and_a_drift_is(tmp_path):
    """The reference's displacement was compared with the recorded sigmas of the means alone,
    which leave out the tracker's per-pose systematic error: a simulated cell with no effect
    at all moved 3x "the readings' own scatter", and diagnose went on to speak of a drift.
    Now the tracker's stated accuracy is the floor, as in the fits: that cell is within it, and
    the same recording with a 60 um/repeat drift added to the reference's readings is not."""
    import dataclasses

    from sim_devices.cell import sim_cell
    from workcell.campaign.executor import CampaignConfig
    from workcell.campaign.run import run_campaign
    from workcell.recording.dataset import Dataset
    from workcell.recording.repeats import repeat_beyond_noise, repeat_drift

    _, robot, tracker, cell = sim_cell("ur5e", "none", 77, beam_break_prob=0.0)
    path = tmp_path / "ref.mcap"
    cfg = CampaignConfig(readings_per_pose=3, settle_s=0.2)
    run_campaign(robot, tracker, cell, path, poses=16, seed=77, config=cfg, reference_every=4)
    ds = Dataset.from_recording(path)
    (r,) = repeat_drift(ds)
    assert r["measurements"] == 5 and not repeat_beyond_noise(r), r
    idx = np.flatnonzero(ds.pose_id == 0)
    p = ds.p_tracker.copy()
    p[idx] += np.arange(len(idx))[:, None] * np.array([60e-6, 0.0, 0.0])
    (r2,) = repeat_drift(dataclasses.replace(ds, p_tracker=p))
    assert repeat_beyond_noise(r2), r2
