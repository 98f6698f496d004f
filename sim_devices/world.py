"""The simulated world shared by every simulated device: the true cell, a clock, joint motion.

Time is simulation time in seconds. `VirtualClock` advances only when told (in-process sims run
as fast as the CPU allows); `ScaledClock` follows the wall clock `time_scale` times faster (the
protocol servers use it). Motion is a synchronous trapezoidal profile under joint speed and
acceleration limits.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from sim_devices.truth import TrueWorkcell


class VirtualClock:
    def __init__(self) -> None:
        self._t = 0.0

    def now(self) -> float:
        return self._t

    def advance(self, dt: float) -> None:
        self._t += max(float(dt), 0.0)

    def sleep(self, dt: float) -> None:
        self.advance(dt)


class ScaledClock:
    def __init__(self, time_scale: float = 1.0) -> None:
        if not time_scale > 0:
            raise ValueError(f"time scale must be > 0, got {time_scale}")
        self.time_scale = float(time_scale)
        self._t0 = time.monotonic()

    def now(self) -> float:
        return (time.monotonic() - self._t0) * self.time_scale

    def sleep(self, dt: float) -> None:
        time.sleep(max(float(dt), 0.0) / self.time_scale)

    def advance(self, dt: float) -> None:  # real time passes by itself
        self.sleep(dt)


class Trajectory:
    """Synchronous trapezoidal joint move from q0 to q1 (all joints arrive together)."""

    def __init__(self, t0, q0, q1, speed, accel, vmax_joint) -> None:
        self.t0, self.q0, self.q1 = float(t0), np.asarray(q0, float), np.asarray(q1, float)
        dq = self.q1 - self.q0
        self.dist = float(np.abs(dq).max())
        self.dir = dq / self.dist if self.dist > 0 else np.zeros(6)
        v = min(float(speed), float(np.min(vmax_joint)))
        a = float(accel)
        if self.dist == 0:
            self.ta = self.tc = 0.0
            self.v = 0.0
        elif self.dist < v * v / a:  # triangular
            self.v = np.sqrt(self.dist * a)
            self.ta, self.tc = self.v / a, 0.0
        else:
            self.v = v
            self.ta, self.tc = v / a, self.dist / v - v / a
        self.a = a
        self.duration = 2 * self.ta + self.tc

    def _s(self, t: float) -> tuple[float, float]:
        t = t - self.t0
        if t <= 0 or self.dist == 0:
            return 0.0, 0.0
        if t >= self.duration:
            return self.dist, 0.0
        if t < self.ta:
            return 0.5 * self.a * t * t, self.a * t
        if t < self.ta + self.tc:
            return 0.5 * self.a * self.ta**2 + self.v * (t - self.ta), self.v
        td = self.duration - t
        return self.dist - 0.5 * self.a * td * td, self.a * td

    def state(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        s, v = self._s(t)
        return self.q0 + s * self.dir, v * self.dir

    def done(self, t: float) -> bool:
        return t - self.t0 >= self.duration


class SimWorld:
    """The true cell plus its state: joints, approach directions, time, tracker readings."""

    def __init__(
        self,
        truth: TrueWorkcell,
        *,
        clock: VirtualClock | ScaledClock | None = None,
        seed: int = 0,
        q0: np.ndarray | None = None,
        noise_stream: int = 0,
    ) -> None:
        self.truth = truth
        self.clock = clock or VirtualClock()
        # noise_stream > 0: another run on the same truth (a resumed campaign) draws other noise
        self.rng = np.random.default_rng(
            seed + 7919 if not noise_stream else [seed + 7919, int(noise_stream)]
        )
        # the encoders' noise has its own stream: how often a campaign reads the arm's state
        # must not change the tracker's noise draws (the data)
        self.encoder_rng = np.random.default_rng([seed + 7919, int(noise_stream), 1])
        self.lock = threading.RLock()
        q0 = np.array([0.0, -1.57, 1.57, -1.57, -1.57, 0.0]) if q0 is None else np.asarray(q0)
        self._traj = Trajectory(0.0, q0, q0, 1.0, 1.0, np.full(6, 1.0))
        self.approach_sign = np.zeros(6)
        self._pose_error = np.zeros(3)
        self._pose_key: bytes | None = None
        self.vmax = truth.nominal.max_joint_speed_rad_s
        self.protective_stop = False

    # ----------------------------------------------------------------- motion
    def command_move(self, q_target, speed: float, accel: float) -> float:
        """Start a joint move now; returns its duration in seconds."""
        with self.lock:
            t = self.clock.now()
            q_now, _ = self._traj.state(t)
            q_target = np.asarray(q_target, float)
            dq = q_target - q_now
            moving = np.abs(dq) > 1e-9
            self.approach_sign = np.where(moving, np.sign(dq), self.approach_sign)
            self._traj = Trajectory(t, q_now, q_target, speed, accel, self.vmax)
            return self._traj.duration

    def stop(self, decel: float = 4.0, at: float | None = None) -> None:
        """Stop where the arm is, or where it was at sim time `at` (<= now): a fault scheduled
        for `at` that a late simulator tick handles afterwards still stops the arm there."""
        with self.lock:
            now = self.clock.now()
            q, _ = self._traj.state(now if at is None else min(at, now))
            self._traj = Trajectory(now, q, q, 1.0, decel, self.vmax)

    def joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        with self.lock:
            return self._traj.state(self.clock.now())

    def motion_done(self) -> bool:
        with self.lock:
            return self._traj.done(self.clock.now())

    def joint_temperatures_c(self) -> np.ndarray:
        return self.truth.joint_temperatures_c(self.clock.now())

    def gravity_torques(self) -> np.ndarray:
        q, _ = self.joint_state()
        return self.truth.gravity_torques(q)

    # ----------------------------------------------------------------- tracker
    def true_smr_tracker(self) -> np.ndarray:
        q, _ = self.joint_state()
        return self.truth.smr_in_tracker(q, self.approach_sign, self.clock.now())

    def read_tracker(self) -> tuple[np.ndarray, str]:
        """One noisy reading of the SMR in the tracker frame and its status."""
        with self.lock:
            nz = self.truth.noise
            if self.rng.random() < nz.beam_break_prob:
                return np.full(3, np.nan), "beam_broken"
            p = self.true_smr_tracker()
            rng_m = float(np.linalg.norm(p))
            sys_, rnd = nz.sigma_parts(rng_m)
            q, _ = self.joint_state()
            key = np.round(q, 6).tobytes()
            if key != self._pose_key:  # new static pose: new systematic error
                self._pose_key = key
                self._pose_error = self.rng.normal(0.0, sys_, 3)
            p = p + self._pose_error + self.rng.normal(0.0, rnd, 3)
            if self.rng.random() < nz.outlier_prob:
                p = p + self.rng.normal(0.0, nz.outlier_scale_m, 3)
            return p, "ok"

    def stated_sigma_m(self, p: np.ndarray) -> np.ndarray:
        """The instrument's stated per-reading 1-sigma per axis (what a tracker reports)."""
        r = float(np.linalg.norm(p)) if np.all(np.isfinite(p)) else 2.0
        return np.full(3, self.truth.noise.sigma_axis(r))
