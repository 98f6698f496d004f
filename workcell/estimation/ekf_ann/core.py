"""Dense extended Kalman filter steps in JAX (pure, jittable, float64).

The filter works on a dense covariance P (n, n). Updates are rank-m (m = measurement size):

    S = H P H^T + R,  K = P H^T S^-1,  x <- x + K e,  P <- P - K S K^T   (= (I - K H) P)

which costs O(n^2 m) instead of the O(n^3) of the Joseph form; `joseph=True` selects the Joseph
form (I - K H) P (I - K H)^T + K R K^T (what filterpy's ExtendedKalmanFilter does) for checks.
P stays exactly symmetric: the rank-m downdate is written as a sum of symmetric outer products
and the prediction symmetrises F P F^T + Q. The normalised innovation squared e^T S^-1 e is returned for the
innovation-based variance-factor test (it is chi^2(m) distributed when the model is adequate).
"""

from __future__ import annotations

from typing import NamedTuple

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
