"""Plots (textual-plotext): the live residual of a campaign and before/after residuals."""

from __future__ import annotations

import math

from textual_plotext import PlotextPlot


class SeriesPlot(PlotextPlot):
    """Lines and scatter series in one plot; `set_series(...)` redraws.

    series: list of (label, xs, ys, kind) with kind "line", "scatter" or "bar"."""

    DEFAULT_CSS = """
    SeriesPlot { height: 1fr; min-height: 6; }
    """

    def __init__(self, title: str = "", xlabel: str = "", ylabel: str = "", **kw) -> None:
        super().__init__(**kw)
        self.title, self.xlabel, self.ylabel = title, xlabel, ylabel
        self.series: list[tuple[str, list, list, str]] = []
        self.note = ""

    def on_mount(self) -> None:
        self.redraw()

    def set_series(self, series: list[tuple[str, list, list, str]], note: str = "") -> None:
        self.series = series
        self.note = note
        self.redraw()

    def redraw(self) -> None:
        plt = self.plt
        plt.clear_data()
        plt.clear_figure()
        title = self.title + (f"  {self.note}" if self.note else "")
        plt.title(title)
        if self.xlabel:
            plt.xlabel(self.xlabel)
        if self.ylabel:
            plt.ylabel(self.ylabel)
        drawn = False
        for label, xs, ys, kind in self.series:
            pts = [
                (x, y) for x, y in zip(xs, ys, strict=False) if y is not None and math.isfinite(y)
            ]
            if not pts:
                continue
            x, y = [p[0] for p in pts], [p[1] for p in pts]
            if kind == "scatter":
                plt.scatter(x, y, label=label, marker="dot")
            elif kind == "bar":
                plt.bar(x, y, label=label)
            else:
                plt.plot(x, y, label=label, marker="braille")
            drawn = True
        if not drawn:
            plt.plot([0], [0])
        self.refresh()


class ResidualPlot(SeriesPlot):
    """Live campaign plot: residual of each pose against the nominal model (um), the running
    RMS, and the EKF-ANN online estimate's RMS when available."""

    def __init__(self, **kw) -> None:
        super().__init__(title="residual vs nominal (um)", xlabel="pose", ylabel="um", **kw)

    def update_live(
        self,
        residuals_um: list[float],
        rms_um: list[float | None],
        ekf_um: list[float | None],
        note: str = "",
    ) -> None:
        xs = list(range(1, len(residuals_um) + 1))
        xr = list(range(1, len(rms_um) + 1))
        series = [
            ("pose residual", xs, residuals_um, "scatter"),
            ("RMS nominal", xr, rms_um, "line"),
        ]
        if any(v is not None for v in ekf_um):
            series.append(("EKF-ANN innovation", list(range(1, len(ekf_um) + 1)), ekf_um, "line"))
        self.set_series(series, note)
