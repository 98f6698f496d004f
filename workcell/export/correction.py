"""Correction of desired targets from any fitted model, for a controller that keeps its nominal
kinematics.

Frames and semantics
- `base`: the robot base frame as the controller knows it. Numerically it is the model's
  registered nominal base: p_tracker = base_ref @ p_base, with `base_ref` the rigid registration of
  the nominal chain to the measurements (`DHModel.base_ref`). Desired and commanded targets are
  SMR (TCP) positions in this frame, in metres; orientations are UR rotation vectors (rad).
- The controller, asked for TCP pose (p, R), solves its nominal IK for q; the real robot then puts
  the SMR at k_real(q) (the model's prediction, mapped to `base`).
- The correction of a desired pose (y*, R*) is the joint vector q with k_real(q) = y* whose nominal
  flange orientation is R* (orientation is what the controller believes: a single-SMR model does not
  observe the real orientation), and the commanded pose is the nominal pose at q: (k_nom(q), R*).
  Joint-space form: q_nominal -> q_corrected; Cartesian form: y* -> commanded position.

Solver: commanded position c by Newton iterations c <- c - J^-1 (k_real(IK_nom(c)) - y*) with
J = d k_real / d c taken as the identity (the correction is a small perturbation of a rigid map;
this contracts by the relative size of the model error, ~1e-3), each IK warm-started from the last.
Nominal IK is damped Gauss-Newton with the geometric Jacobian (numpy, vectorised).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from workcell.errors import UserError
from workcell.kinematics.chain import pack

if TYPE_CHECKING:
    from workcell.estimation.models import FittedModel
    from workcell.recording.dataset import Dataset

# Reference configuration (elbow up, wrist down) from which grid IK starts, per robot.
Q_REF = np.array([np.pi / 2, -2.0, 2.0, -np.pi / 2, -np.pi / 2, 0.0])


CONFIGURATION_BASIS = (
    "arm configuration (IK branch) as three signs: shoulder = sign(a2 cos q2 + a3 cos(q2 + q3) "
    "+ d5 sin(q2 + q3 + q4)) (the wrist's reach in the arm's plane), elbow = sign(sin q3), "
    "wrist = sign(sin q5), with the nominal a2, a3, d5 (`configuration_dh_m`). The correction "
    "holds on that branch only: on another, the same target is reached with other joints and "
    "the correction differs by up to millimetres"
)


def configuration(q: np.ndarray, dh_m: tuple[float, float, float]) -> np.ndarray:
    """(N, 3) signs (shoulder, elbow, wrist) of joints q (N, 6) (`CONFIGURATION_BASIS`), with
    dh_m = (a2, a3, d5) of the nominal chain (`configuration_dh`); 0 exactly at a singularity."""
    a2, a3, d5 = dh_m
    q = np.atleast_2d(np.asarray(q, float))  # the controller's joint values, as URScript sees
    reach = a2 * np.cos(q[:, 1]) + a3 * np.cos(q[:, 1] + q[:, 2])
    reach = reach + d5 * np.sin(q[:, 1] + q[:, 2] + q[:, 3])
    return np.sign(np.stack([reach, np.sin(q[:, 2]), np.sin(q[:, 4])], axis=1)).astype(int)


def configuration_dh(theta: np.ndarray) -> tuple[float, float, float]:
    """(a2, a3, d5) of a packed chain, the lengths `configuration` uses."""
    th = np.asarray(theta, float)
    return float(th[1]), float(th[2]), float(th[6 + 4])


@dataclass
class Conditions:
    """Operating conditions the correction is computed for (the model's aux inputs)."""

    approach_sign: np.ndarray = field(default_factory=lambda: np.ones(6))
    joint_temperature_c: np.ndarray | None = None
    elapsed_s: float | None = None
    payload_kg: float | None = None

    def aux(self, n: int) -> dict:
        out = {"approach_sign": np.tile(np.asarray(self.approach_sign, float), (n, 1))}
        if self.joint_temperature_c is not None:
            out["joint_temperature_c"] = np.tile(
                np.asarray(self.joint_temperature_c, float), (n, 1)
            )
        if self.elapsed_s is not None:
            out["elapsed_s"] = np.full(n, float(self.elapsed_s))
        if self.payload_kg is not None:
            out["payload_kg"] = np.full(n, float(self.payload_kg))
        return out

    def to_dict(self) -> dict:
        return {
            "approach_sign": np.asarray(self.approach_sign, float).tolist(),
            "joint_temperature_c": None
            if self.joint_temperature_c is None
            else np.asarray(self.joint_temperature_c, float).tolist(),
            "elapsed_s": self.elapsed_s,
            "payload_kg": self.payload_kg,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Conditions:
        t = d.get("joint_temperature_c")
        return cls(
            approach_sign=np.asarray(d.get("approach_sign", [1.0] * 6), float),
            joint_temperature_c=None if t is None else np.asarray(t, float),
            elapsed_s=d.get("elapsed_s"),
            payload_kg=d.get("payload_kg"),
        )


@dataclass
class Nominal:
    """The controller's kinematics: nominal DH chain, nominal SMR (TCP) and the registered base."""

    theta: np.ndarray  # (39,) nominal DH + tool (base offsets zero)
    base_ref: np.ndarray  # (4, 4) tracker_T_base (registered)
    robot: str = "unknown"

    @property
    def tool_m(self) -> np.ndarray:
        return np.asarray(self.theta[36:39])

    def to_base(self, p_tracker: np.ndarray) -> np.ndarray:
        R, t = self.base_ref[:3, :3], self.base_ref[:3, 3]
        return (np.asarray(p_tracker) - t) @ R

    def to_tracker(self, p_base: np.ndarray) -> np.ndarray:
        R, t = self.base_ref[:3, :3], self.base_ref[:3, 3]
        return np.asarray(p_base) @ R.T + t

    def frames(self, q: np.ndarray) -> np.ndarray:
        """Nominal DH frames 0..6 in base (N, 7, 4, 4) (numpy, vectorised)."""
        return _frames_np(self.theta, np.atleast_2d(np.asarray(q, float)))

    def fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nominal TCP (SMR) positions (N, 3) and flange rotations (N, 3, 3) in base."""
        T = self.frames(q)[:, 6]
        return T[:, :3, :3] @ self.tool_m + T[:, :3, 3], T[:, :3, :3]

    def ik(
        self, p: np.ndarray, R: np.ndarray, q_seed: np.ndarray, iters: int = 40
    ) -> tuple[np.ndarray, np.ndarray]:
        """Nominal IK of TCP positions p (N, 3) with flange rotations R (N, 3, 3) from seeds.

        Damped Gauss-Newton with the geometric Jacobian, steps clipped to 0.3 rad; the branch is
        the seed's. Returns (q (N, 6), residual norm (N,)); stops early once all converge.
        """
        p = np.atleast_2d(np.asarray(p, float))
        n = len(p)
        R = np.broadcast_to(np.asarray(R, float), (n, 3, 3))
        q = np.array(np.broadcast_to(np.asarray(q_seed, float), (n, 6)))
        r = np.full(n, np.inf)
        for _ in range(iters + 1):
            T = _frames_np(self.theta, q)
            Rq = T[:, 6, :3, :3]
            pq = Rq @ self.tool_m + T[:, 6, :3, 3]
            E = np.einsum("nji,njk->nik", R, Rq)
            w = 0.5 * np.stack(
                [E[:, 2, 1] - E[:, 1, 2], E[:, 0, 2] - E[:, 2, 0], E[:, 1, 0] - E[:, 0, 1]], 1
            )
            res = np.concatenate([pq - p, w], 1)
            r = np.linalg.norm(res, axis=1)
            if np.all(r < 1e-14):
                break
            z = T[:, :6, :3, 2]  # joint axes (N, 6, 3)
            o = T[:, :6, :3, 3]
            Jp = np.cross(z, pq[:, None, :] - o)  # (N, 6, 3)
            Jw = np.einsum("nji,nkj->nki", R, z)  # R^T z
            J = np.concatenate([Jp, Jw], 2).transpose(0, 2, 1)  # (N, 6, 6)
            A = np.einsum("nji,njk->nik", J, J) + 1e-12 * np.eye(6)
            g = np.einsum("nji,nj->ni", J, res)
            dq = -np.linalg.solve(A, g[..., None])[..., 0]
            s = np.max(np.abs(dq), axis=1, keepdims=True)
            q = q + dq * np.minimum(1.0, 0.3 / np.maximum(s, 1e-30))
        return q, r


def _frames_np(theta: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Rz(q + th) Tz(d) Tx(a) Rx(alpha) Ry(beta) per link, as in `workcell.kinematics.chain`."""
    th = np.asarray(theta, float)
    n = len(q)
    T = np.zeros((n, 7, 4, 4))
    T[:, 0] = np.eye(4)
    for i in range(6):
        a, d, al, off, be = th[i], th[6 + i], th[12 + i], th[18 + i], th[24 + i]
        ct, st = np.cos(q[:, i] + off), np.sin(q[:, i] + off)
        ca, sa = np.cos(al), np.sin(al)
        A = np.zeros((n, 4, 4))
        A[:, 0, 0], A[:, 0, 1], A[:, 0, 2], A[:, 0, 3] = ct, -st * ca, st * sa, a * ct
        A[:, 1, 0], A[:, 1, 1], A[:, 1, 2], A[:, 1, 3] = st, ct * ca, -ct * sa, a * st
        A[:, 2, 1], A[:, 2, 2], A[:, 2, 3] = sa, ca, d
        A[:, 3, 3] = 1.0
        if be != 0.0:
            cb, sb = np.cos(be), np.sin(be)
            Ry = np.array([[cb, 0, sb, 0], [0, 1, 0, 0], [-sb, 0, cb, 0], [0, 0, 0, 1.0]])
            A = A @ Ry
        T[:, i + 1] = T[:, i] @ A
    return T


def pad_batch(x: np.ndarray) -> np.ndarray:
    """Pad the batch axis to a power of two (>= 8) by repeating the last row: jitted models then
    compile once per size class instead of once per batch size."""
    x = np.asarray(x, float)
    n = len(x)
    m = max(8, 1 << max(n - 1, 1).bit_length())
    if m > n:
        x = np.concatenate([x, np.repeat(x[-1:], m - n, axis=0)])
    return x


def nominal_for(model: FittedModel, ds: Dataset | None = None) -> Nominal:
    """The controller's kinematics for a fitted model: its nominal chain and registered base.

    DH-based models carry them (`nominal_dh`, `base_ref`, `info.nominal_tool_m`); other models may
    expose them through a wrapped `base_model`/`dh_model`; otherwise the recording `ds` is needed
    (the nominal chain registered on its poses, as `fit` does for the nominal baseline).
    """
    for attr in (None, "base", "base_model", "dh_model", "dh", "geometric"):
        m = model if attr is None else getattr(model, attr, None)
        if m is None or isinstance(m, np.ndarray):
            continue
        nd, base = getattr(m, "nominal_dh", None), getattr(m, "base_ref", None)
        if nd is not None and base is not None:
            info = getattr(m, "info", {}) or {}
            tool = info.get("nominal_tool_m")
            if tool is None and hasattr(m, "theta"):
                tool = np.asarray(m.theta)[36:39]
            th = pack(nd, tool=np.asarray(tool if tool is not None else (0.0, 0.0, 0.0), float))
            robot = getattr(m, "robot_model", "unknown")
            return Nominal(theta=th, base_ref=np.asarray(base, float), robot=robot)
    if ds is None:
        raise UserError(
            f"model {getattr(model, 'method', '?')!r} carries no nominal chain/base; "
            "pass its recording (--recording REC)"
        )
    from workcell.estimation.dh import nominal_registered

    th, base = nominal_registered(ds)
    return Nominal(theta=th, base_ref=base, robot=ds.robot.model)


class Corrector:
    """Desired SMR targets -> commanded targets for a controller with nominal kinematics."""

    def __init__(self, model, nominal: Nominal, conditions: Conditions | None = None) -> None:
        self.model = model
        self.nominal = nominal
        self.conditions = conditions or Conditions()

    def real_base(self, q: np.ndarray) -> np.ndarray:
        """The model's SMR position (N, 3) in base for joints q (N, 6) under the conditions."""
        q = np.atleast_2d(np.asarray(q, float))
        qp = pad_batch(q)
        p = np.asarray(self.model.predict(qp, **self.conditions.aux(len(qp))), float)[: len(q)]
        return self.nominal.to_base(p)

    def real_base_cov(self, q: np.ndarray) -> np.ndarray | None:
        """Covariance (N, 3, 3), base axes, of `real_base(q)` from the model's parameter
        covariance (`prediction_cov`); None when the model carries none."""
        f = getattr(self.model, "prediction_cov", None)
        if f is None:
            return None
        q = np.atleast_2d(np.asarray(q, float))
        qp = pad_batch(q)
        C = f(qp, **self.conditions.aux(len(qp)))
        if C is None:
            return None
        R = self.nominal.base_ref[:3, :3]  # base axes -> tracker axes
        return np.einsum("ji,njk,kl->nil", R, np.asarray(C, float)[: len(q)], R)

    def correct_positions(
        self,
        p_desired: np.ndarray,
        R: np.ndarray,
        q_seed: np.ndarray,
        tol_m: float = 1e-10,
        max_iter: int = 30,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cartesian form. Returns (commanded positions (N, 3), q_corrected (N, 6), residual (N,)).

        Rows that fail (IK or the model not converging) come back non-finite.
        """
        y = np.atleast_2d(np.asarray(p_desired, float))
        n = len(y)
        R = np.broadcast_to(np.asarray(R, float), (n, 3, 3))
        q, ik_r = self.nominal.ik(y, R, q_seed, iters=60)
        c = y.copy()
        err = np.full(n, np.inf)
        for _ in range(max_iter):
            e = self.real_base(q) - y
            err = np.linalg.norm(e, axis=1)
            if not np.all(np.isfinite(err)) or err.max() < tol_m:
                break
            c = c - e
            q, ik_r = self.nominal.ik(c, R, q, iters=8)
        bad = ~np.isfinite(err) | (err > max(1e3 * tol_m, 1e-7)) | (ik_r > 1e-8)
        c[bad] = np.nan
        q = q.copy()
        q[bad] = np.nan
        return c, q, err

    def correct_joints(self, q_nominal: np.ndarray) -> np.ndarray:
        """Joint-space form: joints the user would command -> joints that land where the nominal
        model says q_nominal lands (same nominal orientation)."""
        q0 = np.atleast_2d(np.asarray(q_nominal, float))
        p, R = self.nominal.fk(q0)
        _, q, _ = self.correct_positions(p, R, q0)
        return q


def rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.atleast_2d(np.asarray(r, float))).as_matrix()


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, float)).as_rotvec()
