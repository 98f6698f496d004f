"""A configured safety envelope: written and checked by `workcell envelope`, taken by `campaign
--envelope` (and `validate`), recorded in the session, and reused by `--resume` so the continued
campaign plans the same poses and never leaves it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sim_devices.cell import sim_cell
from workcell.campaign.envelope import load_envelope
from workcell.campaign.executor import CampaignControl
from workcell.campaign.run import run_campaign
from workcell.cli import main
from workcell.recording.reader import read_recording

SEED, POSES = 3, 12


@pytest.fixture
def tight(tmp_path, capsys):
    """The default UR5e envelope with joint 1 narrowed to +-0.5 rad and joint 3 to 0.3..1.5 rad."""
    path = tmp_path / "env.json"
    assert main(["envelope", "--robot", "ur5e", "--out", str(path)]) == 0
    d = json.loads(path.read_text())
    d["joint_limits_rad"][0] = [-0.5, 0.5]
    d["joint_limits_rad"][2] = [0.3, 1.5]
    path.write_text(json.dumps(d))
    capsys.readouterr()
    return path


def q_commanded(path) -> dict[int, list[float]]:
    return {int(s["pose_id"]): s["q_commanded_rad"] for s in read_recording(path).samples}


def inside(q: list[float]) -> bool:
    return -0.5 <= q[0] <= 0.5 and 0.3 <= q[2] <= 1.5


def test_envelope_command_round_trip_and_refusals(tmp_path, tight, capsys):
    assert main(["envelope", "--robot", "ur5e", "--check", str(tight)]) == 0
    out = capsys.readouterr().out
    assert "ok" in out and "joint 1  [-0.5000, +0.5000] rad" in out
    d = json.loads(tight.read_text())
    cases = {
        "deg": ({**d, "joint_limits_rad": np.degrees(d["joint_limits_rad"]).tolist()}, "degrees"),
        "nan": ({**d, "box_min_m": [float("nan"), 0, 0]}, "finite"),
        "five": ({**d, "joint_limits_rad": d["joint_limits_rad"][:5]}, "5 joint limits"),
        "fast": ({**d, "max_speed_rad_s": 50.0}, "joint speed limit"),
        "jerky": ({**d, "max_accel_rad_s2": 1e9}, "joint acceleration limit"),  # found by fuzzing
    }
    cases["binary"] = (b"\x89MCAP0\r\n\xff", "not a text file")
    for name, (bad, match) in cases.items():
        p = tmp_path / f"{name}.json"
        if isinstance(bad, bytes):  # e.g. a recording given where the envelope goes
            p.write_bytes(bad)
        else:
            p.write_text(json.dumps(bad))
        assert main(["envelope", "--check", str(p)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and match in err[0], (name, err)
        # the same file stops a campaign before it connects or writes anything
        rec = tmp_path / f"{name}.mcap"
        argv = ["campaign", "--poses", "3", "--envelope", str(p), "--out", str(rec)]
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and match in err[0] and not rec.exists(), (name, err)


def test_campaign_stays_inside_and_resume_reuses_the_recorded_envelope(tmp_path, tight, capsys):
    # the whole campaign, uninterrupted, in the tight envelope
    full = tmp_path / "full.mcap"
    base = ["campaign", "--robot", "sim", "--tracker", "sim", "--effects", "none"]
    base += ["--seed", str(SEED), "--poses", str(POSES), "--readings", "2"]
    assert main([*base, "--envelope", str(tight), "--out", str(full)]) == 0
    planned = q_commanded(full)
    assert len(planned) == POSES and all(inside(q) for q in planned.values())
    env = read_recording(full).session["campaign"]["envelope"]
    assert env["joint_limits_rad"][0] == [-0.5, 0.5]
    capsys.readouterr()
    assert main(["info", str(full)]) == 0
    assert "envelope    joints [-29..29, -175..-5, 17..86," in capsys.readouterr().out

    # the same campaign stopped after 4 poses (a clean abort stands in for a dead process)
    world, robot, tracker, cell = sim_cell("ur5e", "none", SEED)
    control = CampaignControl()

    def stop_after_4(s: dict) -> None:
        if s["index"] >= 3:
            control.abort.set()

    cut = tmp_path / "cut.mcap"
    run_campaign(
        robot,
        tracker,
        cell,
        cut,
        plan="random",
        poses=POSES,
        seed=SEED,
        envelope=load_envelope(tight, cell.spec),
        control=control,
        on_sample=stop_after_4,
        extra_campaign={"robot_url": "sim", "tracker_url": "sim", "effects": "none"},
    )
    first = q_commanded(cut)
    assert 0 < len(first) < POSES

    # --envelope with --resume is refused: the plan was made inside the recorded one
    assert main(["campaign", "--resume", str(cut), "--envelope", str(tight)]) == 2
    assert "keeps the envelope" in capsys.readouterr().err
    # options a resume would ignore are refused, each in one line, before anything moves
    for extra, words in (
        (["--poses", "100", "--plan", "dopt"], "--plan, --poses: --resume continues the campaign"),
        (["--seed", "3"], "--seed: --resume continues"),
        (["--robot", "ur://10.0.0.2"], "was recorded with --robot sim"),
        (["--online", "ekf-ann"], "filter's state is not recorded"),
        (["--dry-run"], "`workcell info REC` shows what was measured"),
    ):
        assert main(["campaign", "--resume", str(cut), *extra]) == 2, extra
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], err
        assert not (tmp_path / "cut.resumed1.mcap").exists()
    # --resume re-plans inside the recorded envelope: the same poses as the uninterrupted run
    # (--robot naming the recorded cell is no contradiction)
    assert main(["campaign", "--resume", str(cut), "--robot", "sim"]) == 0
    rest = q_commanded(tmp_path / "cut.resumed1.mcap")
    assert set(first) | set(rest) == set(planned) and not set(first) & set(rest)
    for pid, q in {**first, **rest}.items():
        assert np.allclose(q, planned[pid], atol=1e-12), pid
        assert inside(q), (pid, q)


def test_tui_resume_reuses_the_recorded_envelope(tmp_path, tight, monkeypatch):
    """The TUI's resume (backend.start_campaign with resume_from) re-plans inside the recorded
    envelope even when the Plan screen is back on the default one."""
    from workcell.tui import backend

    monkeypatch.chdir(tmp_path)
    dev = backend.open_devices(backend.DeviceConfig(effects="none", seed=SEED))
    try:
        plan = backend.PlanConfig(
            poses=POSES, seed=SEED, readings_per_pose=2, envelope=str(tight), out="a.mcap"
        )
        control = CampaignControl()

        def stop_after_4(s: dict) -> None:
            if s["index"] >= 3:
                control.abort.set()

        backend.start_campaign(
            dev, plan, control=control, on_sample=stop_after_4, on_event=lambda e: None
        )
        first = q_commanded(tmp_path / "a.mcap")
        assert 0 < len(first) < POSES
        plan_default = backend.PlanConfig(poses=POSES, seed=SEED, envelope="default", out="a.mcap")
        path, _ = backend.start_campaign(
            dev,
            plan_default,
            control=CampaignControl(),
            on_sample=lambda s: None,
            on_event=lambda e: None,
            resume_from="a.mcap",
        )
    finally:
        dev.close()
    rest = q_commanded(path)
    assert len(first) + len(rest) == POSES
    assert all(inside(q) for q in rest.values()), rest


def test_validate_moves_inside_the_given_envelope_and_at_its_speed_cap(tmp_path, capsys):
    """`validate --envelope FILE`: targets outside it are skipped and every move is commanded at
    or below its speed and acceleration caps."""
    from sim_devices.inprocess import SimRobot

    rec = tmp_path / "c.mcap"
    argv = ["campaign", "--effects", "none", "--seed", str(SEED), "--poses", "16"]
    assert main([*argv, "--readings", "2", "--out", str(rec)]) == 0
    model = tmp_path / "m.json"
    assert main(["fit", str(rec), "--holdout", "0", "--out", str(model)]) == 0
    slow = tmp_path / "slow.json"
    assert main(["envelope", "--out", str(slow)]) == 0
    d = json.loads(slow.read_text())
    d["max_speed_rad_s"], d["max_accel_rad_s2"] = 0.2, 0.4
    d["joint_limits_rad"][0] = [-1.0, 1.5]  # narrower than the default +-170 deg
    slow.write_text(json.dumps(d))
    moves: list[tuple[np.ndarray, float, float]] = []
    orig = SimRobot.move_joints

    def spy(self, q, speed, accel):
        moves.append((np.asarray(q, float), speed, accel))
        return orig(self, q, speed, accel)

    SimRobot.move_joints = spy
    try:
        rc = main(["validate", str(model), "--envelope", str(slow), "--targets", "6", "--json"])
    finally:
        SimRobot.move_joints = orig
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    out = cap.out
    res = json.loads(out.strip().splitlines()[-1])
    assert res["targets"] + len(res["skipped"]) == 6 and res["targets"] >= 1
    assert moves and all(s <= 0.2 and a <= 0.4 for _, s, a in moves)
    assert all(-1.0 <= q[0] <= 1.5 for q, _, _ in moves)
    # the file's joint-1 range (not the default +-170 deg) is what refused these targets
    assert res["skipped"] and all("joint 1 target" in w for w in res["skipped"]), res["skipped"]


def test_kinematic_margin_keeps_the_true_arm_inside_the_box():
    """The envelope computes with the nominal kinematics; the real arm is off by mm. Scored on
    the simulated true arm (realistic effects, a warm arm): its SMR error from the nominal is
    below the default margin on random poses, and a box face placed where the nominal check
    with no margin would pass a pose whose true SMR is outside is refused with the margin."""
    import dataclasses

    from sim_devices.truth import NOMINAL_SMR_M, make_truth
    from workcell.campaign.envelope import DEFAULT_KINEMATIC_MARGIN_M, default_envelope
    from workcell.campaign.plans import random_configurations
    from workcell.kinematics.chain import base_T_frames, pack
    from workcell.kinematics.robots import UR5E

    env0 = dataclasses.replace(default_envelope(UR5E), kinematic_margin_m=0.0)
    q = random_configurations(UR5E, env0, 300, np.random.default_rng(0), NOMINAL_SMR_M)
    T = np.asarray(base_T_frames(pack(UR5E.dh), q))
    nominal = np.einsum("nab,b->na", T[:, -1, :3, :3], NOMINAL_SMR_M) + T[:, -1, :3, 3]
    err = np.zeros_like(nominal)
    for seed in range(3):
        truth = make_truth("ur5e", "realistic", seed=seed)
        true = np.array([truth.smr_in_base(qi, np.ones(6), 3600.0) for qi in q])
        err = np.where(np.abs(true - nominal) > np.abs(err), true - nominal, err)
    assert np.max(np.abs(err)) < DEFAULT_KINEMATIC_MARGIN_M
    i = int(np.argmin(err[:, 2]))  # the pose whose true SMR sits lowest below its nominal
    assert err[i, 2] < -5e-4  # the sim's arm is off by more than tracker noise
    face = nominal[i, 2] + 0.5 * err[i, 2]  # nominal above the face, true below it
    box = dataclasses.replace(env0, box_min_m=np.r_[env0.box_min_m[:2], face])
    assert box.violations(UR5E, q[i][None], NOMINAL_SMR_M)[0] is None  # no margin: let through
    margin = dataclasses.replace(box, kinematic_margin_m=DEFAULT_KINEMATIC_MARGIN_M)
    why = margin.violations(UR5E, q[i][None], NOMINAL_SMR_M)[0]
    assert why is not None and "kinematic margin" in why


def test_margin_absent_from_an_older_file_or_session(tmp_path):
    """An envelope written before the margin existed: a file gets the default margin (safer),
    a recorded session the 0 it ran with (so that --resume plans the same poses)."""
    from workcell.campaign.envelope import (
        DEFAULT_KINEMATIC_MARGIN_M,
        default_envelope,
        envelope_of_session,
    )
    from workcell.errors import UserError
    from workcell.kinematics.robots import UR5E

    d = default_envelope(UR5E).to_dict()
    assert d.pop("kinematic_margin_m") == DEFAULT_KINEMATIC_MARGIN_M
    path = tmp_path / "old.json"
    path.write_text(json.dumps(d))
    assert load_envelope(path, UR5E).kinematic_margin_m == DEFAULT_KINEMATIC_MARGIN_M
    assert envelope_of_session({"envelope": d}, UR5E, "rec").kinematic_margin_m == 0.0
    for bad in (-0.001, 0.5, float("nan")):
        path.write_text(json.dumps({**d, "kinematic_margin_m": bad}))
        with pytest.raises(UserError, match="kinematic_margin_m"):
            load_envelope(path, UR5E)


def test_margin_from_a_fitted_model_covers_the_true_arm(tmp_path, capsys):
    """`workcell envelope --model`: the margin measured from a model fitted on a simulated
    campaign covers how far the simulated true arm is from the nominal kinematics over the
    configurations the envelope allows (scored on the sim's truth), without being wildly larger;
    `--check` fails (exit 1) for a file whose margin is below the suggestion."""
    import dataclasses

    from sim_devices.truth import make_truth
    from workcell.campaign.envelope import default_envelope
    from workcell.campaign.executor import CampaignConfig
    from workcell.estimation.models import load_model
    from workcell.export.margin import model_deviation
    from workcell.kinematics.chain import base_T_frames, pack
    from workcell.kinematics.robots import UR5E

    seed = 5
    _, robot, tracker, cell = sim_cell("ur5e", "realistic", seed=seed)
    rec = tmp_path / "r.mcap"
    cfg = CampaignConfig(readings_per_pose=2, settle_s=0.2)
    run_campaign(robot, tracker, cell, rec, plan="random", poses=60, seed=seed, config=cfg)
    model_path = tmp_path / "m.json"
    assert main(["fit", str(rec), "--out", str(model_path), "--json"]) == 0
    env = default_envelope(UR5E)
    dev = model_deviation(load_model(model_path), env, UR5E, samples=1500, seed=1)
    # score: the true arm over the same kind of configurations, in its own (true) base frame
    lim = env.joint_limits_rad
    q = np.random.default_rng(1).uniform(lim[:, 0], lim[:, 1], (1500, 6))
    q = q[[v is None for v in env.violations(UR5E, q, cell.tool_m)]]
    T = np.asarray(base_T_frames(pack(UR5E.dh), q))
    nominal = np.einsum("nab,b->na", T[:, -1, :3, :3], cell.tool_m) + T[:, -1, :3, 3]
    truth = make_truth("ur5e", "realistic", seed=seed)
    true = np.array([truth.smr_in_base(qi, np.ones(6), 3600.0) for qi in q])
    true_max = float(np.max(np.linalg.norm(true - nominal, axis=1)))
    assert true_max > 1e-3  # the sim's arm is millimetres off: the test can fail
    assert dev["suggested_margin_m"] >= true_max, (dev, true_max)
    assert dev["suggested_margin_m"] <= 5 * true_max, (dev, true_max)
    capsys.readouterr()
    small = tmp_path / "small.json"
    small.write_text(json.dumps(dataclasses.replace(env, kinematic_margin_m=0.0005).to_dict()))
    assert main(["envelope", "--check", str(small), "--model", str(model_path)]) == 1
    out, err = capsys.readouterr()
    assert "is below the suggested" in out
    # the refusal is also the error line, and the header does not say "ok" (it did, with
    # nothing on stderr and exit 1)
    assert out.splitlines()[0].endswith(f"its margin does not cover {model_path} (below)")
    err = err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"workcell envelope: error: {small}: margin 0.5 mm")
    written = tmp_path / "from_model.json"
    assert main(["envelope", "--out", str(written), "--model", str(model_path)]) == 0
    assert load_envelope(written, UR5E).kinematic_margin_m >= dev["suggested_margin_m"] - 1e-12
    assert main(["envelope", "--check", str(written), "--model", str(model_path)]) == 0
    assert "covers it" in capsys.readouterr().out


def test_validate_moves_inside_the_campaigns_recorded_envelope_by_default(tmp_path, capsys):
    """A campaign run in a narrower envelope, then `validate` without `--envelope`: the moves are
    checked against the envelope recorded with the model's campaign (until 2026-11-25 against
    the arm's default one, which let validation's targets and transits go where the campaign's
    envelope kept the arm out), and the result says which envelope it was."""
    from sim_devices.inprocess import SimRobot

    tight = tmp_path / "tight.json"
    assert main(["envelope", "--out", str(tight)]) == 0
    d = json.loads(tight.read_text())
    d["joint_limits_rad"][0] = [-1.0, 1.5]
    d["max_speed_rad_s"] = 0.3
    tight.write_text(json.dumps(d))
    rec, model = tmp_path / "c.mcap", tmp_path / "m.json"
    argv = ["campaign", "--effects", "none", "--seed", str(SEED), "--poses", "16"]
    assert main([*argv, "--readings", "2", "--envelope", str(tight), "--out", str(rec)]) == 0
    assert main(["fit", str(rec), "--holdout", "0", "--out", str(model)]) == 0
    moves: list[tuple[np.ndarray, float]] = []
    orig = SimRobot.move_joints

    def spy(self, q, speed, accel):
        moves.append((np.asarray(q, float), speed))
        return orig(self, q, speed, accel)

    SimRobot.move_joints = spy
    try:
        rc = main(["validate", str(model), "--targets", "6", "--json"])
    finally:
        SimRobot.move_joints = orig
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    res = json.loads(cap.out.strip().splitlines()[-1])
    assert res["envelope"].startswith("the envelope recorded with the model's campaign")
    assert moves and all(-1.0 <= q[0] <= 1.5 and s <= 0.3 for q, s in moves)
    assert res["skipped"] and all("joint 1 target" in w for w in res["skipped"]), res["skipped"]


def test_envelope_check_refuses_an_envelope_no_pose_fits(tmp_path, tight, capsys):
    """`envelope --check` said "ok" for a 2 cm box no pose reaches; a campaign refused it later."""
    d = json.loads(tight.read_text())
    assert main(["envelope", "--check", str(tight)]) == 0
    assert "reach " in capsys.readouterr().out
    far = tmp_path / "far.json"
    far.write_text(json.dumps({**d, "box_min_m": [0.5, 0.5, 0.5], "box_max_m": [0.52, 0.52, 0.52]}))
    assert main(["envelope", "--check", str(far)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no pose fits" in err[0]


def test_the_floor_holds_for_the_smr_when_the_box_reaches_below_it():
    """The floor was checked for the link frames only and the box for the SMR: an envelope whose
    box reaches below the floor (accepted by `envelope --check`) let a long tool go under the
    table, flange above it (audit, 2026-11-26 night: SMR at z = -0.18 m over a floor at 0).
    Now the floor holds for the SMR too, and says which point crossed it."""
    import dataclasses

    from workcell.campaign.envelope import default_envelope
    from workcell.campaign.plans import random_configurations
    from workcell.kinematics.chain import base_T_frames, pack
    from workcell.kinematics.robots import UR5E

    env = dataclasses.replace(
        default_envelope(UR5E),
        box_min_m=np.array([-1.1, -1.1, -0.6]),
        floor_z_m=0.0,
        kinematic_margin_m=0.0,
    )
    tool = np.array([0.0, 0.0, 0.2])
    q = random_configurations(UR5E, env, 300, np.random.default_rng(0), tool)
    T = np.asarray(base_T_frames(pack(UR5E.dh), q))
    smr_z = (np.einsum("nab,b->na", T[:, -1, :3, :3], tool) + T[:, -1, :3, 3])[:, 2]
    assert len(q) == 300 and smr_z.min() >= 0.0, smr_z.min()
    # a posture with the flange just above the floor and the SMR pointing down below it
    rng = np.random.default_rng(1)
    lo, hi = env.joint_limits_rad[:, 0], env.joint_limits_rad[:, 1]
    cand = rng.uniform(lo, hi, (20000, 6))
    T = np.asarray(base_T_frames(pack(UR5E.dh), cand))
    links_z = T[:, 2:, 2, 3].min(axis=1)
    smr_z = (np.einsum("nab,b->na", T[:, -1, :3, :3], tool) + T[:, -1, :3, 3])[:, 2]
    under = np.flatnonzero((links_z > 0.01) & (smr_z < -0.05))
    assert len(under), "no posture with the SMR alone below the floor among the draws"
    msg = env.violations(UR5E, cand[under[:1]], tool)[0]
    assert msg is not None and msg.startswith("the SMR would go down to z = "), msg
    assert env.violations(UR5E, cand[under[:1]], np.zeros(3))[0] is None  # flange: above
