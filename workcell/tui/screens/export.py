"""Export: format, volume, path; the validation result of the written correction (interpolation
check, and on request the closed-loop check on the connected cell); refusals are shown clearly
(one line, in red, and as a notification)."""

from __future__ import annotations

from pathlib import Path

from rich.markup import escape
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical, VerticalScroll
from textual.widgets import Button, Input, Label, Select, Static

from workcell.errors import UserError
from workcell.estimation.models import interval_um, unexplained_text
from workcell.export.table import coverage_line
from workcell.export.validate import DEFAULT_TARGETS, MAX_TARGETS, closure_line
from workcell.tui.backend import ExportConfig
from workcell.tui.messages import ExportRequested, ValidateAbortRequested, ValidateRequested
from workcell.tui.screens.base import WorkcellScreen, folder_text, um
from workcell.tui.widgets import ConfirmScreen, KeyValue

FORMATS = [
    ("table (JSON + CSV correction grid)", "table"),
    ("urscript (table + URScript functions)", "urscript"),
    ("ros-yaml (UR ROS calibration)", "ros-yaml"),
]


class ExportScreen(WorkcellScreen):
    TITLE_TEXT = "Export"
    DEFAULT_CSS = """
    ExportScreen #form { height: auto; padding: 0 1; }
    ExportScreen .row { height: 3; }
    ExportScreen .row Label { width: 10; padding: 1 1 0 0; }
    ExportScreen .row Input { width: 1fr; }
    ExportScreen .row Select { width: 1fr; }
    ExportScreen .row #targets { width: 12; }
    ExportScreen #status { height: auto; padding: 0 1; }
    ExportScreen #result-box { height: 1fr; border: round $primary; padding: 0 1; }
    """
    BINDINGS = [
        Binding("ctrl+r", "export", "Export"),
        # not ctrl+t: the Devices screen's Disconnect; ctrl+o and ctrl+b are free in an Input
        Binding("ctrl+o", "validate", "Closed-loop check (moves the arm)"),
        Binding("ctrl+b", "abort_check", "Abort the check"),
    ]

    def __init__(self, model: str = "", out: str = "correction") -> None:
        super().__init__()
        self.model, self.out = model, out
        self.summary: dict | None = None
        self.running = False
        self.status = "a correction for the robot controller; refused if it is too large"
        self.result_rows: list[tuple[str, str]] = []
        self.validating = False
        self.validation: dict | None = None

    def body(self) -> ComposeResult:
        with Vertical(id="form"):
            with Horizontal(classes="row"):
                yield Label("Model")
                yield Input(self.model, id="model", placeholder="fitted model .json")
            with Horizontal(classes="row"):
                yield Label("Format")
                yield Select(FORMATS, value="table", allow_blank=False, id="format")
            with Horizontal(classes="row"):
                yield Label("Volume")
                yield Input("", id="volume", placeholder="x0,y0,z0,x1,y1,z1 m (empty: default box)")
                yield Input("", id="spacing", placeholder="spacing m (auto)")
            with Horizontal(classes="row"):
                yield Label("Path")
                yield Input(self.out, id="out")
                yield Button("Export", id="run", variant="primary")
            with Horizontal(classes="row"):
                yield Label("Check")
                yield Input(str(DEFAULT_TARGETS), id="targets", placeholder="targets")
                yield Button("Validate on the cell", id="validate")
        yield Static(self.status, id="status")
        with VerticalScroll(id="result-box"):
            yield KeyValue(id="result")

    def set_model(self, path: str) -> None:
        self.model = path
        if self.is_mounted:
            self.query_one("#model", Input).value = path

    def read_config(self) -> ExportConfig:
        sp = self.text("spacing")
        spacing = None
        if sp:
            spacing = self.number("spacing", float, "spacing")
            if not spacing > 0:
                raise UserError(f"spacing must be > 0 m, got {spacing}")
        return ExportConfig(
            model=self.text("model"),
            format=str(self.query_one("#format", Select).value),
            out=self.text("out") or "correction",
            volume=self.text("volume"),
            spacing_m=spacing,
        )

    def action_export(self) -> None:
        if self.running:
            self.notify("an export is already running", severity="warning")
            return
        try:
            cfg = self.read_config()
            if not cfg.model:
                raise UserError("choose a fitted model (Fit screen saves one)")
        except UserError as e:
            self.notify(str(e), severity="error", title="Export")
            self.refused(str(e))  # not an earlier export's line left under the refusal
            return
        self.running = True
        self.status = f"exporting {cfg.format} ..."
        self.update_view()
        self.post_message(ExportRequested(cfg))

    def action_validate(self) -> None:
        """Closed loop: the connected arm goes to random targets uncorrected and corrected
        through the exported table, the tracker measures both."""
        if self.running or self.validating:
            self.notify("wait for the running export or check", severity="warning")
            return
        table = next((f for f in (self.summary or {}).get("files", []) if f.endswith(".json")), "")
        try:
            if not table:
                raise UserError("export a table (or urscript) first; the check uses its table")
            n = self.number("targets", int, "targets")
            if not 1 <= n <= MAX_TARGETS:
                raise UserError(f"targets must be 1..{MAX_TARGETS}, got {n}")
        except UserError as e:
            self.notify(str(e), severity="error", title="Validate")
            return
        q = (
            f"Run the closed-loop check? The robot will MOVE.\n\n{n} random targets inside "
            "the envelope, each visited uncorrected and then corrected through the table, the "
            "tracker measuring both.\n\nCheck the cell is clear. ctrl+b stops the arm during "
            "the check."
        )
        model = (self.summary or {}).get("model", "")

        def answer(ok: bool | None) -> None:
            if not ok or self.running or self.validating:
                return
            self.validating = True
            self.status = f"closed-loop check on {n} targets: the arm moves (ctrl+b stops it) ..."
            self.update_view()
            self.post_message(ValidateRequested(model, table, n))

        self.app.push_screen(ConfirmScreen(q, yes="Move"), answer)

    def action_abort_check(self) -> None:
        """Stop the closed-loop check: the arm stops where it is (no confirmation: stopping is
        always allowed)."""
        if not self.validating:
            self.notify("no closed-loop check is running", severity="warning")
            return
        self.status = "stopping the closed-loop check ..."
        self.update_view()
        self.post_message(ValidateAbortRequested())

    def on_button_pressed(self, event: Button.Pressed) -> None:
        if event.button.id == "validate":
            self.action_validate()
        else:
            self.action_export()

    def on_input_submitted(self, event: Input.Submitted) -> None:
        if event.input.id != "targets":
            self.action_export()

    # ---------------------------------------------------------------- attributes down
    def show_progress(self, text: str) -> None:
        self.status = text[:200]
        self.update_view()

    def refused(self, message: str) -> None:
        self.running = False
        self.status = f"[b red]REFUSED[/b red] {escape(message)}"
        self.result_rows = [("Result", "nothing written")]
        self.update_view()

    def render_view(self) -> None:
        self.query_one("#status", Static).update(self.status)
        self.query_one("#run", Button).disabled = self.running or self.validating
        self.query_one("#validate", Button).disabled = self.running or self.validating
        self.query_one("#result", KeyValue).set_rows(self.result_rows)

    def show_summary(self, s: dict) -> None:
        self.summary = s
        self.running = False
        v = s.get("validation") or {}
        rows = [("Format", s.get("format", "?"))]
        rows += [("File", Path(f).name) for f in s.get("files", [])]
        rows.append(("Folder", folder_text(s)))
        if s.get("script_size_warning"):
            rows.append(("Size", f"[yellow]{escape(s['script_size_warning'])}[/yellow]"))
        if "grid" in s:
            sp = max(s["grid"]["spacing_m"]) * 1e3
            rows.append(
                ("Grid", f"{' x '.join(map(str, s['grid']['shape']))} nodes, spacing {sp:.1f} mm")
            )
        if v.get("max_interp_error_m") is not None:
            met = v.get("interp_error_target_met")
            verdict = "[green]PASS[/green]" if met else "[yellow]target not met[/yellow]"
            rows.append(
                (
                    "Validation",
                    f"{verdict} max interpolation error {um(v['max_interp_error_m'])} "
                    f"(target {um(v.get('target_interp_error_m'))}, "
                    f"{v.get('interp_error_points')} random points)",
                )
            )
        if v.get("max_correction_m") is not None:
            rows.append(
                (
                    "Correction",
                    f"max {v['max_correction_m'] * 1e3:.3f} mm "
                    f"(bound {float(v.get('correction_bound_m') or 0) * 1e3:g} mm)",
                )
            )
        if v.get("max_std_m") is not None:
            rows.append(
                (
                    "Uncertainty",
                    f"1-sigma of the corrections (model): median {um(v.get('median_std_m'))}, "
                    f"max {um(v['max_std_m'])}",
                )
            )
        elif "grid" in s:
            rows.append(("Uncertainty", "not given: the model carries no covariance"))
        if v.get("nodes_std_exceeds_correction"):
            rows.append(
                (
                    "Undetermined",
                    f"[red]{v['nodes_std_exceeds_correction']} nodes[/red]: the correction's "
                    "1-sigma is larger than the correction (the poses do not determine it)",
                )
            )
        if isinstance(s.get("joint_coverage"), dict):
            rows.append(("Coverage", escape(coverage_line(s["joint_coverage"]))))
        if s.get("base_correction_line"):  # the frame of the targets, as `workcell export`
            rows.append(("Frame", escape(s["base_correction_line"])))
        if s.get("unexplained"):
            rows.append(
                (
                    "Not in it",
                    "the model leaves "
                    + escape(unexplained_text(s["unexplained"]))
                    + " on its held-out poses"
                    + (
                        ", in neither the values nor their +-"
                        if s.get("format") == "ros-yaml"
                        else ""
                    ),
                )
            )
        w = s.get("unexplained_without_outliers")
        if w:
            ids = ", ".join(str(i) for i in w.get("pose_ids", []))
            rows.append(
                ("", f"without held-out outlier pose(s) {ids}: " + escape(unexplained_text(w)))
            )
        rows += [("Conditions", escape(line)) for line in s.get("conditions", [])]
        self.result_rows = rows
        self.status = f"[green]exported[/green] {len(s.get('files', []))} file(s)"
        self.update_view()

    def show_validation(self, r: dict | None, error: str = "") -> None:
        """The closed-loop result (None with `error` when the check failed)."""
        self.validating = False
        self.validation = r
        # the check's rows go first, above the export's (the Frame and Coverage rows are long):
        # the newest result in view without scrolling, also at 80x24
        rows = [row for row in self.result_rows if not row[0].startswith("Closed loop")]
        loop: list[tuple[str, str]] = []
        if r is None:
            self.status = f"[b red]check failed[/b red] {escape(error)}"
        else:
            b, a = r["before"], r["after"]
            ci = interval_um(a.get("rms_ci95_m"), label=False)
            bci = interval_um(b.get("rms_ci95_m"), label=False)
            loop += [
                ("Closed loop", f"{r['targets']} targets, measured by the {r.get('truth', '?')}"),
                (
                    "Closed loop before",
                    f"RMS {um(b['rms_m'])}"
                    + (f" (95 % CI {bci})" if bci else "")
                    + f", max {um(b['max_m'])}",
                ),
                (
                    "Closed loop after",
                    f"RMS {um(a['rms_m'])}"
                    + (f" (95 % CI {ci})" if ci else "")
                    + f", max {um(a['max_m'])}: {r['improvement']:.1f}x better",
                ),
            ]
            if a.get("predicted_rms_std_m") is not None:
                loop.append(
                    (
                        "Closed loop stated",
                        f"the table's 1-sigma at these targets: RMS {um(a['predicted_rms_std_m'])}",
                    )
                )
            if r.get("closure"):  # the first target measured again at the end
                c = closure_line(r["closure"]).removeprefix("closure: ")
                loop.append(("Closed loop closure", c[0].upper() + c[1:]))
            if r.get("skipped"):
                loop.append(("Closed loop skipped", f"{len(r['skipped'])}: {r['skipped'][0]}"))
            self.status = f"[green]closed-loop check done[/green] on {r['targets']} targets"
        self.result_rows = loop + rows
        self.update_view()
        if self.is_mounted:
            self.query_one("#result-box", VerticalScroll).scroll_home(animate=False)
