"""The campaign executor: runs a plan's poses through move -> settle -> measure -> record.

It talks to devices only through the Robot/Tracker Protocols and writes records to a `sink` with
the RecordingWriter's methods (joint_state, tracker_measurement, sample, event); it does not know
MCAP. Faults become `/campaign/event` records and are handled by a small policy:
- beam break / no distance: wait and retry up to `max_beam_retries`, then skip the pose (event);
- tracker I/O error: the driver resyncs; the executor retries, then skips the pose;
- robot connection lost: reconnect with exponential back-off (if the driver can), then continue;
- protective stop: pause, event, and resume when `resume_protective_stop()` says so; the
  `MAX_PROTECTIVE_STOPS_IN_A_ROW`-th stop with no pose recorded since the first ends the campaign
  with the arm left stopped (`CampaignResult.stopped_by == "protective_stop"`);
- a tracker that gives not one usable reading at `MAX_TRACKER_SKIPS_IN_A_ROW` poses in a row (no
  pose recorded between them) ends the campaign (`stopped_by == "tracker"`): it has stopped measuring;
  so does a tracker every reconnect attempt failed to reach, at once (no move to another pose);
  so does a tracker reconnect that reaches another instrument (`OtherInstrument`: another serial
  number, so another station and frame);
- `MAX_REFUSED_IN_A_ROW` poses in a row refused before any motion (their paths from where the arm
  is leave the envelope; no pose recorded, no move made between them), or an adaptive plan with
  no pose left that the arm may reach from where it is (`plans.PlanStuck`), end the campaign
  (`stopped_by == "refused"`), saying which limit the paths cross and where to jog the arm;
- a move cut short by either is never sent again as it was: the arm may have been jogged or
  freedriven meanwhile, so the pose starts over from where the arm is, every path checked again
  (`_MoveInterrupted`; after `max_reconnects` such restarts the pose is skipped); so does a
  reconnect during any other robot call (a state read, an event's clock read) made after a move
  was planned from where the arm was and before it is sent: each move carries the reconnect
  count it was planned at (`_move(q, planned_at)`);
- Ctrl-C / SIGTERM / SIGHUP / abort: stop the robot, record an `abort` event; the caller closes
  the recording. A driver with an `abort_requested` attribute (UrRobot) is given the abort flag
  and stops a move in progress at once. Back-off waits and the tracker's retries look at the
  abort flag (and a signal interrupts a tracker reading itself), so an abort never waits for
  them to run out;
- the kinematic margin does not hold (`watch.MarginWatch`, when given): stop the robot, record
  a `margin` event saying why, end the campaign (`CampaignResult.stopped_by == "margin"`).
Safety: every target (and its approach pre-pose) is checked against the envelope before any
motion; speed and acceleration are capped by the envelope. The executor tells the plan where the
arm is before it asks for each pose (`plans.ArmPosture`, when given): adaptive plans choose among
the poses reachable from there.
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from workcell.campaign.envelope import AT_SENT_TOL_RAD, Envelope, route, route_back_in
from workcell.campaign.plans import (
    ArmPosture,
    Plan,
    PlanStuck,
    PoseTarget,
    fmt_q,
    limit_name,
    limits_summary,
    path_limit,
)
from workcell.drivers.protocols import (
    DeviceError,
    DeviceUnreachable,
    OtherInstrument,
    ProtectiveStop,
    Robot,
    SafetyStop,
    Tracker,
    driver_hooks,
)
from workcell.errors import INTERRUPTED, UserError, stop_if_interrupted
from workcell.kinematics.robots import RobotSpec

# A campaign that meets the same fault again and again with nothing measured in between is not
# going to get anywhere by itself: it stops, the arm stopped, for a person to look (one line).
MAX_PROTECTIVE_STOPS_IN_A_ROW = 3  # protective stops with no pose recorded between them
MAX_TRACKER_SKIPS_IN_A_ROW = 3  # poses skipped for want of tracker readings, none recorded between
# poses refused before any motion, with no pose recorded and no move made between them: the arm
# stands where the plan's paths leave the envelope (a static plan from a start posture it was not
# planned from; ordered for paths, a static plan's poses are not refused one after another)
MAX_REFUSED_IN_A_ROW = 5
OUTLIER_K = 5.0  # a reading farther from its pose's median than this many robust sigmas is rejected

# the signals a command line campaign handles as Ctrl-C (`CampaignControl.install_sigint`)
ABORT_SIGNALS = tuple(
    getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n)
)


class ArmOutsideEnvelope(UserError):
    """The arm is outside the envelope: the campaign will not move it (nothing moved).
    `reason`: which limit it is beyond."""

    def __init__(self, message: str, reason: str = "") -> None:
        super().__init__(message)
        self.reason = reason


class _MoveInterrupted(Exception):
    """A move cut short by a protective stop or a lost robot connection, recovered from. The
    arm may be anywhere now (the operator may have jogged it while the campaign waited), so the
    move must be planned again from where the arm is, never repeated as it was."""


@dataclass
class CampaignConfig:
    readings_per_pose: int = 5
    settle_s: float = 1.0
    settle_speed_rad_s: float = 1e-3
    speed_rad_s: float = 1.0
    accel_rad_s2: float = 2.0
    approach_rad: float = 0.02
    max_beam_retries: int = 5
    beam_retry_wait_s: float = 1.0
    max_reconnects: int = 5
    reconnect_backoff_s: float = 0.5
    outlier_k: float = OUTLIER_K
    payload_kg: float = 0.0
    joint_state_every_s: float = 0.25
    warmup_s: float = 0.0  # exercise the arm this long before the first measurement

    def __post_init__(self) -> None:
        """Refuse settings that make no physical sense (UserError, one line)."""
        for name in ("readings_per_pose", "max_beam_retries", "max_reconnects"):
            v, lo = getattr(self, name), (1 if name == "readings_per_pose" else 0)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < lo:
                raise UserError(
                    f"campaign setting {name} must be a whole number >= {lo}, got {v!r}"
                )
        if self.readings_per_pose > MAX_READINGS_PER_POSE:
            raise UserError(
                f"{_setting('readings_per_pose')} {self.readings_per_pose} is more than "
                f"{MAX_READINGS_PER_POSE} readings a pose (a tracker reading takes about a "
                "second): give the readings to average at each pose, e.g. 5"
            )
        positive = ("settle_speed_rad_s", "speed_rad_s", "accel_rad_s2", "outlier_k")
        non_negative = (
            "settle_s",
            "approach_rad",
            "beam_retry_wait_s",
            "reconnect_backoff_s",
            "payload_kg",
            "joint_state_every_s",
            "warmup_s",
        )
        for name in positive + non_negative:
            v = getattr(self, name)
            ok = isinstance(v, (int, float, np.floating)) and np.isfinite(v)
            ok = ok and (v > 0 if name in positive else v >= 0)
            if not ok:
                what = "> 0" if name in positive else ">= 0"
                raise UserError(f"{_setting(name)} must be a finite number {what}, got {v}")
        # a settle time or warm-up given in ms (or minutes taken for hours) would hold the arm
        # for days: refuse beyond what a campaign could mean
        for name, most in (("settle_s", 600.0), ("warmup_s", 4 * 3600.0)):
            v = getattr(self, name)
            if v > most:
                raise UserError(f"{_setting(name)} {v:g} s is more than {most:g} s; give seconds")


MAX_READINGS_PER_POSE = 1000  # as `workcell validate --readings`


def _setting(name: str) -> str:
    opt = {"settle_s": "--settle", "warmup_s": "--warmup", "readings_per_pose": "--readings"}
    return f"{opt[name]} ({name})" if name in opt else f"campaign setting {name}"


@dataclass
class CampaignControl:
    """Shared flags for a UI: pause/abort requests, protective-stop resume policy."""

    abort: threading.Event = field(default_factory=threading.Event)
    pause: threading.Event = field(default_factory=threading.Event)
    # after a protective stop: resume at once (True) or wait until `resume` is set (a UI asks
    # the operator, who checks the cell, then sets it)
    auto_resume_protective_stop: bool = True
    # the `stop` policy (the command line's default without a terminal): a protective stop
    # ends the campaign with the arm left stopped, for someone to check the cell and resume
    stop_at_protective_stop: bool = False
    resume: threading.Event = field(default_factory=threading.Event)
    waiting_for_resume: threading.Event = field(default_factory=threading.Event)
    # set while an executor runs: before it (planning, connecting) nothing moves and nothing is
    # recorded, so Ctrl-C may stop at once; while it runs, Ctrl-C stops after the current step
    running: threading.Event = field(default_factory=threading.Event)
    # the first abort signal received (0: none; the abort came from a UI or `stop_reason`)
    signum: int = 0
    # why the campaign was stopped when it was not the operator's abort (e.g. a protective stop
    # nobody acknowledged): the `abort` event says it, and the result's `stop_message`
    stop_reason: str = ""
    # the main thread is inside a call a signal may cut short (`interruptible`)
    _interruptible: bool = False

    def install_sigint(self) -> None:
        """Make Ctrl-C, SIGTERM and SIGHUP (`ABORT_SIGNALS`: what `kill`, `timeout` and a closed
        terminal send) this campaign's `on_sigint`; a Ctrl-C that came earlier and that Python
        dropped (`errors.INTERRUPTED`) stops here, before anything connects or moves. Returns
        the handlers it replaced, by signal."""
        old = {}
        for sig in ABORT_SIGNALS:
            old[sig] = signal.signal(sig, self.on_sigint)
        if INTERRUPTED.is_set():
            raise KeyboardInterrupt
        return old

    def on_sigint(self, signum: int = signal.SIGINT, *_: object) -> None:
        """Abort-signal handler for a command line: abort at once before the campaign starts (a
        plan of many poses takes minutes), cleanly (robot stopped, recording closed) once it
        runs; inside an `interruptible` call (a tracker reading) at once, cleanly too."""
        if not self.signum:
            self.signum = int(signum)
        INTERRUPTED.set()  # also before the run: a dropped KeyboardInterrupt still stops it
        self.abort.set()
        if not self.running.is_set() or self._interruptible:
            raise KeyboardInterrupt

    @contextmanager
    def interruptible(self) -> Iterator[None]:
        """A block that an abort signal may cut short with KeyboardInterrupt (it records
        nothing and commands no motion: a tracker reading, a wait). Only in the main thread,
        where signal handlers run; elsewhere (a UI's worker) the block runs as it is."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        self._interruptible = True
        try:
            if self.abort.is_set():
                raise KeyboardInterrupt
            yield
        finally:
            self._interruptible = False

    def abort_message(self) -> str:
        """What the `abort` event says stopped the campaign."""
        if self.stop_reason:
            return f"campaign stopped: {self.stop_reason}; recording closed"
        if self.signum and self.signum != signal.SIGINT:
            return f"campaign aborted by {signal.Signals(self.signum).name}; recording closed"
        return "campaign aborted by the operator; recording closed"


@dataclass
class CampaignResult:
    measured: int = 0
    skipped: int = 0
    aborted: bool = False
    events: int = 0
    skipped_ids: list[int] = field(default_factory=list)
    # "operator" (abort, Ctrl-C, SIGTERM, SIGHUP), "margin" (the margin watch),
    # "unacknowledged" (a protective stop nobody acknowledged), "protective_stop" (too many in a
    # row), "safety_stop" (a safeguard or emergency stop, a safety violation or fault),
    # "tracker" (no tracker readings at too many poses in a row), "refused" (poses refused
    # again and again, or an adaptive plan with no reachable pose left) or "error"
    stopped_by: str = ""
    stop_message: str = ""  # for the last four: one line on why


class _MarginStop(Exception):
    """Raised after a sample when the margin watch finds the kinematic margin does not hold."""


class _CampaignStop(Exception):
    """A fault the campaign will not get past by itself (`MAX_..._IN_A_ROW`): stop the arm,
    close the recording, say why. `kind`: `CampaignResult.stopped_by`."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


class Executor:
    def __init__(
        self,
        robot: Robot,
        tracker: Tracker,
        spec: RobotSpec,
        envelope: Envelope,
        sink,
        *,
        tool_m: np.ndarray,
        config: CampaignConfig | None = None,
        control: CampaignControl | None = None,
        on_sample: Callable[[dict], None] | None = None,
        on_event: Callable[[dict], None] | None = None,
        index0: int = 0,
        t_wall0_ns: int | None = None,
        elapsed0_s: float = 0.0,
        watch=None,
        arm: ArmPosture | None = None,
    ) -> None:
        self.robot, self.tracker, self.spec, self.env, self.sink = (
            robot,
            tracker,
            spec,
            envelope,
            sink,
        )
        self.tool_m = np.asarray(tool_m, float)
        self.cfg = config or CampaignConfig()
        self.control = control or CampaignControl()
        self.on_sample, self.on_event = on_sample, on_event
        self.index = index0
        self.result = CampaignResult()
        self._t_robot0: float | None = None
        self._t_wall0_ns = time.time_ns() if t_wall0_ns is None else t_wall0_ns
        # the last elapsed time read from the robot, with the local monotonic clock then, and
        # the last log time given out: every record's log time comes from the one clock
        self._last_elapsed: float | None = None
        self._last_mono = time.monotonic()
        self._last_ns = 0
        self._last_cmd: np.ndarray | None = None  # the last target the arm arrived at
        # robot reconnects so far: a move planned before one is not sent (the arm may have
        # been jogged while the connection was down)
        self._reconnects = 0
        self._elapsed0 = elapsed0_s
        self._last_js = -1e9
        self._last_js_t: float | None = None  # the controller time of the last state written
        self.watch = watch  # a watch.MarginWatch, or None
        # faults since the last recorded pose (`MAX_..._IN_A_ROW`)
        self._pstops_in_a_row = 0
        self._tracker_skips_in_a_row = 0
        self._tracker_gone = ""  # why, once every tracker reconnect has failed
        # poses refused since the last move to a pose: (pose id, the limit their paths cross,
        # where the arm was, the pose's pre-pose)
        self._refused: list[tuple[int, str, np.ndarray | None, np.ndarray]] = []
        self.arm = arm  # where the arm is, for an adaptive plan (`plans.ArmPosture`)
        self._refused_from: np.ndarray | None = None  # where the arm was at the last refusal
        # the robot's clock at the campaign's start (`t_wall0_ns`): read now, not at the first
        # record (a plan's first step can take seconds, and every log time came that much early)
        if robot is not None:  # None: a dry run's checks (`check_plan`)
            self.elapsed()

    # ------------------------------------------------------------------ time and records
    def elapsed(self) -> float:
        """Seconds since the campaign started, on the robot's clock (virtual time for a
        time-scaled simulation). A robot clock that went back (the controller restarted during a
        reconnect) continues from the last reading plus the local time since."""
        return self._elapsed_at(self._robot_call(lambda: self.robot.state()).t_s)

    def _elapsed_at(self, t: float) -> float:
        """`elapsed` for a robot clock reading t (s)."""
        if self._t_robot0 is None:
            self._t_robot0 = t
        e = self._elapsed0 + t - self._t_robot0
        if self._last_elapsed is not None and e < self._last_elapsed:
            e = self._last_elapsed + (time.monotonic() - self._last_mono)
            self._t_robot0 = t - (e - self._elapsed0)
        self._last_elapsed, self._last_mono = e, time.monotonic()
        return e

    def _t_ns(self, elapsed: float | None = None) -> int:
        """The log time of a record acquired at `elapsed` (now when None): the campaign's start
        plus the elapsed time, never before a log time already given out."""
        e = self.elapsed() if elapsed is None else elapsed
        t = self._t_wall0_ns + int(round((e - self._elapsed0) * 1e9))
        self._last_ns = max(self._last_ns, t)
        return self._last_ns

    def _t_ns_offline(self) -> int:
        """A log time while the robot cannot be asked for its clock: the last elapsed time
        plus the local time since it was read."""
        e = self._elapsed0 if self._last_elapsed is None else self._last_elapsed
        return self._t_ns(e + time.monotonic() - self._last_mono)

    def event(self, level: str, kind: str, message: str, *, echo: bool = True) -> None:
        """Record an event; `on_event` hears it too unless not `echo` (an error the caller is
        about to report itself, which the terminal would otherwise show twice)."""
        self.result.events += 1
        self.sink.event(self._t_ns_safe(), level, kind, message)
        if self.on_event and echo:
            self.on_event({"level": level, "kind": kind, "message": message})

    def _t_ns_safe(self) -> int:
        try:
            return self._t_ns()
        except (Exception, KeyboardInterrupt):
            # robot unreachable while reporting it (KeyboardInterrupt: its reconnect back-off
            # cut short by an abort, while the abort itself is being recorded)
            return self._t_ns_offline()

    def _record_state(self, force: bool = False):
        st = self._robot_call(lambda: self.robot.state())
        e = self.elapsed()
        if force or e - self._last_js >= self.cfg.joint_state_every_s:
            self._write_state(st, e)
        return st

    def _write_state(self, st, e: float) -> None:
        if st.t_s == self._last_js_t:
            return  # the controller's same sample (the arrival, read again): written already
        self._last_js, self._last_js_t = e, st.t_s
        self.sink.joint_state(self._t_ns(e), st.q_rad, st.qd_rad_s, st.torque_nm, st.temperature_c)

    def _state_during_move(self, st) -> None:
        """A state the driver read while a move runs (`state_during_move`, UrRobot): into the
        joint-state stream, so that the recording shows the motion itself."""
        self._write_state(st, self._elapsed_at(st.t_s))

    # ------------------------------------------------------------------ robot with fault policy
    def _robot_call(self, fn, *, repeat: bool = True):
        """fn() with the reconnect policy. A lost connection is reconnected with back-off; then
        fn is called again (`repeat`), or, for a motion, `_MoveInterrupted` is raised so that the
        caller plans the move again from where the arm is."""
        attempt = 0
        while True:
            try:
                return fn()
            except (ProtectiveStop, SafetyStop):
                raise  # its own policy (a protective stop), or the campaign stops (SafetyStop)
            except DeviceError as e:
                if self.control.abort.is_set():
                    raise KeyboardInterrupt from None  # the move stopped for the abort, or failed
                err = e
            while True:  # reconnect, with back-off
                attempt += 1
                reconnect = getattr(self.robot, "reconnect", None)
                if reconnect is None or attempt > self.cfg.max_reconnects:
                    if self.control.abort.is_set():
                        raise KeyboardInterrupt  # an abort during the last try: it is one
                    raise err
                wait = self.cfg.reconnect_backoff_s * 2 ** (attempt - 1)
                self.sink.event(
                    self._t_ns_offline(),
                    "warning",
                    "reconnect",
                    f"robot connection lost ({err}); reconnect {attempt} in {wait:.1f} s",
                )
                self.result.events += 1
                if self.on_event:
                    self.on_event({"level": "warning", "kind": "reconnect", "message": str(err)})
                self._pause(wait)
                try:
                    with self.control.interruptible():  # no record, no motion: Ctrl-C cuts it
                        reconnect()
                    self._reconnects += 1
                    break
                except DeviceError as e:
                    err = e
            if not repeat:
                raise _MoveInterrupted(f"robot connection lost during a move ({err})")

    def _reconnect_tracker(self, err: Exception) -> bool:
        reconnect = getattr(self.tracker, "reconnect", None)
        if reconnect is None:
            return False
        for attempt in range(1, self.cfg.max_reconnects + 1):
            wait = self.cfg.reconnect_backoff_s * 2 ** (attempt - 1)
            self.event(
                "warning",
                "reconnect",
                f"tracker unreachable ({err}); reconnect {attempt} in {wait:.1f} s",
            )
            self._pause(wait)
            try:
                with self.control.interruptible():  # no record, no motion: Ctrl-C cuts it
                    reconnect()
                return True
            except OtherInstrument as e:  # another tracker: its frame is not the recording's
                msg = f"{e}"[:600]
                self.event("error", "stopped", f"{msg}; the campaign stops, the arm stopped")
                raise _CampaignStop("tracker", msg) from None
            except DeviceError as e:
                err = e
        self._tracker_gone = str(err)  # every reconnect failed: no more motion without it
        return False

    def _pause(self, seconds: float) -> None:
        """Wait `seconds` of wall time (a back-off) in small slices; an abort ends the wait at
        once (KeyboardInterrupt). Slices, not `Event.wait`: a signal handler that sets the
        event while this thread holds the event's lock would deadlock."""
        end = time.monotonic() + seconds
        while True:
            if self.control.abort.is_set():
                raise KeyboardInterrupt
            left = end - time.monotonic()
            if left <= 0:
                return
            time.sleep(min(left, 0.05))

    def _move(self, q: np.ndarray, planned_at: int, env: Envelope | None = None) -> None:
        """One joint move whose path the caller has checked from where the arm was when the
        robot had been reconnected `planned_at` times (`self._reconnects` then). A reconnect
        since (during a state or clock read in between) -> `_MoveInterrupted`, nothing sent: the
        arm may have been jogged while the connection was down. The last line of defence: the
        arm's posture is read once more and the path from it checked against `env` (default the
        envelope; the caller's when it brings the arm back into the joint ranges); outside ->
        a `refused` event and `_MoveInterrupted`, nothing sent. Cut short (protective stop, lost
        connection) -> `_MoveInterrupted` once recovered: never sent again from wherever the arm
        is now."""
        q_now, _ = self._where()
        if self._reconnects != planned_at:
            raise _MoveInterrupted(
                "the robot was reconnected after this move was planned from where the arm was "
                "(nothing sent)"
            )
        why = (env or self.env).path_violation(self.spec, q_now, q, self.tool_m)
        if why is not None:
            self.event(
                "error",
                "refused",
                f"a move was not sent: from where the arm is (q = {fmt_q(q_now)} rad) its path "
                f"{why}",
            )
            raise _MoveInterrupted("the path from where the arm is leaves the envelope (not sent)")
        speed, accel = self.env.cap(self.cfg.speed_rad_s, self.cfg.accel_rad_s2)
        try:
            self._robot_call(lambda: self.robot.move_joints(q, speed, accel), repeat=False)
        except SafetyStop as e:
            msg = (
                f"{e}: the controller stopped the arm for safety; a campaign never moves it "
                "again by itself after such a stop: find out why, clear it at the cell (teach "
                "pendant)"
            )
            self.event("error", "stopped", msg)
            raise _CampaignStop("safety_stop", msg) from None
        except ProtectiveStop as e:
            self.event("error", "protective_stop", f"protective stop: {e}")
            self._pstops_in_a_row += 1
            msg = None
            if self._pstops_in_a_row >= MAX_PROTECTIVE_STOPS_IN_A_ROW:
                msg = (
                    f"{self._pstops_in_a_row} protective stops in a row with no pose measured "
                    "between them; the arm is left stopped: find out why the cell stops it "
                    "(a collision, a payload or speed setting)"
                )
            elif self.control.stop_at_protective_stop:
                msg = (
                    f"protective stop during a move ({e}); the arm is left stopped: nobody is at "
                    "a terminal to check the cell (--on-protective-stop stop, the default "
                    "without one), so release it on the teach pendant once the cell is checked"
                )
            if msg is not None:
                self.event("error", "stopped", msg)
                raise _CampaignStop("protective_stop", msg) from None
            self._wait_protective_stop()
            raise _MoveInterrupted("protective stop during a move") from None
        self._last_cmd = np.array(q, float)

    def _stopped_before_start(self) -> None:
        """An arm already in a protective stop when the campaign starts (the last campaign
        stopped for protective stops, or the cell stopped it since): the resume-at-once policy
        is for stops the campaign sees happen during its own moves; this one is released by
        someone who has checked the cell (the `stop` policy names it as from before). With the ask policy the operator is asked at the first
        move, as for any stop."""
        c = self.control
        if not (c.auto_resume_protective_stop or c.stop_at_protective_stop):
            return
        st = self._robot_call(lambda: self.robot.state())
        if getattr(st, "safety", "NORMAL") != "PROTECTIVE_STOP":
            return
        msg = (
            "the arm is in a protective stop from before this campaign, which it did not see "
            "happen and does not release by itself: check the cell, release the stop on the "
            "teach pendant (or run the campaign from a terminal, where it asks); nothing moved"
        )
        self.event("error", "stopped", msg)
        raise _CampaignStop("protective_stop", msg)

    def _wait_protective_stop(self) -> None:
        self.event("warning", "pause", "campaign paused by a protective stop")
        if not self.control.auto_resume_protective_stop:
            self.control.resume.clear()
            self.control.waiting_for_resume.set()
            try:
                while not self.control.abort.is_set() and not self.control.resume.is_set():
                    time.sleep(0.05)
            finally:
                self.control.waiting_for_resume.clear()
        if self.control.abort.is_set():  # Ctrl-C, or nobody acknowledged (`stop_reason`)
            raise KeyboardInterrupt
        unlock = getattr(self.robot, "unlock_protective_stop", None)
        if unlock is not None:
            self._robot_call(unlock)
        self.event(
            "info", "resume", "protective stop cleared; the pose starts over from where the arm is"
        )

    # ------------------------------------------------------------------ steps
    def check_plan(self, targets: list[PoseTarget], start: np.ndarray | None = None) -> list[str]:
        """Dry run: every target, pre-pose, approach and the path from the pose before against
        the envelope; the first pose's path from `start`, the arm's posture when the campaign
        starts, if known (else the campaign checks it when it starts). Returns the problems."""
        problems: list[str] = []
        prev = None if start is None else np.asarray(start, float)
        at_start = start is not None
        for t in targets:
            stop_if_interrupted()  # thousands of path checks: a Ctrl-C Python dropped stops it
            found = self._pose_problems(t, prev)
            if at_start:
                found = [p.replace(" path: ", " path from the arm's start posture: ", 1)
                         for p in found]  # fmt: skip
            problems += found
            if not found:
                prev, at_start = t.q_rad, False  # a refused pose leaves the arm where it was
        return problems

    def _pose_problems(self, t: PoseTarget, prev: np.ndarray | None = None) -> list[str]:
        """Why pose t may not run: its target or pre-pose outside the envelope; else its
        approach path (pre-pose -> target); else, given the pose before, the route to its
        pre-pose (direct or via upright). Empty when it may."""
        pre = self._prepose(t)
        ends = self.env.violations(self.spec, np.array([t.q_rad, pre]), self.tool_m)
        out = [
            f"pose {t.pose_id} {what}: refused before any motion: {v}"
            for v, what in zip(ends, ("target", "approach pre-pose"), strict=True)
            if v is not None
        ]
        if out:
            return out
        v = self.env.path_violation(self.spec, pre, t.q_rad, self.tool_m)
        if v is not None:
            return [f"pose {t.pose_id} approach: {v}"]
        if prev is not None:
            _, v = route(self.env, self.spec, self.tool_m, prev, pre)
            if v is not None:
                return [f"pose {t.pose_id} path: {v}; also via the upright posture"]
        return []

    def _prepose(self, t: PoseTarget) -> np.ndarray:
        return t.q_rad - np.sign(t.approach_sign) * self.cfg.approach_rad

    def _where(self) -> tuple[np.ndarray, str | None]:
        """Where the arm is (read from the robot) and why that is outside the envelope (None:
        inside). At a target on the envelope's edge, encoder noise can read just outside: the
        arm is where it was sent, a checked posture, and that is where it is said to be."""
        q_now = np.asarray(self._robot_call(lambda: self.robot.state()).q_rad, float)
        outside = self.env.violations(self.spec, q_now[None], self.tool_m)[0]
        last = self._last_cmd
        if (
            outside is not None
            and last is not None
            and np.max(np.abs(q_now - last)) < AT_SENT_TOL_RAD
            and self.env.violations(self.spec, last[None], self.tool_m)[0] is None
        ):
            q_now, outside = last, None
        return q_now, outside

    def _tell_plan(self) -> None:
        """Before the plan is asked for its next pose: where the arm is (`self.arm`)."""
        if self.arm is not None:
            self.arm.q = self._where()[0].copy()

    def _move_along(self, q_to: np.ndarray, what: str) -> bool:
        """Move to q_to along joint paths inside the envelope (direct, or via the upright
        posture); False, with a `refused` event and no motion, when neither stays inside. An arm
        the operator left beyond the envelope's joint ranges only comes back along a path checked
        against the box and the floor (a `warning`). One outside the box or below the floor is not
        moved at all: an `error` event, then `ArmOutsideEnvelope` ends the campaign with the
        recording closed, to be resumed once the arm is back inside."""
        q_now, outside = self._where()
        planned_at = self._reconnects  # the posture q_now is read after any reconnect so far
        find_route = route
        check_env = self.env  # what each move's path is checked against once more
        if outside is not None:
            # beyond the envelope's joint ranges only (its SMR above the table, in the box):
            # the way back in may go, checked against the box and floor all along, via the
            # upright posture only if that is inside the envelope itself
            find_route = route_back_in
            loose = self.env.with_arm_joint_ranges(self.spec)
            check_env = loose  # the box and the floor, with the arm's own joint ranges
            if loose.violations(self.spec, q_now[None], self.tool_m)[0] is not None:
                again = (  # nothing measured: the campaign is not kept, nothing to resume
                    "resume the campaign (--resume)"
                    if self.result.measured or self.result.skipped
                    else "start again"
                )
                msg = (
                    f"the arm is outside the envelope ({outside}); no move to {what} from there: "
                    f"jog it inside, then {again}"
                )
                self.event("error", "envelope", msg, echo=False)  # the error says it
                raise ArmOutsideEnvelope(msg, outside)
            self.event(
                "warning",
                "envelope",
                f"the arm starts outside the envelope's joint ranges ({outside}); the move to "
                f"{what} is checked against the box and the floor",
            )
        waypoints, why = find_route(self.env, self.spec, self.tool_m, q_now, q_to)
        if why is not None:
            self.event("error", "refused", f"{what}: {why}; also via the upright posture")
            self._refused_from = q_now
            return False
        if len(waypoints) > 1:
            self.event("info", "via", f"{what}: direct path leaves the envelope; via upright")
        for q in waypoints:
            self._move(q, planned_at, check_env)
        return True

    def _note_refused(self, t: PoseTarget, q_from: np.ndarray | None) -> None:
        """A pose refused before any motion (from q_from: where the arm was; None: the pose
        itself, its target, pre-pose or approach). The `MAX_REFUSED_IN_A_ROW`-th since the arm
        last moved to a pose stops the campaign (`_CampaignStop("refused")`)."""
        pre = self._prepose(t)
        if q_from is None:
            bad = [q for q in (t.q_rad, pre) if self.env.violations(self.spec, q, self.tool_m)[0]]
            name = (
                limit_name(self.env, self.spec, self.tool_m, bad[0])
                if bad
                else path_limit(self.env, self.spec, self.tool_m, pre, t.q_rad)
            )
        else:
            name = path_limit(self.env, self.spec, self.tool_m, q_from, pre)
        self._refused.append((int(t.pose_id), name, q_from, pre))
        if len(self._refused) >= MAX_REFUSED_IN_A_ROW:
            msg = self._refused_message()
            self.event("error", "stopped", f"{msg}; the campaign stops, the arm stopped")
            raise _CampaignStop("refused", msg)

    def _refused_message(self) -> str:
        """One line on `MAX_REFUSED_IN_A_ROW` refused poses: which limit, and what to do."""
        ids = [r[0] for r in self._refused]
        names = [r[1] for r in self._refused]
        q_from = next((r[2] for r in reversed(self._refused) if r[2] is not None), None)
        where = f" from where the arm is (q = {fmt_q(q_from)} rad)" if q_from is not None else ""
        via = ", also via the upright posture," if q_from is not None else ""
        shown = ", ".join(map(str, ids[:8])) + (", ..." if len(ids) > 8 else "")
        return (
            f"{len(ids)} poses in a row refused before any motion (poses {shown}), none "
            f"measured between them: their paths{where} leave the envelope{via} first crossing "
            f"{limits_summary(names)}; "
            + refused_advice(self._refused[0][3], f"pose {ids[0]}'s approach posture")
        )

    def _skip(self, t: PoseTarget) -> None:
        self.result.skipped += 1
        self.result.skipped_ids.append(t.pose_id)

    def _stop_if_tracker_gone(self) -> None:
        """Every tracker reconnect failed: stop before the arm moves to another pose."""
        if self._tracker_gone:
            msg = (
                f"tracker unreachable after {self.cfg.max_reconnects} reconnect attempts "
                f"({self._tracker_gone}); the arm is not moved to another pose without it"
            )[:600]
            self.event("error", "stopped", f"{msg}; the campaign stops, the arm stopped")
            raise _CampaignStop("tracker", msg)

    def run_pose(self, t: PoseTarget) -> dict | None:
        self._stop_if_tracker_gone()
        problems = self._pose_problems(t)
        if problems:
            self.event("error", "refused", problems[0])
            self._skip(t)
            self._note_refused(t, None)
            return None
        for _ in range(self.cfg.max_reconnects + 1):
            try:
                return self._run_pose_once(t)
            except _MoveInterrupted as e:
                self.event(
                    "warning",
                    "retry",
                    f"pose {t.pose_id}: {e}; the arm may have been moved meanwhile: the pose "
                    "starts over from where the arm is, every path checked again",
                )
        self.event(
            "error", "skip", f"pose {t.pose_id}: its moves were cut short too often; skipped"
        )
        self._skip(t)
        return None

    def _run_pose_once(self, t: PoseTarget) -> dict | None:
        pre = self._prepose(t)
        if not self._move_along(pre, f"pose {t.pose_id}"):
            self._skip(t)
            self._note_refused(t, self._refused_from)
            return None
        at_pre = self._reconnects  # the arm arrived at the pre-pose (a reconnect would raise)
        self._refused.clear()  # the arm moved on: refusals before say nothing about here
        self._record_state(force=True)
        self._move(t.q_rad, at_pre)  # checked from the pre-pose: not after a reconnect since
        approach = np.sign(t.q_rad - pre)
        self._settle()
        return self._measure(t, approach)

    def _settle(self) -> None:
        waited = 0.0
        still = 0.0
        step = max(self.cfg.settle_s / 4, 0.05)
        while still < self.cfg.settle_s and waited < 10 * self.cfg.settle_s + 5:
            self._robot_call(lambda: self.robot.sleep(step))
            waited += step
            st = self._record_state()
            if np.max(np.abs(st.qd_rad_s)) < self.cfg.settle_speed_rad_s:
                still += step
            else:
                still = 0.0
        if still < self.cfg.settle_s:
            self.event("warning", "settle", f"joints did not settle within {waited:.1f} s")

    def _measure(self, t: PoseTarget, approach: np.ndarray) -> dict | None:
        n = self.cfg.readings_per_pose
        good, qs, temps = [], [], []
        failures = 0
        problem = ""  # the last reason a reading was not usable
        want = n  # two readings that disagree get a third, so the median can tell the bad one
        while len(good) < want:
            if self.control.abort.is_set():  # a tracker that fails slowly must not hold it up
                raise KeyboardInterrupt
            try:
                with self.control.interruptible():
                    r = self.tracker.measure()
            except DeviceUnreachable as e:
                problem = str(e)
                failures += 1
                for kind, msg in _pop_faults(self.tracker):
                    self.event("warning", kind, msg)
                if failures > self.cfg.max_beam_retries or not self._reconnect_tracker(e):
                    break
                continue
            except DeviceError as e:
                problem = str(e)
                failures += 1
                for kind, msg in _pop_faults(self.tracker):
                    self.event("warning", kind, msg)
                self.event("warning", "retry", f"pose {t.pose_id}: tracker error ({e}); retrying")
                if failures > self.cfg.max_beam_retries:
                    break
                continue
            for kind, msg in _pop_faults(self.tracker):
                self.event("warning", kind, msg)
            self.sink.tracker_measurement(
                self._t_ns(), r.position_m, r.sigma_m, r.status, _instrument_time_s(r)
            )
            if r.status != "ok" or not np.all(np.isfinite(r.position_m)):
                problem = f"status {r.status}" if r.status != "ok" else "non-finite coordinates"
                said = (r.extra or {}).get("message") if isinstance(r.extra, dict) else None
                if isinstance(said, str) and said:  # the driver's why ("2250 m ... a unit?")
                    problem += f": {said}"
                failures += 1
                self.event(
                    "warning",
                    "beam_broken" if r.status == "beam_broken" else "retry",
                    f"pose {t.pose_id}: tracker status {r.status}; retry {failures}",
                )
                if failures > self.cfg.max_beam_retries:
                    break
                self._robot_call(lambda: self.robot.sleep(self.cfg.beam_retry_wait_s))
                continue
            st = self._record_state()
            good.append((np.asarray(r.position_m, float), np.asarray(r.sigma_m, float)))
            qs.append(st.q_rad)
            if st.temperature_c is not None:
                temps.append(st.temperature_c)
            if want == len(good) == 2 and (gap := readings_disagree(good, self.cfg.outlier_k)):
                want = 3
                self.event(
                    "info",
                    "outlier",
                    f"pose {t.pose_id}: its two readings are {gap * 1e6:.1f} um apart; a third "
                    "decides which one is off",
                )
        need = max(2, (n + 1) // 2) if n > 1 else 1
        if len(good) < need:
            self.event(
                "error",
                "skip",
                f"pose {t.pose_id} skipped: {len(good)} of {n} readings after {failures} failures",
            )
            self.result.skipped += 1
            self.result.skipped_ids.append(t.pose_id)
            # no reading at all: the tracker may have stopped measuring (some: it measures)
            self._tracker_skips_in_a_row = self._tracker_skips_in_a_row + 1 if not good else 0
            self._stop_if_tracker_gone()
            if self._tracker_skips_in_a_row >= MAX_TRACKER_SKIPS_IN_A_ROW:
                msg = (
                    f"tracker gave no usable reading at {self._tracker_skips_in_a_row} poses in a "
                    f"row (last problem: {problem or 'too few readings'})"[:600]
                )
                self.event("error", "stopped", f"{msg}; the campaign stops, the arm stopped")
                raise _CampaignStop("tracker", msg)
            return None
        P = np.array([g[0] for g in good])
        S = np.array([g[1] for g in good])
        keep = reject_outliers(P, S, self.cfg.outlier_k)
        if (~keep).any():
            self.event("info", "outlier", f"pose {t.pose_id}: {(~keep).sum()} reading(s) rejected")
        P, S = P[keep], S[keep]
        mean = P.mean(0)
        if len(P) > 1:
            sig = np.maximum(P.std(0, ddof=1), S.mean(0) / 4) / np.sqrt(len(P))
        else:
            sig = S[0]
        e = self.elapsed()
        sample = {
            "index": self.index,
            "pose_id": int(t.pose_id),
            "q_commanded_rad": np.asarray(t.q_rad, float).tolist(),
            "q_measured_rad": np.mean(qs, axis=0).tolist(),
            "approach_sign": [int(s) for s in approach],
            "tracker_position_m": mean.tolist(),
            "tracker_sigma_m": sig.tolist(),
            "n_readings": int(len(P)),
            "joint_temperature_c": np.mean(temps, axis=0).tolist() if temps else None,
            "ambient_temperature_c": None,
            "elapsed_s": float(e),
            "payload_kg": float(self.cfg.payload_kg),
            "tracker_readings": int(len(good) + failures),
            "rejected_readings": int((~keep).sum()),
        }
        self.sink.sample(self._t_ns(e), sample)
        self.index += 1
        self.result.measured += 1
        self._pstops_in_a_row = self._tracker_skips_in_a_row = 0
        if self.on_sample:
            self.on_sample(sample)
        if self.watch is not None:
            verdict = self.watch.update(sample)
            if verdict is not None and verdict.stop:
                self.event("error", "margin", verdict.stop)
                raise _MarginStop
        return sample

    def warm_up(self, q_centre: np.ndarray) -> None:
        """Move the arm back and forth around q_centre for `warmup_s` of robot time, so the
        joints reach their working temperature before measuring (no measurement is taken)."""
        if self.cfg.warmup_s <= 0:
            return
        why = self.env.violations(self.spec, np.atleast_2d(q_centre), self.tool_m)[0]
        if why is not None:  # the warm-up moves around the first target: never outside
            self.event("error", "refused", f"warm-up skipped: its centre (first target): {why}")
            return
        cycle = self._warmup_cycle(np.asarray(q_centre, float))
        if cycle is None:
            self.event(
                "warning",
                "refused",
                "warm-up skipped: no move of even 0.04 rad around the first target stays inside "
                "the envelope; give the joints their working temperature another way",
            )
            return
        self.event("info", "warmup", f"warming up for {self.cfg.warmup_s:.0f} s before measuring")
        start = self.elapsed()
        k = 0
        while self.elapsed() - start < self.cfg.warmup_s:
            if self.control.abort.is_set():
                raise KeyboardInterrupt
            before = self.elapsed()
            try:
                if not self._move_along(cycle[k % len(cycle)], "the warm-up"):
                    break
            except _MoveInterrupted as e:  # the next warm-up move is planned from where it is
                self.event("warning", "retry", f"the warm-up: {e}")
            self._record_state(force=False)
            k += 1
            if k >= len(cycle) and self.elapsed() <= before:  # no robot time passes: never spin
                self.event("warning", "warmup", "warm-up stopped: its moves take no time")
                break
        self.event("info", "warmup", f"warm-up done after {k} moves")

    def _warmup_cycle(self, q_centre: np.ndarray) -> list[np.ndarray] | None:
        """The warm-up's waypoints around q_centre: +-offsets (0.3-0.5 rad a joint) scaled down
        until at least one side lies inside the envelope; a side outside is replaced by the
        centre. None when no scale down to a tenth fits."""
        offsets = np.array([0.4, -0.3, 0.3, -0.4, 0.4, 0.5])
        for scale in (1.0, 0.5, 0.25, 0.1):
            sides = [q_centre + scale * offsets, q_centre - scale * offsets]
            inside = [self.env.violations(self.spec, q, self.tool_m)[0] is None for q in sides]
            if any(inside):
                return [q if ok else q_centre for q, ok in zip(sides, inside, strict=True)]
        return None

    def run(self, plan: Plan) -> CampaignResult:
        """Run the plan to its end, or until an abort or a stop; the result says which. A driver
        whose moves an abort can cut short (`abort_requested`, UrRobot) is given the abort flag
        for the campaign only: a move after it (a TUI's validation on the same robot after an
        aborted campaign) is not refused by this campaign's abort. A driver that reports the
        arm's state while it moves (`state_during_move`) has those states recorded too."""
        with driver_hooks(
            self.robot,
            abort_requested=self.control.abort.is_set,
            state_during_move=self._state_during_move,
        ):
            return self._run(plan)

    def _run(self, plan: Plan) -> CampaignResult:
        sample = None
        self.control.running.set()
        try:
            self._stopped_before_start()
            self._tell_plan()
            t = next(plan)
            self.warm_up(t.q_rad)
            while True:
                if self.control.abort.is_set():
                    raise KeyboardInterrupt
                while self.control.pause.is_set() and not self.control.abort.is_set():
                    time.sleep(0.05)
                sample = self.run_pose(t)
                self._tell_plan()
                t = plan.send(sample)
        except StopIteration:
            self._margin_summary()
        except PlanStuck as e:  # an adaptive plan with no pose the arm may reach from here
            msg = (
                f"{e}; " + refused_advice(e.suggest, "one of the plan's poses, the farthest inside")
            )[:1500]
            self.result.aborted, self.result.stopped_by = True, "refused"
            self.result.stop_message = msg
            self._stop_robot()
            self.event("error", "stopped", f"{msg}; the campaign stops, the arm stopped")
            self._margin_summary()
        except KeyboardInterrupt:
            self.result.aborted, self.result.stopped_by = True, "operator"
            if self.control.stop_reason:
                self.result.stopped_by = "unacknowledged"
                self.result.stop_message = self.control.stop_reason
            self._stop_robot()
            self._margin_summary()
            self.event("warning", "abort", self.control.abort_message())
        except _MarginStop:
            self.result.aborted, self.result.stopped_by = True, "margin"
            self._stop_robot()
        except _CampaignStop as e:  # its `stopped` event is recorded
            self.result.aborted, self.result.stopped_by = True, e.kind
            self.result.stop_message = str(e)
            self._stop_robot()
            self._margin_summary()
        except BaseException as e:
            # anything else (a device fault beyond the retries, the arm found outside the
            # envelope, a closed output pipe, a bug): the arm is stopped and the recording
            # says why before it is closed; the caller reports the error
            self.result.aborted, self.result.stopped_by = True, "error"
            self._stop_robot()
            # a user error's own words; anything else also names its type (a bug's report).
            # Recorded, not echoed to `on_event`: the caller reports this very error, and the
            # terminal showed it twice ("ArmOutsideEnvelope: ...", then the error line)
            why = str(e) if isinstance(e, UserError) else f"{type(e).__name__}: {e}"
            try:
                self.event(
                    "error",
                    "stopped",
                    f"campaign stopped after {self.result.measured} poses: {why}"[:500],
                    echo=False,
                )
            except Exception:  # noqa: BLE001 - the recording itself may be what failed
                pass
            raise
        # `running` stays set: a late Ctrl-C must not cut the recording's closing short
        return self.result

    def _margin_summary(self) -> None:
        """The margin watch's one line on what it checked (an info event), if it ran."""
        if self.watch is not None:
            text = self.watch.summary()
            stop = self.watch.last is not None and self.watch.last.stop
            self.event("error" if stop else "info", "margin", text)

    def _stop_robot(self) -> None:
        try:
            self.robot.stop()
        except Exception:  # noqa: BLE001 - stopping is best effort while ending a campaign
            pass


def refused_advice(suggest: np.ndarray | None, what: str) -> str:
    """What to do about a campaign stopped by refused moves (`stopped_by == "refused"`)."""
    at = f" (e.g. q = {fmt_q(suggest)} rad, {what})" if suggest is not None else ""
    return (
        f"jog the arm to a posture well inside the envelope{at} and resume, or widen the "
        "envelope there (a new campaign: a resume keeps the recorded envelope)"
    )


def _instrument_time_s(r) -> float | None:
    """The reading's own time stamp in seconds (the driver's `instrument_time_ms`), or None."""
    from workcell.recording.checks import is_finite_number

    ms = (r.extra or {}).get("instrument_time_ms")
    return float(ms) / 1000.0 if is_finite_number(ms) else None


def _pop_faults(tracker) -> list[tuple[str, str]]:
    pop = getattr(tracker, "pop_faults", None)
    return list(pop()) if pop else []


def readings_disagree(good: list, k: float) -> float | None:
    """The distance between two readings [(position, sigma), ...] when it exceeds k stated
    sigmas (3-D, as `reject_outliers` judges one reading against the median), else None: two
    readings cannot say which one is off; a third, and the median, can."""
    (p0, s0), (p1, s1) = good[:2]
    gap = float(np.linalg.norm(p1 - p0))
    scale = float(np.linalg.norm(0.5 * (s0 + s1)))
    return gap if np.isfinite(scale) and gap > k * scale else None


def reject_outliers(P: np.ndarray, S: np.ndarray, k: float) -> np.ndarray:
    """Readings farther from the median than k robust sigmas (floored by the stated sigma)."""
    if len(P) < 3:
        return np.ones(len(P), bool)
    med = np.median(P, axis=0)
    d = np.linalg.norm(P - med, axis=1)
    mad = 1.4826 * np.median(d)
    thr = k * max(mad, float(np.linalg.norm(S.mean(0))))
    keep = d <= thr
    return keep if keep.sum() >= 2 else np.ones(len(P), bool)


def dry_run_plan(
    kind: str,
    spec: RobotSpec,
    env: Envelope,
    n: int,
    *,
    seed: int,
    tool_m: np.ndarray,
    config: CampaignConfig | None = None,
    start_q: np.ndarray | None = None,
) -> tuple[list[PoseTarget] | None, list[str]]:
    """Build a plan and check every target and pre-pose against the envelope; nothing moves.
    `start_q`: the arm's posture when the campaign starts, if known (a simulated arm): the first
    pose's path is checked from there (else the campaign checks it when it starts).

    Returns (targets, problems); targets is None for adaptive plans (chosen during the campaign).
    """
    from workcell.campaign.plans import make_plan

    cfg = config or CampaignConfig()
    gen, q = make_plan(kind, spec, env, n, seed=seed, tool_m=tool_m, approach_rad=cfg.approach_rad)
    if q is None:
        gen.close()
        return None, []
    targets = list(gen)
    ex = Executor(None, None, spec, env, None, tool_m=tool_m, config=cfg)
    return targets, ex.check_plan(targets, start=start_q)


PREVIEW_KINDS = ("dopt", "vopt")  # adaptive plans whose choice at the nominal chain means much


def preview_adaptive_plan(
    kind: str,
    spec: RobotSpec,
    env: Envelope,
    n: int,
    *,
    seed: int,
    tool_m: np.ndarray,
    base_in_tracker: dict | None = None,
    config: CampaignConfig | None = None,
    start_q: np.ndarray | None = None,
) -> tuple[list[PoseTarget], list[str]]:
    """The poses an adaptive design plan (`PREVIEW_KINDS`) would choose if the arm were its
    nominal chain, each answered with the nominal SMR position measured at the tracker's stated
    accuracy, and their envelope check; nothing moves. The campaign chooses from the real
    measurements, which move the choice once the calibrated model departs from the nominal one.
    (bo chases the measured error, which the nominal chain does not have: no preview.)
    `start_q`: the arm's posture when the campaign starts, if known (a simulated arm): the plan
    chooses its first pose among those reachable from there, as the campaign does. A plan left
    with no reachable pose (`PlanStuck`) ends the preview with that as a problem."""
    from workcell.campaign.identification import nominal_smr_in_tracker
    from workcell.campaign.plans import make_plan
    from workcell.recording.tracker_spec import tracker_spec_sigma

    if kind not in PREVIEW_KINDS:
        raise ValueError(f"no preview for plan {kind!r}; {', '.join(PREVIEW_KINDS)} have one")
    cfg = config or CampaignConfig()
    arm = ArmPosture(None if start_q is None else np.asarray(start_q, float))
    gen, _ = make_plan(
        kind, spec, env, n, seed=seed, tool_m=tool_m, approach_rad=cfg.approach_rad, arm=arm
    )
    targets: list[PoseTarget] = []
    stuck: list[str] = []
    try:
        t = next(gen)
        while True:
            targets.append(t)
            q = np.asarray(t.q_rad, float)
            if arm.q is not None:
                arm.q = q  # the campaign measures it there
            p = nominal_smr_in_tracker(spec, q[None], tool_m, base_in_tracker)[0]
            sig = tracker_spec_sigma(p)  # one forward kinematics a pose, not two
            t = gen.send(
                {
                    "index": len(targets) - 1,
                    "pose_id": int(t.pose_id),
                    "q_commanded_rad": q.tolist(),
                    "q_measured_rad": q.tolist(),
                    "approach_sign": [int(x) for x in np.sign(t.approach_sign)],
                    "tracker_position_m": p.tolist(),
                    "tracker_sigma_m": [float(sig[0])] * 3,
                }
            )
    except StopIteration:
        pass
    except PlanStuck as e:
        stuck.append(f"after {len(targets)} poses: {e}")
    ex = Executor(None, None, spec, env, None, tool_m=tool_m, config=cfg)
    return targets, ex.check_plan(targets, start=start_q) + stuck
