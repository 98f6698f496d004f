"""The terminal UI says what the command line says (audit of the TUI's reports): a fit with no
pose held out is labelled as on the training poses; a campaign that recorded no pose is a stop;
the Export screen states the base-correction caveat (and, for ROS YAML, what the model leaves
out); the Diagnose screen runs the non-parametric residual check by default and says so when it
is skipped; the nominal RMS and the closed-loop "before" RMS carry their 95 % interval; after a
run the app's devices stay connected, so the status still shows the robot's safety state.

In-process simulated cell (virtual time) and one 44-pose recording for the module; the
protective-stop case runs on the protocol simulators."""

import asyncio
import shutil
from pathlib import Path

import pytest
from rich.text import Text
from textual.widgets import Checkbox, DataTable, Select, Static
from tuipilot import device_status, until

from workcell.estimation.models import interval_um
from workcell.tui import backend
from workcell.tui import messages as m
from workcell.tui.app import make_app
from workcell.tui.backend import PlanConfig

SIZE = (120, 40)
NO_HOLDOUT = "no hold-out: numbers are on the training poses"  # `workcell fit`'s words


def app_for(poses: int = 2, **kw):
    return make_app(
        plan=PlanConfig(poses=poses, readings_per_pose=2, settle_s=0.2, out="run.mcap"),
        effects="none",
        status_poll_s=0,
        clock=lambda: 0.0,
        online=False,
        cursor_blink=False,
        **kw,
    )


def plain(markup: str) -> str:
    return Text.from_markup(markup).plain


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """A 44-pose recording of the simulated cell (realistic effects), and its dh model."""
    from sim_devices.cell import sim_cell
    from workcell.campaign.executor import CampaignConfig
    from workcell.campaign.run import run_campaign

    d = tmp_path_factory.mktemp("tui_reports")
    _, robot, tracker, cell = sim_cell("ur5e", "realistic", 1)
    cfg = CampaignConfig(readings_per_pose=2, settle_s=0.2)
    run_campaign(robot, tracker, cell, d / "c.mcap", poses=44, seed=1, config=cfg)
    backend.fit(d / "c.mcap", "dh", model_out=d / "c.dh.model.json")
    return d / "c.mcap"


@pytest.fixture
def here(tmp_path, monkeypatch, recording):
    """The recording and its model copied into the test's folder, the working directory."""
    monkeypatch.chdir(tmp_path)
    shutil.copy(recording, tmp_path / "c.mcap")
    shutil.copy(recording.with_name("c.dh.model.json"), tmp_path / "m.json")
    return tmp_path


# --------------------------------------------------------------------------- A: hold-out 0
def test_a_fit_with_nothing_held_out_is_labelled_on_the_training_poses(here):
    """Held-out fraction 0: `workcell fit` says "train RMS ... no hold-out: numbers are on the
    training poses"; the Fit screen's column, status, plot and notice said "held-out RMS"."""
    app = app_for()

    async def fit(pilot, hold: str) -> dict:
        view = app.views["fit"]
        view.query_one("#recording").value = "c.mcap"
        view.query_one("#hold").value = hold
        await pilot.pause()
        n = len(app.notices)
        await pilot.press("ctrl+r")
        await until(pilot, lambda: not view.running and len(app.notices) > n, 60, "fit")
        t = view.query_one("#table", DataTable)
        return {
            "columns": [str(c.label) for c in t.columns.values()],
            "rows": [[str(x) for x in t.get_row(k)] for k in t.rows],
            "status": view.status,
            "notice": app.notices[-1],
            "plot": view.query_one("#plot").title,
        }

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await pilot.press("f4")
            return await fit(pilot, "0"), await fit(pilot, "0.25")

    none, held = asyncio.run(flow())
    assert none["columns"][1] == "train RMS", none
    assert none["status"].startswith("dh: train RMS ") and NO_HOLDOUT in none["status"], none
    assert none["notice"][1] == "Fit done" and none["notice"][2].startswith("dh: train RMS ")
    assert NO_HOLDOUT in none["notice"][2]
    assert "held-out" not in none["plot"] and "training" in none["plot"]
    assert not any("held-out" in " ".join(r) for r in none["rows"]), none["rows"]
    # with poses held out, the labels are the held-out ones
    assert held["columns"][1] == "held-out RMS"
    assert held["status"].startswith("dh: held-out RMS ") and NO_HOLDOUT not in held["status"]
    assert held["notice"][2].startswith("dh: held-out RMS ")
    assert held["plot"].startswith("held-out")


# --------------------------------------------------------------------------- B: no pose recorded
def test_a_campaign_that_recorded_no_pose_is_a_stop_in_the_command_lines_words(
    tmp_path, monkeypatch
):
    """Every pose skipped: `workcell campaign` ends with "no pose recorded ..." (exit 3); the
    app showed "Campaign finished" with an information notice."""
    from workcell.campaign.executor import CampaignResult
    from workcell.campaign.run import campaign_stop
    from workcell.errors import UserError

    monkeypatch.chdir(tmp_path)
    res = CampaignResult(measured=0, skipped=2, aborted=False, events=15)
    with pytest.raises(UserError) as cli:
        campaign_stop(res, "run.mcap")
    assert cli.value.exit_code == 3
    why = "no pose recorded: all 2 poses were skipped (the events above say why)"
    assert str(cli.value).startswith(f"{why}; run.mcap is closed and keeps the events")

    app = app_for()
    rec = {"path": "run.mcap", "samples": 0, "closed_cleanly": True, "repeats": []}

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await pilot.press("f3")
            app.post_message(m.CampaignFinished("run.mcap", res, rec))
            await until(pilot, lambda: app.finished, 5, "finish shown")
            return app.views["campaign"].state

    assert asyncio.run(flow()) == "stopped"
    sev, title, text = app.notices[-1]
    assert (sev, title) == ("error", "Campaign stopped"), app.notices[-1]
    assert text.startswith(why + "; run.mcap is closed and keeps the events"), text
    # the command line's line and the app's are the same function's two halves
    from workcell.campaign.run import nothing_recorded

    assert "; ".join(nothing_recorded(res, "run.mcap")) == str(cli.value)


async def export_on_screen(app, pilot, out: str, fmt: str = "table") -> dict[str, str]:
    """Export m.json from the Export screen (0.12 m spacing) to `out`; its result rows, plain."""
    view = app.views["export"]
    view.query_one("#model").value = "m.json"
    view.query_one("#format", Select).value = fmt
    view.query_one("#out").value = out
    view.query_one("#spacing").value = "0.12"
    await pilot.pause()
    n = len(app.notices)
    await pilot.press("ctrl+r")
    await until(pilot, lambda: not view.running and len(app.notices) > n, 60, "export")
    return {k: plain(v) for k, v in view.result_rows}


# --------------------------------------------------------------------------- C: base correction
def test_the_export_screen_states_the_base_correction_as_the_command_line(here):
    """`workcell export` prints "base correction: targets expressed in another estimate of the
    robot base ... express targets in base_ref" for a table and for ROS YAML; the Export screen
    never showed it, and for ROS YAML showed only the format and the file."""
    from workcell.export.frame import frame_lines
    from workcell.export.table import load_table

    app = app_for()

    async def export(pilot, fmt: str, out: str) -> dict[str, str]:
        return await export_on_screen(app, pilot, out, fmt)

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await pilot.press("f6")
            return await export(pilot, "table", "corr"), await export(pilot, "ros-yaml", "k.yaml")

    table, ros = asyncio.run(flow())
    cli = frame_lines(load_table(here / "corr.json").meta, "the table's nodes")[2]
    assert cli.startswith("base correction: ") and cli.endswith("express targets in base_ref")
    assert table["Frame"] == cli, table
    yaml_lines = [ln.lstrip("# ").strip() for ln in (here / "k.yaml").read_text().splitlines()]
    assert ros["Frame"].startswith("base correction: ") and ros["Frame"] in yaml_lines, ros
    assert "Not in it" in ros and "above the noise floor" in ros["Not in it"], ros


def test_the_export_notice_names_the_folder_and_a_new_one(here):
    """The Export screen's notice and rows named the files only: an export to a folder that did
    not exist made it without a word, and the operator could not tell where the files were."""
    app = app_for()

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await pilot.press("f6")
            rows = []
            for out in ("cell7/today/corr", "cell7/today/corr2"):
                rows.append((await export_on_screen(app, pilot, out), app.notices[-1][2]))
            return rows

    (first, note1), (second, note2) = asyncio.run(flow())
    where = "cell7/today"
    assert (here / "cell7/today/corr.json").is_file()
    assert note1 == f"wrote corr.json, corr.csv in {where}, a new folder", note1
    assert first["Folder"] == f"{where}, a new folder", first
    assert note2 == f"wrote corr2.json, corr2.csv in {where}", note2
    assert second["Folder"] == where, second


# --------------------------------------------------------------------------- D: diagnose
def test_diagnose_runs_the_residual_check_by_default_and_says_when_it_was_skipped(
    here, monkeypatch
):
    """`workcell diagnose` runs the non-parametric residual check (its summary ends with "What
    is not explained ..."); the Diagnose screen's default "quick" dropped it without a word. Now
    quick is off by default, and a quick diagnosis says the check was skipped and how to run it."""
    asked = []
    real = backend.diagnose

    def fake(recording, *, quick=False, progress=None):
        asked.append(quick)
        return {"summary": "stub", "effects": [], "steps": []}

    monkeypatch.setattr(backend, "diagnose", fake)
    app = app_for()

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await pilot.press("f5")
            view = app.views["diagnose"]
            assert view.query_one("#quick", Checkbox).value is False
            view.query_one("#recording").value = "c.mcap"
            await pilot.pause()
            await pilot.press("ctrl+r")
            await until(pilot, lambda: asked and not view.running, 10, "diagnosis")
            view.show_report(real("c.mcap", quick=True))
            await pilot.pause()
            return str(view.query_one("#summary", Static).render()), view.status

    summary, status = asyncio.run(flow())
    assert asked == [False]  # the command line's diagnosis
    assert "non-parametric residual check was skipped" in summary, summary[-400:]
    assert "What is not explained: " in summary and "workcell diagnose" in summary
    assert "non-parametric residual check skipped" in status


# --------------------------------------------------------------------------- E: intervals
def test_the_nominal_rms_and_the_closed_loop_before_rms_carry_their_interval(here):
    """`workcell fit` gives the nominal RMS's 95 % interval, `workcell validate` both rows'; the
    Fit screen's nominal row and the Export screen's "before" row had none."""
    rep = backend.fit("c.mcap", "dh", model_out="again.json")
    nci = interval_um(rep["nominal_rms_ci95_m"], label=False)
    assert nci
    check = {
        "targets": 19,
        "truth": "tracker",
        "before": {"rms_m": 412.3e-6, "max_m": 590.1e-6, "rms_ci95_m": [380.2e-6, 450.9e-6]},
        "after": {"rms_m": 11.8e-6, "max_m": 19.6e-6, "rms_ci95_m": [10.4e-6, 13.5e-6]},
        "improvement": 34.9,
    }
    app = app_for()

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await pilot.press("f4")
            fit = app.views["fit"]
            fit.show_report(rep)
            await pilot.pause()
            t = fit.query_one("#table", DataTable)
            rows = [[str(x) for x in t.get_row(k)] for k in t.rows]
            await pilot.press("f6")
            ex = app.views["export"]
            ex.show_validation(check)
            await pilot.pause()
            return rows, dict(ex.result_rows)

    rows, export_rows = asyncio.run(flow())
    names = [r[0] for r in rows]
    k = names.index("nominal (base registered)")
    assert rows[k + 1][:2] == ["  95 % CI of its RMS", nci], rows
    assert export_rows["Closed loop before"] == (
        "RMS 412.3 um (95 % CI 380.2-450.9 um), max 590.1 um"
    ), export_rows


# --------------------------------------------------------------------------- F: after a run
def test_the_devices_stay_connected_after_a_campaign(tmp_path, monkeypatch):
    """A run closes the devices it is given (as the command line's process ends); the app went
    on treating them as connected: the tracker showed "disconnected" (and a UR controller
    UNREACHABLE every poll). Now the app's devices stay open until it disconnects them."""
    monkeypatch.chdir(tmp_path)
    app = app_for()

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await pilot.press("ctrl+r")
            await until(pilot, lambda: app.devices is not None, 30, "connect")
            await pilot.press("f3", "s")
            await until(pilot, lambda: type(app.screen).__name__ == "ConfirmScreen", 10, "ask")
            await pilot.press("y")
            await until(pilot, lambda: app.finished, 60, "campaign end")
            return await device_status(app, pilot, 10)

    status = asyncio.run(flow())
    assert app.finished[-1].result.measured == 2, app.notices
    assert status["robot_ok"] and status["robot_mode"] != "UNREACHABLE", status
    assert status["tracker_status"] == "connected", status
    assert not [n for n in app.notices if n[1] == "Devices" and n[0] != "information"]


def test_held_devices_close_for_good_only_when_the_app_closes_them():
    """`backend.Held`: a run's close() leaves the driver open and its next connect() starts
    from a closed driver (as before); Devices.close() closes it, through a test wrapper too."""
    calls = []

    class Driver:
        def connect(self):
            calls.append("connect")

        def close(self):
            calls.append("close")

    class Wrapper:  # as the fault tests wrap an app's device
        def __init__(self, inner):
            self.inner = inner

        def __getattr__(self, name):
            return getattr(self.inner, name)

    d = backend.Held(Driver())
    d.flag = 1  # a run's attributes (the executor's abort flag) go to the driver
    assert d._device.flag == 1
    d.close()
    assert calls == []
    d.connect()
    assert calls == ["close", "connect"]
    d.connect()
    assert calls == ["close", "connect", "connect"]
    backend._release(Wrapper(d))
    assert calls[-1] == "close"


def test_a_protective_stop_stays_visible_after_the_run_on_a_ur_controller(tmp_path, monkeypatch):
    """On the protocol simulators (UR controller over RTDE): a campaign aborted in a protective
    stop; afterwards the Devices status shows PROTECTIVE_STOP, not UNREACHABLE ("not connected;
    call connect()") at every poll."""
    monkeypatch.chdir(tmp_path)
    app = make_app(
        sim=True,
        sim_host="127.0.0.74",
        seed=3,
        time_scale=20.0,
        sim_faults={"protective_stop_at_move": [4]},
        plan=PlanConfig(poses=4, readings_per_pose=2, settle_s=0.3, seed=3, out="ps.mcap"),
        status_poll_s=0,
        clock=lambda: 0.0,
        online=False,
        cursor_blink=False,
    )

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            try:
                await until(pilot, lambda: app.devices is not None, 90, "--sim start + connect")
                await pilot.press("f3", "s")
                await until(pilot, lambda: type(app.screen).__name__ == "ConfirmScreen", 10, "ask")
                await pilot.press("y")
                await until(pilot, lambda: app.control and app.control.waiting_for_resume.is_set(),
                            120, "protective stop")  # fmt: skip
                app.post_message(m.AbortRequested())
                await until(pilot, lambda: app.finished, 60, "campaign end")
                return await device_status(app, pilot, 20)
            finally:
                if app.devices is not None:
                    app.devices.close()

    status = asyncio.run(flow())
    assert status["robot_ok"], status
    assert status["safety"] == "PROTECTIVE_STOP", status
    assert status["tracker_status"] == "connected", status


def test_an_unreachable_robot_is_said_when_it_changes_not_at_every_poll(tmp_path, monkeypatch):
    """The status poll (every 2 s) notified "robot unreachable" at every poll while the robot
    stayed unreachable. Now once per change: unreachable (again only if the error changes),
    then "reachable again"."""
    monkeypatch.chdir(tmp_path)
    app = app_for()
    down = {"robot_ok": False, "robot_error": "connection refused", "robot_mode": "UNREACHABLE"}
    up = {"robot_ok": True, "robot_mode": "RUNNING"}

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await pilot.press("ctrl+r")
            await until(pilot, lambda: app.devices is not None, 30, "connect")
            for st in (down, down, down, up, up, down):
                app.post_message(m.DeviceStatus(dict(st)))
                await pilot.pause(0.05)
            await pilot.pause(0.2)

    asyncio.run(flow())
    said = [n[2] for n in app.notices if n[1] == "Devices" and "reach" in n[2]]
    assert said == [
        "robot unreachable: connection refused",
        "robot reachable again",
        "robot unreachable: connection refused",
    ], said


def test_campaign_finished_keeps_textuals_stop():
    """The message's stop report has its own name: as `stop` it hid Textual's `Message.stop()`,
    which bubbling calls ("'dict' object is not callable"; found by a type check)."""
    msg = m.CampaignFinished("x.mcap", None, {}, {"reason": "r", "recording": "kept"})
    assert msg.stop_report == {"reason": "r", "recording": "kept"}
    assert msg.stop() is msg and msg._stop_propagation


@pytest.mark.parametrize("size", [(80, 24), (200, 60)])
def test_the_diagnose_tables_held_out_gain_is_on_screen(size):
    """The held-out gain and its interval (with a NOT confirmed flag) were the last column of a
    table 78 columns wide holding 103: off-screen at 80x24 and at 200x60 (TUI audit)."""
    ev_in = {"heldout_gain_m": 4.1e-5, "heldout_gain_ci95_m": [2.2e-5, 6.3e-5]}
    ev_out = {"heldout_gain_m": 2e-6, "heldout_gain_ci95_m": [-1e-6, 5e-6],
              "heldout_confirms": False}  # fmt: skip
    rep = {
        "summary": "two effects",
        "effects": [
            {
                "key": "c2",
                "description": "joint 2 compliance under gravity torque",
                "joint": 2,
                "explained_fraction": 0.61,
                "evidence": ev_in,
            },
            {
                "key": "h3",
                "description": "joint 3 transmission error, 1st harmonic",
                "joint": 3,
                "explained_fraction": 0.05,
                "evidence": ev_out,
            },
        ],  # fmt: skip
        "steps": [{"after": "c2", "heldout_rms_m": 4e-5}, {"after": "h3", "heldout_rms_m": 3.9e-5}],
        "rms_before_m": 8.2e-5,
        "rms_after_m": 3.9e-5,
        "noise_floor_m": 2e-5,
    }
    app = app_for(2)

    async def flow():
        async with app.run_test(size=size) as pilot:
            await pilot.press("f5")
            view = app.views["diagnose"]
            view.show_report(rep)
            await pilot.pause()
            t = view.query_one("#effects", DataTable)
            labels = [str(c.label) for c in t.columns.values()]
            k = labels.index("held-out gain um (95 %)")
            # where the gain column ends on the screen (each cell padded by 1 on each side)
            right = t.region.x + sum(
                c.get_render_width(t) for c in list(t.columns.values())[: k + 1]
            )
            cells = [str(t.get_row(r)[k]) for r in t.rows]
            return right, t.region, cells

    right, region, cells = asyncio.run(flow())
    assert right <= region.x + region.width, (right, region)
    assert "41 (22..63)" in cells and "2.0 (-1.0..5.0) NOT confirmed" in cells, cells


def test_the_ctrl_c_hint_is_plain_text():
    """Textual's own Ctrl-C hint went through the app's plain-text notices and showed its
    markup: "Press [b]ctrl+q[/b] to quit the app" (TUI audit)."""
    app = app_for(2)

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await pilot.press("f3")  # no input focused: ctrl+c is not a copy there
            await pilot.press("ctrl+c")
            await pilot.pause()

    asyncio.run(flow())
    hints = [n for n in app.notices if n[1] == "Do you want to quit?"]
    assert hints and hints[-1][2] == "Press ctrl+q to quit the app", app.notices
