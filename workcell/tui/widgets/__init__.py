"""Reusable widgets of the terminal UI."""

from workcell.tui.widgets.confirm import ConfirmScreen, PathPrompt
from workcell.tui.widgets.plots import ResidualPlot, SeriesPlot
from workcell.tui.widgets.table import KeyValue

__all__ = ["ConfirmScreen", "PathPrompt", "ResidualPlot", "SeriesPlot", "KeyValue"]
