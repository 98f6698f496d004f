"""Standard DH forward kinematics in numpy, for the nominal arm only.

`workcell.kinematics.chain` is the estimation's chain (JAX, with the Hayati beta terms and the
base/tool parameters). Checks that run before any estimation (`recording.consistency`, called by
`workcell info`) need only the nominal flange poses; this keeps them from loading JAX.
"""

from __future__ import annotations

import numpy as np

from workcell.kinematics.robots import DH


def base_T_flange_nominal(dh: DH, q_rad: np.ndarray) -> np.ndarray:
    """Flange poses in base (N, 4, 4) of joint vectors `q_rad` (N, n) for the standard DH
    parameters `dh` (each link Rz(q + theta_offset) Tz(d) Tx(a) Rx(alpha)); the same values as
    `chain.base_T_flange(pack(dh), q)` (tested)."""
    q = np.asarray(q_rad, dtype=float)
    n = len(np.asarray(dh.a))
    if q.ndim != 2 or q.shape[1] != n:
        raise ValueError(f"q_rad: expected shape (N, {n}), got {q.shape}")
    a, d = np.asarray(dh.a, float), np.asarray(dh.d, float)
    alpha, off = np.asarray(dh.alpha, float), np.asarray(dh.theta_offset, float)
    T = np.broadcast_to(np.eye(4), (len(q), 4, 4)).copy()
    ca, sa = np.cos(alpha), np.sin(alpha)
    for i in range(n):
        th = q[:, i] + off[i]
        ct, st = np.cos(th), np.sin(th)
        A = np.zeros((len(q), 4, 4))
        A[:, 0, 0], A[:, 0, 1], A[:, 0, 2], A[:, 0, 3] = ct, -st * ca[i], st * sa[i], a[i] * ct
        A[:, 1, 0], A[:, 1, 1], A[:, 1, 2], A[:, 1, 3] = st, ct * ca[i], -ct * sa[i], a[i] * st
        A[:, 2, 1], A[:, 2, 2], A[:, 2, 3] = sa[i], ca[i], d[i]
        A[:, 3, 3] = 1.0
        T = T @ A
    return T
