"""The campaign screen says why the campaign engine ended a campaign by itself (audit of the TUI
after the engine learnt to stop: 3 protective stops in a row, a tracker with no usable reading
at 3 poses in a row, the kinematic margin, a device fault beyond the retries): each showed as
"aborted" with only the `stopped` event in its list. Now the state is STOPPED, the status and the
summary give the engine's reason, what the recording keeps and how to resume it, in the command
line's words (`workcell.campaign.run.campaign_stop`, `resume_hint`); an operator's abort stays
"aborted". In-process simulated cell (virtual time); devices wrapped after connecting to fault."""

import asyncio

import numpy as np
import pytest
from rich.text import Text
from tuipilot import connect, until
from wrapped import Wrapped

from workcell.campaign.executor import (
    MAX_PROTECTIVE_STOPS_IN_A_ROW,
    MAX_TRACKER_SKIPS_IN_A_ROW,
    CampaignResult,
)
from workcell.campaign.run import campaign_stop, resume_hint
from workcell.drivers.protocols import DeviceError, ProtectiveStop, TrackerReading
from workcell.errors import UserError
from workcell.recording.reader import read_recording
from workcell.tui import messages as m
from workcell.tui.app import make_app
from workcell.tui.backend import PlanConfig

SIZE = (100, 30)


def app_for(poses: int, **kw):
    return make_app(
        plan=PlanConfig(poses=poses, readings_per_pose=2, settle_s=0.2, out="run.mcap"),
        effects="none",
        status_poll_s=0,
        clock=lambda: 0.0,
        online=False,
        cursor_blink=False,
        **kw,
    )


async def start(app, pilot) -> None:
    await pilot.press("f3", "s")
    await until(pilot, lambda: type(app.screen).__name__ == "ConfirmScreen", 10, "confirm")
    await pilot.press("y")


class FailsFromMove(Wrapped):
    """A robot whose move commands from the `n`-th on raise `error` (a protective stop at every
    move, or a connection that is gone and does not come back: no `reconnect`)."""

    def __init__(self, inner, n: int, error: Exception):
        super().__init__(inner)
        self.n, self.moves, self.error = n, 0, error

    def move_joints(self, q, speed, accel):
        self.moves += 1
        if self.moves >= self.n:
            raise self.error
        return self.inner.move_joints(q, speed, accel)


class BeamLostAfter(Wrapped):
    """A tracker whose beam is lost for good after `n` readings (until `fixed`)."""

    def __init__(self, inner, n: int):
        super().__init__(inner)
        self.n, self.calls, self.fixed = n, 0, False

    def measure(self):
        self.calls += 1
        if self.calls > self.n and not self.fixed:
            return TrackerReading(np.full(3, np.nan), np.full(3, 1e-5), status="beam_broken")
        return self.inner.measure()


def cli_line(res, path) -> str:
    """What `workcell campaign` says for this result (its last line)."""
    with pytest.raises(UserError) as e:
        campaign_stop(res, path)
    return str(e.value)


def rows(scr) -> dict[str, str]:
    """The campaign screen's status rows as they are shown (a cell's text is rich markup)."""
    scr.render_view()
    return {k: Text.from_markup(v).plain for k, v in scr.query_one("#info").rows}


def summary_event(scr) -> dict:
    return next(e for e in reversed(scr.events) if e.get("kind") == scr.state)


def test_protective_stops_again_and_again_say_why_and_how_to_resume(tmp_path, monkeypatch):
    """The third protective stop in a row (the operator pressed p after the first two) ends the
    campaign: STOPPED, not ABORTED, with the engine's reason, the recording kept and the
    command line's resume hint, in the status, the summary and the notice."""
    monkeypatch.chdir(tmp_path)
    app = app_for(6)

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await connect(app, pilot)
            app.devices.robot = FailsFromMove(
                app.devices.robot, 5, ProtectiveStop("simulated protective stop")
            )
            await start(app, pilot)
            scr = app.views["campaign"]
            pauses = lambda: sum(e["kind"] == "pause" for e in app.campaign_log)  # noqa: E731
            for k in range(1, MAX_PROTECTIVE_STOPS_IN_A_ROW):
                waiting = lambda k=k: pauses() == k and scr.state == "protective stop"  # noqa: E731
                await until(pilot, waiting, 10, f"protective stop {k}")
                await pilot.press("p")  # the operator checked the cell
            await until(pilot, lambda: app.finished, 10, "campaign end")
            res = app.finished[-1].result
            assert res.stopped_by == "protective_stop" and res.measured == 2
            assert scr.state == "stopped", scr.state
            why = rows(scr)
            assert why["State"].startswith("STOPPED")
            assert why["Stopped"] == res.stop_message
            assert why["Stopped"].startswith("3 protective stops in a row with no pose measured")
            line = cli_line(res, "run.mcap")
            kept = line.removeprefix(res.stop_message + "; ")
            assert kept.startswith(resume_hint("run.mcap", 2))  # the CLI's own resume hint
            assert why["Recording"] == f"{kept} (on this screen: r)"
            ev = summary_event(scr)
            assert ev["level"] == "error"
            assert ev["message"].startswith(f"{line} (on this screen: r); 2 measured")
            sev, title, text = app.notices[-1]
            assert (sev, title) == ("error", "Campaign stopped") and text == ev["message"]
            assert not any(title == "UI error" for _, title, _ in app.notices), app.notices

    asyncio.run(flow())
    rec = read_recording(tmp_path / "run.mcap")
    assert rec.closed_cleanly and len(rec.samples) == 2


def test_a_tracker_without_readings_says_why_and_resumes_with_r(tmp_path, monkeypatch):
    """No usable reading at 3 poses in a row ends the campaign: STOPPED with the engine's
    reason and the CLI's "fix the tracker, then resume" line; once the beam is back, r on the
    campaign screen continues the recording as the status says."""
    monkeypatch.chdir(tmp_path)
    app = app_for(8)

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await connect(app, pilot)
            tracker = app.devices.tracker = BeamLostAfter(app.devices.tracker, 6)
            await start(app, pilot)
            scr = app.views["campaign"]
            await until(pilot, lambda: app.finished, 10, "campaign end")
            res = app.finished[-1].result
            assert res.stopped_by == "tracker" and res.measured == 3
            assert res.skipped == MAX_TRACKER_SKIPS_IN_A_ROW
            assert scr.state == "stopped", scr.state
            why = rows(scr)
            assert why["State"].startswith("STOPPED")
            assert why["Stopped"] == res.stop_message
            assert why["Stopped"].startswith("tracker gave no usable reading at 3 poses in a row")
            assert "beam_broken" in why["Stopped"]
            line = cli_line(res, "run.mcap")
            assert why["Recording"] == (
                "the arm is stopped and run.mcap is closed and keeps 3 poses: fix the tracker, "
                "then `workcell campaign --resume run.mcap` (on this screen: r)"
            )
            assert line == f"{res.stop_message}; " + why["Recording"].removesuffix(
                " (on this screen: r)"
            )
            ev = summary_event(scr)
            assert ev["message"].startswith(f"{line} (on this screen: r); 3 measured")
            assert app.notices[-1][:2] == ("error", "Campaign stopped")
            # the beam is back: r resumes the recording the status names
            tracker.fixed = True
            await pilot.press("r")
            await until(pilot, lambda: type(app.screen).__name__ == "PathPrompt", 10, "prompt")
            await pilot.press("ctrl+u")
            for ch in "run.mcap":
                await pilot.press(ch)
            await pilot.press("enter")
            await until(pilot, lambda: type(app.screen).__name__ == "ConfirmScreen", 10, "ask")
            await pilot.press("y")
            await until(pilot, lambda: len(app.finished) >= 2, 10, "resumed campaign end")
            fin = app.finished[-1]
            assert fin.result is not None and not fin.result.aborted, app.notices[-3:]
            assert scr.state == "finished" and "Stopped" not in rows(scr)
            new = read_recording(fin.path)
            assert new.session["chained_from"]["samples"] == 3

    asyncio.run(flow())


def test_the_margin_stop_names_its_reason_and_no_resume(tmp_path, monkeypatch):
    """The SMR declared 15 mm too far out: the margin watch ends the campaign. STOPPED with the
    watch's own reason (the `margin` error event), the poses the recording keeps and that a
    resume would not help (it keeps the SMR offset and envelope), never a --resume line."""
    monkeypatch.chdir(tmp_path)
    app = make_app(
        plan=PlanConfig(poses=20, readings_per_pose=2, settle_s=0.2, seed=2, out="run.mcap"),
        seed=2,
        smr_offset="0,0,0.075",
        status_poll_s=0,
        clock=lambda: 0.0,
        online=False,
        cursor_blink=False,
    )

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await connect(app, pilot)
            await start(app, pilot)
            scr = app.views["campaign"]
            await until(pilot, lambda: app.finished, 12, "campaign end")
            res = app.finished[-1].result
            assert res.stopped_by == "margin" and 0 < res.measured < 20
            assert scr.state == "stopped", scr.state
            stop = [e for e in app.campaign_log if e["kind"] == "margin"][-1]
            assert stop["level"] == "error"
            why = rows(scr)
            assert why["Stopped"] == stop["message"] and "smr_offset_m" in why["Stopped"]
            assert why["Recording"] == (
                f"run.mcap is closed and keeps {res.measured} poses; a resume keeps its SMR "
                "offset and envelope, so start a new campaign instead"
            )
            ev = summary_event(scr)
            assert ev["message"].startswith(f"{stop['message']}; {why['Recording']}; ")
            assert "--resume" not in ev["message"]

    asyncio.run(flow())


def test_a_device_fault_beyond_the_retries_is_a_stop_with_the_resume_line(tmp_path, monkeypatch):
    """The robot's connection is lost for good mid-campaign (no reconnect): the command line
    says the error, which file keeps how many poses and how to continue (exit 3). The screen
    said "FAILED" and "campaign failed". Now it is STOPPED with that same line."""
    monkeypatch.chdir(tmp_path)
    app = app_for(6)

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await connect(app, pilot)
            err = DeviceError("robot connection lost (simulated [Errno 104] reset)")
            app.devices.robot = FailsFromMove(app.devices.robot, 5, err)
            await start(app, pilot)
            scr = app.views["campaign"]
            await until(pilot, lambda: app.finished, 10, "campaign end")
            assert app.finished[-1].result is None
            assert scr.state == "stopped", scr.state
            why = rows(scr)
            assert why["State"].startswith("STOPPED")
            assert why["Stopped"] == str(err)  # markup-like text shown as it is
            hint = resume_hint("run.mcap", 2)
            assert why["Recording"] == f"{hint} (on this screen: r)"
            ev = summary_event(scr)
            # the command line's line (`device_errors_say_resume`), then the recording
            assert ev["message"].startswith(f"{err}; {hint} (on this screen: r); ")
            assert "run.mcap: 2 samples, closed cleanly" in ev["message"]
            assert ("error", "Campaign stopped") == app.notices[-1][:2]

    asyncio.run(flow())
    assert len(read_recording(tmp_path / "run.mcap").samples) == 2


def test_an_operators_abort_stays_aborted_and_an_unacknowledged_stop_is_a_stop(
    tmp_path, monkeypatch
):
    """What the app shows for the results it is given: the operator's abort is ABORTED with no
    stop rows; a protective stop nobody acknowledged (the command line's `stop_reason`) is
    STOPPED with that reason and the resume hint."""
    monkeypatch.chdir(tmp_path)
    app = app_for(6)
    rec = {"path": "run.mcap", "samples": 4, "closed_cleanly": True, "repeats": []}

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await pilot.press("f3")
            scr = app.views["campaign"]
            res = CampaignResult(measured=4, aborted=True, stopped_by="operator", events=9)
            app.post_message(m.CampaignFinished("run.mcap", res, rec))
            await until(pilot, lambda: len(app.finished) == 1, 5, "abort shown")
            assert scr.state == "aborted"
            assert "Stopped" not in rows(scr)
            assert summary_event(scr)["message"].startswith("4 measured, 0 skipped, 9 events")
            assert app.notices[-1][:2] == ("warning", "Campaign aborted")
            reason = "the protective stop was not acknowledged: standard input ended"
            res = CampaignResult(
                measured=4, aborted=True, stopped_by="unacknowledged", stop_message=reason
            )
            app.post_message(m.CampaignFinished("run.mcap", res, rec))
            await until(pilot, lambda: len(app.finished) == 2, 5, "stop shown")
            assert scr.state == "stopped"
            why = rows(scr)
            assert why["Stopped"] == reason
            assert why["Recording"] == (
                f"the arm is left stopped; {resume_hint('run.mcap', 4)} (on this screen: r)"
            )

    asyncio.run(flow())
