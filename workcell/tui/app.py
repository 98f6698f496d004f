"""The shop-floor terminal UI: `make_app(...)` builds it for `workcell tui` and for the tests.

The app owns the state (open devices, the plan, the campaign control flags, the last recording
and model) and runs every blocking call (device I/O, campaign, fits, diagnosis, export) in a
thread worker. Screens post request messages up; workers post result messages up (from their
threads); the app then sets attributes on the screens. Every failure becomes a notification.
"""

from __future__ import annotations

import functools
import signal
import threading
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import numpy as np
from rich.markup import escape
from textual.app import App
from textual.binding import Binding

from workcell.errors import UserError
from workcell.estimation.models import interval_um
from workcell.tui import backend
from workcell.tui import messages as m
from workcell.tui.backend import DeviceConfig, PlanConfig
from workcell.tui.jobs import campaign_job
from workcell.tui.screens import (
    CampaignScreen,
    DevicesScreen,
    DiagnoseScreen,
    ExportScreen,
    FitScreen,
    PlanScreen,
)
from workcell.tui.screens.base import folder_text
from workcell.tui.screens.campaign import campaign_outcome
from workcell.tui.screens.devices import config_changes
from workcell.tui.screens.fit import headline as fit_headline
from workcell.tui.widgets import ConfirmScreen

# events the operator must see even when not looking at the Campaign screen
NOTIFY_KINDS = {
    "reconnect": "warning",
    "skip": "warning",
    "refused": "error",
    "protective_stop": "error",
    "pause": "warning",
    "resume": "information",
    "abort": "warning",
    "margin": "information",  # the watch's summary; its stop is an error event
}


def guarded(handler):
    """A message handler that reports its own failure as a notification instead of crashing
    the app (a display bug must never stop a campaign)."""

    @functools.wraps(handler)
    def wrapper(self, *args, **kw):
        try:
            return handler(self, *args, **kw)
        except Exception as e:  # noqa: BLE001
            tb = traceback.format_exception_only(type(e), e)[-1].strip()
            self.notify(f"{handler.__name__}: {tb}", title="UI error", severity="error", timeout=10)
            return None

    return wrapper


def next_free(path: Path) -> Path:
    if not path.exists():
        return path
    k = 2
    while True:
        p = path.with_name(f"{path.stem}-{k}{path.suffix}")
        if not p.exists():
            return p
        k += 1


class WorkcellApp(App):
    TITLE = "workcell"
    ENABLE_COMMAND_PALETTE = False
    CSS = """
    Screen { background: $background; }
    """
    BINDINGS = [
        Binding("f1", "show('devices')", "Devices"),
        Binding("f2", "show('plan')", "Plan"),
        Binding("f3", "show('campaign')", "Campaign"),
        Binding("f4", "show('fit')", "Fit"),
        Binding("f5", "show('diagnose')", "Diagnose"),
        Binding("f6", "show('export')", "Export"),
        Binding("ctrl+q", "quit", "Quit", priority=True),
    ]

    def __init__(
        self,
        devices: DeviceConfig,
        plan: PlanConfig,
        *,
        clock: Callable[[], float] = time.monotonic,
        status_poll_s: float = 2.0,
        autoconnect: bool = False,
        start_screen: str = "devices",
        notify_timeout_s: float = 6.0,
        online: bool = True,
        cursor_blink: bool = True,
    ) -> None:
        super().__init__()
        self.online = online
        self.cursor_blink = cursor_blink
        self.device_config = devices
        self.plan = plan
        self.clock = clock
        self.status_poll_s = status_poll_s
        self.autoconnect = autoconnect
        self.start_screen = start_screen
        self.notify_timeout_s = notify_timeout_s
        self.devices: backend.Devices | None = None
        self.control = None  # CampaignControl while a campaign runs
        # clear while a campaign's worker thread runs (set by that thread when it ends, with the
        # recording closed: `workcell tui`'s exit after a signal waits for it)
        self.campaign_idle = threading.Event()
        self.campaign_idle.set()
        self.campaign_running = False
        self.last_fit: dict | None = None
        self.last_diagnosis: dict | None = None
        self.last_export: dict | None = None
        self.last_validation: dict | None = None
        self.validating = False  # the closed-loop check moves the arm: no campaign meanwhile
        self._validate_abort: threading.Event | None = None  # the running check's abort
        self.campaign_log: list[dict] = []  # events of the current campaign (tests read it)
        self.finished: list[m.CampaignFinished] = []
        self.notices: list[tuple[str, str, str]] = []
        self._t0 = None
        self._awaiting_recovery = False
        self._quit_after_campaign = False
        self._quit_return_code = 0
        self.exit_signal = 0  # the abort signal that made it quit (`abort_signal`), 0: none
        self._robot_unreachable_said: str | None = None  # the last "unreachable" notice's error
        self.views = {
            "devices": DevicesScreen(devices),
            "plan": PlanScreen(plan),
            "campaign": CampaignScreen(),
            "fit": FitScreen(),
            "diagnose": DiagnoseScreen(),
            "export": ExportScreen(out="correction"),
        }

    # ------------------------------------------------------------------ navigation
    def on_mount(self) -> None:
        for name, screen in self.views.items():
            self.install_screen(screen, name)
        self.push_screen(self.start_screen)
        self.current_view = self.start_screen
        self._push_context()
        if self.status_poll_s and self.status_poll_s > 0:
            self.set_interval(self.status_poll_s, self._poll_status)
        if self.autoconnect:
            self.call_after_refresh(self._connect, self.device_config)

    def action_show(self, name: str) -> None:
        if name not in self.views:
            return
        if getattr(self, "current_view", None) == name and self.screen is self.views[name]:
            return
        if self.screen is not self.views.get(self.current_view):
            return  # a modal is open; answer it first
        self.current_view = name
        self.switch_screen(name)

    def notify(
        self, message: str, *, title: str = "", severity="information", timeout=None, **kw
    ) -> None:
        """Toast, and keep a log of every notice (`notices`: (severity, title, message))."""
        self.notices.append((severity, title, str(message)))
        kw.setdefault("markup", False)
        super().notify(
            message,
            title=title,
            severity=severity,
            timeout=self.notify_timeout_s if timeout is None else timeout,
            **kw,
        )

    def action_help_quit(self) -> None:
        """Textual's answer to Ctrl-C, in plain text: notices here are not markup, and its own
        showed "Press [b]ctrl+q[/b] to quit the app" (a TUI audit)."""
        for key, active in self.active_bindings.items():
            if active.binding.action in ("quit", "app.quit"):
                self.notify(f"Press {key} to quit the app", title="Do you want to quit?")
                return

    def notify_error(self, text: str, title: str = "") -> None:
        self.notify(text, title=title, severity="error", timeout=1.5 * self.notify_timeout_s)

    # ------------------------------------------------------------------ what a start runs with
    def devices_form_problem(self) -> str | None:
        """Why the arm must not move now with the devices connected (None when it may): the
        Devices form says other devices, an SMR offset or a time scale than those connected,
        and a campaign would run with the connected ones, not what the operator sees."""
        dev = self.devices
        if dev is None:
            return None
        try:
            changes = config_changes(dev.config, self.views["devices"].read_config())
        except UserError as e:
            changes = [f"a value the connection would refuse ({e})"]
        if not changes:
            return None
        return (
            "the Devices form differs from the devices connected: "
            + "; ".join(changes)
            + ". The arm would move with the connected ones: reconnect on F1 Devices (ctrl+r) "
            "to use the form's, or set the form back; nothing moved"
        )

    def campaign_settings(self) -> tuple[PlanConfig, list[float]]:
        """What `s` or `r` on the Campaign screen starts with, read when the key is pressed: the
        Plan form as it stands (validated as the dry run validates it, its envelope file loaded
        for the connected arm) and the connected SMR offset (m on the flange). The form's plan
        becomes the app's. Refuses with UserError (nothing moves) a plan the dry run would
        refuse, and a Devices form other than the devices connected (`devices_form_problem`)."""
        try:
            plan = self.views["plan"].read_plan()
        except UserError as e:
            raise UserError(f"F2 Plan: {e}; nothing moved") from None
        self.plan = plan
        self._push_context()
        dev = self.devices
        if dev is None:
            raise UserError("connect the devices first (F1 Devices)")
        if why := self.devices_form_problem():
            raise UserError(why)
        try:
            backend.envelope_for(plan, dev)  # an unusable file: refused before the question
        except (ValueError, OSError) as e:
            raise UserError(f"envelope {plan.envelope}: {e}") from None
        return plan, np.asarray(dev.cell.tool_m, float).tolist()

    def _push_context(self) -> None:
        """Attributes down: what each screen shows about the shared state."""
        self.views["campaign"].set_context(self.plan, self.devices is not None)

    async def action_quit(self) -> None:
        if self.campaign_running and self.control is not None:

            def answer(ok: bool | None) -> None:
                if ok:
                    self._abort_and_quit("aborting the campaign before quitting ...")

            self.push_screen(
                ConfirmScreen("A campaign is running. Abort it and quit?", yes="Abort + quit"),
                answer,
            )
            return
        self._quit_now()

    def _abort_and_quit(self, note: str, return_code: int = 0) -> None:
        """Abort the running campaign and quit once it has ended (robot stopped, recording
        closed: `on_campaign_finished`); with none running (it ended meanwhile, e.g. while the
        quit question was open), quit now."""
        control = self.control
        if control is None or not self.campaign_running:
            self._quit_now(return_code)
            return
        self._quit_after_campaign = True
        self._quit_return_code = return_code
        control.abort.set()
        control.pause.clear()
        self.views["campaign"].set_state("aborting")
        self.notify(note, severity="warning")

    def _quit_now(self, return_code: int = 0) -> None:
        if self.validating and self.devices is not None:
            if self._validate_abort is not None:  # its move stops at once (the driver's flag)
                self._validate_abort.set()
            try:  # the closed-loop check has no pause: stop the arm where it is
                self.devices.robot.stop()
            except Exception:  # noqa: BLE001 - stopping is best effort while quitting
                pass
        self._close_devices()
        self.exit(return_code=return_code)

    def abort_signal(self, signum: int) -> None:
        """SIGTERM, SIGHUP or SIGINT (`kill`, a closed terminal), run on the event loop
        (`workcell tui` installs the handler): as the command line does, a running campaign is aborted cleanly
        (the arm stopped, the `abort` event written, the recording closed) and the app quits
        when it has ended; otherwise it quits at once, devices closed. Exit code 128 + signum."""
        self.exit_signal = self.exit_signal or signum
        try:
            name = signal.Signals(signum).name
        except ValueError:
            name = f"signal {signum}"
        self._abort_and_quit(f"{name}: aborting the campaign before quitting ...", 128 + signum)

    def on_unmount(self) -> None:
        if self.control is not None:
            self.control.abort.set()
        self._close_devices()  # never leave simulators started by --sim behind

    def _close_devices(self) -> None:
        if self.devices is not None:
            self.devices.close()
            self.devices = None

    # ------------------------------------------------------------------ workers
    def _thread(self, fn, job: str, *, group: str | None = None) -> None:
        """Run fn() in a thread worker; any exception becomes a JobFailed message."""

        def run() -> None:
            try:
                fn()
            except UserError as e:
                self.post_message(m.JobFailed(job, str(e)))
            except (ValueError, OSError, RuntimeError) as e:
                self.post_message(m.JobFailed(job, f"{type(e).__name__}: {e}"))
            except Exception as e:  # noqa: BLE001 - the UI reports, it never crashes
                tb = traceback.format_exception_only(type(e), e)[-1].strip()
                self.post_message(m.JobFailed(job, f"unexpected error: {tb}"))

        self.run_worker(run, name=job, group=group or job, thread=True, exit_on_error=False)

    @guarded
    def on_job_failed(self, msg: m.JobFailed) -> None:
        self.notify_error(msg.error, title=msg.job)
        if msg.job == "connect":
            self.views["devices"].show_status(None)
        elif msg.job == "dry-run":
            self.views["plan"].show_result(f"[red]dry run failed[/red]: {escape(msg.error)}")
        elif msg.job == "fit":
            self.views["fit"].set_running(False, f"fit failed: {escape(msg.error)}")
        elif msg.job == "diagnose":
            self.views["diagnose"].done(f"diagnosis failed: {escape(msg.error)}")
        elif msg.job == "export":
            self.views["export"].refused(msg.error)
        elif msg.job == "validate":
            self.validating = False
            self.views["export"].show_validation(None, msg.error)

    # ------------------------------------------------------------------ devices
    @guarded
    def on_connect_requested(self, msg: m.ConnectRequested) -> None:
        self._connect(msg.config)

    def _connect(self, cfg: DeviceConfig) -> None:
        if self.campaign_running or self.validating:
            self.notify_error("the arm is moving (campaign or closed-loop check); reconnect after")
            return
        self.device_config = cfg
        old, self.devices = self.devices, None
        self._push_context()

        def work() -> None:
            if old is not None:
                old.close()
            dev = backend.open_devices(cfg)
            self.post_message(m.DevicesOpened(dev, backend.probe(dev)))

        self.views["devices"].show_busy(f"connecting to {cfg.robot} / {cfg.tracker} ...")
        self._thread(work, "connect")

    @guarded
    def on_devices_opened(self, msg: m.DevicesOpened) -> None:
        self.devices = msg.devices
        self.views["devices"].show_status(msg.status)
        self.views["plan"].show_envelope(backend.envelope_summary(msg.devices.envelope))
        for note in msg.devices.notes:
            self.notify(note, severity="warning", title="Devices")
        self.notify(
            f"connected: {msg.devices.kind}", title="Devices", timeout=self.notify_timeout_s
        )
        self._push_context()

    @guarded
    def on_disconnect_requested(self, msg: m.DisconnectRequested) -> None:
        if self.campaign_running or self.validating:
            self.notify_error(
                "the arm is moving (campaign or closed-loop check); wait or abort first"
            )
            return
        dev, self.devices = self.devices, None
        self._push_context()
        self.views["devices"].show_status(None)
        if dev is not None:
            self._thread(dev.close, "disconnect")
            self.notify("disconnected", title="Devices", timeout=self.notify_timeout_s)

    @guarded
    def on_status_requested(self, msg: m.StatusRequested) -> None:
        self._poll_status(force=True)

    def _poll_status(self, force: bool = False) -> None:
        dev = self.devices
        if dev is None or (self.campaign_running and not force):
            return
        if self.campaign_running:
            self.notify("status is shown on the Campaign screen while it runs")
            return
        self._thread(lambda: self.post_message(m.DeviceStatus(backend.probe(dev))), "status")

    @guarded
    def on_device_status(self, msg: m.DeviceStatus) -> None:
        if self.devices is not None:
            self.views["devices"].show_status(msg.status)
            # said when it changes, not at every poll (every 2 s): the Devices screen shows it
            said = self._robot_unreachable_said
            if not msg.status.get("robot_ok", True):
                err = str(msg.status.get("robot_error", ""))
                if err != said:
                    self.notify(f"robot unreachable: {err}", severity="warning", title="Devices")
                self._robot_unreachable_said = err
            elif said is not None:
                self.notify("robot reachable again", title="Devices")
                self._robot_unreachable_said = None

    # ------------------------------------------------------------------ plan
    @guarded
    def on_dry_run_requested(self, msg: m.DryRunRequested) -> None:
        self.plan = msg.plan
        self._push_context()
        dev = self.devices
        if dev is None:
            self.views["plan"].show_result(
                "[yellow]not connected[/yellow]: the dry run needs the cell (robot model, tool, "
                "envelope); connect on F1 Devices"
            )
            self.notify_error("connect the devices first (F1)", title="Plan")
            return
        self._thread(
            lambda: self.post_message(m.PlanChecked(msg.plan, backend.dry_run(msg.plan, dev))),
            "dry-run",
        )

    @guarded
    def on_plan_checked(self, msg: m.PlanChecked) -> None:
        self.views["plan"].show_check(msg.plan, msg.result)
        if not msg.result.get("ok"):
            self.notify_error(
                f"dry run: {len(msg.result.get('problems', []))} problem(s); nothing will move",
                title="Plan",
            )

    # ------------------------------------------------------------------ campaign
    @guarded
    def on_campaign_start_requested(self, msg: m.CampaignStartRequested) -> None:
        if self.campaign_running:
            self.notify_error("a campaign is already running")
            return
        if self.validating:
            self.notify_error("the closed-loop check is moving the arm; wait for it (F6)")
            return
        dev = self.devices
        if dev is None:
            self.notify_error("connect the devices first (F1)")
            return
        from workcell.campaign.executor import CampaignControl

        plan = msg.plan
        self.control = control = CampaignControl()
        # after a protective stop the operator checks the cell and presses p to resume, as the
        # command line asks on its terminal; the campaign never unlocks the arm by itself
        control.auto_resume_protective_stop = False
        self.campaign_running = True
        self.campaign_log = []
        self._awaiting_recovery = False
        self.views["campaign"].set_state("starting")

        online = self.online

        def work() -> None:
            try:
                campaign_job(
                    self.post_message,
                    dev,
                    plan,
                    control,
                    resume_from=msg.resume_from,
                    online=online,
                )
            finally:  # the recording is closed (or was never opened): the worker is done
                self.campaign_idle.set()

        self.campaign_idle.clear()
        self._thread(work, "campaign")

    @guarded
    def on_campaign_started(self, msg: m.CampaignStarted) -> None:
        self._t0 = self.clock()
        self._n0 = 0
        self.views["campaign"].begin(msg.total, msg.recording, msg.ekf_note, msg.references)

    @guarded
    def on_sample_recorded(self, msg: m.SampleRecorded) -> None:
        scr = self.views["campaign"]
        n = scr.done + 1
        eta = None
        if self._t0 is not None and n > 0:
            dt = self.clock() - self._t0
            eta = dt / n * max(scr.total - n, 0) if dt > 0 else None
        scr.add_sample(msg.sample, msg.live, msg.estimate, eta)
        if self._awaiting_recovery:
            self._awaiting_recovery = False
            self.notify(
                f"campaign recovered: pose {msg.sample['pose_id']} recorded after the reconnect",
                title="Campaign",
                timeout=self.notify_timeout_s,
            )

    @guarded
    def on_estimate_updated(self, msg: m.EstimateUpdated) -> None:
        self.views["campaign"].add_estimate(msg.index, msg.estimate)

    @guarded
    def on_campaign_event(self, msg: m.CampaignEvent) -> None:
        ev = msg.event
        self.campaign_log.append(ev)
        self.views["campaign"].add_event(ev)
        kind = ev.get("kind")
        if kind == "reconnect":
            self._awaiting_recovery = True
        if kind == "pause" and "protective stop" in str(ev.get("message")):
            self.views["campaign"].set_state("protective stop")
            ev = {
                **ev,
                "message": f"{ev.get('message')}: check the cell, then press p to resume "
                "(a aborts)",
            }
        sev = NOTIFY_KINDS.get(kind)
        if sev and ev.get("level") == "error":
            sev = "error"
        if sev:
            self.notify(
                f"{kind}: {ev.get('message')}",
                title="Campaign",
                severity=sev,
                timeout=self.notify_timeout_s,
            )

    @guarded
    def on_pause_requested(self, msg: m.PauseRequested) -> None:
        c = self.control
        if c is None or not self.campaign_running:
            return
        scr = self.views["campaign"]
        if c.waiting_for_resume.is_set():  # the operator has checked the cell
            c.resume.set()
            scr.set_state("running")
            self.notify(
                "resuming after the protective stop",
                title="Campaign",
                timeout=self.notify_timeout_s,
            )
        elif c.pause.is_set():
            c.pause.clear()
            scr.set_state("running")
            self.notify("resumed", title="Campaign", timeout=self.notify_timeout_s)
        else:
            c.pause.set()
            scr.set_state("paused")
            self.notify(
                "pausing after the current pose", title="Campaign", timeout=self.notify_timeout_s
            )

    @guarded
    def on_abort_requested(self, msg: m.AbortRequested) -> None:
        if self.control is not None and self.campaign_running:
            self.control.abort.set()
            self.control.pause.clear()
            self.views["campaign"].set_state("aborting")

    @guarded
    def on_campaign_finished(self, msg: m.CampaignFinished) -> None:
        self.campaign_running = False
        self.finished.append(msg)
        scr = self.views["campaign"]
        res, rec = msg.result, msg.recording or {}
        stop = msg.stop_report
        if stop is None and res is not None:
            stop = backend.stop_report(res, msg.path, self.campaign_log)
        state, summary = campaign_outcome(res, rec, stop, msg.path)
        scr.finish(state, summary, stop)
        for line in rec.get("repeats") or []:  # the reference pose, over the whole recording
            scr.add_event({"level": "info", "kind": "reference", "message": line})
        if rec.get("samples"):
            self.views["fit"].set_recording(rec["path"])
            self.views["diagnose"].set_recording(rec["path"])
        if state != "failed":
            self.notify(
                summary,
                title=f"Campaign {state}",
                timeout=self.notify_timeout_s * (1.5 if state == "stopped" else 1.0),
                severity={"finished": "information", "stopped": "error"}.get(state, "warning"),
            )
        # next campaign: a fresh recording path
        if self.plan and self.plan.out and Path(self.plan.out).exists():
            new = next_free(Path(self.plan.out))
            self.plan = PlanConfig(**{**self.plan.__dict__, "out": str(new)})
            self.views["plan"].set_out(str(new))
        self.control = None
        self._push_context()
        if self._quit_after_campaign:
            self._close_devices()
            self.exit(return_code=self._quit_return_code)

    # ------------------------------------------------------------------ fit / diagnose / export
    @guarded
    def on_fit_requested(self, msg: m.FitRequested) -> None:
        def progress(text: str) -> None:
            self.post_message(m.JobProgress("fit", str(text)))

        def work() -> None:
            rep = backend.fit(msg.recording, msg.method, holdout=msg.holdout, progress=progress)
            self.post_message(m.FitFinished(rep))

        self._thread(work, "fit")

    @guarded
    def on_job_progress(self, msg: m.JobProgress) -> None:
        view = self.views.get(msg.job)
        if view is not None and hasattr(view, "show_progress"):
            view.show_progress(msg.text)

    @guarded
    def on_fit_finished(self, msg: m.FitFinished) -> None:
        self.last_fit = msg.report
        self.views["fit"].show_report(msg.report)
        self._read_warnings(msg.report, "Fit")
        if msg.report.get("model"):
            self.views["export"].set_model(msg.report["model"])
        self.notify(
            fit_headline(msg.report),  # "train RMS ..." when no pose was held out, as the CLI
            title="Fit done",
            timeout=self.notify_timeout_s,
        )
        if msg.report.get("model_note"):
            self.notify(
                msg.report["model_note"],
                title="Model file",
                severity="warning",
                timeout=self.notify_timeout_s,
            )

    def _read_warnings(self, report: dict, title: str) -> None:
        """A recording read only in part (damaged, cut off): each problem as a warning, as the
        command line prints it before its fit or diagnosis."""
        for line in report.get("read_warnings") or []:
            self.notify(
                line.removeprefix("warning: "),
                title=f"{title}: recording read in part",
                severity="warning",
                timeout=self.notify_timeout_s,
            )

    @guarded
    def on_diagnose_requested(self, msg: m.DiagnoseRequested) -> None:
        def progress(text: str) -> None:
            self.post_message(m.JobProgress("diagnose", str(text)))

        def work() -> None:
            rep = backend.diagnose(msg.recording, quick=msg.quick, progress=progress)
            self.post_message(m.DiagnoseFinished(rep))

        self._thread(work, "diagnose")

    @guarded
    def on_diagnose_finished(self, msg: m.DiagnoseFinished) -> None:
        self.last_diagnosis = msg.report
        self.views["diagnose"].show_report(msg.report)
        self._read_warnings(msg.report, "Diagnose")
        self.notify(
            f"{len(msg.report.get('effects', []))} effect(s) found",
            title="Diagnosis done",
            timeout=self.notify_timeout_s,
        )

    @guarded
    def on_export_requested(self, msg: m.ExportRequested) -> None:
        def log(text: str) -> None:
            self.post_message(m.JobProgress("export", str(text)))

        def work() -> None:
            self.post_message(m.ExportFinished(backend.export(msg.config, log=log)))

        self._thread(work, "export")

    @guarded
    def on_export_finished(self, msg: m.ExportFinished) -> None:
        self.last_export = msg.summary
        self.views["export"].show_summary(msg.summary)
        self.notify(
            f"wrote {', '.join(Path(f).name for f in msg.summary.get('files', []))} "
            f"in {folder_text(msg.summary)}",
            title="Export done",
            timeout=self.notify_timeout_s,
        )

    @guarded
    def on_validate_requested(self, msg: m.ValidateRequested) -> None:
        view = self.views["export"]
        dev = self.devices
        why = (
            "connect the devices first (F1)"
            if dev is None
            else "a campaign is running; the check moves the same arm"
            if self.campaign_running
            else self.devices_form_problem() or ""
        )
        if why:
            view.show_validation(None, why)
            self.notify_error(why, title="Validate")
            return
        self.validating = True
        self._validate_abort = abort = threading.Event()
        # the Plan form's envelope as it stands now (not the last dry run's)
        envelope = self.views["plan"].envelope_file()

        def log(text: str) -> None:
            self.post_message(m.JobProgress("export", str(text)))

        def work() -> None:
            res = backend.closed_loop(
                msg.model,
                msg.table,
                dev,
                msg.targets,
                log=log,
                envelope_file=envelope,
                abort=abort,
            )
            self.post_message(m.ValidateFinished(res))

        self._thread(work, "validate")

    @guarded
    def on_validate_abort_requested(self, msg: m.ValidateAbortRequested) -> None:
        if self.validating and self._validate_abort is not None:
            # the check's thread stops a move under way (the driver's abort_requested) and
            # sends no other; not stopped from here, where a driver call could block the UI
            self._validate_abort.set()

    @guarded
    def on_validate_finished(self, msg: m.ValidateFinished) -> None:
        self.validating = False
        self.last_validation = msg.result
        self.views["export"].show_validation(msg.result)
        r = msg.result
        ci = interval_um((r.get("after") or {}).get("rms_ci95_m"))
        self.notify(
            f"RMS {r['before_rms_m'] * 1e6:.1f} -> {r['after_rms_m'] * 1e6:.1f} um on "
            f"{r['targets']} targets" + (f"; after: {ci}" if ci else ""),  # as `validate` logs
            title="Closed-loop check",
            timeout=self.notify_timeout_s,
        )
        for w in r.get("warnings") or []:  # a table for another thermal state than the arm's
            self.notify(
                w, title="Closed-loop check", severity="warning", timeout=self.notify_timeout_s
            )


def make_app(
    robot: str = "sim",
    tracker: str = "sim",
    *,
    sim: bool = False,
    model: str = "ur5e",
    effects: str = "realistic",
    seed: int = 0,
    time_scale: float = 1.0,
    sim_host: str = "127.0.0.2",
    sim_faults: dict | None = None,
    sim_tracker_faults: dict | None = None,
    smr_offset: str = "",
    payload: str = "",
    plan: PlanConfig | None = None,
    clock: Callable[[], float] = time.monotonic,
    status_poll_s: float = 2.0,
    autoconnect: bool | None = None,
    start_screen: str = "devices",
    notify_timeout_s: float = 6.0,
    online: bool = True,
    cursor_blink: bool = True,
) -> WorkcellApp:
    """The app, configured. `sim=True` starts the protocol simulators on connect (and connects
    at start unless `autoconnect=False`); `robot="sim"` with `tracker="sim"` is the in-process
    simulation (virtual time). `clock` feeds the ETA (tests pass a fixed clock); `online` feeds
    the samples to the EKF-ANN online estimate (in its own thread) during campaigns;
    `cursor_blink=False` makes screenshots deterministic."""
    cfg = DeviceConfig(
        robot=robot,
        tracker=tracker,
        model=model,
        effects=effects,
        seed=seed,
        time_scale=time_scale,
        start_sim=sim,
        sim_host=sim_host,
        sim_faults=sim_faults,
        sim_tracker_faults=sim_tracker_faults,
        smr_offset=smr_offset,
        payload=payload,
    )
    return WorkcellApp(
        cfg,
        plan or PlanConfig(),
        clock=clock,
        status_poll_s=status_poll_s,
        autoconnect=sim if autoconnect is None else autoconnect,
        start_screen=start_screen,
        notify_timeout_s=notify_timeout_s,
        online=online,
        cursor_blink=cursor_blink,
    )
