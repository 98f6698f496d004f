"""Closed loop on the simulated robot: a model equal to the true geometry corrects to the table's
interpolation error; the nominal-only 'correction' does nothing."""

import dataclasses

import numpy as np
import pytest

from sim_devices.cell import sim_cell
from workcell.campaign.envelope import Guard, default_envelope
from workcell.errors import UserError
from workcell.estimation.dh import DHModel
from workcell.export.build import make_table
from workcell.export.validate import (
    commanded_joints,
    random_targets,
    run_validation,
    sim_measure,
)
from workcell.kinematics.chain import pack
from workcell.kinematics.robots import DH


def _truth_model(truth):  # tests may read the truth; here it builds a perfect geometric model
    dh = DH(a=truth.a, d=truth.d, alpha=truth.alpha, theta_offset=truth.theta_offset)
    th = pack(dh, tool=truth.smr_flange_m, beta=truth.beta)
    return DHModel(
        robot_model="ur5e",
        nominal_dh=truth.nominal.dh,
        theta=th,
        base_ref=truth.tracker_T_base,
        cov=np.zeros((39, 39)),
        free=np.ones(39, bool),
        info={"nominal_tool_m": [0, 0, 0.06]},
    )


def _cell_and_table():
    """A simulated cell with DH errors only and the correction table of its true geometry
    (5 um interpolation error): (world, cell, table, correction)."""
    world, robot, tracker, cell = sim_cell("ur5e", "none", 3)
    table, corr = make_table(_truth_model(world.truth), target_error_m=5e-6)
    return world, cell, table, corr


def _validate(world, cell, table, corr, env, n: int, seed: int):
    """Run the closed-loop validation on the simulated world: (result, joint path moved)."""
    path = [np.asarray(world.joint_state()[0], float)]

    def move(q):
        path.append(np.asarray(q, float))
        world.clock.advance(world.command_move(q, 0.5, 1.0))

    res = run_validation(
        corr.nominal,
        table,
        move,
        sim_measure(world),
        n=n,
        seed=seed,
        guard=Guard(env, cell.spec, cell.tool_m),
        q_start=path[0],
    )
    return res, path


def test_closed_loop_geometry_only():
    world, cell, table, corr = _cell_and_table()
    res, _ = _validate(world, cell, table, corr, default_envelope(cell.spec), n=12, seed=1)
    assert res["targets"] >= 10
    assert res["before_rms_m"] > 2e-4  # the nominal controller misses by the DH errors
    assert res["after_rms_m"] < 1e-5  # interpolation error (5 um max) + nothing else
    assert res["after"]["max_m"] < 1.5e-5


def test_every_validation_move_stays_inside_the_envelope():
    """Closed-loop validation moves the arm between random targets: every motion (transit to a
    pre-pose, approach) is path-checked before it starts, and a target that cannot be reached
    inside the envelope is skipped before its first motion. A workspace box as tight as the
    table's volume makes the plain joint moves between targets leave it (checked first)."""
    world, cell, table, corr = _cell_and_table()
    env = dataclasses.replace(
        default_envelope(cell.spec), box_min_m=table.lo_m.copy(), box_max_m=table.hi_m.copy()
    )
    centre = 0.5 * (table.lo_m + table.hi_m)
    q0 = commanded_joints(corr.nominal, table, centre[None], np.array([0]), False)[0]
    world.clock.advance(world.command_move(q0, 0.5, 1.0))
    n, seed = 30, 1

    # the unguarded sequence of joint moves (what validation did before) leaves the box
    P, k = random_targets(table, n, seed)
    sign = np.sign(np.asarray(table.meta["conditions"]["approach_sign"]))
    q_u = commanded_joints(corr.nominal, table, P, k, corrected=False)
    q_c = commanded_joints(corr.nominal, table, P, k, corrected=True)
    seq = [q0]
    for i in range(n):  # per target: uncorrected, then corrected, each via its pre-pose
        for q in (q_u[i], q_c[i]):
            seq += [q - sign * 0.02, q]
    leaving = [
        j
        for j in range(len(seq) - 1)
        if np.all(np.isfinite(seq[j + 1]))
        and np.all(np.isfinite(seq[j]))
        and env.path_violation(cell.spec, seq[j], seq[j + 1], cell.tool_m) is not None
    ]
    assert leaving, "the test's envelope must be one the unguarded moves would leave"

    res, path = _validate(world, cell, table, corr, env, n=n, seed=seed)
    assert res["skipped"] and res["targets"] == n - len(res["skipped"]) >= n // 2
    for a, b in zip(path[:-1], path[1:], strict=True):
        assert env.path_violation(cell.spec, a, b, cell.tool_m) is None
    assert res["after_rms_m"] < 1e-5  # the targets it did measure are still corrected


def test_validation_refuses_to_start_outside_the_envelope():
    world, cell, table, corr = _cell_and_table()
    env = default_envelope(cell.spec)
    q_out = np.array(world.joint_state()[0], float)
    q_out[1] = -0.2  # shoulder down: the forearm below the table
    assert env.violations(cell.spec, q_out[None], cell.tool_m)[0] is not None
    moved = []
    with pytest.raises(UserError, match="outside the envelope before validation"):
        run_validation(
            corr.nominal,
            table,
            moved.append,
            sim_measure(world),
            n=5,
            guard=Guard(env, cell.spec, cell.tool_m),
            q_start=q_out,
        )
    assert moved == []


def test_the_tables_stated_uncertainty_matches_the_corrected_error(tmp_path):
    """In a DH-only world, a DH fit from a 40-pose campaign is the right model: what it leaves
    after correction is its estimation error plus the table's interpolation error. The table's
    own 1-sigma (from the fit's covariance) must be of that size, pooled over the first four
    truth seeds (single seeds scatter: one realisation of the parameter error each)."""
    from workcell.campaign.executor import CampaignConfig
    from workcell.campaign.run import run_campaign
    from workcell.estimation.dh import fit_dh
    from workcell.recording.dataset import Dataset

    ratios = []
    for seed in range(4):
        world, robot, tracker, cell = sim_cell("ur5e", "none", seed, beam_break_prob=0.0)
        path = tmp_path / f"c{seed}.mcap"
        cfg = CampaignConfig(readings_per_pose=2, settle_s=0.2)
        run_campaign(robot, tracker, cell, path, poses=40, seed=seed, config=cfg)
        table, corr = make_table(fit_dh(Dataset.from_recording(path)), target_error_m=2e-6)
        res, _ = _validate(world, cell, table, corr, default_envelope(cell.spec), n=20, seed=seed)
        pred = res["after"]["predicted_rms_std_m"]
        assert 1e-6 < pred < 1e-4
        ratios.append(res["after"]["rms_m"] / pred)
    pooled = float(np.sqrt(np.mean(np.square(ratios))))
    assert 0.4 < pooled < 2.5, ratios


def test_the_tui_closed_loop_check_validates_as_the_command_line(tmp_path, monkeypatch):
    """The terminal UI's closed-loop check (`backend.closed_loop`) guards its moves with the
    SMR the model's campaign declared, refuses in one line when the Devices screen declares
    another, and warns when the table is for another thermal state than the arm's (the check
    `validate` uses, fed the connected arm's temperatures)."""
    import workcell.export.validate as xv
    from workcell.cli import main
    from workcell.tui import backend

    monkeypatch.chdir(tmp_path)
    argv = ["campaign", "--effects", "none", "--seed", "3", "--poses", "16", "--readings", "2"]
    assert main([*argv, "--smr-offset", "0,0,0.062", "--out", "c.mcap"]) == 0
    assert main(["fit", "c.mcap", "--holdout", "0", "--out", "m.json"]) == 0
    backend.export(backend.ExportConfig(model="m.json", out="t", spacing_m=0.15))
    seen = []

    def mismatch(model, table, temps_c, *, ui=False):
        seen.append((np.asarray(temps_c, float), ui))
        return "the table is for another thermal state"

    monkeypatch.setattr(xv, "thermal_mismatch", mismatch)
    other = backend.open_devices(backend.DeviceConfig(effects="none", seed=3))
    with pytest.raises(UserError, match=r"the Devices screen declares \[0.0, 0.0, 0.06\] m"):
        backend.closed_loop("m.json", "t.json", other, 2)
    other.close()
    dev = backend.open_devices(backend.DeviceConfig(effects="none", seed=3, smr_offset="0,0,0.062"))
    lines = []
    try:
        res = backend.closed_loop("m.json", "t.json", dev, 2, log=lines.append)
    finally:
        dev.close()
    assert res["warnings"] == ["the table is for another thermal state"]
    assert "warning: the table is for another thermal state" in lines
    assert len(seen) == 1 and seen[0][1] and seen[0][0].shape == (6,)
    assert np.all(np.isfinite([res["after"]["rms_m"], res["before"]["rms_m"]]))
    # a table for another payload than the simulated arm carries: refused, as `validate` does
    # (the TUI's check did not compare payloads)
    monkeypatch.setattr(xv, "payload_mismatch", lambda *a, **k: "the table is for 5 kg")
    dev = backend.open_devices(backend.DeviceConfig(effects="none", seed=3, smr_offset="0,0,0.062"))
    try:
        with pytest.raises(UserError, match=r"t.json: the table is for 5 kg$"):
            backend.closed_loop("m.json", "t.json", dev, 2)
    finally:
        dev.close()


def _saved_variant(tmp_path, table, name, change):
    import json

    d = json.loads(json.dumps(table.to_dict()))
    change(d)
    p = tmp_path / f"{name}.json"
    p.write_text(json.dumps(d))
    return p


@pytest.mark.parametrize(
    "name, change, match",
    [
        (
            "mm",
            lambda d: d.__setitem__("delta_m", (np.asarray(d["delta_m"]) * 1000).tolist()),
            r"delta_m reaches .* beyond the bound 5 mm it was built with: it looks like millimetres",
        ),
        (
            "deg",
            lambda d: d.__setitem__("orientations_rotvec", [[0, 180, 0]]),
            "180 rad, more than a full turn: it looks like degrees, give radians",
        ),
        (
            "nobound",  # no bound in the meta: 0.1 m, more than any calibration corrects
            lambda d: (
                d["meta"].pop("correction_bound_m"),
                d.__setitem__("delta_m", (np.asarray(d["delta_m"]) * 1000).tolist()),
            ),
            "beyond 0.1 m, more than any calibration corrects: it looks like millimetres",
        ),
        (
            "bound",  # a bound edited up does not let millimetres through
            lambda d: d["meta"].__setitem__("correction_bound_m", 5.0),
            r"correction_bound_m must be a number of metres in \(0, 0.1\]",
        ),
        (
            "grid",
            lambda d: d["grid"].update(
                lo_m=[x * 1000 for x in d["grid"]["lo_m"]],
                hi_m=[x * 1000 for x in d["grid"]["hi_m"]],
            ),
            "beyond any arm's reach: it looks like millimetres",
        ),
    ],
)
def test_a_table_in_millimetres_or_degrees_is_refused(tmp_path, name, change, match):
    """`validate --table` moves the arm by the table's numbers: a table in millimetres (the
    corrected RMS was 293 mm) or degrees was accepted; now refused on loading, in one line."""
    from workcell.export.table import load_table

    _, _, table, _ = _cell_and_table()
    load_table(_saved_variant(tmp_path, table, "ok", lambda d: None))  # as written: accepted
    with pytest.raises(UserError, match=match) as e:
        load_table(_saved_variant(tmp_path, table, name, change))
    assert "\n" not in str(e.value) and "workcell export" in str(e.value)


def test_a_table_of_another_model_is_refused():
    """A table carries what it was built from (recording, arm, registered base, SMR): one of
    another model is named by the first field that differs; its own model's matches exactly
    (and within 1e-9 relative, not beyond)."""
    from workcell.export.validate import table_model_mismatch

    _, _, table, corr = _cell_and_table()
    nom = corr.nominal
    table.meta["recording_sha256"] = "ab" * 32
    assert table_model_mismatch(table, nom, "ab" * 32) is None
    assert table_model_mismatch(table, nom, None) is None  # a model without one: not compared
    w = table_model_mismatch(table, nom, "cd" * 32)
    assert "a model of another recording" in w and "workcell export" in w
    w = table_model_mismatch(table, nom, "cd" * 32, ui=True)  # the terminal UI's remedy
    assert w.endswith("export the table from this model on the Export screen")

    def moved(key, f):
        n2 = dataclasses.replace(nom, theta=nom.theta.copy(), base_ref=nom.base_ref.copy())
        f(n2)
        return table_model_mismatch(table, n2, "ab" * 32)

    assert "'ur5e' arm, this model is of a 'ur10'" in moved(
        "robot", lambda n: setattr(n, "robot", "ur10")
    )
    w = moved("base_ref", lambda n: n.base_ref.__setitem__((0, 3), n.base_ref[0, 3] + 1e-6))
    assert w.startswith("the table's base_ref (the registered base") and "another model" in w
    assert "table's tcp_m" in moved("tcp_m", lambda n: n.theta.__setitem__(38, n.theta[38] + 1e-6))
    tiny = 1e-10 * np.abs(nom.base_ref).max()
    assert (
        moved("base_ref", lambda n: n.base_ref.__setitem__((0, 3), n.base_ref[0, 3] + tiny)) is None
    )
    table.meta.pop("base_ref")  # a table without the field: not compared
    assert moved("base_ref", lambda n: n.base_ref.__setitem__((0, 3), 5.0)) is None


def test_a_table_of_another_fit_of_the_same_recording_is_refused(tmp_path):
    """Recording, arm, base and SMR can all agree while the model differs (the augmented model's
    table given to validate the DH model of the same recording was accepted and reported the
    augmented table's 1-sigma): the table carries the model's fingerprint. Its own model, saved
    and loaded again, matches; any other parameter vector does not."""
    from workcell.estimation.models import load_model, model_fingerprint, save_model
    from workcell.export.validate import table_model_mismatch

    _, _, table, corr = _cell_and_table()
    model = corr.model
    assert table.meta["model_fingerprint"] == model_fingerprint(model)
    again = load_model(save_model(model, tmp_path / "m.json"))
    assert table_model_mismatch(table, corr.nominal, None, model=again) is None
    other = dataclasses.replace(model, theta=model.theta.copy())
    other.theta[3] += 1e-9  # another fit: base, SMR and recording unchanged
    w = table_model_mismatch(table, corr.nominal, None, model=other)
    assert "another model of this recording (dh model" in w and "workcell export" in w
    assert table_model_mismatch(table, corr.nominal, None) is None  # no model given: not compared
    # a table from before 2026-11-26 names its recording (since the first day), not its model:
    # the model is not compared
    table.meta.pop("model_fingerprint")
    table.meta["recording_sha256"] = "ab" * 32
    assert table_model_mismatch(table, corr.nominal, None, model=other) is None
    # a table naming neither (edited by hand): cannot be told to belong to the model, refused
    table.meta.pop("recording_sha256")
    w = table_model_mismatch(table, corr.nominal, None, model=other)
    assert "names neither the model nor the recording" in w


def test_the_improvement_and_the_bias_carry_their_uncertainty():
    """`validate` printed its improvement factor and (JSON) the bias with none (uncertainty audit,
    2026-11-27): the bias carries its standard error over the targets, the improvement a paired
    bootstrap interval that covers the true ratio of the error distributions."""
    from workcell.estimation.models import rms_ratio_interval
    from workcell.export.validate import accuracy_stats

    rng = np.random.default_rng(2)
    ev = rng.normal([5e-6, 0, -5e-6], 1e-5, (40, 3))
    st = accuracy_stats(ev)
    np.testing.assert_allclose(st["bias_base_std_m"], ev.std(0, ddof=1) / np.sqrt(40))
    assert np.all(np.isnan(accuracy_stats(ev[:1])["bias_base_std_m"]))
    covered = 0
    for k in range(40):  # before ~ 10x after in RMS: the true ratio is 10
        r = np.random.default_rng(100 + k)
        before = np.linalg.norm(r.normal(0, 1e-4, (20, 3)), axis=1)
        after = np.linalg.norm(r.normal(0, 1e-5, (20, 3)), axis=1)
        lo, hi = rms_ratio_interval(before, after)
        covered += lo <= 10.0 <= hi
    assert covered >= 34, covered  # a 95 % interval: about 38 of 40
    assert np.isnan(rms_ratio_interval(before[:2], after[:2])[0])


def test_the_drift_trend_is_a_calibrated_test_and_estimate():
    """`drift_trend`: under no drift its p-value is uniform (about 5 % below 0.05), also when one
    axis is 4x noisier than the others (a pooled variance gave about 10 %: the review of
    2026-11-27); a drift of the corrected error shows, and the stated 1-sigma of each axis's
    change matches its scatter."""
    from workcell.export.validate import drift_trend

    rng = np.random.default_rng(5)
    t = np.sort(rng.uniform(0, 600, 20))  # 20 targets over 10 min
    for sd in ([5e-6] * 3, [5e-6, 5e-6, 20e-6]):
        ps, changes, stated = [], [], []
        for _ in range(1000):
            d = drift_trend(rng.normal(0, sd, (20, 3)), t)
            ps.append(d["p_value"])
            changes.append(np.asarray(d["rate_base_m"]) * d["span"])
            stated.append(np.asarray(d["rate_std_m"]) * d["span"])
        below = np.mean(np.array(ps) < 0.05)
        assert 0.035 < below < 0.065, (sd, below)
        np.testing.assert_allclose(
            np.sqrt(np.mean(np.square(stated), 0)), np.std(changes, 0), rtol=0.1
        )
    ev = rng.normal(0, 5e-6, (20, 3)) + np.outer(t / 600, [20e-6, 0, 0])  # 20 um in 10 min
    d = drift_trend(ev, t)
    assert d["p_value"] < 0.01 and d["change_m"] == pytest.approx(20e-6, abs=3 * d["change_std_m"])
    assert drift_trend(ev[:5], t[:5]) is None and drift_trend(ev, np.zeros(20)) is None


def test_a_drifting_cell_is_warned_about_in_the_validation(capsys):
    """The closed loop on the simulated cell: a tracker reading that creeps 2 um a target
    (40 um over the validation; a stand settling) shows as a drift of the corrected error and a
    warning; the same validation without it says a drift line with no warning."""
    logs = {}
    for creep in (0.0, 2e-6):
        world, cell, table, corr = _cell_and_table()
        env = default_envelope(cell.spec)
        inner = sim_measure(world)
        calls = []

        def measure(inner=inner, calls=calls, creep=creep):
            calls.append(1)
            return inner() + np.array([creep * len(calls) / 2, 0.0, 0.0])

        path = [np.asarray(world.joint_state()[0], float)]

        def move(q, world=world):
            world.clock.advance(world.command_move(q, 0.5, 1.0))

        lines = []
        res = run_validation(corr.nominal, table, move, measure, n=20, seed=4,
                             guard=Guard(env, cell.spec, cell.tool_m), q_start=path[0],
                             log=lines.append)  # fmt: skip
        logs[creep] = (res, lines)
    res0, lines0 = logs[0.0]
    res1, lines1 = logs[2e-6]
    assert res0["drift"]["p_value"] > 0.01 and "warning" not in res0["drift"]
    assert any(x.startswith("  drift: the corrected error changes by") for x in lines0)
    assert not any("drifted during the validation" in x for x in lines0)
    assert res1["drift"]["p_value"] < 0.01 and res1["drift"]["unit"] == "target"
    assert res1["drift"]["change_m"] == pytest.approx(2e-6 * (res1["targets"] - 1), rel=0.3)
    assert any(x.startswith("warning: the corrected error drifted") for x in lines1)
    from workcell.export.validate import validation_warnings

    assert validation_warnings(res0) == []
    # both go to `warnings` (validate --json, the TUI): the closure's and the drift's
    assert validation_warnings(res1) == [res1["closure"]["warning"], res1["drift"]["warning"]]


def test_a_moved_tracker_is_refused_at_the_first_target():
    """A tracker wheeled elsewhere since the fit (here 0.3 m along x) makes every uncorrected
    target miss by the move: validate stops at the first one with one line, instead of printing
    a metre-sized "validation" (as it did on a real cell until 2026-11-28)."""
    world, cell, table, corr = _cell_and_table()
    measure = sim_measure(world)
    moved = []

    def measure_moved():
        return measure() + np.array([0.3, 0.0, 0.0])

    def move(q):
        moved.append(q)
        world.clock.advance(world.command_move(q, 0.5, 1.0))

    with pytest.raises(UserError, match=r"measured 300\.\d mm from where the model puts it"):
        run_validation(corr.nominal, table, move, measure_moved, n=8, seed=1)
    assert len(moved) == 2  # the first target's pre-pose and the target, nothing after


def test_an_uncalibrated_cell_within_the_bound_is_validated():
    """The check is no tighter than calibration errors: a tracker 5 mm off still validates (its
    bias after the correction shows the 5 mm)."""
    world, cell, table, corr = _cell_and_table()
    measure = sim_measure(world)
    res = run_validation(
        corr.nominal, table, lambda q: world.clock.advance(world.command_move(q, 0.5, 1.0)),
        lambda: measure() + np.array([0.0, 0.005, 0.0]), n=4, seed=1,
    )  # fmt: skip
    assert res["targets"] == 4
    assert 4e-3 < res["after_rms_m"] < 6e-3


def test_a_later_target_off_does_not_discard_the_validation():
    """The registration check is the first target's: one reading 30 mm off at the fifth target
    (a bumped SMR) stays in the results as that target's error."""
    world, cell, table, corr = _cell_and_table()
    measure = sim_measure(world)
    calls = [0]

    def measure_one_off():
        calls[0] += 1
        return measure() + (np.array([0.03, 0.0, 0.0]) if calls[0] == 9 else 0.0)

    res = run_validation(
        corr.nominal, table, lambda q: world.clock.advance(world.command_move(q, 0.5, 1.0)),
        measure_one_off, n=8, seed=1,
    )  # fmt: skip
    assert res["targets"] == 8 and res["before"]["max_m"] > 0.029


def test_an_arm_moved_between_validation_moves_goes_on_only_along_checked_paths():
    """Someone jogs the arm (inside the envelope) while it stands between two validation moves,
    to a posture from which the straight path to the next commanded posture leaves the
    envelope. The validation reads the arm's posture again before every move, as a campaign
    does: it goes on from where the arm is along a checked path, or sends nothing and says so.
    It planned each path from where it had sent the arm last, and drove it 124 mm below the
    floor (a safety audit, 2026-11-29)."""
    _, cell, table, corr = _cell_and_table()
    env = default_envelope(cell.spec)
    guard = Guard(env, cell.spec, cell.tool_m)

    def run(jog_after: int | None = None, q_jog=None):
        """Validate on a fresh copy of the cell; after move `jog_after` someone moves the arm
        to q_jog. (the moves sent, (where the arm was, where it was sent) each, lines, error)"""
        world = sim_cell("ur5e", "none", 3)[0]
        sent, segments, lines = [], [], []

        def where():
            return np.asarray(world.joint_state()[0], float)

        def move(q):
            q = np.asarray(q, float)
            segments.append((where(), q))
            sent.append(q)
            world.clock.advance(world.command_move(q, 0.5, 1.0))
            if len(sent) == jog_after:
                world.clock.advance(world.command_move(q_jog, 1.0, 2.0))  # someone else

        try:
            run_validation(corr.nominal, table, move, sim_measure(world), n=6, seed=2,
                           guard=guard, q_start=where, log=lines.append)  # fmt: skip
        except UserError as e:
            return sent, segments, lines, str(e)
        return sent, segments, lines, None

    planned, _, _, err = run()
    assert err is None and len(planned) > 8
    k = 5  # the jog comes after the 5th move, aimed at the 6th
    lim = env.joint_limits_rad
    cands = np.random.default_rng(0).uniform(lim[:, 0], lim[:, 1], (4000, 6))
    q_jog = next(
        c
        for c in cands
        if guard.pose(c) is None and guard.direct(c, planned[k]) is not None
        and guard.route(c, planned[k])[1] is None
    )  # fmt: skip
    _, segments, lines, err = run(jog_after=k, q_jog=q_jog)
    bad = [(a, b) for a, b in segments if env.path_violation(cell.spec, a, b, cell.tool_m)]
    assert not bad, f"{len(bad)} move(s) left the envelope, the first from {bad[0][0]}"
    assert err is not None or any("was moved during the validation" in x for x in lines)


def test_an_arm_moved_where_no_checked_path_leads_on_is_not_moved():
    """The last line of defence itself: an arm found outside the box (moved there since the last
    move) is not sent anywhere; one line says why and what to do."""
    from workcell.export.validate import _from_where_the_arm_is

    world, cell, _, _ = _cell_and_table()
    env = default_envelope(cell.spec)
    guard = Guard(env, cell.spec, cell.tool_m)
    q0 = np.asarray(world.joint_state()[0], float)
    q_out = q0.copy()
    q_out[1] = -0.2  # shoulder down: the forearm below the table
    assert guard.pose(q_out) is not None
    sent = []
    move = _from_where_the_arm_is(sent.append, lambda: q_out, guard, q0, lambda _: None)
    with pytest.raises(UserError, match="moved during the validation.*nothing sent"):
        move(q0)
    assert sent == []
    # where it was sent (within encoder noise): the move goes as planned
    move = _from_where_the_arm_is(sent.append, lambda: q0 + 5e-5, guard, q0, lambda _: None)
    move(q0)
    assert len(sent) == 1


def test_an_interrupted_validation_move_stops_the_arm():
    """Ctrl-C, SIGTERM or SIGHUP during a validation move: the arm is stopped before the
    interrupt goes on (it was left to finish its move; a safety audit, 2026-11-29), and the
    command turns SIGTERM and SIGHUP into that interrupt (they ended the process at once)."""
    import os
    import signal

    from workcell.commands.validate import _interrupt_on_abort_signals
    from workcell.export.validate import robot_mover

    class Arm:
        stopped = 0

        def move_joints(self, q, speed, accel):
            raise KeyboardInterrupt

        def stop(self):
            self.stopped += 1

        def sleep(self, s):
            pass

    arm = Arm()
    with pytest.raises(KeyboardInterrupt):
        robot_mover(arm)(np.zeros(6))
    assert arm.stopped == 1

    old = _interrupt_on_abort_signals()
    try:
        assert set(old) >= {signal.SIGTERM}
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGTERM)  # the handler runs as kill returns
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    assert signal.getsignal(signal.SIGTERM) is old[signal.SIGTERM]


def test_the_tui_closed_loop_check_stops_on_the_operators_abort(tmp_path, monkeypatch):
    """The TUI's closed-loop check had no abort: once started (50 targets, minutes at real
    speed) only quitting the app stopped the arm (TUI audit). `abort` set during the check:
    no further move is sent, the arm is stopped, one line says so."""
    import threading

    from workcell.cli import main
    from workcell.tui import backend

    monkeypatch.chdir(tmp_path)
    argv = ["campaign", "--effects", "none", "--seed", "3", "--poses", "16", "--readings", "2"]
    assert main([*argv, "--out", "c.mcap"]) == 0
    assert main(["fit", "c.mcap", "--holdout", "0", "--out", "m.json"]) == 0
    backend.export(backend.ExportConfig(model="m.json", out="t", spacing_m=0.15))
    dev = backend.open_devices(backend.DeviceConfig(effects="none", seed=3))
    abort = threading.Event()
    moves, stops = [], []
    inner_move, inner_stop = dev.robot.move_joints, dev.robot.stop

    def move_joints(q, speed, accel):
        moves.append(np.array(q, float))
        inner_move(q, speed, accel)
        if len(moves) == 3:
            abort.set()  # the operator's ctrl+b, during the third move

    def stop():
        stops.append(1)
        inner_stop()

    monkeypatch.setattr(dev.robot, "move_joints", move_joints)
    monkeypatch.setattr(dev.robot, "stop", stop)
    try:
        with pytest.raises(UserError, match="closed-loop check aborted: the arm is stopped"):
            backend.closed_loop("m.json", "t.json", dev, 10, abort=abort)
    finally:
        dev.close()
    assert len(moves) == 3 and stops, (len(moves), len(stops))
