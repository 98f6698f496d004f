"""What the terminal UI's pilot tests share: wait for a condition with a message that says
where the app stood, connect the devices, type into an input, ask which screen is up."""

from __future__ import annotations

import time


async def until(pilot, cond, timeout_s: float = 180.0, what: str = "") -> None:
    """Pause the pilot until `cond()`; after `timeout_s` fail saying the screen, the campaign
    view's state and the last notices."""
    t0 = time.monotonic()
    while not cond():
        await pilot.pause(0.05)
        if time.monotonic() - t0 > timeout_s:
            app = pilot.app
            camp = getattr(app, "views", {}).get("campaign")
            raise AssertionError(
                f"timed out waiting for {what or cond}: screen {type(app.screen).__name__}, "
                f"campaign {getattr(camp, 'state', None)} after {getattr(camp, 'done', None)} "
                f"poses, last notices {getattr(app, 'notices', [])[-3:]}"
            )


def screen_is(app, name: str) -> bool:
    return type(app.screen).__name__ == name


async def connect(app, pilot, timeout_s: float = 60.0) -> None:
    await pilot.press("ctrl+r")
    await until(pilot, lambda: app.devices is not None, timeout_s, "connect")


async def set_input(pilot, screen, wid: str, value: str) -> None:
    screen.query_one(f"#{wid}").value = value
    await pilot.pause()


async def device_status(app, pilot, timeout_s: float = 10.0):
    """Ask the Devices screen for a fresh status poll and return what it shows."""
    from workcell.tui import messages as m

    view = app.views["devices"]
    view.status = None
    app.post_message(m.StatusRequested())
    await until(pilot, lambda: view.status is not None, timeout_s, "status")
    return view.status
