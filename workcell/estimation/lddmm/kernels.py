"""Gaussian reproducing kernels for the LDDMM vector-field spaces V (on X) and W (on Y).

K(a, b) = exp(-|a - b|^2 / (2 width^2)) * Id  (scalar kernel times identity), the Green's
kernel of an infinite-order operator L, so the RKHS embeds in H^inf as the paper requires.
"""

from __future__ import annotations

from workcell._jax import jnp


def sqdist(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Pairwise squared distances by explicit differences (accurate): (A,d),(B,d) -> (A,B)."""
    d = a[:, None, :] - b[None, :, :]
    return jnp.sum(d * d, axis=-1)


def sqdist_gemm(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """Pairwise squared distances via |a|^2+|b|^2-2ab (fast, for large batches), clipped >= 0."""
    d2 = jnp.sum(a * a, -1)[:, None] + jnp.sum(b * b, -1)[None, :] - 2.0 * (a @ b.T)
    return jnp.maximum(d2, 0.0)


def gauss(a: jnp.ndarray, b: jnp.ndarray, width: float) -> jnp.ndarray:
    """Gaussian kernel matrix K_ij = exp(-|a_i - b_j|^2 / (2 width^2)); (A,d),(B,d) -> (A,B)."""
    return jnp.exp(-sqdist(a, b) / (2.0 * width * width))


def gauss_gemm(a: jnp.ndarray, b: jnp.ndarray, width: float) -> jnp.ndarray:
    """Same as `gauss` with the GEMM distance formula (batched evaluation)."""
    return jnp.exp(-sqdist_gemm(a, b) / (2.0 * width * width))


def gauss_point(a: jnp.ndarray, b: jnp.ndarray, width: float) -> jnp.ndarray:
    """Kernel row of one point a (d,) against centres b (B,d) -> (B,)."""
    d = b - a[None, :]
    return jnp.exp(-jnp.sum(d * d, -1) / (2.0 * width * width))
