"""Plan: plan type, poses, envelope, settle time, readings per pose, reference interval,
recording path; a dry-run check of every target against the envelope before anything moves."""

from __future__ import annotations

from rich.markup import escape
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical, VerticalScroll
from textual.widgets import Button, Input, Label, Select, Static

from workcell.errors import UserError
from workcell.tui.backend import PlanConfig
from workcell.tui.messages import DryRunRequested
from workcell.tui.screens.base import WorkcellScreen
from workcell.tui.widgets import KeyValue

PLAN_KINDS = [
    ("random (uniform in the envelope)", "random"),
    ("grid (joints 1-3, varied wrist)", "grid"),
    ("bo (adaptive, GP-UCB)", "bo"),
    ("dopt (adaptive, D-optimal)", "dopt"),
    ("vopt (adaptive, least mean prediction variance)", "vopt"),
]


class PlanScreen(WorkcellScreen):
    TITLE_TEXT = "Plan"
    DEFAULT_CSS = """
    PlanScreen #form { height: auto; padding: 0 1; }
    PlanScreen .row { height: 3; }
    PlanScreen .row Label { width: 12; padding: 1 1 0 0; }
    PlanScreen .row Input { width: 1fr; }
    PlanScreen .row Select { width: 1fr; }
    PlanScreen .row Button { margin-left: 1; min-width: 12; }
    PlanScreen #result-box { border: round $primary; padding: 0 1; height: 1fr; min-height: 4; }
    """
    BINDINGS = [
        Binding("ctrl+r", "dry_run", "Dry run"),
        Binding("ctrl+g", "to_campaign", "Campaign"),
    ]

    def __init__(self, plan: PlanConfig) -> None:
        super().__init__()
        self.plan = plan
        self.checked: PlanConfig | None = None  # the plan the last successful dry run was for
        self.envelope_rows: list[str] = []
        self.result_text = "No dry run yet: nothing has been checked."

    def body(self) -> ComposeResult:
        p = self.plan
        with Vertical(id="form"):
            with Horizontal(classes="row"):
                yield Label("Plan")
                yield Select(PLAN_KINDS, value=p.kind, allow_blank=False, id="kind")
                yield Label("Poses")
                yield Input(str(p.poses), id="poses", type="integer")
            with Horizontal(classes="row"):
                yield Label("Settle s")
                yield Input(f"{p.settle_s:g}", id="settle", type="number")
                yield Label("Readings")
                yield Input(str(p.readings_per_pose), id="readings", type="integer")
                yield Label("Ref. every")
                ref = Input(str(p.reference_every), id="ref-every", type="integer")
                ref.tooltip = (
                    "0: no reference. N: the first pose is measured again after every N poses "
                    "and at the end, a drift record without a model"
                )
                yield ref
            with Horizontal(classes="row"):
                yield Label("Envelope")
                yield Input(p.envelope, id="envelope", placeholder="default or envelope.json")
                yield Label("Seed")
                yield Input(str(p.seed), id="seed", type="integer")
            with Horizontal(classes="row"):
                yield Label("Recording")
                yield Input(p.out, id="out", placeholder="campaign.mcap")
                yield Button("Dry run", id="dry-run", variant="primary")
                yield Button("Campaign", id="to-campaign")
        with VerticalScroll(id="result-box"):
            yield KeyValue(id="envelope-info")
            yield Static(self.result_text, id="result")

    def read_plan(self) -> PlanConfig:
        """The form's plan, validated as the command line validates its options (UserError, one
        line); it becomes this screen's plan. Before the screen is first shown, the form is the
        plan it was given. The dry run, the campaign's start and its resume all read it here."""
        if not self.is_mounted:
            self.plan.validate()
            return self.plan
        kind = self.query_one("#kind", Select).value
        p = PlanConfig(
            kind=str(kind),
            poses=self.number("poses", int, "poses"),
            seed=self.number("seed", int, "seed"),
            settle_s=self.number("settle", float, "settle time"),
            readings_per_pose=self.number("readings", int, "readings per pose"),
            envelope=self.text("envelope") or "default",
            out=self.text("out"),
            warmup_s=self.plan.warmup_s,
            reference_every=self.number("ref-every", int, "reference interval"),
        )
        p.validate()
        self.plan = p
        return p

    def envelope_file(self) -> str:
        """The form's envelope as it stands: "default" or a file (what the closed-loop check
        moves inside, without validating the rest of the plan)."""
        if not self.is_mounted:
            return self.plan.envelope or "default"
        return self.text("envelope") or "default"

    def action_dry_run(self) -> None:
        try:
            p = self.read_plan()
        except UserError as e:
            self.notify(str(e), severity="error", title="Plan")
            # not an earlier check's result left on screen under the refusal (TUI audit)
            self.show_result(f"[red]not checked[/red]: {escape(str(e))}")
            return
        self.show_result(f"checking {p.poses} {p.kind} poses ...")
        self.post_message(DryRunRequested(p))

    def action_to_campaign(self) -> None:
        self.app.action_show("campaign")

    def on_button_pressed(self, event: Button.Pressed) -> None:
        if event.button.id == "dry-run":
            self.action_dry_run()
        else:
            self.action_to_campaign()

    def on_input_submitted(self, event: Input.Submitted) -> None:
        self.action_dry_run()

    # ---------------------------------------------------------------- attributes down
    def render_view(self) -> None:
        rows = self.envelope_rows
        kv = self.query_one("#envelope-info", KeyValue)
        if rows:
            kv.set_rows([("Envelope", rows[0])] + [("", r) for r in rows[1:]])
        else:
            kv.set_rows([("Envelope", "default for the robot model (shown once connected)")])
        self.query_one("#result", Static).update(self.result_text)

    def set_out(self, path: str) -> None:
        self.plan = PlanConfig(**{**self.plan.__dict__, "out": path})
        if self.is_mounted:
            self.query_one("#out", Input).value = path

    def show_result(self, text: str) -> None:
        self.result_text = text
        self.update_view()

    def show_envelope(self, rows: list[str]) -> None:
        self.envelope_rows = rows
        self.update_view()

    def show_check(self, plan: PlanConfig, result: dict) -> None:
        self.checked = plan if result.get("ok") else None
        if result.get("adaptive"):
            text = (
                f"[b]{plan.kind}[/b]: adaptive; each of the {plan.poses} poses is chosen during the "
                "campaign and checked against the envelope before it moves.  "
                + ("[green]OK[/green]" if result.get("ok") else "[red]see below[/red]")
            )
            if result.get("preview"):
                text += (
                    f"\npreview: the poses {plan.kind} chooses if the arm is its nominal chain "
                    "(the campaign's choice moves with what is measured)"
                )
            for x in result["problems"][:8]:
                text += "\n  [red]" + escape(x) + "[/red]"
        elif result["problems"]:
            shown = "\n".join("  " + escape(x) for x in result["problems"][:8])
            more = len(result["problems"]) - 8
            text = (
                f"[red]{len(result['problems'])} problem(s)[/red] in {result['targets']} poses; "
                f"the campaign will refuse them:\n{shown}"
                + (f"\n  ... {more} more" if more > 0 else "")
            )
        else:
            text = (
                f"[green]dry run OK[/green]: {result['targets']} poses and their approach "
                f"pre-poses inside the envelope; nothing moved. Recording: {plan.out}"
            )
        if result.get("reference"):
            text += "\n" + escape(result["reference"])
        for line in result.get("identification") or []:
            warn = line.startswith("warning:")
            text += "\n" + (f"[yellow]{escape(line)}[/yellow]" if warn else escape(line))
        self.show_result(text)
