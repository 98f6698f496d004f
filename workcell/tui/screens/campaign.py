"""Campaign: start after an explicit confirmation, with the Plan form as it stands when `s` is
pressed (refused while the Devices form differs from the devices connected); progress with ETA;
the current pose, joints, last tracker reading and its sigma; live residual plot (nominal model,
EKF-ANN online estimate); the event log; pause, resume, abort (confirmed); resume of an
interrupted recording. A campaign the engine stopped by itself (a fault it will not get past,
the margin watch) is STOPPED, not aborted: the status says why, what the recording keeps and how
to resume it."""

from __future__ import annotations

from pathlib import Path

from rich.markup import escape
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.widgets import Label, ProgressBar, RichLog

from workcell.errors import UserError
from workcell.tui.messages import AbortRequested, CampaignStartRequested, PauseRequested
from workcell.tui.screens.base import WorkcellScreen, um
from workcell.tui.widgets import ConfirmScreen, KeyValue, PathPrompt, ResidualPlot


def fmt_duration(s: float | None) -> str:
    if s is None or s != s or s < 0:
        return "--:--"
    s = int(round(s))
    h, r = divmod(s, 3600)
    m, sec = divmod(r, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m:02d}:{sec:02d}"


def envelope_name(envelope: str) -> str:
    """The Plan screen's envelope as the start confirmation names it."""
    return "the arm's default" if envelope in ("", "default") else envelope


def smr_name(smr_m) -> str:
    return ",".join(f"{float(x):g}" for x in smr_m)


# a campaign is under way in these states ("protective stop": waiting for the operator)
ACTIVE = ("running", "paused", "starting", "protective stop")


def campaign_outcome(res, rec: dict, stop: dict | None, path: str | None) -> tuple[str, str]:
    """The finished campaign's state ("finished", "aborted", "stopped" or "failed") and its
    one-line summary, from the engine's result `res` (None after an error), the recording's
    check `rec` and the stop report `stop` (why the engine ended it by itself, what the
    recording keeps, how to resume)."""
    ok = "closed cleanly" if rec.get("closed_cleanly") else "NOT closed cleanly"
    # why the engine ended it by itself, what the recording keeps, how to resume (the
    # event's kind and the notice's title say "stopped")
    why = f"{stop['reason']}; {stop['recording']}; " if stop else ""
    if res is None and not stop:
        state = "failed"
        summary = (
            f"campaign failed; recording {rec.get('path', '-')} holds "
            f"{rec.get('samples', 0)} samples"
            if rec
            else "campaign failed before recording"
        )
    elif res is None:
        state = "stopped"
        summary = f"{why}{Path(rec.get('path', '-')).name}: {rec.get('samples', '?')} samples, {ok}"
    else:
        state = "stopped" if stop else "aborted" if res.aborted else "finished"
        summary = (
            f"{why}{res.measured} measured, {res.skipped} skipped, {res.events} events; "
            f"{Path(path).name}: {rec.get('samples', '?')} samples, {ok}"
        )
    return state, summary


class CampaignScreen(WorkcellScreen):
    TITLE_TEXT = "Campaign"
    DEFAULT_CSS = """
    CampaignScreen #top { height: auto; }
    CampaignScreen #info { width: 1fr; padding: 0 1; }
    CampaignScreen #progress-row { height: 1; padding: 0 1; }
    CampaignScreen #progress-row ProgressBar { width: 1fr; }
    CampaignScreen #eta { width: auto; padding-left: 1; }
    CampaignScreen #lower { height: 1fr; }
    CampaignScreen ResidualPlot { width: 3fr; min-height: 6; }
    CampaignScreen #events { width: 2fr; border: round $primary; min-height: 4; }
    CampaignScreen.narrow #lower { layout: vertical; }
    CampaignScreen.narrow ResidualPlot { width: 1fr; }
    CampaignScreen.narrow #events { width: 1fr; height: 6; }
    """
    BINDINGS = [
        Binding("s", "start", "Start"),
        Binding("p", "pause", "Pause/resume"),
        Binding("a", "abort", "Abort"),
        Binding("r", "resume_recording", "Resume rec."),
    ]

    def __init__(self) -> None:
        super().__init__()
        self.plan = None  # PlanConfig set by the app
        self.connected = False
        self.state = "idle"
        self.total = 0  # measurements: poses and the reference pose's repeats
        self.done = 0
        self.references = 0
        self.recording: str | None = None
        self.residuals_um: list[float] = []
        self.rms_um: list[float | None] = []
        self.ekf_um: list[float | None] = []
        self.ekf_note = ""
        self.eta_s: float | None = None
        self.events: list[dict] = []
        self.last_sample: dict | None = None
        self.last_live: dict | None = None
        self.last_est: dict | None = None
        self.position: dict[int, int] = {}  # sample index -> position in the plot
        # why the campaign engine ended the last campaign by itself (`backend.stop_report`:
        # reason, what the recording keeps and how to resume), None otherwise
        self.stop: dict | None = None

    def body(self) -> ComposeResult:
        with Vertical(id="top"):
            yield KeyValue(id="info")
            with Horizontal(id="progress-row"):
                yield ProgressBar(total=1, show_eta=False, id="progress")
                yield Label("ETA --:--", id="eta")
        with Horizontal(id="lower"):
            yield ResidualPlot(id="plot")
            yield RichLog(id="events", max_lines=500, wrap=True, markup=True)

    # ---------------------------------------------------------------- actions (requests up)
    def _settings(self):
        """The plan and SMR offset a campaign started now runs with (`campaign_settings`: the
        Plan form as it stands, the devices connected, read when the key is pressed), or None
        after a notice saying why nothing will move."""
        try:
            return self.app.campaign_settings()
        except UserError as e:
            self.app.notify(str(e), severity="error", title="Campaign", markup=False)
            return None

    def action_start(self) -> None:
        if self.state in ACTIVE:
            self.notify("a campaign is already running", severity="warning")
            return
        if not self.connected:
            self.notify("connect the devices first (F1 Devices)", severity="error")
            return
        got = self._settings()
        if got is None:
            return
        p, smr = got
        q = (
            f"Start the campaign? The robot will MOVE.\n\n{p.poses} {p.kind} poses, "
            f"{p.readings_per_pose} readings each, settle {p.settle_s:g} s\n"
            + (
                f"the first pose measured again after every {p.reference_every} poses and at "
                f"the end ({p.measurements() - p.poses} more)\n"
                if p.reference_every
                else ""
            )
            + f"envelope: {escape(envelope_name(p.envelope))}\n"
            + f"SMR offset: {smr_name(smr)} m on the flange\n"
            + f"recording: {escape(p.out)}\n\nCheck the cell is clear."
        )

        def answer(ok: bool | None) -> None:
            if ok:
                self.post_message(CampaignStartRequested(p))

        self.app.push_screen(ConfirmScreen(q, yes="Start"), answer)

    def action_pause(self) -> None:
        if self.state not in ("running", "paused", "protective stop"):
            self.notify("no campaign is running", severity="warning")
            return
        self.post_message(PauseRequested())

    def action_abort(self) -> None:
        if self.state not in ACTIVE:
            self.notify("no campaign is running", severity="warning")
            return

        def answer(ok: bool | None) -> None:
            if ok:
                self.post_message(AbortRequested())

        self.app.push_screen(
            ConfirmScreen(
                "Abort the campaign? The robot stops; the recording is closed and can be "
                "resumed later (r).",
                yes="Abort",
            ),
            answer,
        )

    def action_resume_recording(self) -> None:
        if self.state in ACTIVE:
            self.notify("a campaign is already running", severity="warning")
            return
        if not self.connected or self.plan is None:
            self.notify("connect the devices (F1) and set a plan (F2) first", severity="error")
            return
        settings = self._settings()  # the Plan form's envelope: a resume refuses another one
        if settings is None:
            return
        plan, _ = settings

        def got(path: str | None) -> None:
            if not path:
                return

            def answer(ok: bool | None) -> None:
                if ok:
                    self.post_message(CampaignStartRequested(plan, resume_from=path))

            self.app.push_screen(
                ConfirmScreen(
                    f"Resume {escape(path)}? The remaining poses of its plan are measured into "
                    "a new chained recording, inside the envelope and with the SMR offset it was "
                    "recorded with. The robot will MOVE.",
                    yes="Resume",
                ),
                answer,
            )

        # the recording of the campaign that just ended on this screen (the Plan screen has
        # moved on to a new path by then), else the Plan screen's
        last = self.recording if self.state in ("aborted", "stopped", "failed") else None
        self.app.push_screen(PathPrompt("Interrupted recording to resume:", last or plan.out), got)

    # ---------------------------------------------------------------- attributes down
    def set_context(self, plan, connected: bool) -> None:
        self.plan, self.connected = plan, connected
        if self.state in ("idle", "finished", "aborted", "stopped", "failed") and self.done == 0:
            self.total = plan.measurements() if plan else 0
            self.references = self.total - plan.poses if plan else 0
        self.update_view()

    def begin(self, total: int, recording: str, ekf_note: str, references: int = 0) -> None:
        self.state = "running"
        self.total, self.done, self.references = total, 0, references
        self.residuals_um, self.rms_um, self.ekf_um = [], [], []
        self.ekf_note = ekf_note
        self.recording = recording
        self.last_sample = self.last_live = self.last_est = None
        self.position = {}
        self.eta_s = None
        self.stop = None
        self.events = []
        if self.is_mounted:
            self.query_one("#events", RichLog).clear()
        self.update_view()

    def set_state(self, state: str) -> None:
        self.state = state
        self.update_view()

    def add_sample(self, sample: dict, live: dict, est: dict | None, eta_s: float | None) -> None:
        self.done += 1
        self.last_sample, self.last_live, self.last_est = sample, live, est
        res = live.get("residuals_m") or []
        if res:
            self.residuals_um = [r * 1e6 for r in res]
        self.rms_um.append(None if live.get("rms_m") is None else live["rms_m"] * 1e6)
        self.ekf_um.append(None)
        self.position[int(sample.get("index", -1))] = len(self.rms_um) - 1
        self.eta_s = eta_s
        self.update_view()

    def add_estimate(self, index: int, est: dict) -> None:
        self.last_est = est
        if est.get("error"):
            self.ekf_note = "EKF-ANN unavailable"
        k = self.position.get(index)
        if k is not None and est.get("rms_m") is not None:
            self.ekf_um[k] = est["rms_m"] * 1e6
        self.update_view()

    def add_event(self, ev: dict) -> None:
        self.events.append(ev)
        if self.is_mounted:
            self._write_event(ev)

    def _write_event(self, ev: dict) -> None:
        colour = {"error": "red", "warning": "yellow"}.get(ev.get("level"), "cyan")
        self.query_one("#events", RichLog).write(
            f"[{colour}]{escape(str(ev.get('kind')))}[/{colour}] {escape(str(ev.get('message')))}"
        )

    def finish(self, state: str, summary: str, stop: dict | None = None) -> None:
        """The campaign ended: `state` finished, aborted (the operator), stopped (the engine by
        itself, `stop` says why and how to resume) or failed; `summary` goes in the event log."""
        self.state = state
        self.stop = stop
        if state == "finished":
            self.eta_s = 0.0
        self.add_event(
            {
                "level": {"finished": "info", "stopped": "error"}.get(state, "warning"),
                "kind": state,
                "message": summary,
            }
        )
        self.update_view()

    def on_mount(self) -> None:
        super().on_mount()
        for ev in self.events:
            self._write_event(ev)

    def render_view(self) -> None:
        bar = self.query_one("#progress", ProgressBar)
        bar.update(total=max(self.total, 1), progress=self.done)
        self.query_one("#eta", Label).update(f"ETA {fmt_duration(self.eta_s)}")
        self.query_one("#plot", ResidualPlot).update_live(
            self.residuals_um, self.rms_um, self.ekf_um, self.ekf_note
        )
        rows: list[tuple[str, str]] = []
        rec = self.recording or (self.plan.out if self.plan else "-")
        rows.append(
            (
                "State",
                f"{self.state.upper()}  {self.done}/{self.total} "
                + (
                    f"measurements ({self.references} of the reference)"
                    if self.references
                    else "poses"
                )
                + f"  -> {Path(str(rec)).name}",
            )
        )
        if self.stop and self.state == "stopped":  # the engine's words, not markup
            rows.append(("Stopped", escape(str(self.stop.get("reason", "")))))
            rows.append(("Recording", escape(str(self.stop.get("recording", "")))))
        s = self.last_sample
        if s:
            q = " ".join(f"{x:+.3f}" for x in s["q_measured_rad"])
            p = " ".join(f"{x:+.4f}" for x in s["tracker_position_m"])
            sig = max(s["tracker_sigma_m"]) * 1e6
            rows.append(("Pose", f"{s['pose_id']}  q [{q}] rad"))
            rows.append(("Tracker", f"[{p}] m  sigma {sig:.1f} um  n={s['n_readings']}"))
        else:
            rows.append(("Pose", "-"))
            rows.append(("Tracker", "-"))
        live, est = self.last_live, self.last_est
        if live and live.get("rms_m") is not None:
            resid = f"last {um(live['residual_m'])}, RMS {um(live['rms_m'])} (nominal)"
        elif live:
            resid = f"base registration needs 4 poses ({live['n']} so far)"
        else:
            resid = "-"
        if est and est.get("rms_m") is not None:
            resid += f"; EKF-ANN innovation RMS {um(est['rms_m'])}"
        elif self.ekf_note:
            resid += f"; {self.ekf_note}"
        elif est and est.get("text"):
            resid += "; " + est["text"].replace("ekf-ann", "EKF-ANN").split("  ")[-1].strip()
        rows.append(("Residual", resid))
        if not self.connected and self.state == "idle":
            rows.append(("", "not connected: F1 Devices"))
        elif self.state == "idle":
            rows.append(("", "press s to start (asks for confirmation)"))
        self.query_one("#info", KeyValue).set_rows(rows)
