"""Shared pieces of the screens: header/footer, a title line, number parsing."""

from __future__ import annotations

from textual.app import ComposeResult
from textual.screen import Screen
from textual.widgets import Footer, Header, Input

from workcell.errors import UserError


def folder_text(summary: dict) -> str:
    """Where an output's files went: the folder as the operator typed it (relative to the
    folder `workcell tui` was started in), and whether the export made it."""
    folder = summary.get("folder") or "."
    text = "the working folder" if folder == "." else folder
    return text + (", a new folder" if summary.get("new_folder") else "")


class WorkcellScreen(Screen):
    """A screen with the app header and the key footer; subclasses yield their body."""

    TITLE_TEXT = ""

    def compose(self) -> ComposeResult:
        yield Header(show_clock=False, icon="")
        yield from self.body()
        yield Footer()

    def body(self) -> ComposeResult:  # pragma: no cover - overridden
        yield from ()

    def on_mount(self) -> None:
        self.sub_title = self.TITLE_TEXT
        if not getattr(self.app, "cursor_blink", True):  # deterministic screenshots
            for w in self.query(Input):
                w.cursor_blink = False
        self.render_view()

    def render_view(self) -> None:
        """Draw the stored attributes (screens are composed lazily, on first show)."""

    def on_resize(self) -> None:
        # screens whose CSS has `.narrow` rules re-flow below 100 columns; others ignore it
        self.set_class(self.size.width < 100, "narrow")

    def set_recording(self, path: str) -> None:
        """For screens with a `#recording` input: remember the path and show it."""
        self.recording = path
        if self.is_mounted:
            self.query_one("#recording", Input).value = path

    def update_view(self) -> None:
        if self.is_mounted:
            self.render_view()

    # values of Input widgets, validated with one clear line
    def text(self, wid: str) -> str:
        return self.query_one(f"#{wid}", Input).value.strip()

    def number(self, wid: str, kind=float, what: str | None = None):
        raw = self.text(wid)
        try:
            return kind(raw)
        except ValueError:
            raise UserError(f"{what or wid}: expected a number, got {raw!r}") from None


def um(x) -> str:
    return "-" if x is None else f"{float(x) * 1e6:.1f} um"
