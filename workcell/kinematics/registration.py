"""Robust rigid registration of an arm's nominal SMR positions to tracker measurements.

`register_nominal` answers "do these tracker positions follow this arm at all?" before any fit:
the tracker_T_base transform and the SMR offset in the flange that bring the nominal model's SMR
positions onto the measured ones, with a Cauchy loss so that a few gross readings (a lost beam
written as zeros, another target) neither drag the registration nor hide: they come out with
large distances. The model's own DH errors are left in the distances (a few millimetres at most
on an arm a tracker can calibrate).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from workcell.kinematics.frames import (
    check_points,
    kabsch,
    matrix_from_rotvec,
    right_jacobian,
    rotvec_from_matrix,
    skew_batch,
    transform_from,
)

# the SMR offset may move from its nominal value, but a metre of change costs like 0.1 m of
# residual: enough to pin it when the poses barely turn the flange
TOOL_PRIOR_WEIGHT = 0.1


@dataclass(frozen=True)
class Registration:
    tracker_T_base: np.ndarray  # (4, 4)
    p_flange_smr_m: np.ndarray  # (3,) SMR offset in the flange frame
    distance_m: np.ndarray  # (N,) |registered nominal SMR - measured| per pose


def smr_registration_problem(
    R_flange: np.ndarray,
    t_flange: np.ndarray,
    p_tracker: np.ndarray,
    p_flange_smr_m: npt.ArrayLike,
    prior_weight: float = TOOL_PRIOR_WEIGHT,
) -> tuple[
    Callable[[np.ndarray, np.ndarray], np.ndarray],
    Callable[[np.ndarray, np.ndarray], np.ndarray],
    np.ndarray,
]:
    """The least-squares problem behind every registration with the SMR offset free: flange
    rotations `R_flange` (N, 3, 3) and positions `t_flange` (N, 3) in base, measured SMR
    positions `p_tracker` (N, 3), nominal offset `p_flange_smr_m` (3,). Returns
    (residual(x, rows), jacobian(x, rows), x0): x = (rotvec of tracker_T_base, its translation,
    the SMR offset); the residual stacks the position errors of poses `rows` (m) and
    `prior_weight` times the offset's change; `jacobian` is its exact derivative (for
    `least_squares(jac=...)`: finite differences cost nine residuals a step); x0 is the Kabsch
    registration with the nominal offset."""
    R, t = np.asarray(R_flange, float), np.asarray(t_flange, float)
    P = check_points(p_tracker, "p_tracker")
    tool0 = np.asarray(p_flange_smr_m, dtype=float).reshape(3)
    T0 = kabsch(np.einsum("nij,j->ni", R, tool0) + t, P)
    x0 = np.concatenate([rotvec_from_matrix(T0[:3, :3]), T0[:3, 3], tool0])

    def residual(x: np.ndarray, rows: np.ndarray) -> np.ndarray:
        p_base = np.einsum("nij,j->ni", R[rows], x[6:]) + t[rows]
        r = (p_base @ matrix_from_rotvec(x[:3]).T + x[3:6] - P[rows]).ravel()
        return np.concatenate([r, prior_weight * (x[6:] - tool0)])

    def jacobian(x: np.ndarray, rows: np.ndarray) -> np.ndarray:
        Rb = matrix_from_rotvec(x[:3])
        p_base = np.einsum("nij,j->ni", R[rows], x[6:]) + t[rows]
        n = len(p_base)
        J = np.zeros((3 * n + 3, 9))
        # d(Rb p)/d rotvec = -Rb [p]x Jr(rotvec), Jr the right Jacobian of SO(3)
        J[: 3 * n, :3] = (-Rb @ skew_batch(p_base) @ right_jacobian(x[:3])).reshape(3 * n, 3)
        J[: 3 * n, 3:6] = np.tile(np.eye(3), (n, 1))
        J[: 3 * n, 6:] = (Rb @ R[rows]).reshape(3 * n, 3)
        J[3 * n :, 6:] = prior_weight * np.eye(3)
        return J

    return residual, jacobian, x0


def register_nominal(
    base_T_flange: np.ndarray,
    p_tracker: np.ndarray,
    p_flange_smr_m: npt.ArrayLike,
    *,
    robust_m: float = 5e-3,
) -> Registration:
    """Register nominal flange poses `base_T_flange` (N, 4, 4) with SMR offset `p_flange_smr_m`
    (3,) to measured SMR positions `p_tracker` (N, 3), N >= 3. `robust_m`: the Cauchy loss's
    scale (distances far beyond it barely pull)."""
    from scipy.optimize import least_squares

    P = check_points(p_tracker, "p_tracker")
    T = np.asarray(base_T_flange, dtype=float)
    if T.shape != (len(P), 4, 4):
        raise ValueError(f"base_T_flange: expected shape ({len(P)}, 4, 4), got {T.shape}")
    residual, jac, x0 = smr_registration_problem(T[:, :3, :3], T[:, :3, 3], P, p_flange_smr_m)
    rows = np.arange(len(P))
    x = least_squares(
        residual,
        x0,
        jac=jac,
        args=(rows,),
        x_scale=np.full(9, 0.1),
        loss="cauchy",
        f_scale=robust_m,
        max_nfev=200,
    ).x
    dist = np.linalg.norm(residual(x, rows)[:-3].reshape(-1, 3), axis=1)
    return Registration(transform_from(matrix_from_rotvec(x[:3]), x[3:6]), x[6:].copy(), dist)
