"""In-process simulated campaign: plans inside the envelope, refusal before motion, recording."""

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sim_devices.cell import sim_cell
from workcell.campaign.envelope import EnvelopeViolation, default_envelope, route
from workcell.campaign.executor import ArmOutsideEnvelope, CampaignConfig, Executor
from workcell.campaign.plans import PoseTarget, make_plan, random_configurations
from workcell.campaign.run import run_campaign
from workcell.kinematics.robots import UR5E
from workcell.recording.reader import read_recording


class RecordingRobot:
    """A robot that records every motion command (to prove nothing moved)."""

    def __init__(self):
        self.moves = []

    def connect(self):
        pass

    def close(self):
        pass

    def move_joints(self, q, speed, accel):
        self.moves.append(np.array(q))

    def state(self):
        from workcell.drivers.protocols import RobotState

        return RobotState(t_s=0.0, q_rad=np.zeros(6), qd_rad_s=np.zeros(6))

    def stop(self):
        pass

    def sleep(self, s):
        pass


class NullSink:
    def __init__(self):
        self.events = []

    def event(self, t, level, kind, msg):
        self.events.append((kind, msg))

    def joint_state(self, *a):
        pass

    def tracker_measurement(self, *a):
        pass

    def sample(self, *a):
        raise AssertionError("nothing may be measured")


@pytest.mark.parametrize("kind", ["random", "grid"])
def test_plans_stay_inside_the_envelope_with_their_approach(kind):
    env = default_envelope(UR5E)
    tool = np.array([0, 0, 0.06])
    gen, q = make_plan(kind, UR5E, env, 40, seed=3, tool_m=tool)
    targets = list(gen)
    assert len(targets) == 40
    ex = Executor(None, None, UR5E, env, None, tool_m=tool)
    assert ex.check_plan(targets) == []
    signs = np.array([t.approach_sign for t in targets])
    # approach directions are varied on purpose: both signs on every joint
    assert np.all((signs > 0).any(0)) and np.all((signs < 0).any(0))


def test_target_outside_envelope_refused_before_any_motion():
    env = default_envelope(UR5E)
    robot, sink = RecordingRobot(), NullSink()
    ex = Executor(robot, None, UR5E, env, sink, tool_m=np.array([0, 0, 0.06]))
    bad = [
        np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.0]),  # joint 2 outside [-175, -5] deg
        np.array([0.0, -1.0, 2.9, 0.0, 0.0, 0.0]),  # joint 3 beyond 160 deg
        np.array([0.0, -0.1, 1.5, 0.0, 0.0, 0.0]),  # forearm down: SMR below the box
        np.array([np.nan, -1.0, 1.0, 0.0, 0.0, 0.0]),
    ]
    for k, q in enumerate(bad):
        assert ex.run_pose(PoseTarget(k, q, np.ones(6))) is None
        with pytest.raises(EnvelopeViolation, match="refused before any motion"):
            env.check(UR5E, q, np.array([0, 0, 0.06]))
    assert robot.moves == []
    assert [k for k, _ in sink.events] == ["refused"] * 4
    assert env.cap(10.0, 10.0) == (env.max_speed_rad_s, env.max_accel_rad_s2)


class ClockRobot(RecordingRobot):
    """Robot time advances one second per move (the warm-up runs on robot time); the arm is
    where it was last sent (it starts at `q0`)."""

    def __init__(self, q0=(0.0, -1.57, 1.57, -1.57, -1.57, 0.0)):
        super().__init__()
        self.q0 = np.array(q0, float)

    def state(self):
        from workcell.drivers.protocols import RobotState

        q = self.moves[-1] if self.moves else self.q0
        return RobotState(t_s=float(len(self.moves)), q_rad=q, qd_rad_s=np.zeros(6))


def test_warm_up_never_leaves_the_envelope():
    """The warm-up swings the arm around the first target: a centre outside the envelope means
    no warm-up at all (one event), and every swing it does make is inside."""
    env = default_envelope(UR5E)
    tool = np.array([0, 0, 0.06])
    cfg = CampaignConfig(warmup_s=8.0)
    robot, sink = ClockRobot(), NullSink()
    ex = Executor(robot, None, UR5E, env, sink, tool_m=tool, config=cfg)
    ex.warm_up(np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.0]))  # joint 2 outside [-175, -5] deg
    assert robot.moves == []
    assert [k for k, _ in sink.events] == ["refused"] and "warm-up skipped" in sink.events[0][1]
    robot, sink = ClockRobot(), NullSink()
    ex = Executor(robot, None, UR5E, env, sink, tool_m=tool, config=cfg)
    ex.warm_up(np.array([0.0, -1.2, 1.2, -1.5, -1.5, 0.0]))
    assert len(robot.moves) >= 8
    assert all(v is None for v in env.violations(UR5E, np.array(robot.moves), tool))


class StillRobot(ClockRobot):
    """Robot time advances only with the distance moved (1 rad/s): a move to where the arm
    already is takes no time, as on the simulated controller."""

    def state(self):
        from workcell.drivers.protocols import RobotState

        q = self.moves[-1] if self.moves else self.q0
        path = np.vstack([self.q0, *self.moves]) if self.moves else self.q0[None]
        t = float(np.abs(np.diff(path, axis=0)).max(axis=1).sum()) if len(path) > 1 else 0.0
        return RobotState(t_s=t, q_rad=q, qd_rad_s=np.zeros(6))


def test_warm_up_scales_its_swing_to_the_envelope_and_never_spins():
    """A first target whose full swing leaves the envelope on both sides (joint 2 near its upper
    limit one way, joint 4 near its lower limit the other): the warm-up used to "move" to the
    centre it was already at, robot time never advanced, and `campaign --warmup 60` spun forever
    (seed 0). It now swings a quarter as far, inside the envelope, and ends."""
    import threading

    env = default_envelope(UR5E)
    tool = np.array([0, 0, 0.06])
    centre = np.array([0.0, -0.2, 0.6, -4.3, -1.5, 0.0])
    robot, sink = StillRobot(q0=centre), NullSink()
    ex = Executor(robot, None, UR5E, env, sink, tool_m=tool, config=CampaignConfig(warmup_s=8.0))
    run = threading.Thread(target=ex.warm_up, args=(centre,), daemon=True)
    run.start()
    run.join(timeout=30.0)
    assert not run.is_alive(), "the warm-up did not end"
    assert robot.state().t_s >= 8.0
    assert all(v is None for v in env.violations(UR5E, np.array(robot.moves), tool))
    swing = np.abs(np.array(robot.moves) - centre).max()
    assert 0.05 < swing < 0.4  # scaled down from the full 0.5 rad swing
    # no waypoint fits at all: skipped with one line, no move
    robot, sink = StillRobot(q0=centre), NullSink()
    ex = Executor(robot, None, UR5E, env, sink, tool_m=tool, config=CampaignConfig(warmup_s=8.0))
    ex._warmup_cycle = lambda q: None  # noqa: SLF001 (as if every scale left the envelope)
    ex.warm_up(centre)
    assert robot.moves == [] and "warm-up skipped" in sink.events[-1][1]


def test_sim_campaign_records_every_pose_or_an_event(tmp_path):
    world, robot, tracker, cell = sim_cell("ur5e", "realistic", seed=4, beam_break_prob=0.15)
    p = tmp_path / "c.mcap"
    _, res = run_campaign(
        robot,
        tracker,
        cell,
        p,
        poses=25,
        seed=4,
        config=CampaignConfig(readings_per_pose=3, max_beam_retries=2, payload_kg=cell.payload_kg),
    )
    rec = read_recording(p)
    assert rec.closed_cleanly
    ids = [s["pose_id"] for s in rec.samples]
    skipped = [e for e in rec.events if e["kind"] == "skip"]
    assert len(ids) == res.measured and len(skipped) == res.skipped
    assert res.measured + res.skipped == 25
    assert any(e["kind"] == "beam_broken" for e in rec.events)
    s = rec.samples[0]
    assert len(s["joint_temperature_c"]) == 6 and s["n_readings"] >= 2
    assert set(map(abs, s["approach_sign"])) == {1}
    # elapsed time grows and matches the log time
    el = [x["elapsed_s"] for x in rec.samples]
    assert all(b > a for a, b in zip(el, el[1:], strict=False))


def test_campaign_cli_dry_run_and_required_out(tmp_path):
    cmd = [
        sys.executable,
        "-m",
        "workcell.cli",
        "campaign",
        "--robot",
        "sim",
        "--tracker",
        "sim",
        "--poses",
        "5",
        "--dry-run",
    ]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "nothing moved" in r.stdout and r.stdout.count("pose ") >= 5
    r = subprocess.run(cmd[:-1], capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and "--out" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize(
    "extra, match",
    [
        (["--settle", "-1"], "--settle (settle_s) must be a finite number >= 0"),
        (["--settle", "nan"], "--settle (settle_s) must be a finite number >= 0"),
        (["--warmup", "-5"], "--warmup (warmup_s) must be a finite number >= 0"),
        (["--time-scale", "0"], "--time-scale must be a number from 0.01 to 1000"),
        (["--seed", "-1"], "--seed must be >= 0"),
        (["--poses", "100000000"], "limit 100000"),
    ],
)
def test_campaign_settings_out_of_range_refused_before_moving(tmp_path, capsys, extra, match):
    from workcell.cli import main

    out = tmp_path / "c.mcap"
    argv = ["campaign", "--robot", "sim", "--tracker", "sim", "--poses", "3", "--out", str(out)]
    rc = main(argv + extra)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and match in err[0], err
    assert not out.exists()


@settings(max_examples=80, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_an_envelope_file_is_either_refused_or_really_confines(data):
    """Any JSON in any field of an envelope file: `Envelope.from_dict` refuses it (ValueError,
    one line) or the envelope it builds refuses every target outside its joint limits and
    caps speed. NaN limits used to pass every check (all comparisons with NaN are false)."""
    from jsonfuzz import replace_any_field

    from workcell.campaign.envelope import Envelope

    d = default_envelope(UR5E).to_dict()
    if data.draw(st.booleans(), label="nan"):
        d["joint_limits_rad"][data.draw(st.integers(0, 5))][0] = float("nan")
    else:
        replace_any_field(data, d)
    try:
        env = Envelope.from_dict(json.loads(json.dumps(d)))
    except ValueError as e:
        assert "\n" not in str(e)
        return
    lim = env.joint_limits_rad
    assert np.all(np.isfinite(lim)) and np.all(lim[:, 0] < lim[:, 1])
    if lim.shape != (6, 2):  # an envelope for another arm: refused at the first check
        with pytest.raises(ValueError, match="joints"):
            env.check(UR5E, np.zeros(6), np.array([0, 0, 0.06]))
        return
    j = data.draw(st.integers(0, 5), label="joint")
    q = np.clip(np.zeros(6), lim[:, 0], lim[:, 1])
    q[j] = lim[j, 1] + data.draw(st.floats(1e-6, 10.0), label="beyond")
    with pytest.raises(EnvelopeViolation):
        env.check(UR5E, q, np.array([0, 0, 0.06]))
    speed, accel = env.cap(1e9, 1e9)
    assert 0 < speed < 1e9 and 0 < accel < 1e9


def _grid_dip():
    """A consecutive pair of grid-plan poses (seed 0) whose joint-space path dips below the
    workspace box although both ends are inside: what end-point checks alone would let through.
    (No kinematic margin: with the default 10 mm, this plan has no such pair.)"""
    env = dataclasses.replace(default_envelope(UR5E), kinematic_margin_m=0.0)
    tool = np.array([0, 0, 0.06])
    gen, _ = make_plan("grid", UR5E, env, 60, seed=0, tool_m=tool)
    targets = list(gen)
    ex = Executor(None, None, UR5E, env, None, tool_m=tool)
    for a, b in zip(targets[:-1], targets[1:], strict=True):
        pre = ex._prepose(b)
        if env.path_violation(UR5E, a.q_rad, pre, tool) is not None:
            return env, tool, a, b, pre
    raise AssertionError("no dipping segment in this plan; pick another seed")


def test_joint_paths_between_valid_poses_are_checked_and_routed():
    env, tool, a, b, pre = _grid_dip()
    assert env.violations(UR5E, np.array([a.q_rad, pre]), tool) == [None, None]
    why = env.path_violation(UR5E, a.q_rad, pre, tool)
    assert "of the way" in why and "outside the workspace box" in why
    # the executor goes round it (via the upright posture) or refuses; never along the dip
    robot, sink = ClockRobot(q0=a.q_rad), NullSink()
    ex = Executor(robot, None, UR5E, env, sink, tool_m=tool)
    ok = ex._move_along(pre, f"pose {b.pose_id}")
    path = [a.q_rad, *robot.moves]
    if ok:
        assert len(robot.moves) == 2 and [k for k, _ in sink.events] == ["via"]
    else:
        assert robot.moves == [] and [k for k, _ in sink.events] == ["refused"]
    for q0, q1 in zip(path[:-1], path[1:], strict=True):
        assert env.path_violation(UR5E, q0, q1, tool) is None


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**31 - 1))
def test_route_between_random_valid_poses_never_leaves_the_envelope(seed):
    env = default_envelope(UR5E)
    tool = np.array([0, 0, 0.06])
    a, b = random_configurations(UR5E, env, 2, np.random.default_rng(seed), tool)
    waypoints, why = route(env, UR5E, tool, a, b)
    if why is not None:
        assert waypoints == [] and env.path_violation(UR5E, a, b, tool) is not None
        return
    path = [a, *waypoints]
    assert np.allclose(path[-1], b)
    for q0, q1 in zip(path[:-1], path[1:], strict=True):
        assert env.path_violation(UR5E, q0, q1, tool) is None


def test_a_planned_campaign_has_no_move_that_leaves_the_envelope():
    """The demo's plan (UR5e, 150 random poses, seed 1): in the order drawn, six moves between
    consecutive poses dipped below the box even via the upright posture and the executor refused
    those poses; the planner now defers such a pose until one it can be reached from."""
    env = default_envelope(UR5E)
    tool = np.array([0, 0, 0.06])
    gen, q = make_plan("random", UR5E, env, 150, seed=1, tool_m=tool)
    targets = list(gen)
    assert len(targets) == 150 and len({t.pose_id for t in targets}) == 150
    ex = Executor(None, None, UR5E, env, None, tool_m=tool)
    assert ex.check_plan(targets) == []


def test_encoder_noise_at_the_envelope_edge_does_not_switch_the_path_check_off():
    """An arm sent to a target on a joint limit reads a hair beyond it; the next move is still
    path-checked from the target it was sent to (not taken for an arm outside the envelope).
    The hair: 1.5e-4 rad, beyond the UR driver's arrival tolerance (1e-4) and inside
    `AT_SENT_TOL_RAD` (2e-4 since 2026-11-29; this test read 5e-4 beyond under 1e-3)."""

    class NoisyRobot(ClockRobot):
        def state(self):
            st = super().state()
            return type(st)(
                t_s=st.t_s, q_rad=st.q_rad + np.array([1.5e-4, 0, 0, 0, 0, 0]), qd_rad_s=st.qd_rad_s
            )

    env = default_envelope(UR5E)
    tool = np.array([0, 0, 0.06])
    home = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
    at_limit = home.copy()
    at_limit[0] = env.joint_limits_rad[0, 1]
    assert (
        env.violations(UR5E, np.array([at_limit, at_limit + [1.5e-4, 0, 0, 0, 0, 0]]), tool)[0]
        is None
    )
    assert env.violations(UR5E, (at_limit + [1.5e-4, 0, 0, 0, 0, 0])[None], tool)[0] is not None
    robot, sink = NoisyRobot(q0=home), NullSink()
    ex = Executor(robot, None, UR5E, env, sink, tool_m=tool)
    assert ex._move_along(at_limit, "edge") and ex._move_along(home, "back")
    assert [k for k, _ in sink.events if k == "envelope"] == []
    assert len(robot.moves) == 2

    # 5e-4 rad beyond: not noise but an arm moved since; it is where it reads, outside the joint
    # range, and comes back along a path checked from there (it was taken for the limit posture)
    class MovedRobot(ClockRobot):
        def state(self):
            st = super().state()
            return type(st)(
                t_s=st.t_s, q_rad=st.q_rad + np.array([5e-4, 0, 0, 0, 0, 0]), qd_rad_s=st.qd_rad_s
            )

    robot, sink = MovedRobot(q0=home), NullSink()
    ex = Executor(robot, None, UR5E, env, sink, tool_m=tool)
    assert ex._move_along(at_limit, "edge") and ex._move_along(home, "back")
    assert [k for k, _ in sink.events if k == "envelope"] == ["envelope"]


def test_an_arm_outside_the_envelope_is_not_moved(tmp_path):
    """Placed outside (shoulder down: the forearm under the table), the arm is not moved at all:
    a campaign refuses to start in one line and records nothing; an executor that finds it
    outside mid-campaign (jogged during a pause) says so and stops, resumable."""
    from workcell.errors import UserError

    env = default_envelope(UR5E)
    tool = np.array([0, 0, 0.06])
    outside = np.array([0.0, -0.2, 1.57, -1.57, -1.57, 0.0])
    assert env.violations(UR5E, outside[None], tool)[0] is not None
    robot, sink = ClockRobot(q0=outside), NullSink()
    heard: list[dict] = []
    ex = Executor(robot, None, UR5E, env, sink, tool_m=tool, on_event=heard.append)
    with pytest.raises(ArmOutsideEnvelope, match="jog it inside, then start again"):
        ex._move_along(np.array([0.0, -1.2, 1.2, -1.5, -1.5, 0.0]), "pose 0")
    assert robot.moves == [] and [k for k, _ in sink.events] == ["envelope"]
    # recorded, not echoed: the error itself is the one line the operator reads
    assert heard == []
    ex.result.measured = 4  # found outside mid-campaign (jogged during a pause): resumable
    with pytest.raises(ArmOutsideEnvelope, match=r"then resume the campaign \(--resume\)"):
        ex._move_along(np.array([0.0, -1.2, 1.2, -1.5, -1.5, 0.0]), "pose 5")

    world, srobot, tracker, cell = sim_cell("ur5e", "none", 3)
    world.clock.advance(world.command_move(outside, 0.5, 1.0))
    moved = []
    orig = srobot.move_joints
    srobot.move_joints = lambda *a, **k: (moved.append(a), orig(*a, **k))
    out = tmp_path / "c.mcap"
    with pytest.raises(UserError, match="outside the envelope at the start") as e:
        run_campaign(srobot, tracker, cell, out, plan="random", poses=3, seed=0)
    assert "\n" not in str(e.value) and "nothing was recorded" in str(e.value)
    assert moved == [] and not out.exists()


def test_an_arm_beyond_the_joint_ranges_only_comes_back_along_a_checked_path():
    """An envelope narrower than where the arm stands (joint 3 at 1.57 rad, the envelope's range
    up to 1.5 rad) but with the SMR in the box: the first move goes, said as a warning, along a
    path checked against the box and floor; with the box shrunk so that way dips out, refused."""
    env = default_envelope(UR5E)
    lim = env.joint_limits_rad.copy()
    lim[2] = [0.3, 1.5]
    env = dataclasses.replace(env, joint_limits_rad=lim)
    tool = np.array([0, 0, 0.06])
    home = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0])
    target = np.array([0.0, -1.2, 1.2, -1.5, -1.5, 0.0])
    assert "joint 3" in env.violations(UR5E, home[None], tool)[0]
    robot, sink = ClockRobot(q0=home), NullSink()
    ex = Executor(robot, None, UR5E, env, sink, tool_m=tool)
    assert ex._move_along(target, "pose 0")
    assert len(robot.moves) == 1 and [k for k, _ in sink.events] == ["envelope"]
    assert env.with_arm_joint_ranges(UR5E).path_violation(UR5E, home, target, tool) is None
    # the same start with the floor raised above the arm's links: not moved at all
    high = dataclasses.replace(env, floor_z_m=0.5)
    robot, sink = ClockRobot(q0=home), NullSink()
    ex = Executor(robot, None, UR5E, high, sink, tool_m=tool)
    with pytest.raises(ArmOutsideEnvelope):
        ex._move_along(target, "pose 0")
    assert robot.moves == []


def _shrunk(env, by_m: float):
    """env with every box face moved in and the floor moved up by `by_m`: every clearance drops
    by exactly that much."""
    return dataclasses.replace(
        env,
        box_min_m=env.box_min_m + by_m,
        box_max_m=env.box_max_m - by_m,
        floor_z_m=env.floor_z_m + by_m,
    )


def test_the_path_check_sees_a_dip_between_its_samples():
    """Two postures whose 32 evenly spaced path samples are all inside, while the SMR or a link
    leaves the envelope between two samples: the check refuses the path. (Sampling alone, the
    check before today, let it through.)"""
    env = default_envelope(UR5E)
    tool = np.array([0, 0, 0.06])
    rng = np.random.default_rng(5)
    s32, dense = np.linspace(0, 1, 32), np.linspace(0, 1, 2048)
    found = 0
    for _ in range(100):
        a, b = random_configurations(UR5E, env, 2, rng, tool)
        c_samples = env.clearance(UR5E, a + s32[:, None] * (b - a), tool).min()
        c_dense = env.clearance(UR5E, a + dense[:, None] * (b - a), tool).min()
        if c_samples - c_dense < 2.5e-4:  # a dip of a quarter millimetre (5x the tolerance)
            continue
        tight = _shrunk(env, 0.5 * (c_samples + c_dense))
        samples = a + s32[:, None] * (b - a)
        assert all(v is None for v in tight.violations(UR5E, samples, tool))
        assert any(
            v is not None for v in tight.violations(UR5E, a + dense[:, None] * (b - a), tool)
        )
        # max_step_rad 10: exactly those 32 samples to start from
        why = tight.path_violation(UR5E, a, b, tool, max_step_rad=10.0)
        assert why is not None and "leaves the envelope" in why
        found += 1
    assert found >= 3, found  # 7 of these 100 paths: not a contrived case


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**31 - 1), st.floats(0.0, 0.15))
def test_a_path_the_check_passes_is_inside_all_along(seed, shrink_m):
    """Random postures, envelopes shrunk by up to 15 cm: a path the check lets through has no
    point outside by more than the stated tolerance on a dense sampling (4,096 points)."""
    from workcell.campaign.envelope import PATH_TOL_M

    env = default_envelope(UR5E)
    tool = np.array([0, 0, 0.06])
    a, b = random_configurations(UR5E, env, 2, np.random.default_rng(seed), tool)
    tight = _shrunk(env, shrink_m)
    if tight.path_violation(UR5E, a, b, tool, max_step_rad=10.0) is None:
        s = np.linspace(0, 1, 4096)
        assert tight.clearance(UR5E, a + s[:, None] * (b - a), tool).min() >= -PATH_TOL_M / 2


def test_an_abort_before_the_first_pose_is_an_aborted_recording_not_an_exception(tmp_path):
    """A UI's abort while the campaign is still planning runs through the executor as before
    (robot stopped, abort event, recording closed); only a command-line Ctrl-C that Python
    dropped (`errors.INTERRUPTED`) stops run_campaign before it connects."""
    from sim_devices.cell import sim_cell
    from workcell.campaign.executor import CampaignConfig, CampaignControl
    from workcell.campaign.run import run_campaign
    from workcell.recording.reader import read_recording

    _, robot, tracker, cell = sim_cell("ur5e", "none", seed=1)
    control = CampaignControl()
    control.abort.set()
    path, res = run_campaign(
        robot, tracker, cell, tmp_path / "a.mcap", poses=5, seed=1, control=control,
        config=CampaignConfig(readings_per_pose=2, settle_s=0.2),
    )  # fmt: skip
    assert res.aborted and res.measured == 0
    rec = read_recording(path)
    assert rec.closed_cleanly and any(e["kind"] == "abort" for e in rec.events)


def test_the_dry_run_says_what_the_planned_poses_can_identify(capsys):
    """Before anything moves: 5 poses give 15 equations for the 25 parameters well-spread poses
    identify, so the dry run warns which stay dependent and that 9 poses are the minimum, and
    that a fit needs more; 30 random poses identify all 25 and draw no warning."""
    from workcell.cli import main

    argv = ["campaign", "--robot", "sim", "--tracker", "sim", "--dry-run", "--poses"]
    assert main([*argv, "5"]) == 0
    out = capsys.readouterr().out
    assert "rank 15 of the 25 that well-spread poses give" in out
    dep = next(ln for ln in out.splitlines() if "parameter(s) dependent" in ln)
    assert dep.startswith("warning: these poses leave 10 parameter(s) dependent")
    assert "a point tracker needs at least 9 poses" in dep
    assert "warning: too few poses to fit (5)" in out and "16 poses" in out
    assert "expected after a DH fit" not in out  # no noise-only figure for a fit that can't run
    assert main([*argv, "30"]) == 0
    out = capsys.readouterr().out
    assert "rank 25 of the 25 that well-spread poses give" in out
    assert "warning" not in out
    exp = next(ln for ln in out.splitlines() if ln.startswith("expected after a DH fit"))
    assert "of the 22 training poses" in exp and "x the noise floor of" in exp


def test_a_tight_envelope_still_gives_the_poses_asked_for():
    """In a tight envelope more random candidates are lost to their approach and to the paths
    between them than the 10 % spare covers (20 asked: 18 kept before 2026-11-25); the planner
    then draws more, and the plan it gives passes the dry run's own envelope check."""
    from workcell.campaign.executor import dry_run_plan

    lim = np.array([[-0.5, 0.5], [-2.0, -1.0], [0.8, 1.8], [-2.5, -1.0], [-2.0, -1.0], [-0.5, 0.5]])
    env = dataclasses.replace(
        default_envelope(UR5E),
        joint_limits_rad=lim,
        box_min_m=np.array([-0.2, -0.8, 0.1]),
        box_max_m=np.array([0.6, 0.0, 0.8]),
    )
    tool = np.array([0.0, 0.0, 0.06])  # the simulated cell's SMR
    for n in (20, 30):
        targets, problems = dry_run_plan("random", UR5E, env, n, seed=0, tool_m=tool)
        assert len(targets) == n and not problems, problems
        assert len({t.pose_id for t in targets}) == n
    # the first try is kept where it suffices: the default envelope's plans are unchanged
    q_default = make_plan("random", UR5E, default_envelope(UR5E), 20, seed=0, tool_m=tool)[1]
    q_first = random_configurations(
        UR5E, default_envelope(UR5E), 24, np.random.default_rng(0), tool
    )
    assert all(any(np.array_equal(a, b) for b in q_first) for a in q_default)


class JoggedDuringAFault:
    """The in-process simulated robot, with one fault: at the first move command from the
    `at`-th on whose target allows it, the arm is jogged (as an operator may do while the
    campaign waits) to a posture inside the envelope from which the straight path to that
    target leaves it, and the move fails with
    `fault` (a protective stop, or a lost connection the driver can reconnect). Every motion
    command is recorded with the joint position it starts from."""

    def __init__(self, inner, world, env, tool, at: int, fault: Exception, seed: int = 0):
        self.inner, self.world, self.env, self.tool = inner, world, env, tool
        self.at, self.fault, self.rng = at, fault, np.random.default_rng(seed)
        self.commands: list[tuple[np.ndarray, np.ndarray]] = []
        self.jogged_to = None

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def reconnect(self):
        pass

    def unlock_protective_stop(self):
        pass

    def _jog_for(self, target: np.ndarray) -> np.ndarray | None:
        lo, hi = self.env.joint_limits_rad[:, 0], self.env.joint_limits_rad[:, 1]
        for _ in range(300):
            q = self.rng.uniform(lo, hi)
            if self.env.violations(UR5E, q[None], self.tool)[0] is not None:
                continue
            if self.env.path_violation(UR5E, q, target, self.tool) is not None:
                return q
        return None

    def move_joints(self, q, speed, accel):
        q = np.asarray(q, float)
        n = len(self.commands)
        if n >= self.at and self.jogged_to is None and (jog := self._jog_for(q)) is not None:
            self.jogged_to = jog
            from sim_devices.world import Trajectory

            t = self.world.clock.now()
            self.world._traj = Trajectory(t, self.jogged_to, self.jogged_to, 1.0, 1.0, np.ones(6))
            raise self.fault
        self.commands.append((np.asarray(self.world.joint_state()[0], float), q))
        return self.inner.move_joints(q, speed, accel)


@pytest.mark.parametrize("fault", ["protective stop", "connection lost"])
def test_a_move_cut_short_is_planned_again_from_where_the_arm_was_jogged(fault):
    """After a protective stop or a reconnect, the interrupted move used to be sent again as it
    was, from wherever the arm then stood: the operator may have jogged it meanwhile, and that
    straight path can leave the envelope. Now the pose starts over: every motion command of the
    campaign, from the position the arm had when it was sent, stays inside the envelope, and
    every pose is measured or skipped with an event."""
    from workcell.campaign.executor import CampaignControl
    from workcell.drivers.protocols import DeviceError, ProtectiveStop

    world, robot, tracker, cell = sim_cell("ur5e", "none", 4, beam_break_prob=0.0)
    env = default_envelope(cell.spec)
    err = ProtectiveStop("simulated") if fault == "protective stop" else DeviceError("RTDE lost")
    jog = JoggedDuringAFault(robot, world, env, cell.tool_m, at=7, fault=err)
    samples = []

    class Sink(NullSink):
        def sample(self, *a):
            samples.append(a)

    sink = Sink()
    cfg = CampaignConfig(readings_per_pose=1, settle_s=0.1, reconnect_backoff_s=0.0)
    control = CampaignControl()  # resumes a protective stop by itself
    gen, _ = make_plan("random", cell.spec, env, 6, seed=4, tool_m=cell.tool_m)
    jog.connect(), tracker.connect()
    ex = Executor(jog, tracker, cell.spec, env, sink, tool_m=cell.tool_m, config=cfg,
                  control=control)  # fmt: skip
    res = ex.run(gen)
    assert jog.jogged_to is not None
    for q_from, q_to in jog.commands:
        assert env.path_violation(cell.spec, q_from, q_to, cell.tool_m) is None, (q_from, q_to)
    kinds = [k for k, _ in sink.events]
    assert "retry" in kinds, kinds
    assert res.measured + res.skipped == 6 and len(samples) == res.measured


class JoggedDuringAStateRead(JoggedDuringAFault):
    """As `JoggedDuringAFault`, but the fault is a lost connection on a state read: the first
    read after the `at`-th move command fails (the executor reconnects and reads again), and
    while the connection is down the arm is jogged to a posture inside the envelope from which
    the straight path to where it had been sent leaves the envelope. The read may be the
    state recorded at a pre-pose before the approach, or an event's clock read before a via
    route: moves planned before the reconnect."""

    def __init__(self, *a, silent: bool = False, **kw):
        super().__init__(*a, **kw)
        self.fail_next = False
        self.silent = silent  # jog without a lost connection (freedrive, another client)

    def move_joints(self, q, speed, accel):
        q = np.asarray(q, float)
        self.commands.append((np.asarray(self.world.joint_state()[0], float), q))
        out = self.inner.move_joints(q, speed, accel)
        if len(self.commands) == self.at and self.jogged_to is None:
            self.fail_next = True
        return out

    def state(self):
        from workcell.drivers.protocols import DeviceError

        if self.fail_next:
            self.fail_next = False
            last = self.commands[-1][1]
            # a jog from which even a short step from `last` (the approach) leaves the envelope
            for _ in range(20):
                jog = self._jog_for(last)
                if jog is None:
                    break
                if self.env.path_violation(UR5E, jog, last + 0.02, self.tool) is not None:
                    break
            if jog is not None:
                from sim_devices.world import Trajectory

                self.jogged_to = jog
                t = self.world.clock.now()
                self.world._traj = Trajectory(t, jog, jog, 1.0, 1.0, np.ones(6))
            if not self.silent:
                raise DeviceError("RTDE lost (simulated)")
        return self.inner.state()


@pytest.mark.parametrize("silent", [False, True], ids=["reconnect", "silent"])
@pytest.mark.parametrize("at", [1, 2, 3, 4, 5])
def test_a_move_planned_before_a_reconnect_on_a_state_read_is_planned_again(at, silent):
    """The audit of 2026-11-26 (night): a lost connection on a state read (the state recorded at
    the pre-pose, an event's clock) was reconnected and the read repeated; the approach (or the
    via route) planned before it was then sent from wherever the operator had jogged the arm
    meanwhile: 106 mm below the box. Now every move carries the reconnect count it was planned
    at, and one planned before a reconnect is not sent: the pose starts over from where the arm
    is. Every motion command, from the position the arm had when it was sent, stays inside the
    envelope. `silent`: the arm moved with no lost connection (freedrive, another client):
    each move's path is checked once more from the posture read just before it is sent."""
    from workcell.campaign.executor import CampaignControl

    world, robot, tracker, cell = sim_cell("ur5e", "none", 4, beam_break_prob=0.0)
    env = default_envelope(cell.spec)
    jog = JoggedDuringAStateRead(
        robot, world, env, cell.tool_m, at=at, fault=None, seed=at, silent=silent
    )

    class Sink(NullSink):
        def sample(self, *a):
            pass

    sink = Sink()
    cfg = CampaignConfig(readings_per_pose=1, settle_s=0.1, reconnect_backoff_s=0.0)
    gen, _ = make_plan("random", cell.spec, env, 4, seed=4, tool_m=cell.tool_m)
    jog.connect(), tracker.connect()
    ex = Executor(jog, tracker, cell.spec, env, sink, tool_m=cell.tool_m, config=cfg,
                  control=CampaignControl())  # fmt: skip
    res = ex.run(gen)
    assert jog.jogged_to is not None
    for q_from, q_to in jog.commands:
        assert env.path_violation(cell.spec, q_from, q_to, cell.tool_m) is None, (q_from, q_to)
    assert res.measured + res.skipped == 4


def _tight_joint3():
    """The default UR5e envelope with joint 3 limited to [-2.8, -0.3] rad: the upright posture
    (joint 3 at 0) is outside it."""
    env = default_envelope(UR5E)
    lim = env.joint_limits_rad.copy()
    lim[2] = [-2.8, -0.3]
    return dataclasses.replace(env, joint_limits_rad=lim)


def test_an_arm_beyond_the_joint_ranges_comes_back_without_leaving_them_further():
    """An arm the operator left 0.05 rad beyond joint 1's range: the way back in was routed with
    the arm's own joint ranges throughout, so the upright via posture could take joint 3 to 0,
    outside the envelope's [-2.8, -0.3]. Now the direct path back (which only comes nearer the
    ranges) is checked with the arm's ranges, and a via posture (upright, brought inside the
    ranges) only if it and the move on from it are inside the envelope."""
    from workcell.campaign.envelope import route_back_in

    env, tool = _tight_joint3(), np.array([0.0, 0.0, 0.06])
    q_from = np.array([3.0171, -1.4022, -2.2439, -1.2281, -2.895, 1.2639])
    q_to = np.array([2.6328, -2.463, -1.5196, -4.3954, -1.9976, 2.2753])
    loose = env.with_arm_joint_ranges(UR5E)
    old, _ = route(loose, UR5E, tool, q_from, q_to)  # what the executor used to move along
    assert len(old) == 2 and env.violations(UR5E, old[0][None], tool)[0] is not None
    wps, why = route_back_in(env, UR5E, tool, q_from, q_to)
    assert why is None and len(wps) == 2
    assert env.violations(UR5E, wps[0][None], tool)[0] is None  # inside the envelope
    assert env.path_violation(UR5E, wps[0], q_to, tool) is None
    from workcell.drivers.protocols import RobotState

    robot = RecordingRobot()
    robot.state = lambda: RobotState(  # where the arm was sent last
        t_s=0.0, q_rad=robot.moves[-1] if robot.moves else q_from, qd_rad_s=np.zeros(6)
    )
    ex = Executor(robot, None, UR5E, env, NullSink(), tool_m=tool)
    assert ex._move_along(q_to, "pose 0") is True
    assert len(robot.moves) == 2 and np.allclose(robot.moves[0], wps[0])
    # over random starts beyond joint 1's range of the default envelope (whose joint ranges
    # hold the upright posture): every via posture chosen is inside the envelope, and every
    # leg after the first is checked against it
    env = default_envelope(UR5E)
    loose = env.with_arm_joint_ranges(UR5E)
    rng = np.random.default_rng(7)
    lim = env.joint_limits_rad
    n_via = 0
    for _ in range(3000):
        a, b = rng.uniform(lim[:, 0], lim[:, 1]), rng.uniform(lim[:, 0], lim[:, 1])
        a[0] = lim[0, 1] + rng.uniform(0.01, 0.1)
        if loose.violations(UR5E, a[None], tool)[0] or env.violations(UR5E, b[None], tool)[0]:
            continue
        wps, why = route_back_in(env, UR5E, tool, a, b)
        if len(wps) == 2:
            n_via += 1
            assert env.violations(UR5E, wps[0][None], tool)[0] is None
            assert env.path_violation(UR5E, wps[0], b, tool) is None
        if wps:
            assert loose.path_violation(UR5E, a, wps[0], tool) is None
    assert n_via > 0


def test_an_unexpected_error_stops_the_arm_and_the_recording_says_why(tmp_path):
    """Anything that ends a campaign other than its end, an abort or the margin watch (a fault
    beyond the retries, a closed output pipe, a bug in a callback) stops the arm and leaves a
    `stopped` event in the closed recording before the error reaches the caller; a progress
    line on a closed pipe no longer stops a campaign at all (`run.progress`)."""
    world, robot, tracker, cell = sim_cell("ur5e", "none", 1, beam_break_prob=0.0)
    stops = []
    real_stop = robot.stop
    robot.stop = lambda: (stops.append(True), real_stop())

    def on_sample(s):
        if s["index"] == 2:
            raise RuntimeError("a callback failed")

    cfg = CampaignConfig(readings_per_pose=1, settle_s=0.1)
    with pytest.raises(RuntimeError, match="a callback failed"):
        run_campaign(robot, tracker, cell, tmp_path / "e.mcap", poses=6, seed=1, config=cfg,
                     on_sample=on_sample)  # fmt: skip
    rec = read_recording(tmp_path / "e.mcap")
    assert rec.closed_cleanly and len(rec.samples) == 3 and stops
    (ev,) = [e for e in rec.events if e["kind"] == "stopped"]
    assert ev["level"] == "error" and "RuntimeError: a callback failed" in ev["message"]

    import io
    import sys

    from workcell.campaign.run import progress

    class Closed(io.StringIO):
        def write(self, s):
            raise BrokenPipeError(32, "Broken pipe")

    old, sys.stderr = sys.stderr, Closed()
    try:
        progress("pose 1")  # no exception
    finally:
        sys.stderr = old


class LostOnceAndRestarted:
    """The in-process simulated robot whose connection is lost at the `at`-th move command; the
    reconnect finds a restarted controller whose clock starts again from zero."""

    def __init__(self, inner, at: int):
        self.inner, self.at, self.n, self.lost, self.t_back = inner, at, 0, False, 0.0

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def reconnect(self):
        self.t_back = self.inner.state().t_s  # the controller's clock restarts

    def state(self):
        st = self.inner.state()
        return dataclasses.replace(st, t_s=st.t_s - self.t_back)

    def move_joints(self, q, speed, accel):
        from workcell.drivers.protocols import DeviceError

        self.n += 1
        if self.n == self.at and not self.lost:
            self.lost = True
            raise DeviceError("RTDE lost")
        return self.inner.move_joints(q, speed, accel)


def test_log_times_come_from_one_clock_across_a_reconnect_and_a_controller_restart():
    """Log time is the moment of acquisition (recording format). The reconnect event was stamped
    with the wall clock while every other record used the robot's (virtual, in a time-scaled
    simulation) clock, and a controller whose clock restarted put later records before earlier
    ones. Now every record's log time comes in order, and a sample's log time less its
    `elapsed_s` is the campaign's start throughout."""
    from workcell.campaign.executor import CampaignControl

    world, robot, tracker, cell = sim_cell("ur5e", "none", 4, beam_break_prob=0.0)
    env = default_envelope(cell.spec)
    flaky = LostOnceAndRestarted(robot, at=6)
    records = []

    class Sink:
        def event(self, t, level, kind, msg):
            records.append((t, kind, None))

        def joint_state(self, t, *a):
            records.append((t, "joint_state", None))

        def tracker_measurement(self, t, *a):
            records.append((t, "tracker", None))

        def sample(self, t, s):
            records.append((t, "sample", s["elapsed_s"]))

    cfg = CampaignConfig(readings_per_pose=2, settle_s=0.1, reconnect_backoff_s=0.0)
    gen, _ = make_plan("random", cell.spec, env, 5, seed=2, tool_m=cell.tool_m)
    flaky.connect(), tracker.connect()
    t0 = 10**18
    ex = Executor(flaky, tracker, cell.spec, env, Sink(), tool_m=cell.tool_m, config=cfg,
                  control=CampaignControl(), t_wall0_ns=t0, elapsed0_s=0.0)  # fmt: skip
    res = ex.run(gen)
    assert flaky.lost and "reconnect" in [k for _, k, _ in records]
    assert res.measured == 5
    times = [t for t, _, _ in records]
    assert times == sorted(times), "a log time went back"
    for t, _, e in records:
        if e is not None:
            assert abs(t - t0 - e * 1e9) < 1e3, (t - t0, e)


def test_the_same_controller_sample_is_written_once_to_the_joint_state_stream():
    """At a pre-pose the arrival state read during the move and the state recorded before the
    approach were the same controller sample, written twice with one log time (audit of the
    recording format, 2026-11-26 night); now once. A new sample is written."""
    from workcell.drivers.protocols import RobotState

    class Sink(NullSink):
        def __init__(self):
            super().__init__()
            self.states = []

        def joint_state(self, *a):
            self.states.append(a)

    robot, sink = RecordingRobot(), Sink()
    t = [1.0]
    robot.state = lambda: RobotState(t_s=t[0], q_rad=np.zeros(6), qd_rad_s=np.zeros(6))
    ex = Executor(robot, None, UR5E, default_envelope(UR5E), sink, tool_m=np.zeros(3))
    ex._state_during_move(robot.state())
    ex._record_state(force=True)
    assert len(sink.states) == 1
    t[0] = 1.008
    ex._record_state(force=True)
    assert len(sink.states) == 2


def test_a_campaign_too_short_to_fit_says_so_before_moving_and_fit_says_what_to_do(
    tmp_path, capsys
):
    """Not only the dry run: a campaign of 10 poses warns before its first motion that a fit
    needs 16 (it still measures: a short campaign can be meant); `fit` then refuses with what to
    do, which for 10 poses cannot be a smaller hold-out (until 2026-11-28: no warning, and only
    "only 8 training poses; a fit needs at least 12")."""
    from workcell.cli import main

    rec = tmp_path / "c10.mcap"
    argv = ["campaign", "--robot", "sim", "--tracker", "sim", "--poses", "10", "--out", str(rec)]
    assert main(argv) == 0
    err = capsys.readouterr().err
    warn = err.index("[warning] too_few_to_fit: too few poses to fit (10)")
    assert warn < err.index("pose    0") and "ask for more poses to fit this recording alone" in err
    from workcell.recording.reader import read_recording

    kinds = [e.get("kind") for e in read_recording(rec).events]
    assert kinds.count("too_few_to_fit") == 1  # recorded with the campaign
    assert main(["fit", str(rec)]) == 2
    line = capsys.readouterr().err.strip()
    assert "only 8 training poses (of 10 with 25% held out)" in line and "\n" not in line
    assert "measure a campaign with at least 16 poses" in line and "--holdout" not in line
    assert main(["fit", str(rec), "--holdout", "0"]) == 2  # no hold-out: 12 poses would do
    line = capsys.readouterr().err.strip()
    assert "(of 10 with 0% held out)" in line and "at least 12 poses" in line


def test_a_tight_envelope_plans_in_the_largest_family_the_arm_can_move_between():
    """A box that keeps the SMR at x >= 0.3 m: random poses fall into families (elbow, wrist
    postures) with no path between them that stays inside, and the greedy order kept the family
    of its first pose: "only 2 of 8 poses fit", and fewer again for any smaller count asked.
    After every greedy try falls short, the plan now takes the largest family: 8 of 8, each move
    (pose to pre-pose of the next) checked inside the envelope as the executor moves."""
    from workcell.campaign.plans import Reach

    env = default_envelope(UR5E)
    box_min = np.array(env.box_min_m, float)
    box_min[0] = 0.3
    env = dataclasses.replace(env, box_min_m=box_min)
    tool = np.array([0.0, 0.0, 0.06])
    _, q = make_plan("random", UR5E, env, 8, seed=1, tool_m=tool)
    assert q is not None and len(q) == 8
    plan, _ = make_plan("random", UR5E, env, 8, seed=1, tool_m=tool)
    targets = list(plan)
    signs = np.array([t.approach_sign for t in targets])
    reach = Reach(UR5E, env, tool, q, signs, 0.02)
    for k in range(1, len(q)):
        reach.last = q[k - 1]
        assert reach.approach_ok(k) and reach.ok(k), k


def test_a_plan_with_no_approach_inside_says_so_before_the_arm_has_a_position():
    """`Reach.stuck` at a plan's first pose, where the arm's position is not known yet: only
    the poses' own approaches were checked, and the line names the limit they cross. It
    formatted the unknown position as joints and raised a TypeError instead."""
    from workcell.campaign.plans import PlanStuck, Reach

    env = default_envelope(UR5E)
    tool = np.array([0.0, 0.0, 0.06])
    _, q = make_plan("random", UR5E, env, 4, seed=1, tool_m=tool)
    q = np.array(q, float)
    q[:, 0] = env.joint_limits_rad[0, 1] - 0.005  # joint 1 just inside its upper limit
    signs = -np.ones_like(q)  # approached from above: the pre-poses lie beyond the limit
    reach = Reach(UR5E, env, tool, q, signs, 0.02)
    assert reach.where() is None
    i, passed = reach.first(range(len(q)))
    assert i is None and passed == len(q)
    stuck = reach.stuck(range(len(q)), "dopt")
    assert isinstance(stuck, PlanStuck)
    msg = str(stuck)
    assert "own approach stays inside the envelope" in msg, msg
    assert "joint 1" in msg, msg
