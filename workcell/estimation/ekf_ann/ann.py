"""The non-geometric part: a fully connected network with one tanh hidden layer (seed 004, eq. 2).

Inputs: the 6 joint angles, standardised per joint (u = (q - centre) / scale). Outputs: 3
position corrections in the robot *base* frame, in units of `out_scale_m` (so the weights are
O(1) for corrections of a few tenths of a millimetre); the output layer is linear.

Weight vector layout (K = 10 H + 3 for 6 inputs and 3 outputs):
    [W1^T (6 x H, row-major: input-major), b1 (H), W2 (3 x H, row-major), b2 (3)]

The input-major first layer makes [W1^T; b1^T] a (7, H) block for the augmented input [u, 1],
which the filter's structured covariance products use (`jac_context`). Saved networks carry
`LAYOUT`; a network saved with another layout is refused.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workcell._jax import jax, jnp

N_IN, N_OUT = 6, 3
LAYOUT = "w1-input-major"
OUT_SCALE_M = 1e-4


@dataclass(frozen=True)
class AnnSpec:
    hidden: int = 29
    u_centre: tuple = (0.0,) * N_IN
    u_scale: tuple = (1.0,) * N_IN
    out_scale_m: float = OUT_SCALE_M

    @property
    def n_weights(self) -> int:
        return n_weights(self.hidden)

    def to_dict(self) -> dict:
        return {
            "hidden": self.hidden,
            "u_centre": list(map(float, self.u_centre)),
            "u_scale": list(map(float, self.u_scale)),
            "out_scale_m": float(self.out_scale_m),
            "layout": LAYOUT,
        }

    @classmethod
    def from_dict(cls, d: dict) -> AnnSpec:
        if d.get("layout") != LAYOUT:
            raise ValueError(
                f"network weights saved with layout {d.get('layout', 'h-major (before 2026-11-22)')!r}, "
                f"this version reads {LAYOUT!r}: refit the ekf-ann model"
            )
        spec = cls(
            hidden=int(d["hidden"]),
            u_centre=tuple(float(x) for x in d["u_centre"]),
            u_scale=tuple(float(x) for x in d["u_scale"]),
            out_scale_m=float(d["out_scale_m"]),
        )
        spec.check()
        return spec

    def check(self) -> None:
        """ValueError unless the standardisation is one the fit makes: N_IN finite centres
        (rad), N_IN scales (rad) and the output scale (m) finite and positive, hidden >= 1. A
        scale of 0 read from a hand-edited file saturates that input's neurons: the network
        still predicts finite positions, each off by up to the network's whole correction."""
        if self.hidden < 1:
            raise ValueError(f"ann.hidden must be >= 1, got {self.hidden}")
        for name, v in (("u_centre", self.u_centre), ("u_scale", self.u_scale)):
            a = np.asarray(v, float)
            if a.shape != (N_IN,) or not np.all(np.isfinite(a)):
                raise ValueError(f"ann.{name} must be {N_IN} finite numbers (rad), got {list(v)}")
        sc = np.asarray(self.u_scale, float)
        if np.any(sc <= 0):
            j = int(np.argmin(sc))
            raise ValueError(f"ann.u_scale[{j}] must be positive (rad), got {sc[j]:g}")
        if not (np.isfinite(self.out_scale_m) and self.out_scale_m > 0):
            raise ValueError(f"ann.out_scale_m must be positive (m), got {self.out_scale_m:g}")

    @classmethod
    def from_joints(cls, q: np.ndarray, hidden: int = 29, min_scale_rad: float = 0.2) -> AnnSpec:
        """Standardisation from joint samples (N, 6): centre = mean, scale = max(std, floor)."""
        q = np.asarray(q, float)
        if q.ndim != 2 or q.shape[1] != N_IN or len(q) < 1:
            raise ValueError(f"joint samples: expected shape (N>=1, 6), got {q.shape}")
        if hidden < 1:
            raise ValueError(f"hidden nodes must be >= 1, got {hidden}")
        sc = np.maximum(q.std(axis=0), min_scale_rad)
        return cls(hidden, tuple(q.mean(axis=0).tolist()), tuple(sc.tolist()))


def n_weights(hidden: int) -> int:
    return hidden * N_IN + hidden + N_OUT * hidden + N_OUT


def unpack(
    w: jnp.ndarray, hidden: int
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    H = hidden
    i = 0
    W1 = w[i : i + H * N_IN].reshape(N_IN, H).T
    i += H * N_IN
    b1 = w[i : i + H]
    i += H
    W2 = w[i : i + N_OUT * H].reshape(N_OUT, H)
    i += N_OUT * H
    b2 = w[i : i + N_OUT]
    return W1, b1, W2, b2


def apply_raw(w: jnp.ndarray, u: jnp.ndarray, hidden: int) -> jnp.ndarray:
    """Network output (3,) in output units for one standardised input u (6,)."""
    W1, b1, W2, b2 = unpack(w, hidden)
    return W2 @ jnp.tanh(W1 @ u + b1) + b2


def _layer(w: jnp.ndarray, u: jnp.ndarray, hidden: int):
    """W2, b2, the hidden activations a = tanh(W1 u + b1) and C = W2 diag(1 - a^2) (3, H)."""
    W1, b1, W2, b2 = unpack(w, hidden)
    a = jnp.tanh(W1 @ u + b1)
    return W2, b2, a, W2 * (1.0 - a * a)[None, :]


def apply_raw_and_jac(
    w: jnp.ndarray, u: jnp.ndarray, hidden: int
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Output (3,) and its Jacobian (3, K) with respect to the weights, written out by hand
    (what jax.jacrev computes, without the reverse pass: the filter calls it every sample).

    With a = tanh(W1 u + b1) and C = W2 diag(1 - a^2):
    d out / d W1[h, j] = C[:, h] u_j,  d out / d b1 = C,  d out_o / d W2[o, :] = a,  d out / d b2 = I.
    """
    W2, b2, a, C = _layer(w, u, hidden)
    J = jnp.concatenate(
        [
            (u[None, :, None] * C[:, None, :]).reshape(N_OUT, N_IN * hidden),
            C,
            jnp.kron(jnp.eye(N_OUT), a[None, :]),
            jnp.eye(N_OUT),
        ],
        axis=1,
    )
    return W2 @ a + b2, J


def jac_context(
    M: jnp.ndarray, U: jnp.ndarray, hidden: int
) -> tuple[jnp.ndarray, tuple[jnp.ndarray, jnp.ndarray]]:
    """Precomputation for products J(w, u) @ M with many inputs u and one matrix M (K, k) whose
    rows follow the weight layout (the filter's covariance): the W1 and b1 blocks of J are
    C (x) [u, 1] and its W2 block is I (x) a (see `apply_raw_and_jac`), so with

        V_i = [U[i], 1] @ M[W1 and b1 rows].reshape(7, H k)   -> (H, k) for every input U[i],

    J(w, U[i]) @ M = C @ V_i + [a @ M[W2(o, .)]]_o + M[b2] costs 6 H k multiply-adds (instead of
    3 K k = 30 H k), and the V_i of a whole block come from one matrix product (no transposes:
    the layout is input-major). Returns (V (b, H, k), (M_W2 (H, 3 k), M_b2 (3, k)))."""
    H = hidden
    k = M.shape[1]
    i2, i3 = H * N_IN + H, H * N_IN + H + N_OUT * H
    Ua = jnp.concatenate([U, jnp.ones((len(U), 1), U.dtype)], axis=1)
    V = (Ua @ M[:i2].reshape(N_IN + 1, H * k)).reshape(len(U), H, k)
    M_W2 = M[i2:i3].reshape(N_OUT, H, k).transpose(1, 0, 2).reshape(H, N_OUT * k)
    return V, (M_W2, M[i3 : i3 + N_OUT])


def jac_times(
    w: jnp.ndarray,
    u: jnp.ndarray,
    hidden: int,
    V_i: jnp.ndarray,
    shared: tuple[jnp.ndarray, jnp.ndarray],
) -> jnp.ndarray:
    """J(w, u) @ M (3, k) from the context of `jac_context` (V_i: the row of V for this u)."""
    _, _, a, C = _layer(w, u, hidden)
    M_W2, M_b2 = shared
    return C @ V_i + (a @ M_W2).reshape(N_OUT, -1) + M_b2


def standardise(q: jnp.ndarray, spec: AnnSpec) -> jnp.ndarray:
    return (q - jnp.asarray(spec.u_centre)) / jnp.asarray(spec.u_scale)


def correction_base_m(w: jnp.ndarray, q: jnp.ndarray, spec: AnnSpec) -> jnp.ndarray:
    """Position correction (3,) in metres in the base frame for one joint vector q (6,)."""
    return spec.out_scale_m * apply_raw(w, standardise(q, spec), spec.hidden)


def predict_base_m(w: np.ndarray, q: np.ndarray, spec: AnnSpec) -> np.ndarray:
    """Corrections (N, 3) in metres, base frame, for joints q (N, 6)."""
    q = jnp.atleast_2d(jnp.asarray(q, float))
    return np.asarray(_batch(jnp.asarray(w, float), q, spec))


def _batch_impl(w, q, spec):
    return jax.vmap(lambda qq: correction_base_m(w, qq, spec))(q)


_batch = jax.jit(_batch_impl, static_argnums=2)


def random_weights(hidden: int, seed: int | np.random.Generator = 0) -> np.ndarray:
    """Glorot-normal weights, zero biases (what 'a random ANN' means in this package)."""
    rng = np.random.default_rng(seed)
    W1 = rng.normal(0.0, np.sqrt(2.0 / (N_IN + hidden)), (hidden, N_IN))
    b1 = rng.normal(0.0, 0.1, hidden)
    W2 = rng.normal(0.0, np.sqrt(2.0 / (hidden + N_OUT)), (N_OUT, hidden))
    b2 = np.zeros(N_OUT)
    return np.concatenate([W1.T.ravel(), b1, W2.ravel(), b2])


# ------------------------------------------------------------------ Levenberg-Marquardt
def _lm_impl(w, U, D, mask, lam, steps, hidden):
    """`steps` LM iterations minimising sum mask_i |apply_raw(w, U_i) - D_i|^2."""

    def resid(w):
        r = jax.vmap(lambda u: apply_raw(w, u, hidden))(U) - D
        return (r * mask[:, None]).ravel()

    def cost(w):
        r = resid(w)
        return r @ r

    def body(_, carry):
        w, lam, c = carry
        o, J = jax.vmap(lambda u: apply_raw_and_jac(w, u, hidden))(U)  # hand-written: 3x faster
        r = ((o - D) * mask[:, None]).ravel()
        J = (J * mask[:, None, None]).reshape(-1, J.shape[-1])
        A = J.T @ J
        g = J.T @ r
        dA = jnp.diag(A)
        step = -jnp.linalg.solve(A + lam * (dA + 1e-9) * jnp.eye(A.shape[0]), g)
        w_try = w + step
        c_try = cost(w_try)
        ok = c_try < c
        w = jnp.where(ok, w_try, w)
        c = jnp.where(ok, c_try, c)
        lam = jnp.where(ok, jnp.maximum(lam * 0.3, 1e-7), jnp.minimum(lam * 10.0, 1e7))
        return w, lam, c

    w, lam, c = jax.lax.fori_loop(0, steps, body, (w, lam, cost(w)))
    return w, lam, c


_lm = jax.jit(_lm_impl, static_argnums=(5, 6))


def lm_fit(
    w0: np.ndarray,
    q: np.ndarray,
    corr_base_m: np.ndarray,
    spec: AnnSpec,
    *,
    steps: int = 50,
    max_samples: int = 800,
    rng: np.random.Generator | int = 0,
    lam0: float = 1e-2,
) -> np.ndarray:
    """Levenberg-Marquardt training of the weights on position corrections (N, 3) in metres.

    A shuffled subset of at most `max_samples` samples is used (the shape is padded to
    `max_samples` with zero weight, so one compiled function serves every call).
    """
    q = np.asarray(q, float)
    d = np.asarray(corr_base_m, float) / spec.out_scale_m
    n = len(q)
    if n == 0:
        return np.asarray(w0, float)
    rng = np.random.default_rng(rng)
    m = max_samples
    idx = rng.permutation(n)[:m]
    U = np.zeros((m, N_IN))
    D = np.zeros((m, N_OUT))
    mask = np.zeros(m)
    U[: len(idx)] = (q[idx] - np.asarray(spec.u_centre)) / np.asarray(spec.u_scale)
    D[: len(idx)] = d[idx]
    mask[: len(idx)] = 1.0
    w, _, _ = _lm(jnp.asarray(w0, float), U, D, mask, lam0, int(steps), spec.hidden)
    return np.asarray(w)
