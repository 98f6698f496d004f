"""The safety envelope: joint limits, a workspace box, a floor, and speed/acceleration caps.

Every motion target is checked before any motion; a target outside is refused with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from workcell.kinematics.chain import base_T_frames, pack
from workcell.kinematics.robots import RobotSpec


class EnvelopeViolation(ValueError):
    """A target outside the configured envelope; nothing moved."""


@dataclass
class Envelope:
    joint_limits_rad: np.ndarray  # (n, 2)
    box_min_m: np.ndarray = field(default_factory=lambda: np.array([-1.0, -1.0, 0.05]))
    box_max_m: np.ndarray = field(default_factory=lambda: np.array([1.0, 1.0, 1.2]))
    floor_z_m: float = 0.02  # every DH frame origin (2..n) must stay above this (base frame)
    max_speed_rad_s: float = 1.0
    max_accel_rad_s2: float = 2.0

    def to_dict(self) -> dict:
        return {
            "joint_limits_rad": np.asarray(self.joint_limits_rad).tolist(),
            "box_min_m": np.asarray(self.box_min_m).tolist(),
            "box_max_m": np.asarray(self.box_max_m).tolist(),
            "floor_z_m": self.floor_z_m,
            "max_speed_rad_s": self.max_speed_rad_s,
            "max_accel_rad_s2": self.max_accel_rad_s2,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Envelope:
        return cls(
            joint_limits_rad=np.asarray(d["joint_limits_rad"], float),
            box_min_m=np.asarray(d["box_min_m"], float),
            box_max_m=np.asarray(d["box_max_m"], float),
            floor_z_m=float(d.get("floor_z_m", 0.02)),
            max_speed_rad_s=float(d.get("max_speed_rad_s", 1.0)),
            max_accel_rad_s2=float(d.get("max_accel_rad_s2", 2.0)),
        )

    def violations(self, spec: RobotSpec, q: np.ndarray, tool_m: np.ndarray) -> list[str | None]:
        """For each row of q (N, n): None if inside, else the reason."""
        q = np.atleast_2d(np.asarray(q, float))
        out: list[str | None] = [None] * len(q)
        finite = np.all(np.isfinite(q), axis=1)
        lim = self.joint_limits_rad
        T = np.asarray(base_T_frames(pack(spec.dh), np.where(finite[:, None], q, 0.0)))
        smr = np.einsum("nab,b->na", T[:, -1, :3, :3], np.asarray(tool_m, float)) + T[:, -1, :3, 3]
        for i in range(len(q)):
            if not finite[i]:
                out[i] = "target has non-finite joint values"
                continue
            bad = np.where((q[i] < lim[:, 0]) | (q[i] > lim[:, 1]))[0]
            if len(bad):
                j = bad[0]
                out[i] = (
                    f"joint {j + 1} target {q[i, j]:.4f} rad outside the envelope "
                    f"[{lim[j, 0]:.4f}, {lim[j, 1]:.4f}] rad"
                )
                continue
            if np.any(smr[i] < self.box_min_m) or np.any(smr[i] > self.box_max_m):
                out[i] = (
                    f"SMR at {np.round(smr[i], 3).tolist()} m (base) outside the workspace box "
                    f"{np.round(self.box_min_m, 3).tolist()}..{np.round(self.box_max_m, 3).tolist()}"
                )
                continue
            zmin = T[i, 2:, 2, 3].min()
            if zmin < self.floor_z_m:
                out[i] = (
                    f"a link frame would go down to z = {zmin:.3f} m, below the floor {self.floor_z_m} m"
                )
        return out

    def check(self, spec: RobotSpec, q: np.ndarray, tool_m: np.ndarray) -> None:
        v = self.violations(spec, np.atleast_2d(q), tool_m)[0]
        if v is not None:
            raise EnvelopeViolation(f"refused before any motion: {v}")

    def cap(self, speed: float, accel: float) -> tuple[float, float]:
        return min(speed, self.max_speed_rad_s), min(accel, self.max_accel_rad_s2)


def default_envelope(spec: RobotSpec) -> Envelope:
    """A conservative envelope for measurement poses: arm above the table, no wrapped joints."""
    reach = float(np.abs(spec.dh.a).sum() + np.abs(spec.dh.d[3:]).sum())
    d = np.deg2rad
    lim = np.array(
        [
            [-d(170), d(170)],
            [-d(175), -d(5)],
            [-d(160), d(160)],
            [-d(260), d(80)],
            [-d(170), d(170)],
            [-d(170), d(170)],
        ]
    )
    lim[:, 0] = np.maximum(lim[:, 0], spec.joint_limits_rad[:, 0])
    lim[:, 1] = np.minimum(lim[:, 1], spec.joint_limits_rad[:, 1])
    return Envelope(
        joint_limits_rad=lim,
        box_min_m=np.array([-reach, -reach, 0.05]),
        box_max_m=np.array([reach, reach, reach + spec.dh.d[0]]),
        floor_z_m=0.02,
        max_speed_rad_s=1.0,
        max_accel_rad_s2=2.0,
    )
