"""Snapshot tests of every screen of the terminal UI at 80x24 and 120x40, grouped by screen.

Deterministic: the in-process simulated cell with fixed seeds (virtual time), a fixed clock for
the ETA, relative paths (tests run in a temporary directory), no toasts at capture time. The fit,
diagnosis and export results are computed once per module by the same backend calls the screens
use, then shown on the screen. Update after an intended change with
`pytest tests/test_tui_snapshots.py --snapshot-update` and review the SVGs."""

import pytest
from tuipilot import connect, until

from workcell.tui import backend
from workcell.tui.app import make_app
from workcell.tui.backend import PlanConfig

SIZES = [pytest.param((80, 24), id="80x24"), pytest.param((120, 40), id="120x40")]


def new_app():
    return make_app(
        plan=PlanConfig(poses=10, readings_per_pose=3, settle_s=0.5, out="campaign.mcap"),
        status_poll_s=0,
        clock=lambda: 0.0,
        online=False,
        cursor_blink=False,
    )


async def settle(pilot) -> None:
    pilot.app.clear_notifications()
    await pilot.pause(0.1)
    # a RichLog scrolls to its last line after the refresh that follows a write; do it now,
    # else the capture can catch the event log one scroll step behind (seen once in a full run)
    from textual.widgets import RichLog

    for log in pilot.app.screen.query(RichLog):
        if log.auto_scroll:
            log.scroll_end(animate=False, immediate=True)
    await pilot.pause(0.05)


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """A 44-pose recording of the simulated cell, its dh fit, diagnosis and exported table."""
    import os

    d = tmp_path_factory.mktemp("tui_snap")
    cwd = os.getcwd()
    os.chdir(d)
    try:
        dev = backend.open_devices(backend.DeviceConfig(seed=1))
        from workcell.campaign.executor import CampaignControl

        plan = PlanConfig(poses=44, readings_per_pose=3, settle_s=0.5, seed=1, out="big.mcap")
        backend.start_campaign(
            dev,
            plan,
            control=CampaignControl(),
            on_sample=lambda s: None,
            on_event=lambda e: None,
        )
        fit = backend.fit("big.mcap", "dh")
        diag = backend.diagnose("big.mcap", quick=True)
        exp = backend.export(
            backend.ExportConfig(model=fit["model"], out="correction", spacing_m=0.12)
        )
    finally:
        os.chdir(cwd)
    return {"fit": fit, "diagnose": diag, "export": exp}


@pytest.fixture
def in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


class TestDevicesScreen:
    @pytest.mark.parametrize("size", SIZES)
    def test_disconnected(self, snap_compare, in_tmp, size):
        assert snap_compare(new_app(), terminal_size=size, run_before=settle)

    @pytest.mark.parametrize("size", SIZES)
    def test_connected(self, snap_compare, in_tmp, size):
        async def run_before(pilot):
            await connect(pilot.app, pilot)
            await settle(pilot)

        assert snap_compare(new_app(), terminal_size=size, run_before=run_before)


class TestPlanScreen:
    @pytest.mark.parametrize("size", SIZES)
    def test_dry_run_ok(self, snap_compare, in_tmp, size):
        async def run_before(pilot):
            await connect(pilot.app, pilot)
            await pilot.press("f2", "ctrl+r")
            await until(pilot, lambda: pilot.app.views["plan"].checked is not None)
            await settle(pilot)

        assert snap_compare(new_app(), terminal_size=size, run_before=run_before)


class TestCampaignScreen:
    @pytest.mark.parametrize("size", SIZES)
    def test_confirmation(self, snap_compare, in_tmp, size):
        async def run_before(pilot):
            await connect(pilot.app, pilot)
            await pilot.press("f3", "s")
            await settle(pilot)

        assert snap_compare(new_app(), terminal_size=size, run_before=run_before)

    @pytest.mark.parametrize("size", SIZES)
    def test_finished(self, snap_compare, in_tmp, size):
        async def run_before(pilot):
            await connect(pilot.app, pilot)
            await pilot.press("f3", "s", "y")
            await until(pilot, lambda: pilot.app.finished)
            await settle(pilot)

        assert snap_compare(new_app(), terminal_size=size, run_before=run_before)


class TestFitScreen:
    @pytest.mark.parametrize("size", SIZES)
    def test_report(self, snap_compare, in_tmp, results, size):
        async def run_before(pilot):
            await pilot.press("f4")
            view = pilot.app.views["fit"]
            view.set_recording("big.mcap")
            view.show_report(results["fit"])
            await settle(pilot)

        assert snap_compare(new_app(), terminal_size=size, run_before=run_before)


class TestDiagnoseScreen:
    @pytest.mark.parametrize("size", SIZES)
    def test_report(self, snap_compare, in_tmp, results, size):
        async def run_before(pilot):
            await pilot.press("f5")
            view = pilot.app.views["diagnose"]
            view.set_recording("big.mcap")
            view.show_report(results["diagnose"])
            await settle(pilot)

        assert snap_compare(new_app(), terminal_size=size, run_before=run_before)


class TestExportScreen:
    @pytest.mark.parametrize("size", SIZES)
    def test_result(self, snap_compare, in_tmp, results, size):
        async def run_before(pilot):
            await pilot.press("f6")
            view = pilot.app.views["export"]
            view.set_model("big.dh.model.json")
            view.show_summary(results["export"])
            await settle(pilot)

        assert snap_compare(new_app(), terminal_size=size, run_before=run_before)

    @pytest.mark.parametrize("size", SIZES)
    def test_closed_loop(self, snap_compare, in_tmp, results, size):
        """The closed-loop check's rows under the export's (a fixed result: the layout)."""
        res = {
            "targets": 19,
            "truth": "tracker",
            "skipped": ["target 7: SMR at [0.1, -0.4, 0.46] m (base) outside the workspace box"],
            "before": {"rms_m": 412.3e-6, "max_m": 590.1e-6, "rms_ci95_m": [380.2e-6, 450.9e-6]},
            "after": {
                "rms_m": 11.8e-6,
                "max_m": 19.6e-6,
                "rms_ci95_m": [10.4e-6, 13.5e-6],
                "predicted_rms_std_m": 6.1e-6,
            },
            "improvement": 34.9,
            "closure": {
                "target": 0,
                "displacement_m": 6.1e-6,
                "displacement_base_m": [-2.7e-6, -5.4e-6, -1.1e-6],
                "elapsed_s": 9.0,
                "noise_m": 17.1e-6,
                "beyond_noise": False,
            },
        }

        async def run_before(pilot):
            await pilot.press("f6")
            view = pilot.app.views["export"]
            view.set_model("big.dh.model.json")
            view.show_summary(results["export"])
            view.show_validation(res)
            await settle(pilot)

        assert snap_compare(new_app(), terminal_size=size, run_before=run_before)

    @pytest.mark.parametrize("size", SIZES)
    def test_refused(self, snap_compare, in_tmp, size):
        async def run_before(pilot):
            await pilot.press("f6")
            pilot.app.views["export"].refused(
                "refused: correction 7.200 mm at [0.1, -0.4, 0.3] m (base), orientation 0, "
                "exceeds the bound 5 mm (12 node(s) over); check the model or raise "
                "--max-correction"
            )
            await settle(pilot)

        assert snap_compare(new_app(), terminal_size=size, run_before=run_before)
