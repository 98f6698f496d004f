"""A compact key/value panel (labels aligned, values updated in place)."""

from __future__ import annotations

from rich.table import Table
from textual.widgets import Static


class KeyValue(Static):
    """Rows of `label  value`; `set_rows([(label, value), ...])` replaces them."""

    DEFAULT_CSS = """
    KeyValue { height: auto; }
    """

    def __init__(self, rows: list[tuple[str, str]] | None = None, **kw) -> None:
        super().__init__("", **kw)
        self.rows: list[tuple[str, str]] = list(rows or [])

    def on_mount(self) -> None:
        self.set_rows(self.rows)

    def set_rows(self, rows: list[tuple[str, str]]) -> None:
        self.rows = list(rows)
        t = Table.grid(padding=(0, 1))
        t.add_column(style="bold", no_wrap=True)
        t.add_column(overflow="fold")
        for k, v in self.rows:
            t.add_row(k, v)
        self.update(t)
