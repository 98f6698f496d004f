"""In-process simulated devices implementing workcell's Robot and Tracker Protocols on a SimWorld.

Time is virtual: a move advances the world clock by its duration, so a campaign runs as fast as
the CPU allows while every time stamp, temperature and warm-up curve is that of a real campaign.
"""

from __future__ import annotations

import numpy as np

from sim_devices.world import SimWorld
from workcell.drivers.protocols import DeviceError, PayloadSetting, RobotState, TrackerReading


class SimRobot:
    def __init__(self, world: SimWorld) -> None:
        self.world = world
        self.connected = False
        self._tau_key: bytes | None = None
        self._tau = np.zeros(6)

    def connect(self) -> None:
        self.connected = True

    def close(self) -> None:
        self.connected = False

    def _torques(self, q: np.ndarray) -> np.ndarray:
        key = np.round(q, 9).tobytes()  # the arm is static most of the time: cache
        if key != self._tau_key:
            self._tau_key, self._tau = key, self.world.truth.gravity_torques(q)
        return self._tau

    def state(self) -> RobotState:
        q, qd = self.world.joint_state()
        tau = self._torques(q)
        return RobotState(
            t_s=self.world.clock.now(),
            q_rad=q + self.world.encoder_rng.normal(0.0, 2e-6, 6),  # encoder noise
            qd_rad_s=qd,
            temperature_c=self.world.joint_temperatures_c(),
            torque_nm=-tau,  # the motors hold against gravity
            current_a=-tau / 10.0,
        )

    def move_joints(self, q_rad: np.ndarray, speed_rad_s: float, accel_rad_s2: float) -> None:
        if not self.connected:
            raise DeviceError("simulated robot is not connected")
        dur = self.world.command_move(np.asarray(q_rad, float), speed_rad_s, accel_rad_s2)
        self.world.clock.advance(dur)

    def stop(self) -> None:
        self.world.stop()

    def sleep(self, seconds: float) -> None:
        self.world.clock.advance(seconds)

    def payload_setting(self) -> PayloadSetting:
        """The payload the simulated controller is set to (what the operator declared on its
        pendant, not the true one), as a UR controller reports it over RTDE."""
        t = self.world.truth
        com = np.asarray(t.declared_payload_com_m, float)
        return PayloadSetting(
            float(t.declared_payload_kg), (float(com[0]), float(com[1]), float(com[2]))
        )


class SimTracker:
    def __init__(self, world: SimWorld, reading_time_s: float = 0.1) -> None:
        self.world = world
        self.reading_time_s = reading_time_s
        self.connected = False

    def connect(self) -> None:
        self.connected = True

    def close(self) -> None:
        self.connected = False

    def measure(self) -> TrackerReading:
        if not self.connected:
            raise DeviceError("simulated tracker is not connected")
        self.world.clock.advance(self.reading_time_s)
        p, status = self.world.read_tracker()
        return TrackerReading(
            position_m=p,
            sigma_m=self.world.stated_sigma_m(p),
            status=status,
            t_s=self.world.clock.now(),
        )
