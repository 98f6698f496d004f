"""The payload at the flange: what the operator states and what the controller is set to.

The gravity-dependent terms of a fit (joint compliance, link deflection) are fitted against the
recorded payload, so the recording must state the one the arm carried. A UR controller reports
its payload setting over RTDE (`UrRobot.payload_setting`); `settle_payload` reads it once the
connection is up and reconciles it with what the operator declared."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from workcell.campaign.run import CellSetup
    from workcell.drivers.protocols import Robot

PAYLOAD_MASS_TOL_KG = 0.01  # the teach pendant shows the mass to 0.01 kg
PAYLOAD_COM_TOL_M = 0.001  # and the centre of mass to the millimetre

CLI_HOW = "--payload KG[,CX,CY,CZ]"

_STATED = {
    "declared": "the declared payload",
    "recording": "the payload the resumed recording states",
}


def _implausible(cell, mass_kg: float, com) -> str | None:
    """Why a controller's payload setting is no payload the arm can carry (above its rated
    payload, or a centre of mass beyond `PAYLOAD_COM_MAX_M`, what `--payload` refuses), or
    None. Until 2026-11-28 a controller reporting 1e300 kg had it recorded as the payload."""
    from workcell.campaign.devices import PAYLOAD_COM_MAX_M

    rated = getattr(getattr(cell, "spec", None), "max_payload_kg", None)
    if rated is not None and mass_kg > rated:
        return f"above the {cell.spec.model}'s rated payload of {rated:g} kg"
    if math.hypot(*com) > PAYLOAD_COM_MAX_M:
        return f"its centre of mass {math.hypot(*com):.3g} m from the flange"
    return None


def _payload_text(kg: float, com) -> str:
    c = ", ".join(
        f"{float(x) * 1e3:.1f}" if abs(float(x)) < 10.0 else f"{float(x) * 1e3:.3g}" for x in com
    )
    return f"{kg:.3g} kg at ({c}) mm"


def settle_payload(cell: CellSetup, robot: Robot, how: str = CLI_HOW) -> list[dict]:
    """Ask a robot that reports its controller's payload setting (`payload_setting()`, the
    `PayloadReadable` Protocol) for it, once its connection is up, and reconcile it with the
    cell's: nobody stated the payload -> the controller's setting is recorded (an info note);
    stated and the controller set to another (beyond `PAYLOAD_MASS_TOL_KG` or
    `PAYLOAD_COM_TOL_M`) -> the stated one is kept and a warning says both; nobody stated it and
    the controller does not say -> a warning that 0 kg is recorded. Mutates `cell` (payload,
    `payload_source`, `payload_controller`); returns the notes to record as events. `how`: how
    the operator states a payload where the notes will be read (the option, or the TUI's field)."""
    from workcell.drivers.protocols import PayloadUnavailable

    read = getattr(robot, "payload_setting", None)
    why = "this robot driver does not read a payload setting"
    got = None
    if callable(read):
        try:
            got = read()
        except PayloadUnavailable as e:
            why = str(e)
            cell.payload_controller = {"unavailable": why}
    if got is None:
        if cell.payload_declared:
            return []
        return [
            _note(
                "warning",
                f"no payload stated and the controller's payload setting could not be read "
                f"({why}): {cell.payload_kg:g} kg at the flange is assumed for the gravity-dependent "
                "terms (joint compliance, link deflection); state the payload "
                f"as set on the teach pendant: {how}",
            )
        ]
    com = tuple(float(c) for c in got.com_m)
    cell.payload_controller = {"mass_kg": float(got.mass_kg), "com_m": list(com)}
    odd = _implausible(cell, float(got.mass_kg), com)
    if odd and (not cell.payload_declared or cell.payload_source == "controller"):
        # not adopted (the gravity terms would be fitted against it); recorded as reported
        return [
            _note(
                "warning",
                f"the controller reports a payload of {_payload_text(got.mass_kg, com)}, "
                f"{odd}: not used; {cell.payload_kg:g} kg at the flange is assumed for the "
                "gravity-dependent terms; check the teach pendant's payload setting and state "
                f"the payload: {how}",
            )
        ]
    if not cell.payload_declared or cell.payload_source == "controller":
        cell.payload_kg, cell.payload_com_m = float(got.mass_kg), com
        cell.payload_source = "controller"
        return [
            _note(
                "info",
                f"payload from the controller's setting: {_payload_text(got.mass_kg, com)} "
                "(centre of mass on the flange; the gravity-dependent terms use it); to state "
                f"another: {how}",
            )
        ]
    d_kg = abs(float(got.mass_kg) - float(cell.payload_kg))
    d_com = math.dist(com, tuple(float(c) for c in cell.payload_com_m))
    if d_kg <= PAYLOAD_MASS_TOL_KG and d_com <= PAYLOAD_COM_TOL_M:
        return []
    stated = _STATED.get(cell.payload_source, "the stated payload")
    return [
        _note(
            "warning",
            f"the controller is set to a payload of {_payload_text(got.mass_kg, com)}, {stated} "
            f"is {_payload_text(cell.payload_kg, cell.payload_com_m)} (centre of mass on the "
            "flange): the stated one is kept (the gravity-dependent terms use it); if the arm "
            "carries the controller's, stop and state that one, else correct "
            "the teach pendant's (the controller's own gravity compensation uses its setting)",
        )
    ]


def _note(level: str, message: str) -> dict:
    return {"level": level, "kind": "payload", "message": message}
