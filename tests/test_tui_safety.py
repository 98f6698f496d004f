"""Pilot tests of the terminal UI's safety rules (in-process simulated cell, virtual time, a few
poses): a campaign runs with the Plan and Devices forms as they stand when `s` is pressed (or is
refused), a resume refuses an envelope other than the recorded one, an abort signal stops the
campaign cleanly and quits, the quit question outlives the campaign, and the Devices screen's
time scale follows the command line's rules."""

import asyncio
import json
import os
import signal
import threading

import numpy as np
import pytest
from tuipilot import connect, screen_is, set_input, until

from workcell.recording.reader import read_recording
from workcell.tui import backend
from workcell.tui.app import make_app
from workcell.tui.backend import DeviceConfig, PlanConfig

SIZE = (100, 30)


def app_for(poses: int, **kw):
    return make_app(
        effects="none",
        plan=PlanConfig(poses=poses, readings_per_pose=2, settle_s=0.2, out="run.mcap"),
        status_poll_s=0,
        clock=lambda: 0.0,
        online=False,
        cursor_blink=False,
        **kw,
    )


def tight_envelope(path) -> str:
    """The arm's default envelope with joint 1 kept within +-0.6 rad, written to `path`."""
    from workcell.campaign.envelope import default_envelope
    from workcell.kinematics.robots import robot_by_name

    d = default_envelope(robot_by_name("ur5e")).to_dict()
    d["joint_limits_rad"][0] = [-0.6, 0.6]
    d["max_speed_rad_s"] = 0.5
    path.write_text(json.dumps(d))
    return str(path)


def hold_campaign(monkeypatch, after: int) -> threading.Event:
    """Hold the campaign's worker after its `after`-th sample until the returned event is set
    (the worker may outrun the event loop on a loaded machine)."""
    gate = threading.Event()
    real_start = backend.start_campaign

    def held_start(dev, plan, *, on_sample, **kw):
        n = [0]

        def sample(s):
            on_sample(s)
            n[0] += 1
            if n[0] == after:
                assert gate.wait(60), "the test never released the campaign"

        return real_start(dev, plan, on_sample=sample, **kw)

    monkeypatch.setattr(backend, "start_campaign", held_start)
    return gate


def test_start_runs_the_plan_form_as_typed_and_names_envelope_and_smr(tmp_path, monkeypatch):
    """An envelope file typed on the Plan screen, no dry run, `s`: the confirmation names the
    envelope and the SMR offset, and the campaign runs in that envelope (it ran in the default
    one, joint 1 far beyond the file's limit)."""
    monkeypatch.chdir(tmp_path)
    env = tight_envelope(tmp_path / "tight.json")
    app = app_for(6)

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await connect(app, pilot)
            await pilot.press("f2")
            await set_input(pilot, app.views["plan"], "envelope", env)
            await set_input(pilot, app.views["plan"], "poses", "5")
            await pilot.press("f3", "s")
            await until(pilot, lambda: screen_is(app, "ConfirmScreen"), 10, "confirm")
            q = app.screen.question
            assert f"envelope: {env}" in q and "5 random poses" in q, q
            assert "SMR offset: 0,0,0.06 m on the flange" in q, q
            await pilot.press("y")
            await until(pilot, lambda: app.finished, 60, "campaign end")
            fin = app.finished[-1]
            assert fin.result is not None and not fin.result.aborted, app.notices[-3:]
            rec = read_recording(fin.path)
            assert rec.session["campaign"]["envelope"]["joint_limits_rad"][0] == [-0.6, 0.6]
            assert len(rec.samples) == 5
            q1 = np.array([s["q_measured_rad"][0] for s in rec.samples])
            assert np.all(np.abs(q1) <= 0.6 + 1e-6), q1
            assert app.plan.envelope == env  # the form's plan is the app's now

    asyncio.run(flow())


def test_start_refused_while_the_devices_form_differs_from_the_connection(tmp_path, monkeypatch):
    """An SMR offset typed on the Devices screen without reconnecting: `s` is refused with a
    notice saying to reconnect, nothing moves (it ran with the connected offset); the closed-loop
    check is refused the same way, and takes the Plan form's envelope as it stands."""
    from workcell.errors import UserError
    from workcell.tui import messages as m

    monkeypatch.chdir(tmp_path)
    env = tight_envelope(tmp_path / "tight.json")
    app = app_for(4)
    asked = []

    def fake_closed_loop(*a, envelope_file="default", **kw):
        asked.append(envelope_file)
        raise UserError("not this time")

    monkeypatch.setattr(backend, "closed_loop", fake_closed_loop)

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await connect(app, pilot)
            dv = app.views["devices"]
            await set_input(pilot, dv, "smr-offset", "0,0,0.25")
            await pilot.press("f3", "s")
            await pilot.pause(0.2)
            assert not screen_is(app, "ConfirmScreen") and not app.campaign_running
            sev, _, text = app.notices[-1]
            assert sev == "error" and "SMR offset 0,0,0.25 m" in text and "reconnect" in text
            app.post_message(m.ValidateRequested("model.json", "table.json", 3))
            await pilot.pause(0.2)
            assert not asked and not app.validating
            assert "reconnect" in app.notices[-1][2]
            # the form set back: the question is asked (and refused here)
            await pilot.press("f1")
            await set_input(pilot, dv, "smr-offset", "")
            await pilot.press("f3", "s")
            await until(pilot, lambda: screen_is(app, "ConfirmScreen"), 10, "confirm")
            await pilot.press("n")
            # the closed-loop check moves inside the Plan form's envelope, no dry run needed
            await pilot.press("f2")
            await set_input(pilot, app.views["plan"], "envelope", env)
            app.post_message(m.ValidateRequested("model.json", "table.json", 3))
            await until(pilot, lambda: asked and not app.validating, 10, "closed-loop check")
            assert asked == [env]
        assert not list(tmp_path.glob("*.mcap"))

    asyncio.run(flow())


def interrupted_recording(tmp_path, name: str = "old.mcap") -> str:
    """A 6-pose campaign of the app's cell (in-process, effects none), aborted after 2 poses."""
    from workcell.campaign.executor import CampaignControl

    dev = backend.open_devices(DeviceConfig(effects="none"))
    control = CampaignControl()

    def on_sample(s):
        control.abort.set()

    try:
        plan = PlanConfig(poses=6, readings_per_pose=2, settle_s=0.2, out=str(tmp_path / name))
        path, res = backend.start_campaign(
            dev, plan, control=control, on_sample=on_sample, on_event=lambda e: None
        )
    finally:
        dev.close()
    assert res.aborted and res.measured < 6
    return str(path)


def test_resume_refuses_an_envelope_other_than_the_recorded_one(tmp_path, monkeypatch):
    """The Plan screen's envelope set to a tighter file, then `r` on an interrupted recording:
    refused as the command line refuses `--resume --envelope` (it resumed in the recorded,
    wider envelope); nothing recorded. The default, or a file with the recorded envelope, goes."""
    from workcell.campaign.executor import CampaignControl
    from workcell.errors import UserError

    monkeypatch.chdir(tmp_path)
    old = interrupted_recording(tmp_path)
    env = tight_envelope(tmp_path / "tight.json")
    app = app_for(6)

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await connect(app, pilot)
            await pilot.press("f2")
            await set_input(pilot, app.views["plan"], "envelope", env)
            await pilot.press("f3", "r")
            await until(pilot, lambda: screen_is(app, "PathPrompt"), 10, "path prompt")
            app.screen.query_one("#path").value = "old.mcap"
            await pilot.press("enter")
            await until(pilot, lambda: screen_is(app, "ConfirmScreen"), 10, "confirm")
            await pilot.press("y")
            await until(pilot, lambda: app.finished, 60, "resume refused")
            assert app.finished[-1].result is None
            said = [t for sev, _, t in app.notices if sev == "error"]
            assert any("a resume keeps the envelope old.mcap was recorded with" in t for t in said)
        assert sorted(p.name for p in tmp_path.glob("*.mcap")) == ["old.mcap"]

    asyncio.run(flow())

    # a file holding the recorded envelope is that envelope: the resume goes
    same = tmp_path / "same.json"
    same.write_text(json.dumps(read_recording(old).session["campaign"]["envelope"]))
    dev = backend.open_devices(DeviceConfig(effects="none"))
    try:
        plan = PlanConfig(readings_per_pose=2, envelope=str(tight_envelope(tmp_path / "t2.json")))
        with pytest.raises(UserError, match="a resume keeps the envelope"):
            backend.start_campaign(
                dev, plan, control=CampaignControl(), on_sample=lambda s: None,
                on_event=lambda e: None, resume_from=old,
            )  # fmt: skip
        plan = PlanConfig(envelope=str(same), out="new.mcap")
        path, res = backend.start_campaign(
            dev, plan, control=CampaignControl(), on_sample=lambda s: None,
            on_event=lambda e: None, resume_from=old,
        )  # fmt: skip
        assert not res.aborted and read_recording(path).session["chained_from"]
    finally:
        dev.close()


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGHUP"])
def test_an_abort_signal_stops_the_campaign_cleanly_and_quits(tmp_path, monkeypatch, sig):
    """SIGTERM or SIGHUP mid-campaign (`kill`, a closed terminal): as on the command line the
    campaign is aborted (the `abort` event, the recording closed cleanly) and the app quits
    after it, exit code 128 + signal (the process died with the recording open and the arm
    moving). With no campaign running it quits at once, devices closed."""
    from workcell.commands.tui import install_abort_signals

    monkeypatch.chdir(tmp_path)
    signum = getattr(signal, sig)
    gate = hold_campaign(monkeypatch, 2)
    app = app_for(20)
    old = {}

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            old.update(install_abort_signals(app))
            await connect(app, pilot)
            await pilot.press("f3", "s")
            await until(pilot, lambda: screen_is(app, "ConfirmScreen"), 10, "confirm")
            await pilot.press("y")
            await until(pilot, lambda: app.views["campaign"].done >= 2, 60, "2 poses")
            os.kill(os.getpid(), signum)
            assert app.control.abort.is_set()  # at once, from the handler
            gate.set()
            await until(pilot, lambda: app.return_code is not None, 60, "quit")

    try:
        asyncio.run(flow())
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    assert app.return_code == 128 + signum
    fin = app.finished[-1]
    assert fin.result.aborted and fin.recording["closed_cleanly"]
    rec = read_recording(tmp_path / "run.mcap")
    assert rec.closed_cleanly and any(e["kind"] == "abort" for e in rec.events)
    assert 2 <= len(rec.samples) < 20 and app.devices is None

    # no campaign: quits at once, devices closed
    app2 = app_for(4)
    old.clear()

    async def idle():
        async with app2.run_test(size=SIZE) as pilot:
            old.update(install_abort_signals(app2))
            await connect(app2, pilot)
            os.kill(os.getpid(), signum)
            await until(pilot, lambda: app2.return_code is not None, 10, "quit")

    try:
        asyncio.run(idle())
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    assert app2.return_code == 128 + signum and app2.devices is None


def test_abort_and_quit_after_the_campaign_ended_meanwhile(tmp_path, monkeypatch):
    """The campaign ends while the quit question is open; "Abort + quit" then quits (it raised
    AttributeError on the finished campaign's control)."""
    monkeypatch.chdir(tmp_path)
    gate = hold_campaign(monkeypatch, 2)
    app = app_for(4)

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await connect(app, pilot)
            await pilot.press("f3", "s")
            await until(pilot, lambda: screen_is(app, "ConfirmScreen"), 10, "confirm")
            await pilot.press("y")
            await until(pilot, lambda: app.views["campaign"].done >= 2, 60, "2 poses")
            await pilot.press("ctrl+q")
            await until(pilot, lambda: screen_is(app, "ConfirmScreen"), 10, "quit question")
            gate.set()
            await until(pilot, lambda: app.finished and app.control is None, 60, "finish")
            await pilot.press("y")
            await until(pilot, lambda: app.return_code is not None, 10, "quit")

    asyncio.run(flow())
    assert app.return_code == 0 and app.devices is None
    assert not [n for n in app.notices if n[1] == "UI error"], app.notices
    assert not app.finished[-1].result.aborted


@pytest.mark.parametrize(
    ("scale", "start_sim", "said"),
    [
        ("inf", True, "time scale must be a number from 0.01 to 1000 (e.g. 10), got inf"),
        ("nan", False, "time scale must be a number from 0.01 to 1000"),
        ("5", False, "time scale 5 with Robot sim: the in-process simulation runs on virtual"),
    ],
)
def test_the_devices_time_scale_follows_the_command_line(tmp_path, monkeypatch, scale, start_sim,
                                                         said):  # fmt: skip
    """`inf` was taken (the simulators then failed with an RTDE message), and a time scale
    other than 1 was silently ignored by the in-process simulation: both refused before
    connecting, as `workcell tui` / `workcell campaign --time-scale` refuse them."""
    monkeypatch.chdir(tmp_path)
    app = app_for(4, sim_host="127.0.0.61", autoconnect=False)
    opened = []
    monkeypatch.setattr(backend, "open_devices", lambda cfg: opened.append(cfg))

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            dv = app.views["devices"]
            await set_input(pilot, dv, "time-scale", scale)
            dv.query_one("#start-sim").value = start_sim
            await pilot.pause()
            await pilot.press("ctrl+r")
            await pilot.pause(0.2)
            assert app.notices and app.notices[-1][0] == "error", app.notices
            assert said in app.notices[-1][2], app.notices[-1]
            assert not opened and app.devices is None

    asyncio.run(flow())


def test_the_tui_command_refuses_a_time_scale_the_in_process_simulation_ignores(
    capsys, monkeypatch
):
    from workcell.cli import main
    from workcell.tui.app import WorkcellApp

    monkeypatch.setattr(WorkcellApp, "run", lambda self, *a, **kw: pytest.fail("the UI started"))
    rc = main(["tui", "--time-scale", "5"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert "--time-scale 5 with --robot sim: the in-process simulation runs on virtual" in err[0]
