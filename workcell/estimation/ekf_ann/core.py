"""Dense extended Kalman filter steps in JAX (pure, jittable, float64).

The filter works on a dense covariance P (n, n). Updates are rank-m (m = measurement size):

    S = H P H^T + R,  K = P H^T S^-1,  x <- x + K e,  P <- P - K S K^T   (= (I - K H) P)

which costs O(n^2 m) instead of the O(n^3) of the Joseph form; `joseph=True` selects the Joseph
form (I - K H) P (I - K H)^T + K R K^T (what filterpy's ExtendedKalmanFilter does) for checks.
P stays exactly symmetric: the rank-m downdate is written as a sum of symmetric outer products
and the prediction symmetrises F P F^T + Q. The normalised innovation squared e^T S^-1 e is returned for the
innovation-based variance-factor test (it is chi^2(m) distributed when the model is adequate).

`predict`/`update` are the sample-by-sample reference form (general F, checked against filterpy
with and without the Joseph form). The EKF-ANN filter runs `blocked_scan`: the same rank-m
updates with an additive prediction, the covariance written once per block (checked against
filterpy run sample by sample).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

from workcell._jax import jax, jnp


class UpdateResult(NamedTuple):
    x: jnp.ndarray
    P: jnp.ndarray
    innovation: jnp.ndarray  # e = z - h(x_prior), (m,)
    S: jnp.ndarray  # innovation covariance (m, m)
    nis: jnp.ndarray  # e^T S^-1 e, scalar


def symmetrise(P: jnp.ndarray) -> jnp.ndarray:
    return 0.5 * (P + P.T)


def predict(
    x_pred: jnp.ndarray, P: jnp.ndarray, F: jnp.ndarray | None, Q: jnp.ndarray
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Prediction: x_pred = f(x) given (the nonlinear model), P <- F P F^T + Q (F None = I)."""
    P = P if F is None else F @ P @ F.T
    return x_pred, symmetrise(P + Q)


def update(
    x: jnp.ndarray,
    P: jnp.ndarray,
    z: jnp.ndarray,
    hx: jnp.ndarray,
    H: jnp.ndarray,
    R: jnp.ndarray,
    *,
    joseph: bool = False,
) -> UpdateResult:
    """Measurement update with z (m,), h(x) (m,), H = dh/dx (m, n), R (m, m).

    Rank-m form: with S = L L^T (Cholesky) and B = L^-1 H P (m, n),
        x <- x + B^T L^-1 e,    P <- P - sum_k b_k b_k^T   (b_k the rows of B),
    written as one fused elementwise pass over P. Each term b_k b_k^T is exactly symmetric in
    floating point, so a symmetric P stays exactly symmetric (the symmetrisation is built in).
    """
    e = z - hx
    HP = H @ P  # (m, n) = (P H^T)^T for symmetric P
    S = symmetrise(HP @ H.T + R)
    L = jnp.linalg.cholesky(S)
    B = jax.scipy.linalg.solve_triangular(L, HP, lower=True)  # (m, n)
    le = jax.scipy.linalg.solve_triangular(L, e, lower=True)
    x_new = x + B.T @ le
    if joseph:
        K = jax.scipy.linalg.solve_triangular(L.T, B, lower=False).T  # P H^T S^-1
        IKH = jnp.eye(P.shape[0]) - K @ H
        P_new = symmetrise(IKH @ P @ IKH.T + K @ R @ K.T)
    else:
        D = B[0][:, None] * B[0][None, :]
        for k in range(1, B.shape[0]):
            D = D + B[k][:, None] * B[k][None, :]
        P_new = P - D
    return UpdateResult(x_new, P_new, e, S, le @ le)


class Step(NamedTuple):
    """What one filter step needs from the model (see `blocked_scan`).

    x_bar: predicted state (n,); the covariance prediction is P <- P + Q with Q = diag(q_diag)
    (None: zero) plus q_blk (d, d) on the states [blk_off, blk_off + d) (None: zero);
    hx (m,), H (m, n), R (m, m): the linearised observation at x_bar; aux: per-step outputs;
    HP0: optionally H @ P_0 (m, n) for the covariance P_0 at the start of the block, computed by
    the model from its block context (`prep`) using the structure of H; None: dense H @ P_0.
    """

    x_bar: jnp.ndarray
    q_diag: jnp.ndarray | None
    q_blk: jnp.ndarray | None
    hx: jnp.ndarray
    H: jnp.ndarray
    R: jnp.ndarray
    aux: object
    HP0: jnp.ndarray | None = None


def blocked_scan(
    model: Callable[[jnp.ndarray, Any, tuple[Any, Any]], Step],
    x: jnp.ndarray,
    P: jnp.ndarray,
    z: jnp.ndarray,
    xs: Any,
    *,
    block: int,
    blk_off: int = 0,
    blk_dim: int = 0,
    prep: Callable[[jnp.ndarray, Any], tuple[Any, Any]] | None = None,
) -> tuple[jnp.ndarray, jnp.ndarray, tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray, Any]]:
    """EKF over a sequence with delayed (blocked) covariance updates; same result as the
    sample-by-sample rank-m filter (`update`) with an additive prediction P <- P + Q_i.

    Within a block of `block` samples the covariance is kept as P_i = P_0 + sum Q - V^T V, with
    V (m * block, n) collecting the rows B of every update so far (the terms commute, so this is
    exact). A step then only needs H P_0 and the thin V; the n x n covariance is written once
    per block, by one matrix product P_0 + sum Q - V^T V (BLAS-3) instead of `block` rank-m
    passes over it.

    `model(x, inp, ctx) -> Step`; z (N, m) the measurements; xs a pytree of per-sample inputs
    with leading dimension N, N a multiple of `block`. `prep(P_0, xs_block) -> (per_sample,
    shared)` (optional) builds a context once per block from the block's covariance and inputs;
    the model receives (per_sample[j], shared) and can return H P_0 from it (Step.HP0).
    Returns (x, P, (innovation (N, m), S (N, m, m), nis (N,), aux stacked)).
    """
    n = x.shape[0]
    N = z.shape[0]
    if N % block:
        raise ValueError(f"blocked_scan: {N} samples is not a multiple of the block {block}")
    m = z.shape[1]
    nb = N // block
    zs = z.reshape((nb, block, m))
    xsb = jax.tree_util.tree_map(lambda a: a.reshape((nb, block) + a.shape[1:]), xs)
    eye_blk = blk_dim and slice(blk_off, blk_off + blk_dim)

    def outer(carry, inp_b):
        x, P0 = carry
        zb, xb = inp_b
        per, shared = prep(P0, xb) if prep is not None else (jnp.zeros(block), None)

        def inner(c, inp):
            x, V, Vt, dacc, bacc, j = c
            zi, xi, ci = inp
            st = model(x, xi, (ci, shared))
            H = st.H
            HP0 = H @ P0 if st.HP0 is None else st.HP0
            HP = HP0 - (H @ Vt) @ V
            if st.q_diag is not None:
                dacc = dacc + st.q_diag
                HP = HP + H * dacc[None, :]
            if st.q_blk is not None:
                bacc = bacc + st.q_blk
                HP = HP.at[:, eye_blk].add(H[:, eye_blk] @ bacc)
            e = zi - st.hx
            S = symmetrise((HP[:, None, :] * H[None, :, :]).sum(-1) + st.R)
            B, le = _chol_solve_small(S, HP, e)  # B = L^-1 H P, le = L^-1 e, S = L L^T
            x = st.x_bar + B.T @ le
            V = jax.lax.dynamic_update_slice(V, B, (m * j, 0))
            Vt = jax.lax.dynamic_update_slice(Vt, B.T, (0, m * j))
            return (x, V, Vt, dacc, bacc, j + 1), (e, S, le @ le, st.aux)

        V0 = jnp.zeros((m * block, n), P0.dtype)
        zn = jnp.zeros(n, P0.dtype)
        c0 = (x, V0, V0.T, zn, jnp.zeros((blk_dim, blk_dim), P0.dtype), 0)
        (x, V, Vt, dacc, bacc, _), out = jax.lax.scan(inner, c0, (zb, xb, per))
        P = P0 - Vt @ V + jnp.diag(dacc)
        if blk_dim:
            P = P.at[eye_blk, eye_blk].add(bacc)
        return (x, P), out

    (x, P), out = jax.lax.scan(outer, (x, P), (zs, xsb))
    P = symmetrise(P)  # V^T V from a matrix product is symmetric only to rounding: once per call
    out = jax.tree_util.tree_map(lambda a: a.reshape((N,) + a.shape[2:]), out)
    return x, P, out


def _chol_solve_small(S, HP, e):
    """Cholesky S = L L^T of a small (m, m) matrix, unrolled, and B = L^-1 HP, L^-1 e by forward
    substitution: elementwise operations XLA fuses (LAPACK calls cost more than the arithmetic
    at m = 3). A non-positive pivot gives NaN, as jnp.linalg.cholesky does."""
    m = S.shape[0]
    L = [[None] * m for _ in range(m)]
    for i in range(m):
        for j in range(i + 1):
            v = S[i, j] - sum((L[i][k] * L[j][k] for k in range(j)), jnp.zeros((), S.dtype))
            L[i][j] = jnp.sqrt(v) if i == j else v / L[j][j]
    rows, es = [], []
    for i in range(m):
        r = HP[i] - sum((L[i][k] * rows[k] for k in range(i)), jnp.zeros((), HP.dtype))
        ee = e[i] - sum((L[i][k] * es[k] for k in range(i)), jnp.zeros((), e.dtype))
        rows.append(r / L[i][i])
        es.append(ee / L[i][i])
    return jnp.stack(rows), jnp.stack(es)
