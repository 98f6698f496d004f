"""Pilot tests of the terminal UI against the in-process simulated cell (virtual time): the whole
flow (connect, plan 10 poses, run to the end, fit dh, diagnose, export a table), abort mid-campaign
leaving a valid recording, then resuming it."""

import asyncio
import re
import threading
from pathlib import Path

import numpy as np
import pytest
from tuipilot import connect, screen_is, set_input, until

from workcell.recording.reader import read_recording
from workcell.tui import backend
from workcell.tui.app import make_app
from workcell.tui.backend import PlanConfig

SIZE = (100, 30)


async def until_confirm(app, pilot, what: str) -> None:
    """The key's confirmation screen is up. A loaded machine may need a few more event-loop
    turns than `pilot.press` waits for before the pushed screen is current."""
    await until(pilot, lambda: type(app.screen).__name__ == "ConfirmScreen", 10, f"{what} confirm")


def app_for(poses: int):
    return make_app(
        plan=PlanConfig(poses=poses, readings_per_pose=3, settle_s=0.5, out="run.mcap"),
        status_poll_s=0,
        clock=lambda: 0.0,
        online=False,
        cursor_blink=False,
    )


async def run_campaign(app, pilot, n_finished: int) -> None:
    await pilot.press("f3")
    await pilot.press("s")  # asks first
    await until_confirm(app, pilot, "start")
    await pilot.press("y")
    await until(pilot, lambda: len(app.finished) >= n_finished, 120, "campaign end")


def hold_campaign(monkeypatch, hold: dict) -> threading.Event:
    """The campaign runs in a worker thread and may outrun the event loop on a loaded machine.
    Hold the worker after its `hold["after"]`-th sample until the returned event is set, so a
    pause or abort lands mid-campaign."""
    gate = threading.Event()
    real_start = backend.start_campaign

    def held_start(dev, plan, *, on_sample, **kw):
        n = [0]

        def sample(s):
            on_sample(s)
            n[0] += 1
            if n[0] == hold["after"]:
                assert gate.wait(60), "the test never released the campaign"

        return real_start(dev, plan, on_sample=sample, **kw)

    monkeypatch.setattr(backend, "start_campaign", held_start)
    return gate


def test_whole_flow(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    app = app_for(10)

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await connect(app, pilot)
            assert app.devices.kind == "in-process simulation"
            # plan 10 poses and dry-run them
            await pilot.press("f2")
            plan = app.views["plan"]
            await set_input(pilot, plan, "poses", "10")
            await pilot.press("ctrl+r")
            await until(pilot, lambda: plan.checked is not None, 60, "dry run")
            # refusing the confirmation moves nothing
            await pilot.press("f3")
            await pilot.press("s")
            await pilot.press("n")
            assert not app.campaign_running and not (tmp_path / "run.mcap").exists()
            await run_campaign(app, pilot, 1)
            fin = app.finished[-1]
            assert fin.result.measured + fin.result.skipped == 10
            assert fin.recording["closed_cleanly"] and not fin.result.aborted
            assert app.views["campaign"].done == fin.result.measured
            # 10 poses are too few to fit 30-odd parameters: refused with a notice, no crash
            await pilot.press("f4")
            fit = app.views["fit"]
            assert fit.query_one("#recording").value == "run.mcap"
            await pilot.press("ctrl+r")
            await until(pilot, lambda: not fit.running, 120, "fit refusal")
            assert app.last_fit is None
            assert any(sev == "error" and "poses" in txt for sev, _, txt in app.notices)
            # a campaign large enough to fit and diagnose (next free recording name)
            await pilot.press("f2")
            assert plan.query_one("#out").value == "run-2.mcap"
            await set_input(pilot, plan, "poses", "44")
            await pilot.press("ctrl+r")
            await until(pilot, lambda: plan.checked and plan.checked.poses == 44, 60, "dry run")
            # what a DH fit of these poses should reach, before anything moves
            assert "expected after a DH fit of the 33 training poses" in plan.result_text
            await run_campaign(app, pilot, 2)
            assert app.finished[-1].recording["samples"] >= 40
            # fit dh
            await pilot.press("f4")
            assert fit.query_one("#recording").value == "run-2.mcap"
            await pilot.press("ctrl+r")
            await until(pilot, lambda: app.last_fit is not None, 240, "fit")
            rep = app.last_fit
            assert rep["method"] == "dh"
            assert rep["heldout_rms_m"] < 0.5 * rep["nominal_rms_m"]
            assert (tmp_path / rep["model"]).exists()
            # diagnose (quick: no non-parametric check)
            await pilot.press("f5")
            diag = app.views["diagnose"]
            await pilot.press("ctrl+r")
            await until(pilot, lambda: not diag.running, 300, "diagnosis")
            d = app.last_diagnosis
            assert d is not None, app.notices[-3:]
            assert d["summary"] and d["rms_after_m"] <= d["rms_before_m"]
            # export a table (coarse fixed spacing keeps the test short)
            await pilot.press("f6")
            ex = app.views["export"]
            assert ex.query_one("#model").value == rep["model"]
            await set_input(pilot, ex, "spacing", "0.12")
            await set_input(pilot, ex, "out", "out/correction")
            await pilot.press("ctrl+r")
            await until(pilot, lambda: not ex.running, 240, "export")
            s = app.last_export
            assert s is not None, app.notices[-3:]
            assert {p.rsplit(".", 1)[1] for p in s["files"]} == {"json", "csv"}
            for f in s["files"]:
                assert (tmp_path / f).stat().st_size > 0
            assert s["validation"]["max_interp_error_m"] > 0
            # closed loop on the connected (simulated) cell: the tracker measures both visits
            await set_input(pilot, ex, "targets", "6")
            q0 = app.devices.robot.state().q_rad
            await pilot.press("ctrl+o", "n")  # asked first: the arm moves; no, nothing moves
            await pilot.pause()
            assert not ex.validating and app.last_validation is None
            assert np.max(np.abs(app.devices.robot.state().q_rad - q0)) < 1e-4  # encoder noise
            await pilot.press("ctrl+o", "y")
            await until(pilot, lambda: not ex.validating, 240, "closed-loop check")
            v = app.last_validation
            assert v is not None, app.notices[-3:]
            assert v["truth"] == "tracker" and v["targets"] + len(v["skipped"]) == 6
            assert v["after_rms_m"] < 0.5 * v["before_rms_m"], v
            rows = dict(ex.result_rows)
            assert "Closed loop after" in rows and "x better" in rows["Closed loop after"]
            # beside the table's 1-sigma, what the model leaves out (the fit's held-out figure)
            assert rows["Not in it"].startswith("the model leaves ")
            assert "above the noise floor" in rows["Not in it"]
            assert not [n for n in app.notices if n[1] == "UI error"], app.notices

    asyncio.run(flow())


def test_abort_leaves_valid_recording_then_resume(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    app = app_for(60)
    # The campaign runs in a worker thread and may outrun the event loop on a loaded machine
    # (all 60 poses measured before the pause key is handled). Hold the worker after its third
    # sample until the pause request has landed, so the abort always lands mid-campaign.
    gate = hold_campaign(monkeypatch, {"after": 3})

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await connect(app, pilot)
            await pilot.press("f3")
            scr = app.views["campaign"]
            await pilot.press("s", "y")
            await until(pilot, lambda: scr.done >= 3, 60, "3 poses")
            await pilot.press("p")  # pause between poses, then abort with confirmation
            await until(pilot, lambda: scr.state == "paused", 10, "pause")
            gate.set()
            await pilot.press("a")
            await until_confirm(app, pilot, "abort")
            await pilot.press("y")
            await until(pilot, lambda: app.finished, 60, "abort")
            fin = app.finished[-1]
            assert fin.result.aborted
            rec = read_recording(tmp_path / "run.mcap")
            assert rec.closed_cleanly and not rec.problems
            done = {s["pose_id"] for s in rec.samples}
            assert 3 <= len(done) < 60
            assert any(e["kind"] == "abort" for e in rec.events)
            assert scr.state == "aborted"
            # resume the interrupted recording into a chained file: the prompt offers it (it
            # offered the Plan screen's next free name, run-2.mcap, and accepting that failed)
            await pilot.press("r")
            await until(pilot, lambda: screen_is(app, "PathPrompt"), 10, "resume prompt")
            assert app.screen.query_one("#path").value == "run.mcap"
            await pilot.press("enter")
            await pilot.press("y")
            await until(pilot, lambda: len(app.finished) >= 2, 60, "resume")
            fin2 = app.finished[-1]
            assert fin2.result is not None and not fin2.result.aborted, app.notices[-3:]
            rec2 = read_recording(fin2.path)
            assert rec2.session["chained_from"]["samples"] == len(rec.samples)
            more = {s["pose_id"] for s in rec2.samples}
            assert not done & more
            skipped = fin.result.skipped + fin2.result.skipped
            assert len(done | more) + skipped == 60

    asyncio.run(flow())


@pytest.mark.parametrize("bad", ["-3", "x"])
def test_bad_plan_input_is_a_notice_not_a_crash(tmp_path, monkeypatch, bad):
    monkeypatch.chdir(tmp_path)
    app = app_for(10)

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await pilot.press("f2")
            plan = app.views["plan"]
            plan.show_result("dry run OK: 10 poses inside the envelope")  # an earlier check's
            await set_input(pilot, plan, "poses", bad)
            await pilot.press("ctrl+r")
            await pilot.pause()
            assert app.notices and app.notices[-1][0] == "error"
            # the refusal replaces it (it stayed on screen under the notice: TUI audit)
            assert plan.result_text.startswith("[red]not checked[/red]: "), plan.result_text
            # starting a campaign without devices is refused
            await pilot.press("f3", "s")
            assert app.notices[-1][0] == "error" and not app.campaign_running

    asyncio.run(flow())


def test_the_plan_screen_previews_a_design_plan(tmp_path, monkeypatch):
    """A dry run of vopt on the Plan screen shows the poses the design would choose at the
    nominal chain: checked, with what a fit of them should reach."""
    from textual.widgets import Select

    monkeypatch.chdir(tmp_path)
    app = app_for(20)

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await connect(app, pilot)
            await pilot.press("f2")
            plan = app.views["plan"]
            plan.query_one("#kind", Select).value = "vopt"
            await set_input(pilot, plan, "poses", "20")
            await pilot.press("ctrl+r")
            await until(pilot, lambda: plan.checked is not None, 60, "dry run")
            assert plan.checked.kind == "vopt"
            text = plan.result_text
            assert "preview: the poses vopt chooses if the arm is its nominal chain" in text
            assert "expected after a DH fit of the 15 training poses" in text

    asyncio.run(flow())


def test_online_ekf_ann_estimate_reaches_the_campaign_view(tmp_path, monkeypatch):
    """With the online estimate on (the production default), the EKF-ANN filter runs in its own
    thread during a campaign: once it has initialised (30 samples) its innovation RMS reaches
    the campaign screen's plot series (beside the nominal residual) and its info line (the
    plumbing; the estimate's quality is tested in tests/test_ekf_ann_live.py)."""
    monkeypatch.chdir(tmp_path)
    app = make_app(
        plan=PlanConfig(poses=40, readings_per_pose=3, settle_s=0.5, out="run.mcap"),
        status_poll_s=0,
        clock=lambda: 0.0,
        online=True,
        cursor_blink=False,
    )

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await connect(app, pilot)
            await run_campaign(app, pilot, 1)
            view = app.views["campaign"]
            assert view.ekf_note == ""  # available, not "EKF-ANN unavailable"/"off"
            n = len(view.rms_um)
            assert n == app.finished[-1].result.measured
            # the estimator's thread finishes after the campaign: wait for its last result
            await until(pilot, lambda: view.ekf_um[-1] is not None, 240, "EKF-ANN")
            idx = [k for k, x in enumerate(view.ekf_um) if x is not None]
            assert idx[0] >= 30  # none before the first prediction after the 30 used to initialise
            assert idx == list(range(idx[0], n))  # then one estimate per pose
            ekf = [view.ekf_um[k] for k in idx]
            assert all(np.isfinite(x) and x >= 0.0 for x in ekf) and max(ekf) > 0.0
            view.render_view()
            info = str(view.query_one("#info").rows)
            assert f"EKF-ANN innovation RMS {ekf[-1]:.1f} um" in info, info

    asyncio.run(flow())


def fit_table_rows(rep: dict) -> dict[str, list[str]]:
    """The Fit screen's table for a fit report: {row label: [the other cells]}."""
    from textual.widgets import DataTable

    app = app_for(10)
    rows: dict[str, list[str]] = {}

    async def flow():
        async with app.run_test(size=(120, 40)) as pilot:
            await pilot.press("f4")
            fit = app.views["fit"]
            fit.show_report(rep)
            await pilot.pause()
            t = fit.query_one("#table", DataTable)
            for i in range(t.row_count):
                row = t.get_row_at(i)
                rows[str(row[0])] = [str(c) for c in row[1:]]

    asyncio.run(flow())
    return rows


REAL_D = Path(__file__).resolve().parents[2] / "shared/data/ur10-leica/series_D_iso_cubes.mcap"


@pytest.mark.skipif(not REAL_D.exists(), reason="shared real data not present")
def test_the_fit_screen_names_weakly_identified_parameters(tmp_path, monkeypatch):
    """The real iso-cube series barely separates base_ty from the SMR's tool_z: the Fit screen's
    table says so, with the std inflation."""
    monkeypatch.chdir(tmp_path)
    rep = backend.fit(REAL_D, "dh", model_out=tmp_path / "d.json")
    rows = fit_table_rows(rep)
    assert "weakly identified" in rows, rows
    assert rows["weakly identified"][0] == "1 group"
    assert rows["weakly identified"][1].startswith("base_ty/tool_z (std ")


def test_the_fit_screen_names_heldout_outliers(tmp_path, monkeypatch):
    """A fit report with a held-out outlier (a planted 0.46 mm reading) shows it on the Fit
    screen, with the held-out RMS without it."""
    from sim_devices.cell import sim_cell
    from workcell.campaign.executor import CampaignConfig
    from workcell.campaign.run import run_campaign
    from workcell.estimation.fitting import fit_dataset
    from workcell.recording.dataset import Dataset

    monkeypatch.chdir(tmp_path)
    _, robot, tracker, cell = sim_cell("ur5e", "none", 1, beam_break_prob=0.0, outlier_prob=0.0)
    cfg = CampaignConfig(readings_per_pose=2, settle_s=0.2)
    run_campaign(robot, tracker, cell, tmp_path / "c.mcap", poses=60, seed=1, config=cfg)
    ds = Dataset.from_recording(tmp_path / "c.mcap")
    k = int(ds.holdout_split(0.25)[1][0])
    ds.p_tracker = ds.p_tracker.copy()
    ds.p_tracker[k] += np.array([0.0004, -0.0001, 0.0002])
    _, rep = fit_dataset(ds, method="dh")
    assert rep["heldout_outliers"] is not None
    rows = fit_table_rows(rep)
    assert re.fullmatch(r"1 \(max 4\d\d\.\d um\)", rows["held-out outliers"][0]), rows
    assert rows["held-out outliers"][1].startswith("without: ")


@pytest.mark.slow  # 11 s; the command line path of --reference-every is in make test
def test_reference_pose_from_the_plan_screen_and_kept_by_a_resume(tmp_path, monkeypatch):
    """`Ref. every` on the Plan screen: the dry run says how many more measurements, the
    campaign measures the first pose again (each repeat in the event log with its displacement),
    the progress counts the repeats. A resume of it, with the Plan screen back at 0, keeps the
    recorded interval as the command line does."""
    monkeypatch.chdir(tmp_path)
    app = app_for(10)
    hold = {"after": None}  # hold the second campaign's worker after this many samples
    gate = hold_campaign(monkeypatch, hold)

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await connect(app, pilot)
            await pilot.press("f2")
            plan = app.views["plan"]
            await set_input(pilot, plan, "ref-every", "4")
            await pilot.press("ctrl+r")
            await until(pilot, lambda: plan.checked is not None, 60, "dry run")
            assert (
                "reference: pose 0 measured again after every 4 poses and at the end (3 more"
                in (plan.result_text)
            )
            await run_campaign(app, pilot, 1)
            scr = app.views["campaign"]
            assert scr.state == "finished", app.notices[-3:]
            assert (scr.done, scr.total, scr.references) == (13, 13, 3)
            rec = read_recording(tmp_path / "run.mcap")
            assert rec.session["campaign"]["reference_every"] == 4
            ids = [s["pose_id"] for s in rec.samples]
            assert ids.count(0) == 4 and len(set(ids)) == 10
            refs = [e for e in scr.events if e.get("kind") == "reference"]
            *refs, whole = refs  # each repeat as it came, then the recording's summary
            assert len(refs) == 3 and whole["message"].startswith("pose 0 measured 4 times over")
            first = np.array(rec.samples[0]["tracker_position_m"])
            for e, s in zip(refs, [s for s in rec.samples[1:] if s["pose_id"] == 0], strict=True):
                d_um = np.linalg.norm(np.array(s["tracker_position_m"]) - first) * 1e6
                assert f"{d_um:.1f} um from its first reading" in e["message"]

            # a second campaign with a reference every 3 poses, aborted, then resumed with the
            # Plan screen's interval back at 0: the resume keeps the recorded 3
            await pilot.press("f2")
            await set_input(pilot, plan, "poses", "20")
            await set_input(pilot, plan, "ref-every", "3")
            await set_input(pilot, plan, "out", "ref.mcap")
            await pilot.press("ctrl+r")
            await until(pilot, lambda: plan.checked and plan.checked.poses == 20, 60, "dry run")
            hold["after"] = 5  # 4 poses and the reference's first repeat
            await pilot.press("f3", "s")
            await until_confirm(app, pilot, "start")
            await pilot.press("y")
            await until(pilot, lambda: scr.done >= 5 and scr.state == "running", 60, "5 samples")
            await pilot.press("p")
            await until(pilot, lambda: scr.state == "paused", 10, "pause")
            gate.set()
            await pilot.press("a")
            await until_confirm(app, pilot, "abort")
            await pilot.press("y")
            await until(pilot, lambda: len(app.finished) >= 2, 60, "abort")
            assert app.finished[-1].result.aborted
            old = read_recording(tmp_path / "ref.mcap")
            done = {s["pose_id"] for s in old.samples}
            await pilot.press("f2")
            await set_input(pilot, plan, "ref-every", "0")
            await pilot.press("ctrl+r")
            await until(pilot, lambda: plan.checked and plan.checked.reference_every == 0, 60, "")
            await pilot.press("f3", "r", "ctrl+u")
            for ch in "ref.mcap":
                await pilot.press(ch)
            await pilot.press("enter")
            await until_confirm(app, pilot, "resume")
            await pilot.press("y")
            await until(pilot, lambda: len(app.finished) >= 3, 60, "resume")
            fin = app.finished[-1]
            assert fin.result is not None and not fin.result.aborted, app.notices[-3:]
            new = read_recording(fin.path)
            assert new.session["campaign"]["reference_every"] == 3
            left = 20 - len(done) - app.finished[-2].result.skipped
            ids = [s["pose_id"] for s in new.samples]
            assert ids.count(0) == left // 3 + (left % 3 > 0)  # the reference, measured again
            assert scr.total == left + ids.count(0) and scr.references == ids.count(0)
            assert not (set(ids) - {0}) & done
            # the repeats are compared with pose 0's first reading, in the old file
            first = np.array(old.samples[0]["tracker_position_m"])
            s = next(s for s in new.samples if s["pose_id"] == 0)
            d_um = np.linalg.norm(np.array(s["tracker_position_m"]) - first) * 1e6
            assert any(f"{d_um:.1f} um from" in e["message"] for e in scr.events)

    asyncio.run(flow())


def test_a_recording_read_in_part_is_said_on_the_fit_and_diagnose_screens(tmp_path, monkeypatch):
    """A recording cut short (a crash while writing) is fitted and diagnosed on the samples
    that could be read, as on the command line, and the UI says so with a warning notice
    (before, it fitted the readable part without a word)."""
    from sim_devices.cell import sim_cell
    from workcell.campaign.executor import CampaignConfig
    from workcell.campaign.run import run_campaign as run_engine

    monkeypatch.chdir(tmp_path)
    _, robot, tracker, cell = sim_cell("ur5e", "none", 3)
    cfg = CampaignConfig(readings_per_pose=2, settle_s=0.2)
    run_engine(robot, tracker, cell, tmp_path / "whole.mcap", poses=60, seed=3, config=cfg)
    data = (tmp_path / "whole.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: int(0.85 * len(data))])
    n = len(read_recording(tmp_path / "cut.mcap").samples)
    assert 40 <= n < 60
    app = app_for(10)

    async def flow():
        async with app.run_test(size=SIZE) as pilot:
            await pilot.press("f4")
            fit = app.views["fit"]
            await set_input(pilot, fit, "recording", "cut.mcap")
            await pilot.press("ctrl+r")
            await until(pilot, lambda: app.last_fit is not None, 240, "fit")
            assert app.last_fit["recording_problems"]
            said = [txt for sev, _, txt in app.notices if sev == "warning"]
            assert any(f"using the {n} samples that could be read" in t for t in said), said
            await pilot.press("f5")
            diag = app.views["diagnose"]
            await set_input(pilot, diag, "recording", "cut.mcap")
            k = len(said)
            await pilot.press("ctrl+r")
            await until(pilot, lambda: app.last_diagnosis is not None, 300, "diagnosis")
            said = [txt for sev, _, txt in app.notices if sev == "warning"][k:]
            assert any(f"using the {n} samples that could be read" in t for t in said), said

    asyncio.run(flow())


@pytest.mark.parametrize(
    ("change", "said"),
    [
        ({"poses": 100_001}, "limit 100000"),
        ({"seed": -1}, "seed must be >= 0"),
        ({"reference_every": -2}, "reference interval must be a number of poses"),
        ({"out": "/proc/workcell-test/run.mcap"}, "/proc/workcell-test"),
    ],
)
def test_a_plan_the_command_line_refuses_is_refused_by_the_ui(tmp_path, monkeypatch, change, said):
    """The Plan screen's limits are the command line's (pose count, seed, reference interval),
    and a recording path that cannot be written is refused before anything moves."""
    from workcell.campaign.executor import CampaignControl
    from workcell.errors import UserError

    monkeypatch.chdir(tmp_path)
    plan = PlanConfig(
        **{"poses": 4, "readings_per_pose": 2, "settle_s": 0.2, "out": "run.mcap", **change}
    )
    dev = backend.open_devices(backend.DeviceConfig(effects="none"))
    moved = []
    try:
        with pytest.raises(UserError, match=re.escape(said)):
            backend.start_campaign(
                dev, plan, control=CampaignControl(), on_sample=moved.append,
                on_event=lambda e: None,
            )  # fmt: skip
    finally:
        dev.close()
    assert not moved and not (tmp_path / "run.mcap").exists()
