"""Small device Protocols. Real drivers and simulated ones implement the same ones.

Units SI. Joint vectors ordered base to wrist. Tracker positions are in the `tracker` frame.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

# the farthest a laser tracker measures (longest-range ones reach ~160 m): a coordinate beyond it
# is not a measurement (the serial driver's readings and the recording checks use it)
TRACKER_RANGE_M = 200.0


class DeviceError(RuntimeError):
    """A device failed in a way the campaign's fault policy may handle (retry, reconnect)."""


class DeviceUnreachable(DeviceError):
    """The device cannot be reached at all (address, port, cable)."""


class OtherInstrument(DeviceError):
    """A reconnect reached a device, but not the one connected before (another serial number):
    its frame is not the campaign's. Not retried: the campaign stops."""


class ProtectiveStop(DeviceError):
    """The robot controller entered a protective stop."""


class SafetyStop(DeviceError):
    """The controller stopped the arm for safety other than a protective stop: a safeguard
    stop, an emergency stop, a safety violation or fault. Someone at the cell clears it; a
    campaign never moves the arm again by itself after one (no reconnect, no retry)."""


@dataclass(frozen=True)
class RobotState:
    """One snapshot of the arm as the controller reports it."""

    t_s: float  # controller time, seconds
    q_rad: np.ndarray  # (6,)
    qd_rad_s: np.ndarray  # (6,)
    temperature_c: np.ndarray | None = None  # (6,)
    torque_nm: np.ndarray | None = None  # (6,) estimated joint torque (or None)
    current_a: np.ndarray | None = None  # (6,)
    mode: str = "RUNNING"  # RUNNING, IDLE, POWER_OFF, ...
    safety: str = "NORMAL"  # NORMAL, PROTECTIVE_STOP, EMERGENCY_STOP, ...


@dataclass(frozen=True)
class TrackerReading:
    """One raw tracker reading of the SMR."""

    position_m: np.ndarray  # (3,) in tracker frame (nan if no distance)
    sigma_m: np.ndarray  # (3,) instrument's stated 1-sigma per axis
    status: str = "ok"  # ok, beam_broken, out_of_range, error
    t_s: float = 0.0
    extra: dict = field(default_factory=dict)


@runtime_checkable
class Robot(Protocol):
    def connect(self) -> None: ...
    def close(self) -> None: ...
    def state(self) -> RobotState: ...
    def move_joints(self, q_rad: np.ndarray, speed_rad_s: float, accel_rad_s2: float) -> None:
        """Blocking joint move; raises ProtectiveStop or DeviceError."""
        ...

    def stop(self) -> None: ...
    def sleep(self, seconds: float) -> None:
        """Wait `seconds` of robot time (simulators may scale time)."""
        ...


@dataclass(frozen=True)
class PayloadSetting:
    """The payload a robot controller is set to carry (what its own gravity model uses)."""

    mass_kg: float
    com_m: tuple[float, float, float]  # centre of mass in the flange (tool-flange) frame


class PayloadUnavailable(DeviceError):
    """The controller does not report its payload setting (older software), or the read failed."""


@runtime_checkable
class PayloadReadable(Protocol):
    """A robot whose controller reports its payload setting (optional beside `Robot`)."""

    def payload_setting(self) -> PayloadSetting:
        """The controller's payload setting; raises PayloadUnavailable with the reason."""
        ...


@runtime_checkable
class Tracker(Protocol):
    def connect(self) -> None: ...
    def close(self) -> None: ...
    def measure(self) -> TrackerReading:
        """One reading; status other than `ok` for beam break etc. Raises DeviceError on I/O."""
        ...


def close_quietly(*devices: Robot | Tracker) -> None:
    """Close each device, best effort: a device that fails to close (already gone, connection
    dropped) does not stop the others from closing."""
    for dev in devices:
        try:
            dev.close()
        except Exception:  # noqa: BLE001 - closing is best effort
            pass


@contextmanager
def driver_hooks(robot: object, **hooks: object) -> Iterator[None]:
    """Give a driver its optional hooks for the block (UrRobot's `abort_requested`: a callable
    that cuts a move short when it turns true; `state_during_move`: called with the states read
    while the arm moves), and take them back afterwards (None), so that a later user of the same
    robot is not stopped by this one's abort. A hook the driver has not is skipped."""
    given = [name for name in hooks if hasattr(robot, name)]
    for name in given:
        setattr(robot, name, hooks[name])
    try:
        yield
    finally:
        for name in given:
            setattr(robot, name, None)
