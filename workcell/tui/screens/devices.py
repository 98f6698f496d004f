"""Devices: robot and tracker addresses (sim or real), connect/disconnect, live status."""

from __future__ import annotations

import math

import numpy as np
from rich.markup import escape
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.widgets import Button, Checkbox, Input, Label

from workcell.campaign.devices import parse_payload, parse_smr_offset
from workcell.errors import UserError
from workcell.tui.backend import DeviceConfig
from workcell.tui.messages import ConnectRequested, DisconnectRequested, StatusRequested
from workcell.tui.screens.base import WorkcellScreen
from workcell.tui.widgets import KeyValue


def check_time_scale(
    scale: float, robot: str, start_sim: bool, *, opt: str = "time scale", robot_opt: str = "Robot"
) -> None:
    """The command line's rules for a time scale (`workcell tui`, `workcell campaign
    --time-scale`): a finite number > 0, and other than 1 only for a controller that runs it (the
    simulators started here, or `workcell sim --time-scale X` at ur://HOST): the in-process
    simulation runs on virtual time and would ignore it. `opt`, `robot_opt`: the names the
    operator typed them under (the form's labels, or the command line's options)."""
    from workcell.campaign.devices import check_time_scale_range

    check_time_scale_range(scale, opt)
    if robot == "sim" and not start_sim and scale != 1:
        raise UserError(
            f"{opt} {scale:g} with {robot_opt} sim: the in-process simulation runs on virtual "
            "time, so it has no effect; "
            + (
                "set it to 1 (it is for the simulators started here, or for a `workcell sim "
                "--time-scale X` controller given as Robot ur://HOST)"
                if opt == "time scale"
                else "leave it out (it is for --sim, or for a `workcell sim --time-scale X` "
                "controller, given with --robot ur://HOST)"
            )
        )


def _robot_spec(model: str):
    from workcell.kinematics.robots import robot_by_name

    try:
        return robot_by_name(model)
    except ValueError as e:
        raise UserError(f"Model: {e}") from None


def _smr_text(text: str) -> str:
    v = parse_smr_offset(text, "SMR offset")
    return ",".join(f"{x:g}" for x in v) + " m" + (" (the default)" if not text.strip() else "")


def config_changes(connected: DeviceConfig, form: DeviceConfig) -> list[str]:
    """What the Devices form says differently from the devices connected, one "what VALUE
    (connected: VALUE)" each; [] when a campaign would run with what the form shows."""
    out = []
    for label, a, b in (
        ("Robot", connected.robot, form.robot),
        ("Tracker", connected.tracker, form.tracker),
        ("Model", connected.model, form.model),
    ):
        if a.strip() != b.strip():
            out.append(f"{label} {b} (connected: {a})")
    if not math.isclose(connected.time_scale, form.time_scale, rel_tol=1e-6):
        out.append(f"time scale {form.time_scale:g} (connected: {connected.time_scale:g})")
    if bool(connected.start_sim) != bool(form.start_sim):
        out.append(
            f"start simulators {'on' if form.start_sim else 'off'} "
            f"(connected: {'on' if connected.start_sim else 'off'})"
        )
    if connected.payload.strip() != form.payload.strip():
        out.append(
            f"payload {form.payload.strip() or 'not declared'} "
            f"(connected: {connected.payload.strip() or 'not declared'})"
        )
    smr_a = parse_smr_offset(connected.smr_offset, "SMR offset")
    smr_b = parse_smr_offset(form.smr_offset, "SMR offset")
    if not np.allclose(smr_a, smr_b, rtol=0.0, atol=1e-9):
        out.append(
            f"SMR offset {_smr_text(form.smr_offset)} "
            f"(connected: {_smr_text(connected.smr_offset)})"
        )
    return out


class DevicesScreen(WorkcellScreen):
    TITLE_TEXT = "Devices"
    DEFAULT_CSS = """
    DevicesScreen #form { height: auto; padding: 0 1; }
    DevicesScreen .row { height: 3; }
    DevicesScreen .row Label { width: 16; padding: 1 1 0 0; }
    DevicesScreen .row Input { width: 1fr; }
    DevicesScreen #buttons { height: 3; padding: 0 1; }
    DevicesScreen #buttons Button { margin-right: 1; }
    DevicesScreen #status { padding: 0 1; border: round $primary; height: auto; }
    """
    BINDINGS = [
        Binding("ctrl+r", "connect", "Connect"),
        Binding("ctrl+t", "disconnect", "Disconnect"),
        Binding("ctrl+l", "refresh_status", "Status"),
    ]

    def __init__(self, config: DeviceConfig) -> None:
        super().__init__()
        self.config = config
        self.status: dict | None = None
        self.busy: str | None = None

    def body(self) -> ComposeResult:
        c = self.config
        with Vertical(id="form"):
            with Horizontal(classes="row"):
                yield Label("Robot")
                yield Input(c.robot, id="robot", placeholder="sim or ur://HOST")
            with Horizontal(classes="row"):
                yield Label("Tracker")
                yield Input(c.tracker, id="tracker", placeholder="sim or serial:///dev/ttyX")
            with Horizontal(classes="row"):
                yield Label("Model / scale")
                yield Input(c.model, id="model", placeholder="ur5e")
                yield Input(f"{c.time_scale:g}", id="time-scale", placeholder="time scale")
            with Horizontal(classes="row"):
                yield Label("SMR m / payload")
                yield Input(c.smr_offset, id="smr-offset", placeholder="X,Y,Z m; 0,0,0.06")
                yield Input(c.payload, id="payload", placeholder="kg[,CX,CY,CZ] or empty")
        with Horizontal(id="buttons"):
            yield Button("Connect", id="connect", variant="primary")
            yield Button("Disconnect", id="disconnect")
            yield Checkbox("start simulators", c.start_sim, id="start-sim")
        yield KeyValue(id="status")

    def read_config(self) -> DeviceConfig:
        """The form's devices, refused (UserError) where the command line refuses them. Before
        the screen is first shown, the form is what it was given."""
        if not self.is_mounted:
            return self.config
        scale = self.number("time-scale", float, "time scale")
        robot = self.text("robot") or "sim"
        start_sim = self.query_one("#start-sim", Checkbox).value
        check_time_scale(scale, robot, start_sim)
        c = self.config
        smr = self.text("smr-offset")
        parse_smr_offset(smr, "SMR offset")  # refused here, before connecting
        payload = self.text("payload")
        model = self.text("model") or "ur5e"
        if payload:
            parse_payload(payload, _robot_spec(model), "Payload")
        return DeviceConfig(
            robot=robot,
            tracker=self.text("tracker") or "sim",
            model=self.text("model") or "ur5e",
            effects=c.effects,
            seed=c.seed,
            time_scale=scale,
            start_sim=start_sim,
            sim_host=c.sim_host,
            sim_faults=c.sim_faults,
            sim_tracker_faults=c.sim_tracker_faults,
            smr_offset=smr,
            payload=payload,
        )

    def action_connect(self) -> None:
        try:
            cfg = self.read_config()
        except UserError as e:
            self.notify(str(e), severity="error", title="Devices")
            return
        self.show_busy(f"connecting to {cfg.robot} / {cfg.tracker} ...")
        self.post_message(ConnectRequested(cfg))

    def action_disconnect(self) -> None:
        self.post_message(DisconnectRequested())

    def action_refresh_status(self) -> None:
        self.post_message(StatusRequested())

    def on_button_pressed(self, event: Button.Pressed) -> None:
        if event.button.id == "connect":
            self.action_connect()
        elif event.button.id == "disconnect":
            self.action_disconnect()

    def on_input_submitted(self, event: Input.Submitted) -> None:
        self.action_connect()

    # ---------------------------------------------------------------- attributes down
    def show_busy(self, text: str) -> None:
        self.busy = text
        self.update_view()

    def show_status(self, status: dict | None) -> None:
        self.status, self.busy = status, None
        self.update_view()

    def render_view(self) -> None:
        kv = self.query_one("#status", KeyValue)
        status = self.status
        if self.busy:
            kv.set_rows([("Status", self.busy)])
            return
        if not status:
            kv.set_rows(
                [
                    ("Connection", "not connected"),
                    (
                        "Hint",
                        "sim = in-process simulation; ur://HOST + serial://PORT = hardware "
                        "or `workcell sim`; tick 'start simulators' to start them here",
                    ),
                ]
            )
            return
        q = status.get("q_rad")
        joints = " ".join(f"{x:+.3f}" for x in q) if q else "-"
        rows = [
            ("Connection", f"connected ({status.get('kind', '?')})"),
            ("Robot", f"{status.get('robot')}  mode {status.get('robot_mode')}"),
            ("Safety", str(status.get("safety"))),
            ("Joints (rad)", joints),
            ("Tracker", f"{status.get('tracker')}  {status.get('tracker_status')}"),
            ("Tracker model", str(status.get("tracker_model"))),
        ]
        if status.get("robot_error"):
            rows.append(("Robot error", escape(status["robot_error"])))
        kv.set_rows(rows)
