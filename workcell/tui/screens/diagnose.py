"""Diagnose: the discovery report (summary text, effects table, before/after numbers, plot)."""

from __future__ import annotations

import math
from pathlib import Path

from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, VerticalScroll
from textual.widgets import Button, Checkbox, DataTable, Input, Label, Static

from workcell.tui.messages import DiagnoseRequested
from workcell.tui.screens.base import WorkcellScreen, um
from workcell.tui.widgets import SeriesPlot


class DiagnoseScreen(WorkcellScreen):
    TITLE_TEXT = "Diagnose"
    DEFAULT_CSS = """
    DiagnoseScreen #form { height: 3; padding: 0 1; }
    DiagnoseScreen #form Label { width: 11; padding: 1 1 0 0; }
    DiagnoseScreen #form Input { width: 1fr; }
    DiagnoseScreen #status { height: 1; padding: 0 1; }
    DiagnoseScreen #summary-box { height: 1fr; border: round $primary; padding: 0 1; }
    DiagnoseScreen #lower { height: 1fr; }
    DiagnoseScreen DataTable { width: 3fr; height: 1fr; }
    DiagnoseScreen SeriesPlot { width: 2fr; }
    DiagnoseScreen.narrow DataTable { width: 1fr; }
    DiagnoseScreen.narrow SeriesPlot { display: none; }
    """
    BINDINGS = [Binding("ctrl+r", "diagnose", "Diagnose")]

    def __init__(self, recording: str = "") -> None:
        super().__init__()
        self.recording = recording
        self.report: dict | None = None
        self.running = False
        self.status = "the discovery report: which physics the nominal model left out"

    def body(self) -> ComposeResult:
        with Horizontal(id="form"):
            yield Label("Recording")
            yield Input(self.recording, id="recording", placeholder="campaign.mcap (>= 40 poses)")
            # off by default: the command line's diagnosis, its non-parametric residual check
            # included (`workcell diagnose`; quick is its --no-np)
            yield Checkbox("quick (no GP check)", False, id="quick")
            yield Button("Diagnose", id="run", variant="primary")
        yield Label(self.status, id="status")
        with VerticalScroll(id="summary-box"):
            yield Static("No diagnosis yet.", id="summary")
        with Horizontal(id="lower"):
            yield DataTable(id="effects", cursor_type="none", zebra_stripes=True)
            yield SeriesPlot(title="held-out RMS per step (um)", id="plot")

    def on_mount(self) -> None:
        self.query_one("#effects", DataTable).add_columns(
            # the held-out gain (the evidence) second: it shows at 80 columns, where the table
            # is wider than the screen (it was last, off-screen at 80x24 and 200x60: TUI audit)
            "model / effect",
            "held-out gain um (95 %)",
            "joint",
            "train CV share",
            "held-out RMS, cumulative",
        )
        super().on_mount()

    def action_diagnose(self) -> None:
        if self.running:
            self.notify("a diagnosis is already running", severity="warning")
            return
        rec = self.text("recording")
        if not rec:
            self.notify("choose a recording (.mcap)", severity="error", title="Diagnose")
            return
        self.running = True
        self.status = f"diagnosing {Path(rec).name} ..."
        self.update_view()
        self.post_message(DiagnoseRequested(rec, self.query_one("#quick", Checkbox).value))

    def on_button_pressed(self, event: Button.Pressed) -> None:
        self.action_diagnose()

    def on_input_submitted(self, event: Input.Submitted) -> None:
        self.action_diagnose()

    # ---------------------------------------------------------------- attributes down
    def show_progress(self, text: str) -> None:
        self.status = text[:200]
        self.update_view()

    def done(self, text: str) -> None:
        self.running = False
        self.status = text
        self.update_view()

    def show_report(self, r: dict) -> None:
        self.report = r
        self.done(
            f"{len(r.get('effects', []))} effect(s): held-out RMS {um(r.get('rms_before_m'))} -> "
            f"{um(r.get('rms_after_m'))}"
            + ("; non-parametric residual check skipped" if r.get("np_check_note") else "")
        )

    def render_view(self) -> None:
        self.query_one("#status", Label).update(self.status)
        self.query_one("#run", Button).disabled = self.running
        r = self.report
        if not r:
            return
        text = r.get("summary", "")
        if r.get("np_check_note"):  # quick: no "What is not explained" sentence; say why
            text = f"{text}\n{r['np_check_note']}"
        self.query_one("#summary", Static).update(text)
        t = self.query_one("#effects", DataTable)
        t.clear()
        t.add_row("geometry only (DH+base+SMR)", "", "", "", um(r.get("rms_before_m")))
        step_rms = {s["after"]: s["heldout_rms_m"] for s in r.get("steps", [])}
        for e in r.get("effects", []):
            t.add_row(
                str(e.get("description", e.get("key")))[:34],
                gain_cell(e.get("evidence", {}))
                + ("" if e.get("evidence", {}).get("heldout_confirms", True) else " NOT confirmed"),
                str(e.get("joint") if e.get("joint") is not None else "-"),
                f"{100 * float(e.get('explained_fraction', 0.0)):.0f} %",
                um(step_rms.get(e.get("key"))) if e.get("key") in step_rms else "",
            )
        t.add_row("final (all effects)", "", "", "", um(r.get("rms_after_m")))
        t.add_row("noise floor (expected)", "", "", "", um(r.get("noise_floor_m")))
        steps = [r.get("rms_before_m")] + [s["heldout_rms_m"] for s in r.get("steps", [])]
        steps.append(r.get("rms_after_m"))
        ys = [float(v) * 1e6 for v in steps if v is not None]
        floor = r.get("noise_floor_m")
        series = [("held-out RMS", list(range(len(ys))), ys, "bar")]
        if floor is not None:
            series.append(("noise floor", [0, len(ys) - 1], [floor * 1e6] * 2, "line"))
        self.query_one("#plot", SeriesPlot).set_series(series)


def gain_cell(ev: dict) -> str:
    """An effect's held-out gain (RMS without it minus with it) and its paired 95 % interval, in
    um (an interval reaching zero: within chance; the summary says so in words)."""
    g, ci = ev.get("heldout_gain_m"), ev.get("heldout_gain_ci95_m")
    if g is None or ci is None or not all(math.isfinite(float(v)) for v in (g, *ci)):
        return ""

    def f(v: float) -> str:
        return f"{v * 1e6:.0f}" if abs(v) >= 1e-5 else f"{v * 1e6:.1f}"

    return f"{f(g)} ({f(ci[0])}..{f(ci[1])})"
