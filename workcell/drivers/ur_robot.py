"""Universal Robots arm over the unmodified `ur_rtde` client (RTDE receive + control, dashboard).

`UrRobot(host)` implements the `Robot` Protocol. Reading: an RTDEReceiveInterface subscribed to
an explicit list of outputs (positions, speeds, currents, target moments, temperatures, modes,
status bits, runtime state). Moving: RTDEControlInterface.moveJ in asynchronous mode, then the
driver itself watches the receive stream until the joints have arrived, so it notices at once a
protective stop (safety status bit 2), an emergency stop (bit 7), a stopped control program or a
lost connection, and is never stuck inside the client library when a connection drops.

Errors (all `DeviceError`, the campaign fault policy decides):
- `DeviceUnreachable`: nothing answers at `host` (checked with a short TCP connect first, so a
  wrong address fails in `connect_timeout_s` instead of the operating system's minutes).
- `ProtectiveStop`: the controller reports a protective stop; `unlock_protective_stop()` clears it
  through the dashboard (retrying while PolyScope refuses during its first 5 s) and restarts the
  control program.
- `DeviceError`: connection lost, controller restarted, program stopped, move timed out. Call
  `reconnect()` (the campaign executor does, with back-off).
- `MoveAborted`: `abort_requested` (a callable a campaign sets to its abort flag) turned true
  while a move was under way: the driver sent stopJ at once rather than letting the arm run to
  its target (a Ctrl-C used to wait for the end of the move).
- `WrongRobotModel`: given `model` (the arm the campaign plans and checks the envelope with), the
  controller's dashboard answers `get robot model` with another family ("UR10" for `ur5e`), or
  the same family of the other generation (the dashboard says "UR10" for a CB3 UR10 and a UR10e
  alike, whose link lengths differ by up to 53 mm: the software version tells them apart,
  PolyScope 3.x on a CB3, 5.x or later on an e-Series): refused at every connect, before
  anything powers on or moves. A controller that does not answer a question or answers
  something unreadable is a warning (`warnings`, and `on_warning`, by default one stderr line),
  not a refusal.

- `DeviceUnreachable` also when the address answers, but not as a UR controller: the dashboard
  port (29999) sends bytes that are not text or not a dashboard's answers, or the RTDE port
  (30004) accepts connections but does not answer an RTDE protocol-version request within
  `rtde_answer_timeout_s` (checked on a socket of our own first: the ur_rtde receive
  constructor waits for that answer forever, holding the GIL, so neither a timeout nor Ctrl-C
  could end it).

Payload: `payload_setting()` reads the controller's payload setting (RTDE outputs `payload`,
`payload_cog`) on a short RTDE session of its own; `PayloadUnavailable` when the controller's
software lacks those outputs or does not answer (`campaign.payload.settle_payload` decides).

Time: `time_scale` is the simulated-controller speed-up (1.0 for a real robot). `sleep(s)` waits
s / time_scale wall seconds and move timeouts are scaled the same way. At the first connect the
driver measures the controller's clock (its RTDE `timestamp` over `time_scale_check_s` wall
seconds) and refuses (`TimeScaleMismatch`, before anything moves) a `time_scale` above the
measured rate by more than `TIME_SCALE_TOLERANCE` (+ `TIME_SCALE_SLACK`): on a real controller
`time_scale` 50 would make a 1 s settle last 20 ms. A `time_scale` below the measured rate only
makes every wait longer than asked: a warning.

The RTDEControlInterface lives in a small worker process (`python -m workcell.drivers.ur_robot
--control-worker`), driven over a pipe. Reason: after its RTDE connection drops, ur_rtde 1.6.5's
control interface reconnects from its own receive thread without ever clearing its "reconnect"
flag, starts a second receive thread on the same socket and, in our tests, crashes the process
(segmentation fault) within a second. In a worker, that takes down only the worker: the driver
kills it, raises DeviceError, and `reconnect()` starts a fresh one. The receive interface and the
dashboard client (which never reconnect by themselves) stay in this process.

Note: the ur_rtde constructors hold the Python GIL while they connect; a simulated controller must
therefore run in another process (see sim_devices/ur_process.py).
"""

from __future__ import annotations

import json
import math
import os
import re
import select
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable

import numpy as np

from workcell.drivers.protocols import (
    DeviceError,
    DeviceUnreachable,
    PayloadSetting,
    PayloadUnavailable,
    ProtectiveStop,
    RobotState,
    SafetyStop,
)

RTDE_PORT = 30004
DASHBOARD_PORT = 29999

RECEIVE_VARIABLES = [
    "timestamp",
    "actual_q",
    "actual_qd",
    "target_q",
    "actual_current",
    "target_moment",
    "joint_temperatures",
    "robot_mode",
    "safety_mode",
    "safety_status_bits",
    "runtime_state",
    "robot_status_bits",
]

ROBOT_MODES = {
    -1: "NO_CONTROLLER",
    0: "DISCONNECTED",
    1: "CONFIRM_SAFETY",
    2: "BOOTING",
    3: "POWER_OFF",
    4: "POWER_ON",
    5: "IDLE",
    6: "BACKDRIVE",
    7: "RUNNING",
    8: "UPDATING_FIRMWARE",
}
SAFETY_MODES = {
    1: "NORMAL",
    2: "REDUCED",
    3: "PROTECTIVE_STOP",
    4: "RECOVERY",
    5: "SAFEGUARD_STOP",
    6: "SYSTEM_EMERGENCY_STOP",
    7: "ROBOT_EMERGENCY_STOP",
    8: "VIOLATION",
    9: "FAULT",
    10: "VALIDATE_JOINT_ID",
    11: "UNDEFINED_SAFETY_MODE",
}
RTDE_REQUEST_PROTOCOL_VERSION = 86  # 'V'
RTDE_PROTOCOL_VERSION = 2
TIME_SCALE_TOLERANCE = 0.2  # relative: measuring over ~0.2 s is good to a few per cent
TIME_SCALE_SLACK = 0.05  # absolute, in x real time: scheduling jitter near 1x
BIT_PROTECTIVE_STOP = 1 << 2
# the other stops of RTDE's safety_status_bits (bit 10, "stopped due to safety", comes with any
# of them and with a protective stop): cleared at the cell, never by the client
SAFETY_STOP_BITS = {
    4: "safeguard stop",
    5: "system emergency stop",
    6: "robot emergency stop",
    7: "emergency stop",
    8: "safety violation",
    9: "safety fault",
}
SAFETY_STOP_MASK = sum(1 << bit for bit in SAFETY_STOP_BITS)
RUNTIME_PLAYING = 2
# the RTDE watchdog the control worker sets (ur_rtde setWatchdog): the controller stops the
# program when no input arrives for 1/WATCHDOG_MIN_HZ s of wall time; the worker kicks it
# WATCHDOG_KICKS_PER_PERIOD times as often (slack for a loaded machine's scheduling)
WATCHDOG_MIN_HZ = 2.0
WATCHDOG_KICKS_PER_PERIOD = 10
MAX_JOINT_SPEED = 3.14  # rad/s, ur_rtde's accepted range
MAX_JOINT_ACCEL = 40.0  # rad/s^2


def _import_ur_rtde():
    try:
        import dashboard_client
        import rtde_control
        import rtde_receive
    except ImportError as e:  # pragma: no cover - ur_rtde is a dependency
        raise DeviceError(f"the ur_rtde package is not installed ({e.name})") from None
    return rtde_receive, rtde_control, dashboard_client


def _two_digits(x: float) -> str:
    """49.87 -> '50', 2.513 -> '2.5', 399.2 -> '400'."""
    return f"{float(f'{x:.2g}'):g}"


def _one_line(e: BaseException) -> str:
    if isinstance(e, UnicodeDecodeError):  # ur_rtde hands any bytes to Python as str
        bad = e.object[e.start : e.start + 1].hex() if isinstance(e.object, bytes) else "?"
        return f"an answer that is not text (byte 0x{bad} at {e.start})"
    return " ".join(str(e).split()) or type(e).__name__


class MoveAborted(DeviceError):
    """A move stopped on the way because `abort_requested()` turned true (stopJ sent)."""


class WrongRobotModel(DeviceError):
    """The controller is another arm than the one the caller plans with (`UrRobot(model=)`)."""


class TimeScaleMismatch(DeviceError):
    """`time_scale` is faster than the controller's clock: every wait would be cut short."""


_UR_NAME_RE = re.compile(r"\s*ur\s*(\d+)\s*(?:e|cb3)?\s*", re.IGNORECASE)


_VERSION_RE = re.compile(r"(\d+)\.(\d+)\.(\d+)")


def ur_generation(name: str) -> str | None:
    """'ur5e', 'UR10e' -> 'e-Series'; 'ur10', 'UR5', 'ur5cb3' -> 'CB3'; None if not a UR name.

    A model name without the "e" is a CB3 arm, as in this build's catalogue ("ur10" is the CB3
    UR10)."""
    m = _UR_NAME_RE.fullmatch(str(name))
    if m is None:
        return None
    return "e-Series" if str(name).strip().lower().endswith("e") else "CB3"


def generation_from_version(answer: str) -> tuple[str | None, str | None]:
    """A dashboard `PolyscopeVersion` answer ("URSoftware 5.15.0.11820 (Mar 13 2024)") ->
    (generation, "5.15.0"): 3.x is a CB3 controller, 5.x and later (PolyScope X is 10.x) an
    e-Series one; (None, version or None) when the answer does not say."""
    m = _VERSION_RE.search(str(answer))
    if m is None:
        return None, None
    version = ".".join(m.groups())
    major = int(m.group(1))
    if major == 3:
        return "CB3", version
    if major >= 5:
        return "e-Series", version
    return None, version


def _arm_name(family: str, generation: str | None) -> str:
    """('UR10', 'e-Series') -> 'UR10e'; ('UR10', 'CB3') -> 'CB3 UR10'."""
    return f"{family}e" if generation == "e-Series" else f"CB3 {family}"


def ur_family(name: str) -> str | None:
    """'ur5e', 'UR5', 'UR5e', 'ur5cb3' -> 'UR5'; 'UR10' -> 'UR10'; None if not a UR model name.

    The family is what a controller's dashboard answers to `get robot model` (e-Series and CB3
    alike: a UR5e says "UR5")."""
    m = _UR_NAME_RE.fullmatch(str(name))
    return f"UR{int(m.group(1))}" if m else None


def _stderr_warning(msg: str) -> None:
    print(f"warning: {msg}", file=sys.stderr, flush=True)


class _ControlWorker:
    """An RTDEControlInterface in a child process; JSON lines over its stdin/stdout."""

    def __init__(self, host: str, frequency: float, timeout_s: float = 20.0) -> None:
        self.host = host
        debug = bool(os.environ.get("WORKCELL_UR_DEBUG"))
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "workcell.drivers.ur_robot",
                "--control-worker",
                host,
                repr(float(frequency)),
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=None if debug else subprocess.DEVNULL,
        )
        self._buf = b""
        self._read(timeout_s, "starting the RTDE control interface")

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def call(self, name: str, *args, timeout_s: float = 10.0):
        if not self.alive():
            raise DeviceError(f"UR {self.host}: RTDE control interface has exited")
        try:
            self.proc.stdin.write((json.dumps([name, list(args)]) + "\n").encode())
            self.proc.stdin.flush()
        except OSError:
            self.kill()
            raise DeviceError(f"UR {self.host}: RTDE control interface has exited") from None
        return self._read(timeout_s, name)

    def _read(self, timeout_s: float, what: str):
        fd = self.proc.stdout.fileno()
        t_end = time.monotonic() + timeout_s
        while b"\n" not in self._buf:
            left = t_end - time.monotonic()
            if left <= 0:
                self.kill()
                raise DeviceError(f"UR {self.host}: no answer to {what} within {timeout_s:g} s")
            r, _, _ = select.select([fd], [], [], left)
            if not r:
                continue
            chunk = os.read(fd, 65536)
            if not chunk:
                code = self.proc.poll()
                self.kill()
                raise DeviceError(
                    f"UR {self.host}: RTDE control interface died during {what} (exit code {code})"
                )
            self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        status, value = json.loads(line)
        if status == "ok":
            return value
        if status == "value_error":
            raise ValueError(value)
        raise RuntimeError(value)

    def kill(self) -> None:
        p = self.proc
        if p is None:
            return
        if p.poll() is None:
            p.kill()
        try:
            p.wait(2.0)
        except subprocess.TimeoutExpired:
            pass
        for f in (p.stdin, p.stdout):
            try:
                f.close()
            except OSError:
                pass

    def close(self) -> None:
        if self.alive():
            try:
                self.call("disconnect", timeout_s=3.0)
            except (DeviceError, RuntimeError, ValueError):
                pass
        self.kill()


def _control_worker_main(host: str, frequency: float) -> int:
    """Child side: own the RTDEControlInterface, answer one JSON line per request."""
    proto = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)  # the C++ library prints on stdout: keep it off the protocol pipe
    allowed = {
        "moveJ",
        "stopJ",
        "stopScript",
        "reuploadScript",
        "isConnected",
        "isProgramRunning",
        "disconnect",
        "triggerProtectiveStop",
    }  # no moveL: a Cartesian path is not the joint-space path the envelope checks

    def answer(status: str, value) -> None:
        proto.write(json.dumps([status, value]) + "\n")
        proto.flush()

    try:
        import rtde_control

        rc = rtde_control.RTDEControlInterface(host, frequency)
        # the control script stops the program (and the arm) when this worker stops kicking:
        # a campaign killed, a worker gone, a cable pulled mid-move. Without it a real
        # controller runs an asynchronous move to its end with nobody watching
        rc.setWatchdog(WATCHDOG_MIN_HZ)
    except Exception as e:
        answer("error", _one_line(e))
        os._exit(1)
    answer("ok", True)

    def serve(line: bytes) -> str:
        """Answer one request; its method's name ("" for a request that failed)."""
        try:
            name, args = json.loads(line)
            if name not in allowed:
                raise RuntimeError(f"method {name!r} not available")
            value = getattr(rc, name)(*args)
            if name == "reuploadScript":  # a new program: its watchdog set again
                rc.setWatchdog(WATCHDOG_MIN_HZ)
            answer("ok", value)
            return name
        except ValueError as e:
            answer("value_error", _one_line(e))
        except Exception as e:
            answer("error", _one_line(e))
        return ""

    kick_every = 1.0 / (WATCHDOG_MIN_HZ * WATCHDOG_KICKS_PER_PERIOD)
    buf = b""
    while True:
        if not select.select([0], [], [], kick_every)[0]:  # idle: the watchdog is kicked
            try:
                rc.kickWatchdog()
            except Exception:  # noqa: BLE001 - a lost connection is the next request's answer
                pass
            continue
        chunk = os.read(0, 65536)
        if not chunk:
            break  # the driver's process has gone: no more kicks, the watchdog stops the arm
        *lines, buf = (buf + chunk).split(b"\n")
        if any(serve(line) == "disconnect" for line in lines):
            break
    os._exit(0)  # skip the destructor: it joins threads that a broken reconnect left behind


class _NotRtde(Exception):
    """The peer sent bytes that are not the RTDE packet expected (args[0]: the first of them)."""


class _RtdeClosed(Exception):
    """The peer closed the connection before a whole RTDE packet came."""


def _rtde_packet(s: socket.socket, t_end: float, expect=None) -> tuple[int, bytes]:
    """One RTDE packet (type, body) from socket `s` before `time.monotonic()` reaches `t_end`,
    read exactly (never a byte of the next packet). TimeoutError when it does not come in time,
    `_RtdeClosed` when the peer closes first, `_NotRtde` when its header gives an impossible size
    (3..4096 bytes) or, with `expect` (type, size), another one: judged on the header's 3 bytes,
    so a device that is not an RTDE server is named at once."""
    buf, size = b"", 3
    while len(buf) < size:
        left = t_end - time.monotonic()
        if left <= 0:
            raise TimeoutError
        s.settimeout(left)
        chunk = s.recv(size - len(buf))
        if not chunk:
            raise _RtdeClosed
        buf += chunk
        if size == 3 and len(buf) == 3:
            size = struct.unpack(">H", buf[:2])[0]
            if not 3 <= size <= 4096 or (expect is not None and (buf[2], size) != expect):
                try:  # what else it sent at once, to name it (an HTTP status line...)
                    s.settimeout(0.05)
                    buf += s.recv(9)
                except OSError:
                    pass
                raise _NotRtde(buf)
    return buf[2], buf[3:]


class UrRobot:
    """A UR arm (e-Series, PolyScope 5) through ur_rtde. See the module doc."""

    def __init__(
        self,
        host: str,
        *,
        frequency: float = -1.0,
        time_scale: float = 1.0,
        reconnect_backoff_s: float = 0.5,
        connect_timeout_s: float = 3.0,
        arrival_tol_rad: float = 1e-4,
        settle_speed_rad_s: float = 1e-3,
        auto_power_on: bool = False,
        poll_s: float = 0.002,
        model: str | None = None,
        on_warning: Callable[[str], None] | None = None,
        rtde_answer_timeout_s: float = 10.0,
        time_scale_check_s: float = 0.2,
    ) -> None:
        if not host or not isinstance(host, str):
            raise ValueError(f"host must be a non-empty string, got {host!r}")
        if not time_scale > 0:
            raise ValueError(f"time_scale must be > 0, got {time_scale!r}")
        if not (frequency == -1.0 or frequency > 0):
            raise ValueError(
                f"frequency must be > 0 Hz or -1 (controller default), got {frequency}"
            )
        if model is not None and ur_family(model) is None:
            raise ValueError(f"model {model!r} is not a Universal Robots arm (ur5e, ur10, ...)")
        self.host = host
        self.model = model  # the arm the caller plans with; checked against the controller
        self.controller_model: str | None = None  # its answer to `get robot model`
        self.controller_version: str | None = None  # its PolyScope version, "5.15.0"
        self.warnings: list[str] = []
        self._on_warning = _stderr_warning if on_warning is None else on_warning
        self.frequency = float(frequency)
        self.time_scale = float(time_scale)
        self.reconnect_backoff_s = float(reconnect_backoff_s)
        self.connect_timeout_s = float(connect_timeout_s)
        self.arrival_tol_rad = float(arrival_tol_rad)
        self.settle_speed_rad_s = float(settle_speed_rad_s)
        self.auto_power_on = bool(auto_power_on)
        self.poll_s = float(poll_s)
        self.rtde_answer_timeout_s = float(rtde_answer_timeout_s)
        self.time_scale_check_s = float(time_scale_check_s)  # 0: do not measure
        self.controller_time_scale: float | None = None  # measured at the first connect
        # set by a campaign (its abort flag's `is_set`): a move in progress stops at once when
        # it turns true, instead of running to its target before the abort is seen
        self.abort_requested: Callable[[], bool] | None = None
        # set by a campaign: called with the arm's state while a move runs, at most every
        # `state_during_move_every_s` of controller time (the recording's joint-state stream
        # then shows the motion, not only the postures between moves)
        self.state_during_move: Callable[[RobotState], None] | None = None
        self.state_during_move_every_s = 0.04
        self._rr = None
        self._rc = None
        # this driver has run a control program on the controller: a program found running at
        # a reconnect is taken to be the one its earlier worker left (ur_rtde re-uploads its
        # script by itself on a lost connection), not another client's
        self._had_control = False
        self._db = None
        self._graveyard: list = []  # disconnected client objects (their destructors sleep)
        self._lock = threading.RLock()

    # ================================================================== connection
    def connect(self) -> None:
        with self._lock:
            self._preflight()
            rtde_receive, _, dashboard_client = _import_ur_rtde()
            if self._db is None:
                self._db = dashboard_client.DashboardClient(self.host)
            self._db_connect()
            mode = self._robotmode()
            self._check_model()  # before anything powers on or moves
            self._check_powered(mode)
            if self._rr is None or not self._rr.isConnected():
                self._bury("_rr")
                self._rtde_precheck()
                try:
                    self._rr = rtde_receive.RTDEReceiveInterface(
                        self.host, self.frequency, RECEIVE_VARIABLES
                    )
                except RuntimeError as e:
                    raise self._conn_error("RTDE receive", e) from None
                if not self._rr.isConnected():
                    raise DeviceError(f"UR {self.host}: RTDE receive connection closed at start")
            if self.controller_time_scale is None and self.time_scale_check_s > 0:
                self._check_time_scale(self._rr)  # before the control program, before any move
            if not self._protective_stopped():
                self._ensure_program()

    def close(self) -> None:
        with self._lock:
            rc, self._rc = self._rc, None
            if rc is not None:
                rc.close()
            rr, self._rr = self._rr, None
            if rr is not None:
                try:
                    rr.disconnect()
                except Exception:  # closing must not raise
                    pass
            if self._db is not None:
                try:
                    self._db.disconnect()
                except Exception:
                    pass
                self._db = None
            self._graveyard.clear()

    def reconnect(self, max_wait_s: float = 0.0) -> None:
        """Re-establish every connection after a drop or a controller restart.

        One attempt by default (the campaign executor owns the back-off); with `max_wait_s` > 0
        (robot time) it retries while the controller is unreachable, pausing
        `reconnect_backoff_s`, doubling, until that much time has passed.
        """
        t_end = time.monotonic() + max(max_wait_s, 0.0) / self.time_scale
        pause = self.reconnect_backoff_s
        while True:
            try:
                self._reconnect_once()
                return
            except DeviceUnreachable:
                if time.monotonic() + pause / self.time_scale > t_end:
                    raise
                time.sleep(pause / self.time_scale)
                pause *= 2.0

    def _reconnect_once(self) -> None:
        with self._lock:
            self._preflight()  # DeviceUnreachable while the controller is down
            self._kill_control()
            if self._rr is not None and not self._rr.isConnected():
                self._bury("_rr")
            if self._db is not None:
                try:
                    self._db.disconnect()
                except Exception:
                    pass
            self.connect()

    def __enter__(self) -> UrRobot:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ================================================================== Robot protocol
    def state(self) -> RobotState:
        with self._lock:
            rr = self._receiver()
            try:
                t = rr.getTimestamp()
                q = np.array(rr.getActualQ())
                qd = np.array(rr.getActualQd())
                temps = np.array(rr.getJointTemperatures())
                torque = np.array(rr.getTargetMoment())
                current = np.array(rr.getActualCurrent())
                mode = int(rr.getRobotMode())
                safety = int(rr.getSafetyMode())
                bits = int(rr.getSafetyStatusBits())
            except RuntimeError as e:
                raise DeviceError(
                    f"UR {self.host}: reading the RTDE state failed: {_one_line(e)}"
                ) from None
            if not rr.isConnected():
                raise DeviceError(f"UR {self.host}: RTDE connection lost")
            safety_name = SAFETY_MODES.get(safety, f"SAFETY_{safety}")
            if bits & BIT_PROTECTIVE_STOP:
                safety_name = "PROTECTIVE_STOP"
            return RobotState(
                t_s=float(t),
                q_rad=q,
                qd_rad_s=qd,
                temperature_c=temps,
                torque_nm=torque,
                current_a=current,
                mode=ROBOT_MODES.get(mode, f"MODE_{mode}"),
                safety=safety_name,
            )

    def move_joints(self, q_rad: np.ndarray, speed_rad_s: float, accel_rad_s2: float) -> None:
        q = np.asarray(q_rad, dtype=float)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise ValueError(f"q_rad: expected 6 finite joint angles, got {q.tolist()}")
        if not 0 < speed_rad_s <= MAX_JOINT_SPEED:
            raise ValueError(f"speed_rad_s must be in (0, {MAX_JOINT_SPEED}], got {speed_rad_s}")
        if not 0 < accel_rad_s2 <= MAX_JOINT_ACCEL:
            raise ValueError(f"accel_rad_s2 must be in (0, {MAX_JOINT_ACCEL}], got {accel_rad_s2}")
        with self._lock:
            rr = self._receiver()
            self._raise_if_stopped(rr, "before a move")
            rc = self._ensure_program()
            q0 = np.array(rr.getActualQ())
            try:
                ok = rc.call("moveJ", q.tolist(), float(speed_rad_s), float(accel_rad_s2), True)
            except RuntimeError as e:
                raise DeviceError(f"UR {self.host}: moveJ failed: {_one_line(e)}") from None
            if not ok:
                self._diagnose("moveJ was refused")
            dist = float(np.max(np.abs(q - q0)))
            self._wait_arrival(q, self._duration(dist, speed_rad_s, accel_rad_s2))

    def stop(self) -> None:
        with self._lock:
            rc = self._rc
            if rc is None or not rc.alive():
                raise DeviceError(f"UR {self.host}: not connected; cannot stop")
            try:
                rc.call("stopJ", 2.0, False)
            except RuntimeError as e:
                raise DeviceError(f"UR {self.host}: stopJ failed: {_one_line(e)}") from None

    def sleep(self, seconds: float) -> None:
        time.sleep(max(float(seconds), 0.0) / self.time_scale)

    # ================================================================== protective stop
    def unlock_protective_stop(self, timeout_s: float = 20.0) -> None:
        """Release a protective stop (dashboard) and restart the control program.

        PolyScope refuses an unlock during the first 5 s after the stop: retried until
        `timeout_s` of robot time have passed.
        """
        with self._lock:
            db = self._dashboard()
            deadline = time.monotonic() + timeout_s / self.time_scale + 2.0
            while True:
                try:
                    try:
                        db.closeSafetyPopup()
                    except (RuntimeError, UnicodeDecodeError):
                        pass
                    db.unlockProtectiveStop()
                    break
                except UnicodeDecodeError as e:
                    raise self._not_a_dashboard(f"unlock protective stop: {_one_line(e)}") from None
                except RuntimeError as e:
                    msg = _one_line(e)
                    if "Cannot unlock" in msg and time.monotonic() < deadline:
                        time.sleep(0.5 / self.time_scale)
                        continue
                    raise DeviceError(f"UR {self.host}: unlock protective stop: {msg}") from None
            rr = self._receiver()
            while rr.isConnected() and int(rr.getSafetyStatusBits()) & BIT_PROTECTIVE_STOP:
                if time.monotonic() > deadline:
                    raise DeviceError(f"UR {self.host}: protective stop still active after unlock")
                time.sleep(self.poll_s)
            self._ensure_program()

    # ================================================================== internals
    def _preflight(self) -> None:
        for port in (RTDE_PORT, DASHBOARD_PORT):
            try:
                with socket.create_connection((self.host, port), timeout=self.connect_timeout_s):
                    pass
            except OSError as e:
                reason = e.strerror or type(e).__name__
                if isinstance(e, TimeoutError) or "timed out" in str(e):
                    reason = f"no answer within {self.connect_timeout_s:g} s"
                raise DeviceUnreachable(
                    f"UR controller {self.host} unreachable: port {port}: {reason} "
                    "(check the address, the network and that the controller is on)"
                ) from None

    def _rtde_precheck(self) -> None:
        """Ask the RTDE port for its protocol version on a socket of our own, with a timeout.

        The ur_rtde receive constructor sends the same request and waits for the answer with no
        timeout, holding the GIL: a device that accepts TCP on 30004 but does not speak RTDE
        would hang the program beyond the reach of Ctrl-C. A socket read here is interruptible."""
        where = f"{self.host}:{RTDE_PORT}"
        wait = self.rtde_answer_timeout_s
        check = (
            "check this is a UR controller's address and that the controller has finished "
            "booting (its RTDE interface answers then)"
        )
        t_end = time.monotonic() + wait
        try:
            with socket.create_connection((self.host, RTDE_PORT), self.connect_timeout_s) as s:
                s.sendall(struct.pack(">HBH", 5, RTDE_REQUEST_PROTOCOL_VERSION, 2))
                _rtde_packet(s, t_end, expect=(RTDE_REQUEST_PROTOCOL_VERSION, 4))
        except _RtdeClosed:
            raise DeviceUnreachable(
                f"{where} accepts connections but closed one without an RTDE answer: {check}"
            ) from None
        except _NotRtde as e:
            raise DeviceUnreachable(
                f"{where} answers, but not as a UR RTDE server (it sent {e.args[0][:12]!r} to a "
                f"protocol-version request): {check}"
            ) from None
        except TimeoutError:
            raise DeviceUnreachable(
                f"{where} accepts connections but gives no RTDE answer within {wait:g} s: {check}"
            ) from None
        except OSError as e:
            raise DeviceUnreachable(
                f"UR controller {self.host} unreachable: port {RTDE_PORT}: "
                f"{e.strerror or type(e).__name__} (check the address, the network and that "
                "the controller is on)"
            ) from None

    def payload_setting(self) -> PayloadSetting:
        """The controller's active payload: its RTDE outputs `payload` (kg) and `payload_cog` (m,
        flange frame), read once on a short RTDE session of our own (version, output setup,
        start, one data packet, pause), every read with a timeout. The receive interface is not
        subscribed to them: a controller whose software lacks these outputs would refuse the
        whole recipe. Raises PayloadUnavailable (with the reason) when the controller does not
        offer them or does not answer; nothing here moves or changes a setting."""
        where = f"UR {self.host}"
        t_end = time.monotonic() + self.rtde_answer_timeout_s

        def send(ptype: int, body: bytes = b"") -> None:
            s.sendall(struct.pack(">HB", 3 + len(body), ptype) + body)

        def packet(expect=None) -> tuple[int, bytes]:
            try:
                return _rtde_packet(s, t_end, expect)
            except _RtdeClosed:
                raise PayloadUnavailable(f"{where}: RTDE closed the connection") from None
            except _NotRtde as e:
                raise PayloadUnavailable(
                    f"{where}: answers the payload read, but not in RTDE (it sent "
                    f"{e.args[0][:12]!r})"
                ) from None

        def expect(ptype: int) -> bytes:
            while True:  # skip text messages and anything else the controller sends first
                t, body = packet()
                if t == ptype:
                    return body

        try:
            with socket.create_connection((self.host, RTDE_PORT), self.connect_timeout_s) as s:
                send(RTDE_REQUEST_PROTOCOL_VERSION, struct.pack(">H", RTDE_PROTOCOL_VERSION))
                _, body = packet(expect=(RTDE_REQUEST_PROTOCOL_VERSION, 4))  # the version's
                if body != b"\x01":
                    raise PayloadUnavailable(f"{where}: RTDE protocol version 2 refused")
                send(ord("O"), struct.pack(">d", 10.0) + b"payload,payload_cog")
                setup = expect(ord("O"))
                types = setup[1:].decode("ascii", "replace").split(",")
                if types != ["DOUBLE", "VECTOR3D"]:
                    raise PayloadUnavailable(
                        f"{where}: the controller does not report its payload setting (RTDE "
                        f"outputs payload, payload_cog: {','.join(types)[:40]}; older software)"
                    )
                recipe = setup[0]
                send(ord("S"))
                if expect(ord("S"))[:1] != b"\x01":
                    raise PayloadUnavailable(f"{where}: RTDE refused to start the payload read")
                while True:
                    body = expect(ord("U"))
                    if body[:1] == bytes([recipe]) and len(body) == 1 + 4 * 8:
                        break
                mass, cx, cy, cz = struct.unpack(">dddd", body[1:])
                try:
                    send(ord("P"))
                except OSError:
                    pass
        except TimeoutError:
            raise PayloadUnavailable(
                f"{where}: no answer to the payload read within {self.rtde_answer_timeout_s:g} s"
            ) from None
        except PayloadUnavailable:
            raise
        except OSError as e:
            raise PayloadUnavailable(
                f"{where}: payload read failed ({e.strerror or type(e).__name__})"
            ) from None
        com = (float(cx), float(cy), float(cz))
        if not (math.isfinite(mass) and mass >= 0 and all(math.isfinite(c) for c in com)):
            raise PayloadUnavailable(
                f"{where}: the controller reports an unreadable payload ({mass!r} kg at {com!r})"
            )
        return PayloadSetting(float(mass), com)

    def _check_time_scale(self, rr) -> None:
        """Measure the controller's clock (RTDE timestamp against the wall clock) and refuse a
        `time_scale` faster than it, before anything moves."""
        ratio, wall = self._measure_controller_clock(rr)
        self.controller_time_scale = ratio
        ts = self.time_scale
        if abs(ratio - 1.0) <= TIME_SCALE_TOLERANCE * 1.0 + TIME_SCALE_SLACK:
            suggest = "1 (the controller runs in real time)"
        else:
            suggest = f"{_two_digits(ratio)} (a `workcell sim --time-scale X` runs at X)"
        if ts > ratio * (1.0 + TIME_SCALE_TOLERANCE) + TIME_SCALE_SLACK:
            self.controller_time_scale = None  # measure again at the next connect
            raise TimeScaleMismatch(
                f"UR {self.host}: the controller's clock runs at {_two_digits(ratio)}x real time "
                f"(its RTDE timestamp over {wall:.2f} s), but --time-scale {ts:g} would cut "
                f"every wait {_two_digits(ts / ratio)}x short: a 1 s settle to "
                f"{_two_digits(1000.0 * ratio / ts)} ms, move timeouts likewise; give --time-scale "
                f"{suggest} (nothing moved)"
            )
        if ratio > ts * (1.0 + TIME_SCALE_TOLERANCE) + TIME_SCALE_SLACK:
            self._warn(
                f"UR {self.host}: the controller's clock runs at {ratio:.3g}x real time but "
                f"the time scale is {ts:g}: every settle and wait lasts {ratio / ts:.3g}x "
                f"longer than asked; give --time-scale {suggest}"
            )

    def _measure_controller_clock(self, rr) -> tuple[float, float]:
        """(controller seconds per wall second, wall seconds measured over): from one new RTDE
        timestamp to another `time_scale_check_s` later, each seen as it arrives."""
        limit = max(1.0, 2.0 * self.time_scale_check_s)

        def next_stamp(prev: float) -> tuple[float, float]:
            t_end = time.monotonic() + limit
            while True:
                stamp, now = float(rr.getTimestamp()), time.monotonic()
                if stamp != prev:
                    return stamp, now
                if now > t_end or not rr.isConnected():
                    raise DeviceError(
                        f"UR {self.host}: the controller's RTDE timestamp did not advance "
                        f"within {limit:g} s; check the controller (restart it if it persists)"
                    )
                time.sleep(0.0005)

        c0, w0 = next_stamp(float(rr.getTimestamp()))
        time.sleep(self.time_scale_check_s)
        c1, w1 = next_stamp(float(rr.getTimestamp()))
        if c1 <= c0:
            raise DeviceError(
                f"UR {self.host}: the controller's RTDE timestamp went back while connecting "
                "(a restart?); connect again"
            )
        return (c1 - c0) / (w1 - w0), w1 - w0

    def _not_a_dashboard(self, why: str) -> DeviceUnreachable:
        return DeviceUnreachable(
            f"{self.host}:{DASHBOARD_PORT} answers, but not as a UR dashboard server ({why}); "
            "is this the robot controller's address?"
        )

    def _conn_error(self, what: str, e: BaseException) -> DeviceError:
        msg = _one_line(e)
        if "connect" in msg.lower() or "timeout" in msg.lower():
            return DeviceUnreachable(f"UR controller {self.host} unreachable ({what}): {msg}")
        return DeviceError(f"UR {self.host}: {what}: {msg}")

    def _db_connect(self) -> None:
        try:
            self._db.connect(int(self.connect_timeout_s * 1000))
        except UnicodeDecodeError as e:
            raise self._not_a_dashboard(f"greeting: {_one_line(e)}") from None
        except RuntimeError as e:
            if "cancel" in str(e).lower():  # the port answered TCP, then no greeting in time
                raise DeviceError(
                    f"UR {self.host}: the device at this address accepted the dashboard "
                    f"connection (port 29999) but sent no UR greeting within "
                    f"{self.connect_timeout_s:g} s; is this the robot controller's address?"
                ) from None
            raise self._conn_error("dashboard", e) from None

    def _dashboard(self):
        if self._db is None or not self._db.isConnected():
            if self._db is None:
                _, _, dashboard_client = _import_ur_rtde()
                self._db = dashboard_client.DashboardClient(self.host)
            self._db_connect()
        return self._db

    def _robotmode(self) -> str:
        try:
            mode = self._db.robotmode().strip()
        except UnicodeDecodeError as e:
            raise self._not_a_dashboard(f"robotmode -> {_one_line(e)}") from None
        except RuntimeError as e:
            raise DeviceError(f"UR {self.host}: dashboard robotmode: {_one_line(e)}") from None
        if not mode.startswith("Robotmode:"):  # every UR dashboard server answers this way
            raise self._not_a_dashboard(f"robotmode -> {mode[:40]!r}")
        return mode

    def _warn(self, msg: str) -> None:
        if msg in self.warnings:  # once per driver, not at every reconnect
            return
        self.warnings.append(msg)
        try:
            self._on_warning(msg)
        except Exception:  # noqa: BLE001 - a failing warning sink must not stop the connect
            pass

    def _check_model(self) -> None:
        """Refuse a controller of another arm family than `self.model` (nothing moves)."""
        if self.model is None:
            return
        try:
            answer = " ".join(str(self._db.getRobotModel()).split())
        except Exception as e:  # noqa: BLE001 - an unknown answer only warns
            answer = ""
            why = _one_line(e)
        else:
            why = f"it answered {answer[:60]!r}"
        self.controller_model = answer or None
        said = ur_family(answer) if answer else None
        want = ur_family(self.model)
        if said is None:
            self._warn(
                f"UR {self.host}: could not read the robot model from the controller "
                f"(dashboard `get robot model`: {why}; older software may not "
                f"know it); make sure the arm is a {want}, the model the campaign plans with "
                f"(--model {self.model})"
            )
            return
        from workcell.kinematics.robots import CATALOGUE  # only for the hint

        if said == want:
            self._check_generation(want, CATALOGUE)
            return

        known = [name for name in sorted(CATALOGUE) if ur_family(name) == said]
        if known:
            hint = f"give --model {' or '.join(known)}"
        else:
            hint = f"this build has no kinematics for a {said} (known: {', '.join(CATALOGUE)})"
        raise WrongRobotModel(
            f"UR {self.host}: the controller says it is a {said} but --model is {self.model}: "
            f"plans and envelope checks would use the wrong arm's kinematics; {hint} "
            "(nothing moves until they agree)"
        )

    def _check_generation(self, family: str, catalogue) -> None:
        """Refuse an e-Series controller for a CB3 `model` and the other way round (the
        dashboard's `get robot model` names only the family)."""
        want = ur_generation(self.model)
        try:
            answer = " ".join(str(self._db.polyscopeVersion()).split())
        except Exception as e:  # noqa: BLE001 - an unknown answer only warns
            answer, why = "", _one_line(e)
        else:
            why = f"it answered {answer[:60]!r}"
        said, version = generation_from_version(answer)
        self.controller_version = version
        if said is None:
            self._warn(
                f"UR {self.host}: could not tell a CB3 from an e-Series controller (dashboard "
                f"`PolyscopeVersion`: {why}); make sure the arm is a "
                f"{_arm_name(family, want)}, the model "
                f"the campaign plans with (--model {self.model})"
            )
            return
        if said == want:
            return

        known = [
            name
            for name in sorted(catalogue)
            if ur_family(name) == family and ur_generation(name) == said
        ]
        if known:
            hint = f"give --model {' or '.join(known)}"
        else:
            hint = f"this build has no kinematics for a {_arm_name(family, said)} (known: {', '.join(catalogue)})"
        raise WrongRobotModel(
            f"UR {self.host}: the controller runs PolyScope {version}, so the arm is a "
            f"{_arm_name(family, said)}, but --model {self.model} is a {_arm_name(family, want)}, whose link lengths differ: "
            f"plans and envelope checks would use the wrong arm's kinematics; {hint} (nothing moves "
            "until they agree)"
        )

    def _check_powered(self, mode: str) -> None:
        db = self._db
        if mode.endswith("RUNNING"):
            return
        if not self.auto_power_on:
            raise DeviceError(
                f"UR {self.host}: {mode}; on the teach pendant, power the arm on and release "
                "the brakes (the Initialize screen: ON, then START), then try again"
            )
        try:
            db.powerOn()
            deadline = time.monotonic() + 30.0 / self.time_scale + 2.0
            released = False
            while time.monotonic() < deadline:
                mode = db.robotmode().strip()
                if mode.endswith("RUNNING"):
                    return
                if mode.endswith("IDLE") and not released:
                    db.brakeRelease()
                    released = True
                time.sleep(0.05)
        except UnicodeDecodeError as e:
            raise self._not_a_dashboard(f"power on: {_one_line(e)}") from None
        except RuntimeError as e:
            raise DeviceError(f"UR {self.host}: power on: {_one_line(e)}") from None
        raise DeviceError(f"UR {self.host}: arm did not reach RUNNING after power on ({mode})")

    def _receiver(self):
        rr = self._rr
        if rr is None:
            raise DeviceError(f"UR {self.host}: not connected; call connect()")
        if not rr.isConnected():
            self._kill_control()
            raise DeviceError(f"UR {self.host}: RTDE connection lost")
        return rr

    def _protective_stopped(self) -> bool:
        rr = self._rr
        return rr is not None and bool(int(rr.getSafetyStatusBits()) & BIT_PROTECTIVE_STOP)

    def _raise_if_stopped(self, rr, when: str) -> None:
        bits = int(rr.getSafetyStatusBits())
        if bits & BIT_PROTECTIVE_STOP:
            raise ProtectiveStop(f"UR {self.host}: protective stop {when}")
        if bits & SAFETY_STOP_MASK:  # polled through every move: the names only when stopped
            stops = [name for bit, name in SAFETY_STOP_BITS.items() if bits & (1 << bit)]
            raise SafetyStop(f"UR {self.host}: {', '.join(stops)} {when}")

    def _raise_if_stopped_soon(self, rr, when: str, within_s: float = 0.2) -> None:
        """`_raise_if_stopped`, re-read for `within_s`: a stop's safety bits can arrive a packet
        after the refusal or runtime-state change they explain."""
        t_end = time.monotonic() + within_s
        while rr.isConnected() and time.monotonic() < t_end:
            self._raise_if_stopped(rr, when)
            time.sleep(self.poll_s)

    def _bury(self, name: str) -> None:
        obj = getattr(self, name)
        setattr(self, name, None)
        if obj is None:
            return
        try:
            obj.disconnect()
        except Exception:
            pass
        self._graveyard.append(obj)

    def _kill_control(self) -> None:
        rc, self._rc = self._rc, None
        if rc is not None:
            rc.kill()

    def _wait_playing(self, rr, rc: _ControlWorker, timeout_s: float) -> bool:
        """Both views (our receive stream and the control interface's own) show PLAYING."""
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end and rr.isConnected():
            if int(rr.getRuntimeState()) == RUNTIME_PLAYING and rc.call("isProgramRunning"):
                return True
            time.sleep(0.005)
        return False

    def _refuse_another_client(self, rr, *, moving_only: bool = False) -> None:
        """A program already running on the controller is another client's (a second campaign
        or TUI on the same arm, the teach pendant): uploading ours would take the arm from it
        (a crash audit: the second campaign stopped the first's program). A program of ours
        whose worker has just gone stops within the watchdog's period: waited for. At a
        reconnect (`moving_only`) a program still running may be one ur_rtde re-uploaded by
        itself for our dead worker (without a watchdog): refused only while the arm moves,
        which ours does not once its worker is gone."""
        t_end = time.monotonic() + 3.0 / WATCHDOG_MIN_HZ  # wall time, as the watchdog's
        while int(rr.getRuntimeState()) == RUNTIME_PLAYING:
            if not rr.isConnected():
                raise DeviceError(f"UR {self.host}: RTDE connection lost (connecting)")
            if time.monotonic() > t_end:
                moving = float(np.max(np.abs(rr.getActualQd()))) > self.settle_speed_rad_s
                if moving_only and not moving:
                    return
                raise DeviceError(
                    f"UR {self.host}: a program is running on the controller"
                    + (" and moving the arm" if moving else "")
                    + " (another client's: a campaign or TUI on this arm, or the teach "
                    "pendant); a campaign does not take the arm from it: stop that program "
                    "first, then connect again"
                )
            time.sleep(0.02)

    def _ensure_program(self) -> _ControlWorker:
        """A live control interface whose control program is PLAYING."""
        rr = self._receiver()
        rc = self._rc
        if rc is not None and not rc.alive():
            self._kill_control()
            rc = None
        if rc is None:
            self._refuse_another_client(rr, moving_only=self._had_control)
            for again in (False, True):
                try:
                    rc = _ControlWorker(self.host, self.frequency)
                    break
                except RuntimeError as e:
                    if again or "Failed to execute: stop" not in str(e):
                        raise self._conn_error("RTDE control", e) from None
                # ur_rtde saw a program running and asked the dashboard to stop it, which had
                # stopped by itself meanwhile (an earlier worker's, its watchdog): once more
                time.sleep(3.0 / WATCHDOG_MIN_HZ)
            self._rc = rc
            self._had_control = True  # a program running at a later reconnect may be ours
        if self._wait_playing(rr, rc, 0.1):
            return rc
        try:
            rc.call("reuploadScript")
        except RuntimeError as e:
            self._kill_control()
            raise DeviceError(
                f"UR {self.host}: re-uploading the control script: {_one_line(e)}"
            ) from None
        if self._wait_playing(rr, rc, 5.0):
            return rc
        self._kill_control()
        raise DeviceError(f"UR {self.host}: the control program did not start")

    def _diagnose(self, what: str) -> None:
        """Raise the most specific error for a refused/aborted command."""
        rr = self._rr
        if rr is not None:
            self._raise_if_stopped_soon(rr, f"({what})")
        if rr is None or not rr.isConnected():
            self._kill_control()
            raise DeviceError(f"UR {self.host}: RTDE connection lost ({what})")
        if int(rr.getRuntimeState()) != RUNTIME_PLAYING:
            raise DeviceError(f"UR {self.host}: control program not running ({what})")
        raise DeviceError(f"UR {self.host}: {what}")

    @staticmethod
    def _duration(dist: float, speed: float, accel: float) -> float:
        v = min(speed, MAX_JOINT_SPEED)
        if dist <= v * v / accel:
            return 2.0 * np.sqrt(dist / accel)
        return dist / v + v / accel

    def _wait_arrival(self, q: np.ndarray, expected_s: float) -> None:
        timeout = (2.0 * expected_s + 2.0) / self.time_scale + 2.0
        t_end = time.monotonic() + timeout
        rr = self._rr
        last_state_t = -math.inf
        while True:
            if self.abort_requested is not None and self.abort_requested():
                try:
                    self._rc.call("stopJ", 2.0, False)
                except Exception as e:  # noqa: BLE001 - the caller stops the robot again
                    why = f"; stopJ failed: {_one_line(e)}"
                else:
                    why = ""
                raise MoveAborted(f"UR {self.host}: move stopped by an abort{why}")
            if not rr.isConnected():
                self._kill_control()
                raise DeviceError(f"UR {self.host}: RTDE connection lost during a move")
            self._raise_if_stopped(rr, "during a move")
            if int(rr.getRuntimeState()) != RUNTIME_PLAYING:
                # ur_rtde updates the received fields one by one, so the runtime state can
                # change a packet before the safety bits are seen (CI caught this race)
                self._raise_if_stopped_soon(rr, "during a move")
                raise DeviceError(f"UR {self.host}: control program stopped during a move")
            if self.state_during_move is not None:
                t = float(rr.getTimestamp())
                if t - last_state_t >= self.state_during_move_every_s or t < last_state_t:
                    last_state_t = t
                    self.state_during_move(self.state())
            err = float(np.max(np.abs(np.array(rr.getActualQ()) - q)))
            if err < self.arrival_tol_rad:
                qd = float(np.max(np.abs(rr.getActualQd())))
                if qd < self.settle_speed_rad_s:
                    return
            if time.monotonic() > t_end:
                try:
                    self._rc.call("stopJ", 2.0, False)
                except Exception:
                    pass
                raise DeviceError(
                    f"UR {self.host}: move did not arrive within {timeout:.1f} s "
                    f"(still {err:.2e} rad away)"
                )
            time.sleep(self.poll_s)


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--control-worker":
        sys.exit(_control_worker_main(sys.argv[2], float(sys.argv[3])))
    print(
        "usage: python -m workcell.drivers.ur_robot --control-worker HOST FREQUENCY",
        file=sys.stderr,
    )
    sys.exit(2)
