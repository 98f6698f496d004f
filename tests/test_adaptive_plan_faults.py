"""Adaptive plans (bo, dopt, vopt) in a tight envelope and on resume (audit of 2026-11-26).

- A live adaptive plan checked only its ~50 best candidates for a path from the last measured
  pose and then proposed the unreachable best one anyway: in a tight but valid envelope a dopt
  campaign recorded 2 poses, refused 18 one after another and exited 0. It now takes the best
  candidate the arm may move to from where it really is (all of them tried), and when there is
  none the campaign stops: one line on which limit the paths cross and what to do, exit 3.
- The executor stops after `MAX_REFUSED_IN_A_ROW` refused poses (a static plan started from a
  posture it was not planned from), and the dry run checks the first move from the simulated
  arm's start posture (it used to say "0 problems").
- A resumed adaptive campaign that had skipped poses said "7 to go" and recorded 0 more: it now
  chooses new poses in place of the skipped ones.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sim_devices.cell import sim_cell
from workcell.campaign.envelope import Envelope, default_envelope
from workcell.campaign.executor import CampaignConfig
from workcell.campaign.run import campaign_stop, run_campaign
from workcell.drivers.protocols import TrackerReading
from workcell.errors import UserError
from workcell.recording.reader import read_recording

FAST = CampaignConfig(readings_per_pose=2, settle_s=0.1, beam_retry_wait_s=0.05)

# the audit's envelope: the UR5e's default joint ranges, a 45 x 65 x 45 cm box beside the base
# (`workcell envelope --check`: 4.6 % of random configurations fit). The simulated arm starts at
# [0, -1.57, 1.57, -1.57, -1.57, 0], inside it, but every path from there to the poses a random
# plan draws leaves the box through its top.
TIGHT_BOX = ([-0.7, -0.45, 0.2], [-0.25, 0.2, 0.65])
HOME = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
# inside the tight envelope, and no pose among a seed-0 plan's 64 candidates may be reached from
# it (found by a search over random configurations in the envelope)
STUCK_AT = np.array([2.671838426997156, -1.547641303538305, -2.494732444639152,
                     0.30026848156973607, 2.8688413400624757, -2.696746860873139])  # fmt: skip


def tight(spec) -> Envelope:
    return dataclasses.replace(
        default_envelope(spec), box_min_m=np.array(TIGHT_BOX[0]), box_max_m=np.array(TIGHT_BOX[1])
    )


def quiet_cell(seed=0):
    return sim_cell("ur5e", "none", seed, beam_break_prob=0.0, outlier_prob=0.0)


def cfg_for(cell) -> CampaignConfig:
    return dataclasses.replace(FAST, payload_kg=cell.payload_kg)


def jog(world, robot, q) -> None:
    """The operator moves the simulated arm to q (before the campaign connects)."""
    robot.connect()
    world.clock.advance(world.command_move(np.asarray(q, float), 1.0, 2.0) + 0.1)


def kinds(rec, kind):
    return [e for e in rec.events if e.get("kind") == kind]


def test_dopt_in_a_tight_envelope_takes_the_best_reachable_pose(tmp_path):
    """The audit's repro (dopt in the tight envelope): it used to record 2 poses, the paths to
    the rest all refused at the same spot of the box's top. Now every pose is measured and none
    is refused; every commanded pose is inside the envelope."""
    world, robot, tracker, cell = quiet_cell(0)
    env = tight(cell.spec)
    choices: list[dict] = []
    path, res = run_campaign(
        robot, tracker, cell, tmp_path / "d.mcap", plan="dopt", poses=10, seed=0,
        envelope=env, config=cfg_for(cell),
        plan_kwargs={"n_candidates": 300, "on_choice": choices.append},
    )  # fmt: skip
    rec = read_recording(path)
    assert (res.measured, res.skipped, res.stopped_by) == (10, 0, ""), [
        e["message"] for e in rec.events
    ]
    assert not kinds(rec, "refused")
    assert any(c.get("passed_over_unreachable") for c in choices)  # the check had work to do
    q = np.array([s["q_commanded_rad"] for s in rec.samples])
    assert all(v is None for v in env.violations(cell.spec, q, cell.tool_m))


def test_adaptive_plan_with_no_reachable_pose_stops_in_one_line(tmp_path):
    """An arm standing where no pose of the plan can be reached (every path leaves the envelope,
    also via upright): the campaign moves nothing and stops at once with a line on which limit
    the paths cross and what to do, exit 3, instead of refusing every pose and exiting 0."""
    world, robot, tracker, cell = quiet_cell(0)
    env = tight(cell.spec)
    assert env.violations(cell.spec, STUCK_AT[None], cell.tool_m)[0] is None
    jog(world, robot, STUCK_AT)
    path, res = run_campaign(
        robot, tracker, cell, tmp_path / "s.mcap", plan="dopt", poses=8, seed=0,
        envelope=env, config=cfg_for(cell), plan_kwargs={"n_candidates": 64},
    )  # fmt: skip
    assert res.stopped_by == "refused" and res.measured == 0 and res.skipped == 0
    np.testing.assert_allclose(world.joint_state()[0], STUCK_AT, atol=1e-9)  # nothing moved
    msg = res.stop_message
    assert msg.startswith("the dopt plan has no pose left that the arm may move to from where")
    assert "the paths to all 64 of its remaining poses leave the envelope" in msg
    assert "the workspace box's" in msg or "the floor" in msg
    assert "jog the arm to a posture well inside the envelope (e.g. q = [" in msg
    rec = read_recording(path)
    assert rec.closed_cleanly and not kinds(rec, "refused")
    assert [e["level"] for e in kinds(rec, "stopped")] == ["error"]
    with pytest.raises(UserError) as e:
        campaign_stop(res, path)
    assert e.value.exit_code == 3
    assert f"`workcell campaign --resume {path}` continues it" in str(e.value)


def test_a_plan_refused_again_and_again_stops(tmp_path):
    """A random plan started from the simulated arm's start posture in the tight envelope: the
    first poses' paths all leave the box through its top. It used to skip 16 of 20 and exit 0;
    it now stops after `MAX_REFUSED_IN_A_ROW` refusals, saying which face and where to jog."""
    world, robot, tracker, cell = quiet_cell(0)
    path, res = run_campaign(
        robot, tracker, cell, tmp_path / "r.mcap", plan="random", poses=20, seed=0,
        envelope=tight(cell.spec), config=cfg_for(cell),
    )  # fmt: skip
    assert res.stopped_by == "refused", (res.measured, res.skipped)
    from workcell.campaign.executor import MAX_REFUSED_IN_A_ROW

    assert (res.measured, res.skipped) == (0, MAX_REFUSED_IN_A_ROW)
    msg = res.stop_message
    assert msg.startswith(f"{MAX_REFUSED_IN_A_ROW} poses in a row refused before any motion")
    assert (
        "first crossing the workspace box's top (z = 0.65 m, less the 10 mm kinematic margin)"
    ) in msg
    assert "pose 0's approach posture" in msg and "widen the envelope" in msg
    np.testing.assert_allclose(world.joint_state()[0], HOME, atol=1e-9)
    with pytest.raises(UserError) as e:
        campaign_stop(res, path)
    assert e.value.exit_code == 3


def test_dry_run_checks_the_first_move_from_the_simulated_arms_start_posture(
    tmp_path, capsys, monkeypatch
):
    """The dry run of that random plan said "0 problems" (it checked the first move from
    nowhere); it now checks it from the simulated arm's start posture and says so, and for a
    real controller says that the campaign checks it when it starts."""
    from workcell.campaign import identification
    from workcell.cli import main

    # what a fit of the plan should reach (re-planned at many pose counts: slow here) is not
    # what this test is about
    monkeypatch.setattr(identification, "identification_lines", lambda *a, **k: [])
    monkeypatch.setattr(identification, "plan_pose_count_line", lambda *a, **k: None)

    env_file = tmp_path / "env.json"
    env_file.write_text(__import__("json").dumps(tight(quiet_cell()[3].spec).to_dict()))
    argv = ["campaign", "--robot", "sim", "--tracker", "sim", "--effects", "none", "--dry-run",
            "--poses", "10", "--envelope", str(env_file)]  # fmt: skip
    assert main([*argv, "--plan", "random"]) == 1
    out = capsys.readouterr().out
    assert "pose 0 path from the arm's start posture: the joint path leaves the envelope" in out
    assert "the first move is checked from the simulated arm's start posture q = [" in out
    from workcell.commands.campaign import start_line

    line = start_line(None, "ur://10.0.0.2")
    assert "does not connect to ur://10.0.0.2" in line and "when it starts" in line


class BeamBrokenAfter:
    """The simulated tracker, with the beam broken for the whole pose after the samples counted
    in `at` (1-based) were recorded: that pose is skipped, the next measures again."""

    def __init__(self, inner, at):
        self.inner, self.at, self.n, self.broken = inner, set(at), 0, False

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def sample(self, _s):
        self.n += 1
        self.broken = self.n in self.at

    def event(self, e):
        if e["kind"] == "skip":
            self.broken = False

    def measure(self):
        if self.broken:
            self.inner.world.clock.advance(0.1)
            return TrackerReading(np.full(3, np.nan), np.full(3, np.nan), "beam_broken")
        return self.inner.measure()


@pytest.mark.parametrize("kind", ["bo", "dopt"])
def test_resumed_adaptive_campaign_replaces_the_skipped_poses(tmp_path, kind):
    """An 8-pose campaign whose poses 2 and 5 were skipped (beam broken) recorded 6. Its resume
    said "2 to go" and recorded none (the replay ran through pose 7); it now chooses 2 new poses
    (pose ids 8 and 9), so the chain holds 8, and says so."""
    from workcell.campaign.resume import continuation, resume_plan

    world, robot, inner, cell = quiet_cell(2)
    tracker = BeamBrokenAfter(inner, at={2, 4})
    old = tmp_path / "b.mcap"
    kw = dict(plan=kind, poses=8, seed=2, config=cfg_for(cell), plan_kwargs={"n_candidates": 64})
    _, res = run_campaign(
        robot, tracker, cell, old, **kw, on_sample=tracker.sample, on_event=tracker.event
    )
    assert (res.measured, sorted(res.skipped_ids)) == (6, [2, 5])
    info = resume_plan(str(old))
    world2, robot2, tracker2, cell2 = quiet_cell(2)
    cont = continuation(info, old)
    _, res2 = run_campaign(
        robot2, tracker2, cell2, tmp_path / "b.resumed1.mcap",
        **{**kw, "plan_kwargs": {**kw["plan_kwargs"], **cont.pop("plan_kwargs")}}, **cont,
    )  # fmt: skip
    assert (res2.measured, res2.skipped, res2.stopped_by) == (2, 0, "")
    new = read_recording(tmp_path / "b.resumed1.mcap").samples
    assert [s["pose_id"] for s in new] == [8, 9]
    chain = resume_plan(str(tmp_path / "b.resumed1.mcap"))
    assert len(chain["done"]) == 8  # the campaign's pose count, nothing more to go
    q = [tuple(np.round(s["q_commanded_rad"], 9)) for s in chain["samples"]]
    assert len(set(q)) == 8  # new poses, none measured twice
    from workcell.campaign.resume import to_go_line  # what the resume says it will do

    assert to_go_line(info) == (
        f"2 to go ({kind} chooses 2 new poses in place of skipped ones, pose ids 8 on)"
    )


def test_the_first_pose_is_reachable_from_the_start_posture_and_a_resume_keeps_it(tmp_path):
    """The plan knew nothing of where the arm starts: from the simulated arm's start posture the
    first pose dopt chose in the tight envelope (seed 0) was refused. It now chooses among the
    poses reachable from there; its resume (the arm elsewhere by then) takes the recorded poses
    as recorded rather than refusing a history it cannot re-derive, and finishes the campaign."""
    from workcell.campaign.adaptive import make_adaptive_plan
    from workcell.campaign.executor import CampaignControl
    from workcell.campaign.resume import continuation, resume_plan

    world, robot, tracker, cell = quiet_cell(0)
    env = tight(cell.spec)
    kw = dict(plan="dopt", poses=8, seed=0, envelope=env, config=cfg_for(cell),
              plan_kwargs={"n_candidates": 64})  # fmt: skip
    blind = next(make_adaptive_plan("dopt", cell.spec, env, 8, seed=0, tool_m=cell.tool_m,
                                    n_candidates=64))  # fmt: skip
    control = CampaignControl()

    def die_after_3(s):
        if s["index"] == 2:
            control.abort.set()  # the old process dies after its third pose

    old = tmp_path / "f.mcap"
    _, res = run_campaign(robot, tracker, cell, old, **kw, control=control, on_sample=die_after_3)
    rec = read_recording(old)
    assert res.measured == 3 and not kinds(rec, "refused"), [e["message"] for e in rec.events]
    assert not np.allclose(rec.samples[0]["q_commanded_rad"], blind.q_rad)
    world2, robot2, tracker2, cell2 = quiet_cell(0)
    jog(world2, robot2, rec.samples[-1]["q_commanded_rad"])  # the arm where it was left
    cont = continuation(resume_plan(str(old)), old)
    _, res2 = run_campaign(
        robot2, tracker2, cell2, tmp_path / "f.resumed1.mcap",
        **{**kw, "plan_kwargs": {**kw["plan_kwargs"], **cont.pop("plan_kwargs")}}, **cont,
    )  # fmt: skip
    assert (res2.measured, res2.skipped, res2.stopped_by) == (5, 0, "")
    new = read_recording(tmp_path / "f.resumed1.mcap").samples
    assert [s["pose_id"] for s in new] == [3, 4, 5, 6, 7]
