"""The terminal UI against the protocol-level simulators (`--sim`: UR controller over ur_rtde +
GeoCOM tracker on a pty, time-scaled): the RTDE connection drops mid-campaign, the operator sees
a notification, the campaign reconnects and finishes with a valid recording."""

import asyncio
import time

from tuipilot import until

from workcell.recording.reader import read_recording
from workcell.tui.app import make_app
from workcell.tui.backend import PlanConfig

TIME_SCALE = 20.0


def sim_app(host: str, faults: dict, out: str):
    """The TUI on the protocol simulators (6 poses, time-scaled) with the given robot faults."""
    return make_app(
        sim=True,
        sim_host=host,
        seed=3,
        time_scale=TIME_SCALE,
        sim_faults=faults,
        plan=PlanConfig(poses=6, readings_per_pose=2, settle_s=0.3, seed=3, out=out),
        status_poll_s=0,
        clock=lambda: 0.0,
        online=False,
        cursor_blink=False,
    )


def test_sim_start_device_drop_notifies_and_recovers(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    # the robot's connection drops at pose 3
    app = sim_app("127.0.0.71", {"rtde_drop_at_move": [6]}, "drop.mcap")

    async def flow():
        async with app.run_test(size=(100, 30)) as pilot:
            try:
                await until(pilot, lambda: app.devices is not None, 90, "--sim start + connect")
                dev = app.devices
                assert dev.kind == "protocol simulators"
                assert dev.robot_url.startswith("ur://") and dev.tracker_url.startswith("serial://")
                status = app.views["devices"].status
                assert status["robot_mode"] == "RUNNING" and status["safety"] == "NORMAL"
                await pilot.press("f3", "s", "y")
                await until(pilot, lambda: app.finished, 180, "campaign end")
            finally:
                if app.devices is not None:
                    app.devices.close()
        return app

    asyncio.run(flow())
    fin = app.finished[-1]
    assert fin.result is not None and not fin.result.aborted, app.notices
    rec = read_recording(tmp_path / "drop.mcap")
    assert rec.closed_cleanly
    kinds = [e["kind"] for e in rec.events]
    assert "reconnect" in kinds, kinds
    measured = {s["pose_id"] for s in rec.samples}
    assert len(measured) + fin.result.skipped == 6
    texts = [t for _, _, t in app.notices]
    assert any(t.startswith("reconnect:") for t in texts), texts
    assert any("campaign recovered" in t for t in texts), texts


def test_a_protective_stop_waits_for_the_operator(tmp_path, monkeypatch):
    """A protective stop mid-campaign pauses it: the operator is told to check the cell and
    press p; the arm is not unlocked and no pose is measured until then; after p it finishes."""
    monkeypatch.chdir(tmp_path)
    app = sim_app("127.0.0.72", {"protective_stop_at_move": [6]}, "ps.mcap")

    async def flow():
        async with app.run_test(size=(100, 30)) as pilot:
            try:
                await until(pilot, lambda: app.devices is not None, 90, "--sim start + connect")
                await pilot.press("f3", "s", "y")
                scr = app.views["campaign"]
                await until(pilot, lambda: app.control.waiting_for_resume.is_set(), 120, "stop")
                await until(pilot, lambda: scr.state == "protective stop", 10, "state")
                done = scr.done
                t0 = time.monotonic()
                while time.monotonic() - t0 < 2.0:  # 40 s of the cell's time
                    await pilot.pause(0.1)
                assert scr.done == done and not app.finished
                assert app.control.waiting_for_resume.is_set()
                await pilot.press("p")
                await until(pilot, lambda: app.finished, 180, "campaign end")
            finally:
                if app.devices is not None:
                    app.devices.close()

    asyncio.run(flow())
    fin = app.finished[-1]
    assert fin.result is not None and not fin.result.aborted, app.notices
    rec = read_recording(tmp_path / "ps.mcap")
    kinds = [e["kind"] for e in rec.events]
    assert "protective_stop" in kinds and "resume" in kinds, kinds
    assert len({s["pose_id"] for s in rec.samples}) + fin.result.skipped == 6
    texts = [t for _, _, t in app.notices]
    assert any("check the cell, then press p to resume" in t for t in texts), texts
    assert any("resuming after the protective stop" in t for t in texts), texts
