"""Geometric model of an n-joint arm measured by a tracker: DH chain + base pose + SMR offset.

Parameter vector `theta` (5 n + 9,) with names `param_names(n)` (`PARAM_NAMES` for the 6-joint
arms of the catalogue, 39 values):
  a1..an, d1..dn [m], alpha1..alphan [rad], theta1_offset..thetan_offset [rad]   (standard DH)
  beta1..betan [rad]   Hayati rotation about y_i, appended to link i (0 nominally). Standard DH
                       cannot represent a small tilt between nominally parallel axes (UR joints
                       2-3-4); beta can. It is estimated only where the next axis is parallel.
  base_tx, base_ty, base_tz [m], base_rx, base_ry, base_rz [rad]                  (base pose)
  tool_x, tool_y, tool_z [m]                                                       (SMR in flange)

The base pose is `tracker_T_base = base_ref @ Trans(t) @ Rot(r)` where `base_ref` is a fixed
reference transform (e.g. the rigid registration) and (t, r) are offsets expressed along the
*base* axes, so that `base_rz` is a rotation about joint 1's axis and `base_tz` a shift along it.

All functions are pure JAX, vectorised over N poses, float64. The joint count n is taken from
the shape of the joint vectors (static under jit), so one code path serves 6- and 7-joint arms.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from workcell._jax import jax, jnp
from workcell.kinematics.robots import DH

# What each parameter group is, and in which frame (for reports beside the numbers)
PARAMETER_FRAMES = {
    "a, d, alpha, theta_offset": "standard DH of link i, in frame i-1 (m, rad)",
    "beta": "Hayati tilt of link i about its y axis (rad), where the next axis is parallel",
    "base_t*, base_r*": (
        "tracker_T_base = base_ref @ Trans(t) @ Rot(r): offsets from base_ref (the model's rigid "
        "registration) along the base axes (m, rad; base_rz about joint 1's axis)"
    ),
    "tool_*": "p_flange_smr: the SMR centre in the flange frame (m)",
}

N_JOINTS = 6
BASE_NAMES = ["base_tx", "base_ty", "base_tz", "base_rx", "base_ry", "base_rz"]
TOOL_NAMES = ["tool_x", "tool_y", "tool_z"]


def dh_names(n: int = N_JOINTS) -> list[str]:
    r = range(1, n + 1)
    return (
        [f"a{i}" for i in r]
        + [f"d{i}" for i in r]
        + [f"alpha{i}" for i in r]
        + [f"theta{i}_offset" for i in r]
        + [f"beta{i}" for i in r]
    )


def param_names(n: int = N_JOINTS) -> list[str]:
    """Names of the 5 n + 9 parameters of an n-joint chain, in `theta` order."""
    return dh_names(n) + BASE_NAMES + TOOL_NAMES


def joints_of(theta: Any) -> int:
    """Joint count n of a parameter vector (5 n + 9,); ValueError for any other length."""
    m = int(np.shape(theta)[0])
    n, rem = divmod(m - 9, 5)
    if rem or n < 1:
        raise ValueError(f"theta: expected 5 n + 9 values (39 for 6 joints), got {m}")
    return n


def base_slice(n: int = N_JOINTS) -> slice:
    return slice(5 * n, 5 * n + 6)


def tool_slice(n: int = N_JOINTS) -> slice:
    return slice(5 * n + 6, 5 * n + 9)


def param_index(n: int = N_JOINTS) -> dict[str, int]:
    return {p: i for i, p in enumerate(param_names(n))}


PARAM_NAMES: list[str] = param_names(N_JOINTS)
N_PARAMS = len(PARAM_NAMES)


def param_unit(name: str) -> str:
    return "rad" if name.startswith(("alpha", "theta", "beta", "base_r")) else "m"


PARAM_UNITS = {n: param_unit(n) for n in PARAM_NAMES}
I_TOOL = tool_slice(N_JOINTS)
IDX = param_index(N_JOINTS)


def pack(
    dh: DH,
    base_t: npt.ArrayLike = (0.0, 0.0, 0.0),
    base_r: npt.ArrayLike = (0.0, 0.0, 0.0),
    tool: npt.ArrayLike = (0.0, 0.0, 0.0),
    beta: npt.ArrayLike | None = None,
) -> np.ndarray:
    """Parameter vector from a DH chain, base offsets and tool (SMR) offset."""
    beta = np.zeros(len(dh.a)) if beta is None else np.asarray(beta, float)
    return np.concatenate(
        [
            dh.a,
            dh.d,
            dh.alpha,
            dh.theta_offset,
            beta,
            np.asarray(base_t, float),
            np.asarray(base_r, float),
            np.asarray(tool, float),
        ]
    )


def parallel_beta_names(dh: DH, tol: float = 1e-6) -> list[str]:
    """beta_i worth estimating: link i whose next joint axis is nominally parallel (alpha_i = 0)."""
    return [f"beta{i + 1}" for i in range(len(dh.a) - 1) if abs(np.sin(dh.alpha[i])) < tol]


def unpack_dh(theta: np.ndarray) -> DH:
    t = np.asarray(theta, dtype=float)
    n = joints_of(t)
    return DH(a=t[0:n], d=t[n : 2 * n], alpha=t[2 * n : 3 * n], theta_offset=t[3 * n : 4 * n])


def _rotvec_to_matrix(r):
    th2 = jnp.dot(r, r)
    small = th2 < 1e-12
    th2s = jnp.where(small, 1.0, th2)
    th = jnp.sqrt(th2s)
    A = jnp.where(small, 1.0 - th2 / 6.0, jnp.sin(th) / th)
    B = jnp.where(small, 0.5 - th2 / 24.0, (1.0 - jnp.cos(th)) / th2s)
    K = jnp.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    return jnp.eye(3) + A * K + B * (K @ K)


def _dh_matrix(a, d, alpha, th, beta=0.0):
    """Rz(th) Tz(d) Tx(a) Rx(alpha) Ry(beta)."""
    ct, st = jnp.cos(th), jnp.sin(th)
    ca, sa = jnp.cos(alpha), jnp.sin(alpha)
    A = jnp.array(
        [
            [ct, -st * ca, st * sa, a * ct],
            [st, ct * ca, -ct * sa, a * st],
            [0.0, sa, ca, d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    cb, sb = jnp.cos(beta), jnp.sin(beta)
    Ry = jnp.array(
        [[cb, 0.0, sb, 0.0], [0.0, 1.0, 0.0, 0.0], [-sb, 0.0, cb, 0.0], [0.0, 0.0, 0.0, 1.0]]
    )
    return A @ Ry


def _link(theta, i, qi, n):
    beta = theta[4 * n + i] if theta.shape[0] >= 5 * n else 0.0
    return _dh_matrix(theta[i], theta[n + i], theta[2 * n + i], qi + theta[3 * n + i], beta)


def base_T_flange_single(theta: Any, q: Any) -> Any:
    """Flange pose in base for one joint vector q (n,). theta (>= 4 n,) holds the DH part."""
    n = q.shape[0]
    T = jnp.eye(4)
    for i in range(n):
        T = T @ _link(theta, i, q[i], n)
    return T


def base_T_frames_single(theta: Any, q: Any) -> Any:
    """All DH frames 0..n in base for one q (n,): (n + 1, 4, 4)."""
    n = q.shape[0]
    Ts = [jnp.eye(4)]
    for i in range(n):
        Ts.append(Ts[-1] @ _link(theta, i, q[i], n))
    return jnp.stack(Ts)


def tracker_T_base(theta: Any, base_ref: Any) -> Any:
    b = base_slice(joints_of(theta)).start
    t = theta[b : b + 3]
    R = _rotvec_to_matrix(theta[b + 3 : b + 6])
    off = jnp.eye(4).at[:3, :3].set(R).at[:3, 3].set(t)
    return base_ref @ off


def base_pose_with_std(
    theta: npt.ArrayLike, base_ref: npt.ArrayLike, cov: npt.ArrayLike | None = None
) -> dict[str, Any]:
    """tracker_T_base (the base_ref registration with the fitted base offsets) as a translation
    (m) and a quaternion (w, x, y, z); with a parameter covariance `cov` (P, P) also the 1-sigma
    of its translation and of a small rotation about the tracker's axes (rad), first order."""
    from workcell.kinematics.frames import quat_wxyz_from_matrix

    th = jnp.asarray(theta, dtype=float)
    ref = jnp.asarray(base_ref, dtype=float)
    T = np.asarray(tracker_T_base(th, ref), float)
    out = {
        "translation_m": T[:3, 3].tolist(),
        "quaternion_wxyz": quat_wxyz_from_matrix(T[:3, :3]).tolist(),
    }
    if cov is None:
        return out
    C = np.asarray(cov, float)
    if C.shape != (th.shape[0],) * 2 or not np.all(np.isfinite(C)):
        return out
    J = np.asarray(jax.jacfwd(lambda t: tracker_T_base(t, ref))(th))
    W = np.einsum("ijp,kj->ikp", J[:3, :3, :], T[:3, :3])  # dR R^T: skew in each column
    Jb = np.vstack([J[:3, 3, :], np.stack([W[2, 1], W[0, 2], W[1, 0]])])
    sd = np.sqrt(np.clip(np.diag(Jb @ C @ Jb.T), 0, None))
    out["translation_std_m"] = sd[:3].tolist()
    out["rotation_std_rad"] = sd[3:].tolist()
    return out


def p_tracker_single(theta: Any, base_ref: Any, q: Any) -> Any:
    """SMR position in the tracker frame for one q (n,); theta (5 n + 9,)."""
    T = tracker_T_base(theta, base_ref) @ base_T_flange_single(theta, q)
    tool = theta[tool_slice(q.shape[0])]
    return T[:3, :3] @ tool + T[:3, 3]


def p_tracker_and_jacobian_single(theta: Any, base_ref: Any, q: Any) -> tuple[Any, Any]:
    """(p (3,), dp/dq (3, n)): SMR position in the tracker frame and its Jacobian w.r.t. the
    joint angles for one q (n,), analytic: joint i turns about z of frame i-1 (q_i enters link
    i only through its first factor Rz), so column i is R_tb (z_{i-1} x (p_base - o_{i-1})).
    Same values as jax.jacfwd of `p_tracker_single` (tested), a fraction of the cost."""
    n = q.shape[0]
    Ts = base_T_frames_single(theta, q)
    tool = theta[tool_slice(n)]
    p_b = Ts[-1, :3, :3] @ tool + Ts[-1, :3, 3]
    jb = jnp.cross(Ts[:-1, :3, 2], p_b[None, :] - Ts[:-1, :3, 3])  # (n, 3)
    Ttb = tracker_T_base(theta, base_ref)
    return Ttb[:3, :3] @ p_b + Ttb[:3, 3], Ttb[:3, :3] @ jb.T


def _bucket(n: int) -> int:
    """Pad batch sizes to a few buckets so jit compiles once per bucket, not once per N."""
    if n <= 64:
        return 64
    return 1 << (n - 1).bit_length() if n <= 65536 else ((n + 65535) // 65536) * 65536


try:
    from jax.core import Tracer as _Tracer
except ImportError:  # pragma: no cover - a jax that no longer exports it there
    from jax._src.core import Tracer as _Tracer


def _batched(fn):
    """Wrap a jitted (theta, [base_ref,] q) function: pad q to a bucket size, slice back."""

    def wrapper(*args):
        *head, q = args
        # concrete values are padded and cut in numpy, so a new N compiles nothing (jax's eager
        # concatenate and slice compile once per shape: 243 compiles in four tight-envelope
        # plans); inside a trace everything stays in jax
        traced = any(isinstance(a, _Tracer) for a in args)
        xp = jnp if traced else np
        q = xp.asarray(q, dtype=xp.float64)
        n = q.shape[0]
        m = _bucket(n)
        if m != n:
            q = xp.concatenate([q, xp.zeros((m - n, q.shape[1]), q.dtype)])
        out = fn(*head, q)
        return out[:n] if traced else np.asarray(out)[:n]

    wrapper.__doc__ = fn.__doc__
    wrapper.__wrapped__ = fn
    return wrapper


@jax.jit
def _p_tracker(theta, base_ref, q):
    return jax.vmap(p_tracker_single, in_axes=(None, None, 0))(theta, base_ref, q)


@jax.jit
def _base_T_flange(theta, q):
    return jax.vmap(base_T_flange_single, in_axes=(None, 0))(theta, q)


@jax.jit
def _jac_params(theta, base_ref, q):
    return jax.vmap(jax.jacfwd(p_tracker_single, argnums=0), in_axes=(None, None, 0))(
        theta, base_ref, q
    )


@jax.jit
def _jac_joints(theta, base_ref, q):
    return jax.vmap(jax.jacfwd(p_tracker_single, argnums=2), in_axes=(None, None, 0))(
        theta, base_ref, q
    )


@jax.jit
def _base_T_frames(theta, q):
    return jax.vmap(base_T_frames_single, in_axes=(None, 0))(theta, q)


p_tracker = _batched(_p_tracker)
p_tracker.__doc__ = "SMR positions (N, 3) in the tracker frame for joints q (N, n)."
base_T_flange = _batched(_base_T_flange)
base_T_flange.__doc__ = "Flange poses (N, 4, 4) in base."
jac_params = _batched(_jac_params)
jac_params.__doc__ = "d p_tracker / d theta: (N, 3, 5 n + 9) (39 for 6 joints)."
jac_joints = _batched(_jac_joints)
jac_joints.__doc__ = "d p_tracker / d q: (N, 3, n)."
base_T_frames = _batched(_base_T_frames)
base_T_frames.__doc__ = "DH frames 0..n in base for each pose: (N, n + 1, 4, 4)."


def check_joints(q: np.ndarray, name: str = "q_rad", n: int = N_JOINTS) -> np.ndarray:
    """Validate joint vectors (N, n) or (n,) -> (N, n) float64."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        q = q[None, :]
    if q.ndim != 2 or q.shape[1] != n:
        raise ValueError(f"{name}: expected shape (N, {n}), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError(f"{name}: contains non-finite values")
    return q
