"""The six screens of the terminal UI."""

from workcell.tui.screens.campaign import CampaignScreen
from workcell.tui.screens.devices import DevicesScreen
from workcell.tui.screens.diagnose import DiagnoseScreen
from workcell.tui.screens.export import ExportScreen
from workcell.tui.screens.fit import FitScreen
from workcell.tui.screens.plan import PlanScreen

SCREENS = {
    "devices": DevicesScreen,
    "plan": PlanScreen,
    "campaign": CampaignScreen,
    "fit": FitScreen,
    "diagnose": DiagnoseScreen,
    "export": ExportScreen,
}

__all__ = [
    "SCREENS",
    "CampaignScreen",
    "DevicesScreen",
    "DiagnoseScreen",
    "ExportScreen",
    "FitScreen",
    "PlanScreen",
]
