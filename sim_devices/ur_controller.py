"""A protocol-level simulated Universal Robots e-Series controller on a `SimWorld`.

The unmodified `ur_rtde` client (RTDEReceiveInterface, RTDEControlInterface, DashboardClient)
works against it. It serves, on one host address (use a loopback alias such as 127.0.0.2):

- RTDE, port 30004, protocol version 2, reporting controller version 5.15.0 for an e-Series arm
  (3.15.8 for a CB3 arm such as "ur10", as a real CB3 controller would). Output recipes may
  name any output the client knows (about 150: joints, TCP, modes, status bits, registers...);
  input recipes may name the input registers. `U` packets stream at the requested frequency in
  simulated time (500 Hz for the client's default) but never faster than `max_stream_hz` of wall
  time, so a time-scaled run stays cheap.
- Dashboard, port 29999: greeting, PolyscopeVersion (the same version), get serial number, get
  robot model (the
  family name of the simulated arm, "UR5" for a UR5e, "UR10" for a UR10), power on/off, brake
  release, robotmode, safetymode/safetystatus, programState, running, play, stop, pause, unlock
  protective stop, close (safety) popup, is in remote control (-> true; e-Series only, a CB3
  does not understand it, nor get operational mode), load, quit, ...
- Primary script port, port 30003: a program (`def name(): ... end`) uploaded there starts to
  "run" (runtime_state 2, PLAYING). The URScript is not interpreted: the register handshake of
  ur_rtde's control script is emulated (out_int0 = 1 ready, command in in_int0, out_int0 = 2 done,
  NO_CMD, ready again). Emulated commands: moveJ (1), moveJ_IK (2), moveL (3), moveL_FK (4),
  protective stop (31), stopL (33), stopJ (34), stop script (255). moveL / moveJ_IK targets go
  through a damped-least-squares IK on the nominal chain and are executed as *joint* moves (no
  straight-line tool path). Real-time commands (servo/speed...) keep the handshake but do nothing.
  Sync moves signal "done" on arrival; async moves at once, with the progress register
  (output_int_register_2) maintained the way the script does.

Physics: moves go to `world.command_move` (synchronous trapezoid) with the speed clamped to the
robot's joint speed limits and the acceleration to `max_accel_rad_s2`; a target outside the joint
limits or non-finite triggers a protective stop instead. Reported values: actual_q (target +
2 urad encoder noise), actual_qd, target_q/qd/qdd, joint_temperatures (the world's warm-up),
target_moment (motor torque holding gravity, -tau_g), actual/target_current (= moment / k_t with
k_t 13.3 N m/A for the large joints and 9.3 for the wrists), actual_TCP_pose (nominal forward
kinematics of actual_q, flange TCP), robot_mode, joint_mode, safety_mode, safety_status_bits
(bit 0 normal, bit 2 protective stop, bit 10 stopped due to safety), robot_status_bits, runtime_state,
timestamp (simulated seconds since the world clock started).

Semantics chosen where a real controller's behaviour is not pinned down by the client:
- A protective stop halts the arm at once and *pauses* the program (runtime_state 4); the dashboard
  `unlock protective stop` clears it once `pstop_unlock_delay_s` (5 s like PolyScope) of simulated
  time have passed (earlier -> the PolyScope refusal message). The program must then be restarted
  (`play`, or a new upload, e.g. RTDEControlInterface.reuploadScript()).
- The control script's RTDE watchdog (command 35, ur_rtde's setWatchdog: the minimum input
  frequency in input double register 0) stops the program and the arm when the watched input
  register gets no update for 1/frequency s of wall time (the link's time, not the scaled
  clock). Losing the RTDE connection that carries the script's inputs stops them at once when a
  watchdog is set; without one the program goes on and a move under way runs to its end, as on a
  controller (since 2026-11-29: the simulator stopped the arm on any lost client, which the
  driver, setting no watchdog, would not have had on hardware).
- A restart closes every socket and listener, stops the arm and the program, and listens again
  after `restart_down_s` of simulated time (robot mode kept unless `restart_power_off`).

Faults (`faults` dict; times are simulated seconds on the world clock; moves are counted from 1 over
every move command the emulated script executes):
    rtde_drop_after_s        list of times: close every RTDE connection (clients must reconnect)
    rtde_drop_at_move        list of move numbers: same, half-way through that move
    protective_stop_at_s     list of times: protective stop
    protective_stop_at_move  list of move numbers: protective stop half-way through that move
    restart_at_s             time or list of times: controller restart
    restart_at_move          list of move numbers: restart half-way through that move
    restart_down_s           how long a restart keeps the ports closed (default 2.0)
    restart_power_off        after a restart the robot is POWER_OFF (default False)
`inject(kind, **kw)` triggers one now: kinds `rtde_drop`, `protective_stop`, `restart` (down_s=),
`safeguard_stop` and `emergency_stop` (down_s=: the arm halts, the program pauses, the safety mode
and its status bit are set, and the stop clears by itself after down_s of simulated time, as a
light curtain's safeguard input or an e-stop released at the cell would; the program stays
paused).
"""

from __future__ import annotations

import contextlib
import re
import socket
import struct
import threading
import time
from collections.abc import Callable

import numpy as np

from sim_devices.world import ScaledClock, SimWorld

RTDE_PORT = 30004
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003

CONTROLLER_VERSION = (5, 15, 0, 11820)  # an e-Series controller (PolyScope 5)
CB3_CONTROLLER_VERSION = (3, 15, 8, 106339)  # a CB3 controller (PolyScope 3)
SERIAL_NUMBER = "20235500001"


def controller_version(model: str) -> tuple[int, int, int, int]:
    """The software version a real controller of this arm reports: 5.x for an e-Series arm
    ("ur5e"), 3.x for a CB3 arm ("ur10", "ur5cb3"). The RTDE `v` answer and the dashboard's
    PolyscopeVersion both carry it."""
    m = re.fullmatch(r"\s*ur\s*\d+\s*(e|cb3)?\s*", str(model), re.IGNORECASE)
    if m and (m.group(1) or "").lower() != "e":
        return CB3_CONTROLLER_VERSION
    return CONTROLLER_VERSION


def dashboard_model_name(model: str) -> str:
    """What `get robot model` answers for an arm: the family name, as a real controller does
    (a UR5e and a CB3 UR5 both answer "UR5", a UR10 or UR10e "UR10"); any other model name
    upper-cased."""
    m = re.fullmatch(r"\s*ur\s*(\d+)\s*(?:e|cb3)?\s*", str(model), re.IGNORECASE)
    return f"UR{m.group(1)}" if m else str(model).strip().upper()


# robot_mode
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
MODE_POWER_OFF, MODE_IDLE, MODE_RUNNING = 3, 5, 7
# safety_mode
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
}
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP = 1, 3
SAFETY_SAFEGUARD_STOP, SAFETY_ROBOT_EMERGENCY_STOP = 5, 7
# safety_status_bits of RTDE for each stopped safety mode (bit 10: stopped due to safety)
SAFETY_BITS = {
    SAFETY_PROTECTIVE_STOP: (1 << 2) | (1 << 10),
    SAFETY_SAFEGUARD_STOP: (1 << 4) | (1 << 10),
    SAFETY_ROBOT_EMERGENCY_STOP: (1 << 6) | (1 << 7) | (1 << 10),
}
# runtime_state
RT_STOPPED, RT_PLAYING, RT_PAUSED = 1, 2, 4
RUNTIME_NAMES = {
    0: "STOPPING",
    1: "STOPPED",
    2: "PLAYING",
    3: "PAUSING",
    4: "PAUSED",
    5: "RESUMING",
}
JOINT_RUNNING, JOINT_POWER_OFF, JOINT_IDLE = 253, 239, 255

# control-script command ids (ur_rtde RobotCommand::Type)
CMD_NO_CMD, CMD_MOVEJ, CMD_MOVEJ_IK, CMD_MOVEL, CMD_MOVEL_FK = 0, 1, 2, 3, 4
CMD_PROTECTIVE_STOP, CMD_STOPL, CMD_STOPJ, CMD_STOP_SCRIPT = 31, 33, 34, 255
CMD_SET_WATCHDOG = 35  # rtde_set_watchdog(input_int_register_<offset>, freq, "stop")
RT_CMDS = frozenset({24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})

K_T_NM_PER_A = np.array([13.3, 13.3, 13.3, 9.3, 9.3, 9.3])
ENCODER_NOISE_RAD = 2e-6

FAULT_KEYS = frozenset(
    {
        "rtde_drop_after_s",
        "rtde_drop_at_move",
        "protective_stop_at_s",
        "protective_stop_at_move",
        "restart_at_s",
        "restart_at_move",
        "restart_down_s",
        "restart_power_off",
    }
)

# ------------------------------------------------------------------ RTDE variable types
_FMT = {
    "DOUBLE": "d",
    "VECTOR6D": "6d",
    "VECTOR3D": "3d",
    "INT32": "i",
    "UINT32": "I",
    "UINT64": "Q",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
    "UINT8": "B",
    "BOOL": "?",
}


def _output_types() -> dict[str, str]:
    t = {}
    for n in (
        "timestamp",
        "actual_execution_time",
        "speed_scaling",
        "target_speed_fraction",
        "actual_momentum",
        "actual_main_voltage",
        "actual_robot_voltage",
        "actual_robot_current",
        "standard_analog_input0",
        "standard_analog_input1",
        "standard_analog_output0",
        "standard_analog_output1",
        "payload",
        "tool_analog_input0",
        "tool_analog_input1",
        "tool_output_voltage",
        "tool_output_current",
        "tool_temperature",
        "tcp_force_scalar",
    ):
        t[n] = "DOUBLE"
    for n in (
        "target_q",
        "target_qd",
        "target_qdd",
        "target_current",
        "target_moment",
        "actual_q",
        "actual_qd",
        "actual_qdd",
        "actual_current",
        "actual_current_as_torque",
        "actual_moment",
        "joint_control_output",
        "actual_TCP_pose",
        "actual_TCP_speed",
        "actual_TCP_force",
        "target_TCP_pose",
        "target_TCP_speed",
        "joint_temperatures",
        "actual_joint_voltage",
        "ft_raw_wrench",
        "payload_inertia",
    ):
        t[n] = "VECTOR6D"
    for n in ("actual_tool_accelerometer", "payload_cog", "elbow_position", "elbow_velocity"):
        t[n] = "VECTOR3D"
    for n in ("robot_mode", "safety_mode", "tool_mode"):
        t[n] = "INT32"
    for n in (
        "runtime_state",
        "robot_status_bits",
        "safety_status_bits",
        "output_bit_registers0_to_31",
        "output_bit_registers32_to_63",
        "input_bit_registers0_to_31",
        "input_bit_registers32_to_63",
    ):
        t[n] = "UINT32"
    t["actual_digital_input_bits"] = "UINT64"
    t["actual_digital_output_bits"] = "UINT64"
    t["joint_mode"] = "VECTOR6INT32"
    for i in range(48):
        t[f"output_int_register_{i}"] = "INT32"
        t[f"output_double_register_{i}"] = "DOUBLE"
        t[f"input_int_register_{i}"] = "INT32"
        t[f"input_double_register_{i}"] = "DOUBLE"
    return t


def _input_types() -> dict[str, str]:
    t = {
        "external_force_torque": "VECTOR6D",
        "speed_slider_mask": "UINT32",
        "speed_slider_fraction": "DOUBLE",
        "standard_digital_output_mask": "UINT8",
        "standard_digital_output": "UINT8",
        "configurable_digital_output_mask": "UINT8",
        "configurable_digital_output": "UINT8",
        "tool_digital_output_mask": "UINT8",
        "tool_digital_output": "UINT8",
        "standard_analog_output_mask": "UINT8",
        "standard_analog_output_type": "UINT8",
        "standard_analog_output_0": "DOUBLE",
        "standard_analog_output_1": "DOUBLE",
        "input_bit_registers0_to_31": "UINT32",
        "input_bit_registers32_to_63": "UINT32",
    }
    for i in range(48):
        t[f"input_int_register_{i}"] = "INT32"
        t[f"input_double_register_{i}"] = "DOUBLE"
    return t


OUTPUT_TYPES = _output_types()
INPUT_TYPES = _input_types()


# ------------------------------------------------------------------ nominal kinematics (numpy)
def _rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(r))
    if th < 1e-12:
        return np.eye(3)
    k = r / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def _matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    th = float(np.arccos(c))
    if th < 1e-9:
        return 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if np.pi - th < 1e-6:
        # near pi: axis from the symmetric part
        B = (R + np.eye(3)) / 2.0
        k = np.sqrt(np.clip(np.diag(B), 0.0, None))
        i = int(np.argmax(k))
        k = B[i] / k[i]
        return th * k / np.linalg.norm(k)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return th * w / (2.0 * np.sin(th))


class NominalChain:
    """Forward kinematics and a numeric IK of the controller's own (nominal) DH model."""

    def __init__(self, a, d, alpha, theta_offset) -> None:
        self.a, self.d = np.asarray(a, float), np.asarray(d, float)
        self.alpha, self.off = np.asarray(alpha, float), np.asarray(theta_offset, float)

    def fk(self, q: np.ndarray) -> np.ndarray:
        T = np.eye(4)
        for i in range(6):
            th = q[i] + self.off[i]
            ct, st = np.cos(th), np.sin(th)
            ca, sa = np.cos(self.alpha[i]), np.sin(self.alpha[i])
            A = np.array(
                [
                    [ct, -st * ca, st * sa, self.a[i] * ct],
                    [st, ct * ca, -ct * sa, self.a[i] * st],
                    [0.0, sa, ca, self.d[i]],
                    [0.0, 0.0, 0.0, 1.0],
                ]
            )
            T = T @ A
        return T

    def pose(self, q: np.ndarray) -> np.ndarray:
        T = self.fk(q)
        return np.concatenate([T[:3, 3], _matrix_to_rotvec(T[:3, :3])])

    def ik(self, pose: np.ndarray, q0: np.ndarray, iters: int = 200) -> np.ndarray | None:
        """Damped least squares from q0; None if it does not converge to 1e-9 m / rad."""
        p_t, R_t = np.asarray(pose[:3], float), _rotvec_to_matrix(np.asarray(pose[3:], float))
        q = np.array(q0, float)

        def err(qq):
            T = self.fk(qq)
            e_rot = _matrix_to_rotvec(R_t @ T[:3, :3].T)
            return np.concatenate([p_t - T[:3, 3], e_rot])

        e = err(q)
        lam = 1e-3
        for _ in range(iters):
            if np.linalg.norm(e) < 1e-10:
                return q
            J = np.empty((6, 6))
            h = 1e-7
            for j in range(6):
                dq = np.zeros(6)
                dq[j] = h
                J[:, j] = -(err(q + dq) - e) / h
            step = np.linalg.solve(J.T @ J + lam * np.eye(6), J.T @ e)
            q_new = q + step
            e_new = err(q_new)
            if np.linalg.norm(e_new) < np.linalg.norm(e):
                q, e, lam = q_new, e_new, max(lam / 3.0, 1e-9)
            else:
                lam *= 10.0
        return q if np.linalg.norm(e) < 1e-9 else None


# ------------------------------------------------------------------ helpers
def _recv_exact(sock: socket.socket, n: int) -> bytes | None:
    buf = bytearray()
    while len(buf) < n:
        try:
            chunk = sock.recv(n - len(buf))
        except OSError:
            return None
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)


def _as_list(v) -> list[float]:
    if v is None:
        return []
    if isinstance(v, (int, float)):
        return [float(v)]
    return [float(x) for x in v]


def validate_faults(faults: dict | None) -> dict:
    f = dict(faults or {})
    unknown = set(f) - FAULT_KEYS
    if unknown:
        raise ValueError(
            f"unknown UR controller fault(s) {sorted(unknown)}; known: {sorted(FAULT_KEYS)}"
        )
    out: dict = {}
    for k in ("rtde_drop_after_s", "protective_stop_at_s", "restart_at_s"):
        vals = sorted(_as_list(f.get(k)))
        if any(not np.isfinite(v) or v < 0 for v in vals):
            raise ValueError(f"{k}: times must be finite and >= 0 s, got {vals}")
        out[k] = vals
    for k in ("rtde_drop_at_move", "protective_stop_at_move", "restart_at_move"):
        given = _as_list(f.get(k))
        if any(not np.isfinite(v) or v != int(v) or v < 1 for v in given):
            # int(inf) raised OverflowError (a traceback); 1.5 became move 1
            raise ValueError(f"{k}: move numbers are whole numbers from 1, got {given}")
        out[k] = {int(v) for v in given}
    down = float(f.get("restart_down_s", 2.0))
    if not (np.isfinite(down) and down >= 0):
        raise ValueError(f"restart_down_s must be >= 0 s, got {down}")
    out["restart_down_s"] = down
    out["restart_power_off"] = bool(f.get("restart_power_off", False))
    return out


class _Conn:
    """One accepted client socket with a send lock."""

    def __init__(self, sock: socket.socket, kind: str) -> None:
        self.sock = sock
        self.kind = kind
        self.lock = threading.Lock()
        self.closed = threading.Event()
        self.controls_script = False  # carries the control script's input registers

    def send(self, data: bytes) -> bool:
        if self.closed.is_set():
            return False
        try:
            with self.lock:
                self.sock.sendall(data)
            return True
        except OSError:
            self.close()
            return False

    def close(self) -> None:
        if self.closed.is_set():
            return
        self.closed.set()
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        with contextlib.suppress(OSError):
            self.sock.close()


# ------------------------------------------------------------------ the controller
class UrControllerSim:
    """Serve RTDE (30004), dashboard (29999) and the script port (30003) for one `SimWorld`.

    Time is the world's clock: a `ScaledClock` is used as is (`time_scale`, if given, must match
    it); a world with a virtual clock gets `ScaledClock(time_scale or 1.0)`.
    """

    def __init__(
        self,
        world: SimWorld,
        host: str = "127.0.0.2",
        *,
        time_scale: float | None = None,
        faults: dict | None = None,
        seed: int = 0,
        max_stream_hz: float = 125.0,
        max_accel_rad_s2: float = 40.0,
        pstop_unlock_delay_s: float = 5.0,
        ports: tuple[int, int, int] = (RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT),
        log: Callable[[str], None] | None = None,
    ) -> None:
        if time_scale is not None and not time_scale > 0:
            raise ValueError(f"time_scale must be > 0, got {time_scale!r}")
        if not max_stream_hz > 0:
            raise ValueError(f"max_stream_hz must be > 0, got {max_stream_hz!r}")
        self.world = world
        with world.lock:
            # a protocol server needs wall-clock time: give a virtual-clock world a scaled clock
            if not isinstance(world.clock, ScaledClock):
                world.clock = ScaledClock(1.0 if time_scale is None else time_scale)
            elif time_scale is not None and abs(world.clock.time_scale - time_scale) > 1e-12:
                raise ValueError(
                    f"time_scale {time_scale} differs from the world clock's "
                    f"{world.clock.time_scale}"
                )
        self.clock = world.clock
        self.time_scale = float(self.clock.time_scale)
        self.host = host
        self.faults = validate_faults(faults)
        self.max_stream_hz = float(max_stream_hz)
        self.max_accel = float(max_accel_rad_s2)
        self.pstop_unlock_delay_s = float(pstop_unlock_delay_s)
        self.rtde_port, self.dashboard_port, self.script_port = ports
        self._log = log or (lambda msg: None)
        spec = world.truth.nominal
        self.spec = spec
        self.controller_version = controller_version(spec.model)
        self.chain = NominalChain(spec.dh.a, spec.dh.d, spec.dh.alpha, spec.dh.theta_offset)
        self.rng = np.random.default_rng(seed + 104729)

        self.lock = threading.RLock()
        self.robot_mode = MODE_RUNNING
        self.safety_mode = SAFETY_NORMAL
        self.runtime_state = RT_STOPPED
        self.program_loaded = False
        self.program_name = "<unnamed>"
        self.pstop_time: float | None = None
        self.pstop_reason = ""
        self.in_int = np.zeros(48, dtype=np.int64)
        self.in_dbl = np.zeros(48)
        self.out_int = np.zeros(48, dtype=np.int64)
        self.out_dbl = np.zeros(48)
        self.reg_offset = 0
        self._executing = False
        self._pending_done: str | None = None  # "motion" while a sync move runs
        self._async_running = False
        self._async_wr_count = 0
        self._async_op_id = 0
        self.move_count = 0
        self._scheduled: list[tuple[float, str]] = []  # (sim time, kind)
        self._time_faults = sorted(
            [(t, "rtde_drop") for t in self.faults["rtde_drop_after_s"]]
            + [(t, "protective_stop") for t in self.faults["protective_stop_at_s"]]
            + [(t, "restart") for t in self.faults["restart_at_s"]]
        )
        self.events: list[tuple[float, str]] = []  # (sim time, what) for tests/diagnosis
        self.stats = {
            "rtde_conns": 0,
            "dashboard_conns": 0,
            "script_uploads": 0,
            "moves": 0,
            "rtde_drops": 0,
            "protective_stops": 0,
            "watchdog_stops": 0,
            "restarts": 0,
        }

        self._prev_qd = np.zeros(6)
        self._prev_t = 0.0
        self._snap: dict | None = None
        self._grav: np.ndarray | None = None
        self._fk_key = b""
        self._fk: tuple[np.ndarray, np.ndarray] = (np.zeros(6), np.zeros(3))
        self._grav_key = b""
        self._grav_wall = 0.0
        self._snap_wall = 0.0

        self._stop = threading.Event()
        self._down_until: float | None = None  # sim time the restart ends
        self._safety_until: float | None = None  # sim time an injected safety stop clears
        # the control script's RTDE watchdog (ur_rtde setWatchdog): wall time, as the link's
        self._watchdog_hz: float | None = None
        self._watchdog_last = time.monotonic()
        self._last_tick_wall = time.monotonic()  # the control loop's last pass (wall time)
        self._listeners: dict[int, socket.socket] = {}
        self._conns: set[_Conn] = set()
        self._script_owner: _Conn | None = None
        self._threads: list[threading.Thread] = []
        self._started = False

    # ================================================================== lifecycle
    def start(self) -> UrControllerSim:
        if self._started:
            return self
        self._stop.clear()
        self._open_listeners()
        self._started = True
        t = threading.Thread(target=self._control_loop, name="ur-sim-control", daemon=True)
        t.start()
        self._threads.append(t)
        self._event("controller started")
        return self

    def stop(self) -> None:
        self._stop.set()
        self._close_listeners()
        self._close_conns(None)
        for t in list(self._threads):
            if t is not threading.current_thread():
                t.join(timeout=2.0)
        self._threads.clear()
        self._started = False

    def __enter__(self) -> UrControllerSim:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _event(self, what: str) -> None:
        t = self.clock.now()
        self.events.append((t, what))
        self._log(f"[ur-sim {t:9.3f}] {what}")

    # ================================================================== listeners
    def _open_listeners(self) -> None:
        for port, kind in (
            (self.rtde_port, "rtde"),
            (self.dashboard_port, "dashboard"),
            (self.script_port, "script"),
        ):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((self.host, port))
            except OSError as e:
                s.close()
                self._close_listeners()
                raise OSError(f"UR sim: cannot listen on {self.host}:{port}: {e}") from None
            s.listen(8)
            s.settimeout(0.1)
            self._listeners[port] = s
            t = threading.Thread(
                target=self._accept_loop, args=(s, kind), name=f"ur-sim-accept-{kind}", daemon=True
            )
            t.start()
            self._threads.append(t)

    def _close_listeners(self) -> None:
        for s in list(self._listeners.values()):
            with contextlib.suppress(OSError):
                s.close()
        self._listeners.clear()

    def _close_conns(self, kind: str | None) -> None:
        with self.lock:
            conns = [c for c in self._conns if kind is None or c.kind == kind]
        for c in conns:
            c.close()

    def _accept_loop(self, srv: socket.socket, kind: str) -> None:
        while not self._stop.is_set():
            try:
                sock, _ = srv.accept()
            except TimeoutError:
                continue
            except OSError:
                return  # listener closed (stop or restart)
            sock.settimeout(None)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            # a client that stops reading must not block the controller: sends time out
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, struct.pack("ll", 2, 0))
            conn = _Conn(sock, kind)
            with self.lock:
                self._conns.add(conn)
            target = {
                "rtde": self._serve_rtde,
                "dashboard": self._serve_dashboard,
                "script": self._serve_script,
            }[kind]
            t = threading.Thread(
                target=self._run_conn, args=(target, conn), name=f"ur-sim-{kind}", daemon=True
            )
            t.start()

    def _run_conn(self, target, conn: _Conn) -> None:
        try:
            target(conn)
        except Exception as e:  # a broken client must never take the controller down
            self._event(f"{conn.kind} connection error: {e!r}")
        finally:
            conn.close()
            with self.lock:
                self._conns.discard(conn)
                if conn.controls_script and self._script_owner is conn:
                    self._script_owner = None
                    self._control_client_lost()

    # ================================================================== faults
    def inject(self, kind: str, **kw) -> None:
        """Trigger a fault now: `rtde_drop`, `protective_stop` (reason=), `restart` (down_s=)."""
        if kind == "rtde_drop":
            self._rtde_drop()
        elif kind == "protective_stop":
            with self.lock:
                self._protective_stop(str(kw.get("reason", "injected")))
        elif kind == "restart":
            down = float(kw.get("down_s", self.faults["restart_down_s"]))
            if not (np.isfinite(down) and down >= 0):  # NaN: the controller never came back
                raise ValueError(f"restart down_s must be a finite time >= 0 s, got {down}")
            self._restart(down)
        elif kind in ("safeguard_stop", "emergency_stop"):
            down = float(kw.get("down_s", 1.0))
            if not (np.isfinite(down) and down >= 0):
                raise ValueError(f"{kind} down_s must be a finite time >= 0 s, got {down}")
            mode = (
                SAFETY_SAFEGUARD_STOP if kind == "safeguard_stop" else SAFETY_ROBOT_EMERGENCY_STOP
            )
            with self.lock:
                self._halt_and_pause()
                self.safety_mode = mode
                self._safety_until = self.clock.now() + down
            self._event(f"fault: {kind.replace('_', ' ')} ({down:.2f} s)")
        else:
            raise ValueError(
                f"unknown fault kind {kind!r}; known: rtde_drop, protective_stop, restart, "
                "safeguard_stop, emergency_stop"
            )

    def _rtde_drop(self) -> None:
        self.stats["rtde_drops"] += 1
        self._event("fault: dropping every RTDE connection")
        self._close_conns("rtde")

    def _restart(self, down_s: float) -> None:
        self.stats["restarts"] += 1
        self._event(f"fault: controller restart ({down_s:.2f} s down)")
        with self.lock:
            self._down_until = self.clock.now() + down_s
            self.world.stop()
            self._end_program()
            if self.faults["restart_power_off"]:
                self.robot_mode = MODE_POWER_OFF
            self.safety_mode = SAFETY_NORMAL
            self.pstop_time = None
            self.world.protective_stop = False
            self.program_loaded = False
        self._close_listeners()
        self._close_conns(None)

    def _protective_stop(self, reason: str, at: float | None = None) -> None:
        """Caller holds self.lock. `at`: the sim time the stop was due (default now)."""
        if self.safety_mode == SAFETY_PROTECTIVE_STOP:
            return
        self.stats["protective_stops"] += 1
        self._halt_and_pause(at)
        self.world.protective_stop = True
        self.safety_mode = SAFETY_PROTECTIVE_STOP
        self.pstop_time = self.clock.now()
        self.pstop_reason = reason
        self._event(f"protective stop: {reason}")

    def _halt_and_pause(self, at: float | None = None) -> None:
        """Caller holds self.lock: a safety stop halts the arm (where it was at sim time `at`,
        default now) and pauses the program; a move under way is not completed."""
        self.world.stop(at=at)
        self._pending_done = None
        self._async_running = False
        if self.runtime_state == RT_PLAYING:
            self.runtime_state = RT_PAUSED

    def _control_client_lost(self) -> None:
        """Caller holds self.lock: the RTDE client feeding the control script went away. With
        a watchdog set its inputs stop, so it stops the program (here at once; on a controller
        within 1/min_frequency); without one, as on a controller, the program goes on and a
        move under way runs to its end."""
        if self.runtime_state in (RT_PLAYING, RT_PAUSED) and self._watchdog_hz:
            self.stats["watchdog_stops"] += 1
            self.world.stop()
            self._end_program()
            self._event("control client lost: the watchdog stopped the program")
        elif self.runtime_state in (RT_PLAYING, RT_PAUSED):
            self._event("control client lost: no watchdog set, the program goes on")

    # ================================================================== control loop
    def _control_loop(self) -> None:
        period = 0.004  # input packets also run the script step at once
        while not self._stop.is_set():
            try:
                self._tick()
            except Exception as e:  # keep serving; record what went wrong
                self._event(f"control loop error: {e!r}")
            time.sleep(period)

    def _tick(self) -> None:
        now = self.clock.now()
        if self._down_until is not None:
            if now >= self._down_until:
                self._down_until = None
                try:
                    self._open_listeners()
                    self._event("controller back after restart")
                except OSError as e:
                    self._event(f"restart: {e}")
                    self._down_until = now + 0.5
            return
        wall = time.monotonic()
        starved, self._last_tick_wall = wall - self._last_tick_wall > 0.05, wall
        with self.lock:
            hz = self._watchdog_hz
            if starved:
                # this process was not scheduled for a while (a loaded machine): inputs that
                # arrived meanwhile wait in the socket, unread; a controller's real-time loop
                # never stalls, so the client is not blamed for it
                self._watchdog_last = wall
            if hz and self.runtime_state == RT_PLAYING:
                quiet = wall - self._watchdog_last
                if quiet > 1.0 / hz:
                    self.stats["watchdog_stops"] += 1
                    self._event(f"watchdog: no input for {quiet:.2f} s: program stopped")
                    self._end_program()
            if self._safety_until is not None and now >= self._safety_until:
                self._safety_until = None
                self.safety_mode = SAFETY_NORMAL
                self._event("safety stop cleared at the cell")
        todo = []
        while self._time_faults and self._time_faults[0][0] <= now:
            todo.append(self._time_faults.pop(0))
        with self.lock:
            while self._scheduled and self._scheduled[0][0] <= now:
                todo.append(self._scheduled.pop(0))
        for t_fault, kind in todo:
            if kind == "rtde_drop":
                self._rtde_drop()
            elif kind == "protective_stop":
                with self.lock:
                    # the arm stops where it was when the fault was due, however late this tick
                    self._protective_stop("fault injection", at=t_fault)
            elif kind == "restart":
                self._restart(self.faults["restart_down_s"])
                return
        with self.lock:
            if self.runtime_state == RT_PLAYING:
                self._script_step()
            elif self._async_running and self.world.motion_done():
                self._async_running = False
                self._write_async_progress(-1)

    # ---------------------------------------------------------------- emulated control script
    def _script_step(self) -> None:
        """One pass of the rtde_control main loop (caller holds the lock)."""
        o = self.reg_offset
        if self._async_running and self.world.motion_done():
            self._async_running = False
            self._write_async_progress(-1)
        if self._pending_done == "motion" and self.world.motion_done():
            self._pending_done = None
            self.out_int[o + 0] = 2
        cmd = int(self.in_int[o + 0])
        if cmd in RT_CMDS:
            self.out_int[o + 0] = 1
            return
        if cmd == CMD_NO_CMD:
            self._executing = False
            self._pending_done = None
            self.out_int[o + 0] = 1
            return
        if self._executing:
            return
        self._executing = True
        if cmd == CMD_STOP_SCRIPT:
            self._event("script: stop script")
            self._end_program()
            return
        self._process_cmd(cmd)
        if self.runtime_state == RT_PLAYING and self._pending_done is None:
            self.out_int[o + 0] = 2

    def _process_cmd(self, cmd: int) -> None:
        o = self.reg_offset
        if cmd in (CMD_MOVEJ, CMD_MOVEJ_IK, CMD_MOVEL, CMD_MOVEL_FK):
            target = self.in_dbl[o : o + 6].copy()
            speed, accel = float(self.in_dbl[o + 6]), float(self.in_dbl[o + 7])
            is_async = int(self.in_int[o + 1]) == 1
            if cmd in (CMD_MOVEJ_IK, CMD_MOVEL):
                q_now, _ = self.world.joint_state()
                q = self.chain.ik(target, q_now)
                if q is None:
                    self._event(f"script: no inverse kinematics for pose {target.tolist()}")
                    self._end_program()  # a runtime error ends the program
                    return
                target = q
                if cmd == CMD_MOVEL:  # tool speed/accel (m/s): use a moderate joint profile
                    speed, accel = min(speed * 4.0, 1.05), min(accel * 4.0, 1.4)
            self._start_move(target, speed, accel, is_async)
        elif cmd in (CMD_STOPJ, CMD_STOPL):
            self._event("script: stop motion")
            self.world.stop()
            if self._async_running:
                self._async_running = False
                self._write_async_progress(-1)
        elif cmd == CMD_PROTECTIVE_STOP:
            self._protective_stop("protective_stop() requested by the client")
        elif cmd == CMD_SET_WATCHDOG:
            hz = float(self.in_dbl[o + 0])  # read_input_float_reg(0)
            if np.isfinite(hz) and hz > 0:
                self._watchdog_hz = hz
                self._watchdog_last = time.monotonic()
                self._event(f"script: watchdog set ({hz:g} Hz)")
        # anything else: acknowledged without effect

    def _start_move(self, q_target: np.ndarray, speed: float, accel: float, is_async: bool) -> None:
        self.move_count += 1
        self.stats["moves"] += 1
        k = self.move_count
        lim = self.spec.joint_limits_rad
        if not np.all(np.isfinite(q_target)) or not (np.isfinite(speed) and np.isfinite(accel)):
            self._protective_stop(f"move {k}: non-finite target or profile")
            return
        if np.any(q_target < lim[:, 0]) or np.any(q_target > lim[:, 1]):
            self._protective_stop(f"move {k}: target outside the joint limits")
            return
        speed = float(np.clip(speed, 1e-4, float(np.min(self.world.vmax))))
        accel = float(np.clip(accel, 1e-4, self.max_accel))
        dur = self.world.command_move(q_target, speed, accel)
        self._event(f"move {k}: {dur:.3f} s {'async' if is_async else 'sync'}")
        t_half = self.clock.now() + 0.5 * dur
        for key, kind in (
            ("rtde_drop_at_move", "rtde_drop"),
            ("protective_stop_at_move", "protective_stop"),
            ("restart_at_move", "restart"),
        ):
            if k in self.faults[key]:
                self._scheduled.append((t_half, kind))
        self._scheduled.sort()
        if is_async:
            self._async_running = True
            self._write_async_progress(0)
        else:
            self._pending_done = "motion"

    def _write_async_progress(self, value: int) -> None:
        self._async_wr_count = (self._async_wr_count + 1) % 128
        if value == 0:
            self._async_op_id = (self._async_op_id + 1) % 128
        reg = self._async_wr_count * 65536 + self._async_op_id * 16777216
        if value >= 0:
            reg += min(value, 32767) + 32768
        self.out_int[self.reg_offset + 2] = reg

    def _start_program(self, name: str) -> bool:
        """Caller holds the lock."""
        if self.robot_mode != MODE_RUNNING or self.safety_mode != SAFETY_NORMAL:
            self._event(f"program {name!r} not started: robot not ready")
            return False
        self.world.stop()
        self.runtime_state = RT_PLAYING
        self.program_name = name
        self.program_loaded = True
        self._executing = False
        self._pending_done = None
        self._async_running = False
        self._write_async_progress(-1)
        self.out_int[self.reg_offset + 0] = 0
        self._event(f"program {name!r} playing")
        return True

    def _end_program(self) -> None:
        if self.runtime_state != RT_STOPPED:
            self.world.stop()
        self.runtime_state = RT_STOPPED
        self._watchdog_hz = None  # the program's setting
        self._executing = False
        self._pending_done = None
        self._async_running = False

    # ================================================================== state snapshot
    def snapshot(self) -> dict:
        """The controller's current output values (cached for a millisecond)."""
        wall = time.monotonic()
        if self._snap is not None and wall - self._snap_wall < 0.004:
            return self._snap
        with self.lock:
            t = self.clock.now()
            q, qd = self.world.joint_state()
            dt = t - self._prev_t
            qdd = (qd - self._prev_qd) / dt if dt > 1e-6 else np.zeros(6)
            if dt > 1e-6:
                self._prev_qd, self._prev_t = qd.copy(), t
            tau_g = self._gravity(q, qd, wall)
            temps = self.world.joint_temperatures_c()
            moment = -tau_g
            current = moment / K_T_NM_PER_A
            q_act = q + self.rng.normal(0.0, ENCODER_NOISE_RAD, 6)
            key = q.tobytes()
            if key != self._fk_key:  # the TCP pose of the (noise-free) joints, cached at rest
                T = self.chain.fk(q)
                pose = np.concatenate([T[:3, 3], _matrix_to_rotvec(T[:3, :3])])
                accel = T[:3, :3].T @ np.array([0.0, 0.0, 9.80665])
                self._fk_key, self._fk = key, (pose, accel)
            pose, accel = self._fk
            h = 1e-3
            tcp_speed = (self.chain.pose(q + h * qd) - pose) / h if np.any(qd) else np.zeros(6)
            safety_bits = SAFETY_BITS.get(self.safety_mode, 1)
            playing = self.runtime_state == RT_PLAYING
            powered = self.robot_mode in (4, 5, 6, 7)
            status_bits = (1 if powered else 0) | (2 if playing else 0)
            jm = {MODE_RUNNING: JOINT_RUNNING, MODE_IDLE: JOINT_IDLE}.get(
                self.robot_mode, JOINT_POWER_OFF
            )
            truth = self.world.truth
            snap = {
                "timestamp": t,
                "target_q": q,
                "target_qd": qd,
                "target_qdd": qdd,
                "target_current": current,
                "target_moment": moment,
                "actual_q": q_act,
                "actual_qd": qd,
                "actual_qdd": qdd,
                "actual_current": current,
                "actual_current_as_torque": moment,
                "actual_moment": moment,
                "joint_control_output": current,
                "actual_TCP_pose": pose,
                "actual_TCP_speed": tcp_speed,
                "actual_TCP_force": np.zeros(6),
                "target_TCP_pose": pose,
                "target_TCP_speed": tcp_speed,
                "actual_digital_input_bits": 0,
                "joint_temperatures": temps,
                "actual_execution_time": 0.35,
                "robot_mode": self.robot_mode,
                "joint_mode": [jm] * 6,
                "safety_mode": self.safety_mode,
                "actual_tool_accelerometer": accel,
                "speed_scaling": 1.0,
                "target_speed_fraction": 1.0,
                "actual_momentum": 0.0,
                "actual_main_voltage": 48.0,
                "actual_robot_voltage": 48.0 if powered else 0.0,
                "actual_robot_current": float(0.4 + 0.05 * np.abs(current).sum()),
                "actual_joint_voltage": np.full(6, 48.0 if powered else 0.0),
                "actual_digital_output_bits": 0,
                "runtime_state": self.runtime_state,
                "robot_status_bits": status_bits,
                "safety_status_bits": safety_bits,
                "standard_analog_input0": 0.0,
                "standard_analog_input1": 0.0,
                "standard_analog_output0": 0.0,
                "standard_analog_output1": 0.0,
                "ft_raw_wrench": np.zeros(6),
                "payload": float(truth.declared_payload_kg),  # as set on the controller
                "payload_cog": np.asarray(truth.declared_payload_com_m, float),
                "payload_inertia": np.zeros(6),
                "elbow_position": np.zeros(3),
                "elbow_velocity": np.zeros(3),
                "out_int": self.out_int.copy(),
                "out_dbl": self.out_dbl.copy(),
                "in_int": self.in_int.copy(),
                "in_dbl": self.in_dbl.copy(),
            }
        self._snap, self._snap_wall = snap, wall
        return snap

    def _gravity(self, q: np.ndarray, qd: np.ndarray, wall: float) -> np.ndarray:
        """Gravity torques (the truth model costs milliseconds): exact at rest, refreshed at
        most every 20 ms of wall time while moving."""
        key = q.tobytes()
        if key == self._grav_key:
            return self._grav
        if self._grav is not None and np.any(qd) and wall - self._grav_wall < 0.02:
            return self._grav
        self._grav = self.world.truth.gravity_torques(q)
        self._grav_key, self._grav_wall = key, wall
        return self._grav

    @staticmethod
    def _value(snap: dict, name: str):
        if name.startswith("output_int_register_"):
            return int(snap["out_int"][int(name.rsplit("_", 1)[1])])
        if name.startswith("output_double_register_"):
            return float(snap["out_dbl"][int(name.rsplit("_", 1)[1])])
        if name.startswith("input_int_register_"):
            return int(snap["in_int"][int(name.rsplit("_", 1)[1])])
        if name.startswith("input_double_register_"):
            return float(snap["in_dbl"][int(name.rsplit("_", 1)[1])])
        return snap.get(name, 0)

    # ================================================================== RTDE server
    def _serve_rtde(self, conn: _Conn) -> None:
        self.stats["rtde_conns"] += 1
        sock = conn.sock
        out_names: list[str] = []
        out_fmt = ""
        out_id = 0
        out_freq = 500.0
        in_recipes: dict[int, tuple[list[str], str]] = {}
        streamer: threading.Thread | None = None
        streaming = threading.Event()

        def reply(ptype: int, payload: bytes) -> None:
            conn.send(struct.pack(">HB", 3 + len(payload), ptype) + payload)

        while not conn.closed.is_set() and not self._stop.is_set():
            head = _recv_exact(sock, 3)
            if head is None:
                break
            size, ptype = struct.unpack(">HB", head)
            body = _recv_exact(sock, size - 3) if size > 3 else b""
            if body is None:
                break
            if ptype == ord("V"):
                ver = struct.unpack(">H", body[:2])[0] if len(body) >= 2 else 0
                reply(ord("V"), struct.pack(">B", 1 if ver in (1, 2) else 0))
            elif ptype == ord("v"):
                reply(ord("v"), struct.pack(">IIII", *self.controller_version))
            elif ptype == ord("O"):
                if len(body) < 8:
                    reply(ord("O"), b"\x00NOT_FOUND")
                    continue
                freq = struct.unpack(">d", body[:8])[0]
                names = [n for n in body[8:].decode("ascii", "replace").split(",") if n]
                types = [OUTPUT_TYPES.get(n, "NOT_FOUND") for n in names]
                out_id = out_id % 255 + 1  # a one-byte id: the 256th raised ValueError
                reply(ord("O"), bytes([out_id]) + ",".join(types).encode())
                if "NOT_FOUND" not in types:
                    out_names = names
                    out_fmt = ">B" + "".join(_FMT[t] for t in types)
                    # 500 Hz for none; at least 0.01 Hz (1e-300 Hz overflowed the stream's
                    # sleep and killed its thread)
                    out_freq = min(max(freq, 0.01), 500.0) if freq > 0 else 500.0
            elif ptype == ord("I"):
                names = [n for n in body.decode("ascii", "replace").split(",") if n]
                types = [INPUT_TYPES.get(n, "NOT_FOUND") for n in names]
                rid = len(in_recipes) + 1
                if rid > 255:  # a one-byte id: the 256th raised ValueError, dropping the link
                    reply(ord("I"), bytes([0]) + b"NOT_FOUND")
                    continue
                if "NOT_FOUND" not in types:
                    in_recipes[rid] = (names, ">" + "".join(_FMT[t] for t in types))
                    if "input_int_register_0" in names or "input_int_register_24" in names:
                        conn.controls_script = True
                        with self.lock:
                            self._script_owner = conn
                reply(ord("I"), bytes([rid]) + ",".join(types).encode())
            elif ptype == ord("S"):
                ok = bool(out_names)
                reply(ord("S"), b"\x01" if ok else b"\x00")
                if ok and not streaming.is_set():
                    streaming.set()
                    streamer = threading.Thread(
                        target=self._stream,
                        args=(conn, out_names, out_fmt, out_freq, streaming),
                        name="ur-sim-rtde-stream",
                        daemon=True,
                    )
                    streamer.start()
            elif ptype == ord("P"):
                streaming.clear()
                if streamer is not None:
                    streamer.join(timeout=1.0)
                    streamer = None
                reply(ord("P"), b"\x01")
            elif ptype == ord("U"):
                if not body:
                    continue
                rec = in_recipes.get(body[0])
                if rec is None:
                    continue
                names, fmt = rec
                try:
                    vals = struct.unpack(fmt, body[1:])
                except struct.error:
                    continue
                self._apply_inputs(names, vals)
            # other packet types (M text, ...) are ignored
        streaming.clear()

    def _apply_inputs(self, names: list[str], vals: tuple) -> None:
        with self.lock:
            i = 0
            for n in names:
                t = INPUT_TYPES[n]
                width = 6 if t.startswith("VECTOR6") else 1
                v = vals[i : i + width]
                i += width
                if n.startswith("input_int_register_"):
                    k = int(n.rsplit("_", 1)[1])
                    self.in_int[k] = int(v[0])
                    if k == self.reg_offset:  # the register the watchdog watches
                        self._watchdog_last = time.monotonic()
                elif n.startswith("input_double_register_"):
                    self.in_dbl[int(n.rsplit("_", 1)[1])] = float(v[0])
            # let the script react at once (the real loop runs at 500 Hz)
            if self.runtime_state == RT_PLAYING:
                self._script_step()

    def _stream(
        self, conn: _Conn, names: list[str], fmt: str, freq: float, streaming: threading.Event
    ) -> None:
        wall_period = 1.0 / min(freq * self.time_scale, self.max_stream_hz)
        next_t = time.monotonic()
        while streaming.is_set() and not conn.closed.is_set() and not self._stop.is_set():
            snap = self.snapshot()
            vals: list = [1]
            for n in names:
                v = self._value(snap, n)
                if isinstance(v, (list, tuple, np.ndarray)):
                    vals.extend(
                        float(x) if isinstance(x, (float, np.floating)) else int(x) for x in v
                    )
                else:
                    vals.append(v)
            payload = struct.pack(fmt, *vals)
            if not conn.send(struct.pack(">HB", 3 + len(payload), ord("U")) + payload):
                return
            next_t += wall_period
            delay = next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                next_t = time.monotonic()

    # ================================================================== dashboard server
    def _serve_dashboard(self, conn: _Conn) -> None:
        self.stats["dashboard_conns"] += 1
        conn.send(b"Connected: Universal Robots Dashboard Server\n")
        f = conn.sock.makefile("rb")
        try:
            while not conn.closed.is_set() and not self._stop.is_set():
                try:
                    raw = f.readline()
                except OSError:
                    return
                if not raw:
                    return
                line = raw.decode("utf-8", "replace").strip()
                if not line:
                    if raw.strip(b" \t\r\n"):  # control characters only: answered, not lost
                        conn.send(b"could not understand: '" + raw.strip() + b"'\n")
                    continue
                answer, close = self._dashboard(line)
                conn.send((answer + "\n").encode())
                if close:
                    return
        finally:
            with contextlib.suppress(OSError):
                f.close()

    def _dashboard(self, line: str) -> tuple[str, bool]:
        low = line.lower()
        v = self.controller_version
        with self.lock:
            if low == "polyscopeversion":
                return f"URSoftware {v[0]}.{v[1]}.{v[2]}.{v[3]} (Mar 13 2024)", False
            if low == "version":
                return f"{v[0]}.{v[1]}.{v[2]}.{v[3]}", False
            if low == "get serial number":
                return SERIAL_NUMBER, False
            if low == "get robot model":
                return dashboard_model_name(self.spec.model), False
            if low == "is in remote control" and tuple(v[:2]) >= (5, 6):  # 5.6+ only; a CB3
                return "true", False  # answers it as an unknown command
            if low == "robotmode":
                return f"Robotmode: {ROBOT_MODES[self.robot_mode]}", False
            if low == "safetymode":
                return f"Safetymode: {SAFETY_MODES[self.safety_mode]}", False
            if low == "safetystatus":
                return f"Safetystatus: {SAFETY_MODES[self.safety_mode]}", False
            if low == "programstate":
                return f"{RUNTIME_NAMES[self.runtime_state]} {self.program_name}", False
            if low == "running":
                playing = self.runtime_state == RT_PLAYING
                return f"Program running: {'true' if playing else 'false'}", False
            if low == "power on":
                if self.robot_mode == MODE_POWER_OFF:
                    self.robot_mode = MODE_IDLE
                    self._event("dashboard: power on")
                return "Powering on", False
            if low == "power off":
                self.world.stop()
                self._end_program()
                self.robot_mode = MODE_POWER_OFF
                self._event("dashboard: power off")
                return "Powering off", False
            if low == "brake release":
                if self.robot_mode in (MODE_IDLE, 4):
                    self.robot_mode = MODE_RUNNING
                    self._event("dashboard: brake release")
                return "Brake releasing", False
            if low == "play":
                if not self.program_loaded or not self._start_program(self.program_name):
                    return "Failed to execute: play", False
                return "Starting program", False
            if low == "stop":
                if self.runtime_state == RT_STOPPED:
                    return "Failed to execute: stop", False
                self._end_program()
                self._event("dashboard: stop")
                return "Stopped", False
            if low == "pause":
                if self.runtime_state != RT_PLAYING:
                    return "Failed to execute: pause", False
                self.world.stop()
                self.runtime_state = RT_PAUSED
                return "Pausing program", False
            if low == "unlock protective stop":
                if self.safety_mode == SAFETY_PROTECTIVE_STOP:
                    since = self.clock.now() - (self.pstop_time or 0.0)
                    if since < self.pstop_unlock_delay_s:
                        return (
                            "Cannot unlock protective stop until 5s after occurrence. "
                            "Always inspect cause of protective stop before unlocking"
                        ), False
                    self.safety_mode = SAFETY_NORMAL
                    self.world.protective_stop = False
                    self.pstop_time = None
                    self._event("dashboard: protective stop released")
                return "Protective stop releasing", False
            if low == "close popup":
                return "closing popup", False
            if low == "close safety popup":
                return "closing safety popup", False
            if low.startswith("popup"):
                return "showing popup", False
            if low == "restart safety":
                self.safety_mode = SAFETY_NORMAL
                self.world.protective_stop = False
                self.pstop_time = None
                self.robot_mode = MODE_POWER_OFF
                self._end_program()
                return "Restarting safety", False
            if low == "get loaded program":
                if not self.program_loaded:
                    return "No program loaded", False
                return f"Loaded program: {self.program_name}", False
            if low.startswith("load "):
                self.program_name = line[5:].strip()
                self.program_loaded = True
                return f"Loading program: {self.program_name}", False
            if low == "isprogramsaved":
                return f"true {self.program_name}", False
            if low.startswith("addtolog"):
                return "Added log message", False
            if low.startswith("setuserrole"):
                return f"Setting user role: {line[12:].strip()}", False
            if low == "get operational mode" and tuple(v[:2]) >= (5, 6):
                return "NONE", False
            if low == "quit":
                return "Disconnected", True
            if low == "shutdown":
                return "Shutting down", True
        return f"could not understand: '{line}'", False

    # ================================================================== script port
    _OFFSET_RE = re.compile(rb"reg_offset_int = # int register offset\n\s*(\d+)")
    _DEF_RE = re.compile(rb"^def\s+([A-Za-z_][A-Za-z0-9_]*)\s*\(\s*\)\s*:", re.M)
    _END_RE = re.compile(rb"^end[ \t]*\r?$", re.M)

    def _serve_script(self, conn: _Conn) -> None:
        buf = bytearray()
        while not conn.closed.is_set() and not self._stop.is_set():
            try:
                chunk = conn.sock.recv(65536)
            except OSError:
                return
            if not chunk:
                return
            buf += chunk
            while True:
                m_def = self._DEF_RE.search(buf)
                if m_def is None:
                    if len(buf) > 1 << 20:
                        buf.clear()
                    break
                m_end = self._END_RE.search(buf, m_def.end())
                if m_end is None:
                    break
                name = bytes(m_def.group(1)).decode()
                program = bytes(buf[m_def.start() : m_end.end()])
                del buf[: m_end.end()]
                self._program_uploaded(name, program)

    def _program_uploaded(self, name: str, program: bytes) -> None:
        self.stats["script_uploads"] += 1
        m = self._OFFSET_RE.search(program)
        with self.lock:
            if name != "rtde_control":
                # custom functions (sendCustomScriptFunction...): acknowledge like a finished call
                self._event(f"script: ran custom program {name!r} ({len(program)} bytes)")
                return
            off = m.group(1) if m else b"0"
            if off not in (b"0", b"24"):  # ur_rtde's two register banks (0-23, 24-47)
                # a real controller's script would fail at its first register read; here every
                # control tick raised IndexError past register 47, filling the event list
                self._event(
                    f"script: {name!r} refused: register offset {off[:12].decode()} is neither "
                    "0 nor 24"
                )
                return
            self.reg_offset = int(off)
            self._event(
                f"script: {name!r} uploaded ({len(program)} bytes, "
                f"register offset {self.reg_offset})"
            )
            self._start_program(name)
