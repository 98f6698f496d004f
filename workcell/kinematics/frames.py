"""Rotations and rigid transforms (numpy). Names follow `A2B` / `x_from_y` conventions.

A transform `tracker_T_base` maps coordinates in `base` to coordinates in `tracker`:
p_tracker = tracker_T_base @ [p_base, 1].
"""

from __future__ import annotations

import numpy as np


def check_transform(T: np.ndarray) -> np.ndarray:
    """Validate a rigid homogeneous transform (4, 4) or a stack (..., 4, 4): finite, bottom row
    0 0 0 1, a rotation block orthonormal with determinant +1; raise ValueError if not."""
    T = np.asarray(T, dtype=float)
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"expected a transform of shape (..., 4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError("transform contains non-finite values")
    if np.abs(T[..., 3, :] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-9:
        raise ValueError(f"bottom row {T[..., 3, :].tolist()}, not [0, 0, 0, 1]")
    R = T[..., :3, :3]
    err = np.abs(np.einsum("...ji,...jk->...ik", R, R) - np.eye(3)).max()
    if err > 1e-6 or np.any(np.linalg.det(R) <= 0):
        raise ValueError(
            f"a rotation block that is not a rotation (max |R^T R - I| = {err:.2e}, "
            f"det {np.min(np.linalg.det(R)):.3g})"
        )
    return T


def check_points(p: np.ndarray, name: str = "points") -> np.ndarray:
    """Validate an array of 3-D points (N, 3); raise ValueError with the offending shape."""
    p = np.asarray(p, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (N, 3), got {p.shape}")
    return p


def skew(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def skew_batch(v: np.ndarray) -> np.ndarray:
    """[v]x for each row of v (N, 3) -> (N, 3, 3)."""
    v = np.asarray(v, float)
    z = np.zeros(len(v))
    return np.stack(
        [
            np.stack([z, -v[:, 2], v[:, 1]], -1),
            np.stack([v[:, 2], z, -v[:, 0]], -1),
            np.stack([-v[:, 1], v[:, 0], z], -1),
        ],
        axis=1,
    )


def right_jacobian(r: np.ndarray) -> np.ndarray:
    """Right Jacobian (3, 3) of SO(3) at rotation vector r: R(r + d) ~ R(r) exp([Jr d]x)."""
    r = np.asarray(r, float)
    th = float(np.linalg.norm(r))
    K = skew(r)
    if th < 1e-6:  # series: I - K/2 + K^2/6
        return np.eye(3) - 0.5 * K + K @ K / 6.0
    return np.eye(3) - (1 - np.cos(th)) / th**2 * K + (th - np.sin(th)) / th**3 * K @ K


def matrix_from_rotvec(r: np.ndarray) -> np.ndarray:
    """Rodrigues formula for a rotation vector (3,) -> (3, 3)."""
    r = np.asarray(r, dtype=float)
    th = float(np.linalg.norm(r))
    K = skew(r)
    if th < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th**2 * K @ K


def rotvec_from_matrix(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def matrix_from_quat_wxyz(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.shape != (4,):
        raise ValueError(f"quaternion: expected shape (4,), got {q.shape}")
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError("quaternion has zero or non-finite norm")
    w, x, y, z = q / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_wxyz_from_matrix(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


def transform_from(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def apply_transform(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to points (N, 3)."""
    return p @ T[:3, :3].T + T[:3, 3]


def kabsch(p_from: np.ndarray, p_to: np.ndarray) -> np.ndarray:
    """Rigid transform `to_T_from` minimising sum |to_T_from p_from - p_to|^2 (no scale)."""
    p_from = check_points(p_from, "p_from")
    p_to = check_points(p_to, "p_to")
    if len(p_from) != len(p_to) or len(p_from) < 3:
        raise ValueError(f"kabsch needs >= 3 matched points, got {len(p_from)} and {len(p_to)}")
    c_from, c_to = p_from.mean(0), p_to.mean(0)
    H = (p_from - c_from).T @ (p_to - c_to)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return transform_from(R, c_to - R @ c_from)
