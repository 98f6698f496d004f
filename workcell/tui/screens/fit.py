"""Fit: choose a recording and a method; the fit runs in a worker with progress; a before/after
table with held-out numbers and a residual plot. With no pose held out (fraction 0) the numbers
are on the training poses and every label says so, as `workcell fit` does."""

from __future__ import annotations

from pathlib import Path

from rich.markup import escape
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.widgets import Button, DataTable, Input, Label, Select

from workcell.errors import UserError
from workcell.estimation.models import evaluated_figure, interval_um
from workcell.tui.messages import FitRequested
from workcell.tui.screens.base import WorkcellScreen, um
from workcell.tui.widgets import SeriesPlot

METHODS = [
    ("dh (geometric, Levenberg-Marquardt)", "dh"),
    ("lddmm (diffeomorphic)", "lddmm"),
    ("gp (residual GP on DH)", "gp"),
    ("ekf-ann replay", "ekf-ann"),
]


# what `workcell fit` says of a fit with no pose held out (`fitting.fit_dataset`'s split)
NO_HOLDOUT = "no hold-out: numbers are on the training poses"


def held_out(r: dict) -> bool:
    """Whether the report's `heldout_*` figures are on held-out poses (False: a fit with the
    held-out fraction 0, whose figures are on the training poses)."""
    return bool(r.get("heldout_poses", 1))


def rms_label(r: dict) -> str:
    """The name of the report's `heldout_rms_m`, as `workcell fit` prints it."""
    return "held-out RMS" if held_out(r) else "train RMS"


def headline(r: dict) -> str:
    """One line of a fit: the method, its RMS (named for the poses it is on) and its 95 %
    interval; the status line and the app's notice."""
    ci = interval_um(evaluated_figure(r, "rms_ci95_m"))
    return (
        f"{r.get('method', '?')}: {rms_label(r)} {um(evaluated_figure(r, 'rms_m'))}"
        + (f" ({ci})" if ci else "")
        + ("" if held_out(r) else f"; {NO_HOLDOUT}")
    )


class FitScreen(WorkcellScreen):
    TITLE_TEXT = "Fit"
    DEFAULT_CSS = """
    FitScreen #form { height: auto; padding: 0 1; }
    FitScreen .row { height: 3; }
    FitScreen .row Label { width: 11; padding: 1 1 0 0; }
    FitScreen .row Input { width: 1fr; }
    FitScreen .row Select { width: 1fr; }
    FitScreen #hold { width: 10; }
    FitScreen #status { height: auto; width: 100%; padding: 0 1; }
    FitScreen #lower { height: 1fr; }
    FitScreen DataTable { width: 1fr; height: 1fr; min-height: 5; }
    FitScreen SeriesPlot { width: 1fr; }
    FitScreen.narrow #lower { layout: vertical; }
    FitScreen.narrow DataTable { height: auto; }
    """
    BINDINGS = [Binding("ctrl+r", "fit", "Run fit")]

    def __init__(self, recording: str = "") -> None:
        super().__init__()
        self.recording = recording
        self.report: dict | None = None
        self.running = False
        self.status = "choose a recording and a method, then Fit (ctrl+r)"

    def body(self) -> ComposeResult:
        with Vertical(id="form"):
            with Horizontal(classes="row"):
                yield Label("Recording")
                yield Input(self.recording, id="recording", placeholder="campaign.mcap")
            with Horizontal(classes="row"):
                yield Label("Method")
                yield Select(METHODS, value="dh", allow_blank=False, id="method")
                yield Label(" Held out")
                yield Input("0.25", id="hold", type="number")
                yield Button("Fit", id="fit", variant="primary")
        yield Label(self.status, id="status")
        with Horizontal(id="lower"):
            yield DataTable(id="table", cursor_type="none", zebra_stripes=True)
            yield SeriesPlot(
                title="held-out error per pose (um)", xlabel="held-out pose", id="plot"
            )

    def on_mount(self) -> None:
        self.query_one("#table", DataTable).add_columns("", "held-out RMS", "max")
        super().on_mount()

    def action_fit(self) -> None:
        if self.running:
            self.notify("a fit is already running", severity="warning")
            return
        try:
            rec = self.text("recording")
            if not rec:
                raise UserError("choose a recording (.mcap)")
            hold = self.number("hold", float, "held-out fraction")
            if not 0.0 <= hold < 0.9:
                raise UserError(f"held-out fraction must be in [0, 0.9), got {hold}")
        except UserError as e:
            self.notify(str(e), severity="error", title="Fit")
            self.set_running(False, f"not fitted: {escape(str(e))}")  # not an earlier line
            return
        method = str(self.query_one("#method", Select).value)
        self.set_running(True, f"fitting {method} on {Path(rec).name} ...")
        self.post_message(FitRequested(rec, method, hold))

    def on_button_pressed(self, event: Button.Pressed) -> None:
        self.action_fit()

    def on_input_submitted(self, event: Input.Submitted) -> None:
        self.action_fit()

    # ---------------------------------------------------------------- attributes down
    def set_running(self, running: bool, text: str) -> None:
        self.running = running
        self.status = text
        self.update_view()

    def show_progress(self, text: str) -> None:
        self.status = text[:200]
        self.update_view()

    def show_report(self, r: dict) -> None:
        self.report = r
        model = r.get("model")
        self.running = False
        self.status = headline(r) + (f"; model saved as {Path(model).name}" if model else "")
        self.update_view()

    def render_view(self) -> None:
        self.query_one("#status", Label).update(self.status)
        self.query_one("#fit", Button).disabled = self.running
        r = self.report
        if not r:
            return
        t = self.query_one("#table", DataTable)
        # the first column is named for the poses its figures are on (held out, or training)
        t.clear(columns=True)
        t.add_columns("", rms_label(r), "max")
        method = r.get("method", "?")
        if "nominal_rms_m" in r:
            t.add_row(
                "nominal (base registered)", um(r["nominal_rms_m"]), um(r.get("nominal_max_m"))
            )
            nci = interval_um(r.get("nominal_rms_ci95_m"), label=False)
            if nci:
                t.add_row("  95 % CI of its RMS", nci, "")
        fig = evaluated_figure
        t.add_row(f"{method} fitted", um(fig(r, "rms_m")), um(fig(r, "max_m")))
        ci = interval_um(fig(r, "rms_ci95_m"), label=False)
        if ci:
            t.add_row("  95 % CI of its RMS", ci, "")
        if r.get("train_rms_m") is not None and held_out(r):  # else: the row above
            t.add_row(f"{method} on training poses", um(r["train_rms_m"]), "")
        if r.get("stated_noise_floor_m") is not None:
            t.add_row("floor: repeatability", um(r["stated_noise_floor_m"]), "")
        if r.get("tracker_noise_floor_m") is not None:
            t.add_row("floor: tracker accuracy", um(r["tracker_noise_floor_m"]), "")
        u = r.get("unexplained")
        if u:
            up = u.get("upper_m")
            t.add_row(
                "unexplained above it", um(u["rms_m"]), f"up to {um(up)}" if up is not None else ""
            )
        ho = r.get("heldout_outliers")
        if ho:
            t.add_row(
                "held-out outliers",
                f"{len(ho['pose_ids'])} (max {um(max(ho['errors_m']))})",
                f"without: {um(ho['heldout_rms_m'])}",
            )
        t.add_row(
            "poses",
            f"{r.get('train_poses', '-')} train",
            f"{r.get('heldout_poses', '-')} held out"
            + ("" if held_out(r) else ": the figures are on the training poses"),
        )
        unid = r.get("unidentifiable") or []
        if unid:
            groups = ["/".join(g) if isinstance(g, list | tuple) else str(g) for g in unid]
            t.add_row("fixed (not identifiable)", f"{len(groups)} groups", ", ".join(groups[:2]))
        weak = (r.get("identifiability") or {}).get("weakly_identified") or []
        if weak:
            t.add_row(
                "weakly identified",
                f"{len(weak)} group{'s' if len(weak) > 1 else ''}",
                ", ".join(
                    f"{'/'.join(g['parameters'])} (std {g['std_inflation']:.0f}x)" for g in weak[:2]
                ),
            )
        smr = r.get("smr_change")
        if smr:
            t.add_row(
                "SMR vs declared",
                f"{smr['change_m'] * 1e3:.1f} mm off (std {smr['std_m'] * 1e3:.2f} mm)",
                "declare " + ", ".join(f"{x:.4f}" for x in smr["fitted_m"]) + " m, fit again",
            )
        res = r.get("residuals") or {}
        if res:
            before = [x * 1e6 for x in res.get("before_m", [])]
            after = [x * 1e6 for x in res.get("after_m", [])]
            plot = self.query_one("#plot", SeriesPlot)
            on = "held-out" if held_out(r) else "training (no hold-out)"
            plot.title = f"{on} error per pose (um)"
            plot.xlabel = "held-out pose" if held_out(r) else "training pose"
            plot.set_series(
                [
                    ("nominal", list(range(1, len(before) + 1)), before, "scatter"),
                    (method, list(range(1, len(after) + 1)), after, "line"),
                ]
            )
