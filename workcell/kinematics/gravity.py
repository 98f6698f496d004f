"""Gravity torques of a 6-joint arm (numpy, vectorised over poses).

`gravity_torques_nm` returns the torque that gravity (links + payload) applies about each joint
axis, in N m, with the sign convention of the joint angle: a positive value pulls the joint towards
increasing angle. A joint of compliance c [rad/(N m)] deflects by c * tau.
"""

from __future__ import annotations

import numpy as np

from workcell.kinematics.chain import base_T_frames, pack
from workcell.kinematics.robots import RobotSpec

G_BASE = np.array([0.0, 0.0, -9.80665])  # gravity in the base frame (base z up)


def gravity_torques_nm(
    spec: RobotSpec,
    q_rad: np.ndarray,
    payload_kg: float | np.ndarray = 0.0,
    payload_com_m: np.ndarray = (0.0, 0.0, 0.0),
    g_base: np.ndarray = G_BASE,
    theta: np.ndarray | None = None,
) -> np.ndarray:
    """Gravity torques (N, 6) for joints q (N, 6). `payload_kg` may be per pose (N,)."""
    q = np.atleast_2d(np.asarray(q_rad, dtype=float))
    th = pack(spec.dh) if theta is None else np.asarray(theta, float)
    if th.shape[0] < 39:
        th = np.concatenate([th, np.zeros(39 - th.shape[0])])
    T = np.asarray(base_T_frames(th, q))  # (N, 7, 4, 4)
    N = q.shape[0]
    masses = np.broadcast_to(spec.link_masses_kg, (N, 6))
    pay = np.broadcast_to(np.asarray(payload_kg, float), (N,))
    # centres of mass in base: link j in frame j (1..6); payload in flange frame 6
    coms = np.einsum("njab,jb->nja", T[:, 1:, :3, :3], spec.link_coms_m) + T[:, 1:, :3, 3]
    pcom = (
        np.einsum("nab,b->na", T[:, 6, :3, :3], np.asarray(payload_com_m, float)) + T[:, 6, :3, 3]
    )
    tau = np.zeros((N, 6))
    for i in range(6):  # joint i+1 rotates about z of frame i
        z = T[:, i, :3, 2]
        o = T[:, i, :3, 3]
        f = masses[:, i:, None] * g_base  # (N, k, 3)
        m = np.cross(coms[:, i:, :] - o[:, None, :], f).sum(1)
        m += np.cross(pcom - o, pay[:, None] * g_base)
        tau[:, i] = np.einsum("na,na->n", m, z)
    return tau
