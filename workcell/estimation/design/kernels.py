"""Kernels over end-effector poses on S3 x R3 (Das, Touma & Burdick, seed 002).

Poses are rows ``[qw, qx, qy, qz, px, py, pz]``: a unit quaternion (scalar first) and a
position in metres, so a pose set is an ``(N, 7)`` array.  Every kernel here is vectorised over
pose sets: ``k(A: (N, 7), B: (M, 7)) -> (N, M)``.  Only inner products of quaternions are used,
so the component order does not matter as long as both arguments use the same one.

Heat ("squared-exponential") kernel on S3
-----------------------------------------
The paper (Sec. III, after Borovitskiy et al. 2020, Ex. 9) writes the SE kernel on S3 as

    k(q1, q2) = sigma^2 / C_inf * sum_n c_{n,3} C_n^(1)(cos d) exp(-kappa^2/2 * n (n + 2))

with ``C_n^(1) = U_n`` (Chebyshev polynomials of the second kind, the Gegenbauer polynomials
of S3), ``n (n + 2)`` the Laplace-Beltrami eigenvalues and ``c_{n,3} = n + 1`` (addition
theorem on S3: the ``(n+1)^2`` degree-n spherical harmonics sum to ``(n+1) U_n(cos d) / 2pi^2``).
So with ``t = kappa^2 / 2`` and ``a_n = (n + 1) exp(-t n (n + 2))``:

    k(x) = S(x) / S(1),     S(x) = sum_n a_n U_n(x),     S(1) = sum_n (n + 1)^2 e^{-t n(n+2)}

which gives ``k(q, q) = 1`` (times the variance).  Where the paper's ``d`` comes from, and the
antipodal identification ``q ~ -q``, is the variant choice:

* ``variant="so3"`` (default, our documented choice): the heat kernel of the rotation group
  ``SO(3) = S3 / {+-1}`` with the metric of the unit S3.  It is the S3 heat kernel symmetrised
  over the two lifts, ``(k_S3(c) + k_S3(-c)) / 2`` renormalised, i.e. only the even degrees
  ``n = 2l`` survive and the argument is ``x = |<q1, q2>|``.  Each ``U_2l(<q1,q2>)`` is a
  positive-definite zonal function on S3 (Schoenberg), so the kernel is provably PD, and it is
  invariant under ``q -> -q``.  Small-distance behaviour ``exp(-theta^2 / (2 kappa^2))`` with
  ``theta = arccos|<q1,q2>|`` the *half* rotation angle, i.e. a rotation-angle lengthscale of
  ``2 kappa``.
* ``variant="paper"``: the paper's formula taken literally: ``d = d_S3(q1, q2) = 2 arccos|<q1,q2>|``
  (eq. 1, the rotation angle) inserted into the S3 series, ``x = cos d = 2 <q1,q2>^2 - 1``.
  Antipodally invariant; rotation-angle lengthscale ``kappa``.  Positive definiteness is not
  shown in the paper: expanding in SO(3) characters the coefficients are alternating tail sums
  of ``a_n``; they came out positive in our numerical checks (and random Gram matrices are PSD,
  see tests), but we have no proof, hence not the default.
* ``variant="s3"``: the plain S3 heat kernel at ``x = <q1, q2>`` (no identification: ``q`` and
  ``-q`` are far apart).  Reference/testing only.

Truncation.  ``|U_n(x)| <= n + 1`` on ``[-1, 1]``, so the tail after degree ``N`` is bounded by
``T_N = sum_{m >= N+2} m^2 e^{-t (m^2 - 1)} <= e^t * int_{N+1}^inf x^2 e^{-t x^2} dx``
(valid when ``x^2 e^{-t x^2}`` decreases on ``[N+1, inf)``, i.e. ``N + 1 >= 1/sqrt(t)``), which
has the closed form
``e^t [ M e^{-t M^2} / (2t) + sqrt(pi) erfc(sqrt(t) M) / (4 t^1.5) ]``, ``M = N + 1``.  For the
normalised kernel, ``|S_N(x)/S_N(1) - S(x)/S(1)| <= 2 T_N / S_N(1)`` (using ``|S_N(x)| <= S_N(1)``
and ``S_N(1) >= 1``).  :func:`heat_kernel_num_terms` returns the smallest ``N`` for which this
bound is ``<= tol``; the same bound holds for the even-only (``so3``) series.

Naive kernel (counter-example)
------------------------------
:func:`naive_geodesic_kernel` is ``exp(-d_geo^2 / (2 l^2))`` with ``d_geo = 2 arccos|<q1,q2>|``;
:func:`naive_se3_kernel` is the paper's eq. (5) with ``d_SE3 = ||[g1 ||p_i - p_j||, g2 d_S3]||``.
Both are *not* positive definite in general: Example 1 of the paper (reproduced in the tests)
gives eigenvalues ``(-0.000102, 0.00836, 0.0356, 3.956)``.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from scipy.special import erfcx

Variant = Literal["so3", "paper", "s3"]
_VARIANTS = ("so3", "paper", "s3")
_MAX_TERMS = 200_000
_QUAT_NORM_TOL = 1e-3


# ----------------------------------------------------------------------------- validation


def _as_poses(poses: np.ndarray, name: str) -> np.ndarray:
    """Return ``poses`` as a float ``(N, 7)`` array with unit quaternions (renormalised)."""
    arr = np.asarray(poses, dtype=float)
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 7:
        raise ValueError(f"{name} must have shape (N, 7) [qw qx qy qz px py pz], got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains non-finite values")
    return np.concatenate([_normalise_quats(arr[:, :4], name), arr[:, 4:]], axis=1)


def _as_quats(quats: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(quats, dtype=float)
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise ValueError(f"{name} must have shape (N, 4) [qw qx qy qz], got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains non-finite values")
    return _normalise_quats(arr, name)


def _normalise_quats(q: np.ndarray, name: str) -> np.ndarray:
    norms = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > _QUAT_NORM_TOL)
    if bad.size:
        raise ValueError(
            f"{name}: quaternion rows must be unit norm (tolerance {_QUAT_NORM_TOL}); "
            f"row {bad[0]} has norm {norms[bad[0]]:.6g}"
        )
    return q / norms[:, None]


def _as_positions(p: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(p, dtype=float)
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3) positions in metres, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains non-finite values")
    return arr


def _check_positive(value: float, name: str) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"{name} must be a finite positive number, got {value!r}")
    return v


def _check_variant(variant: str) -> str:
    if variant not in _VARIANTS:
        raise ValueError(f"variant must be one of {_VARIANTS}, got {variant!r}")
    return variant


# ------------------------------------------------------------------------------- geometry


def quaternion_inner(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    """Inner products ``<qa_i, qb_j>`` of unit quaternions, ``(N, 4), (M, 4) -> (N, M)``."""
    a = _as_quats(qa, "qa")
    b = _as_quats(qb, "qb")
    return np.clip(a @ b.T, -1.0, 1.0)


def quaternion_geodesic_distance(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    """Rotation angle between orientations, eq. (1): ``2 arccos|<qa_i, qb_j>|`` in rad, (N, M).

    Invariant under ``q -> -q``; values in ``[0, pi]``.
    """
    return 2.0 * np.arccos(np.abs(quaternion_inner(qa, qb)))


# ------------------------------------------------------------------- heat-kernel series


def heat_kernel_truncation_bound(kappa: float, n_max: int, variant: Variant = "so3") -> float:
    """Upper bound on ``|k_truncated - k_exact|`` of the normalised S3 heat kernel.

    ``n_max`` is the highest degree kept (``n = 0..n_max``).  Returns ``inf`` when the integral
    bound does not apply yet (``n_max + 1 < 1/sqrt(t)``, ``t = kappa^2/2``).  See module doc.
    """
    t = 0.5 * _check_positive(kappa, "kappa") ** 2
    _check_variant(variant)
    if n_max < 0:
        raise ValueError(f"n_max must be >= 0, got {n_max}")
    return float(_bound_many(t, np.array([n_max]), variant)[0])


def _bound_many(t: float, n_max: np.ndarray, variant: str) -> np.ndarray:
    n_max = np.asarray(n_max, dtype=float)
    big_m = n_max + 1.0
    # e^t * int_M^inf x^2 e^{-t x^2} dx, written without overflow.
    decay = np.exp(-t * (big_m**2 - 1.0))
    tail = (
        big_m * decay / (2.0 * t)
        + math.sqrt(math.pi) / (4.0 * t**1.5) * erfcx(math.sqrt(t) * big_m) * decay
    )
    norm = _norm_partial(t, n_max.astype(int).max(), variant)[n_max.astype(int)]
    bound = 2.0 * tail / norm
    return np.where(big_m * math.sqrt(t) >= 1.0, bound, np.inf)


def _coefficients(t: float, n_max: int, variant: str) -> np.ndarray:
    n = np.arange(n_max + 1, dtype=float)
    a = (n + 1.0) * np.exp(-t * n * (n + 2.0))
    if variant == "so3":
        a[1::2] = 0.0
    return a


def _norm_partial(t: float, n_max: int, variant: str) -> np.ndarray:
    """Partial sums ``S_N(1) = sum_{n<=N} a_n (n+1)`` for ``N = 0..n_max``."""
    a = _coefficients(t, n_max, variant)
    return np.cumsum(a * (np.arange(n_max + 1) + 1.0))


def heat_kernel_num_terms(kappa: float, tol: float = 1e-12, variant: Variant = "so3") -> int:
    """Smallest highest degree ``N`` with truncation bound ``<= tol`` (the series has N+1 terms)."""
    t = 0.5 * _check_positive(kappa, "kappa") ** 2
    tol = _check_positive(tol, "tol")
    _check_variant(variant)
    start = max(0, math.ceil(1.0 / math.sqrt(t)) - 1)
    # Gaussian decay: the tail is below tol once t (N+1)^2 > log(1/tol) + a margin.
    guess = math.ceil(math.sqrt((math.log(1.0 / tol) + 50.0) / t)) + 2
    stop = min(max(start, guess) + 2, _MAX_TERMS)
    candidates = np.arange(start, stop + 1)
    ok = np.flatnonzero(_bound_many(t, candidates, variant) <= tol)
    if ok.size == 0:
        raise ValueError(
            f"kappa={kappa!r} too small: more than {_MAX_TERMS} terms needed for tol={tol!r}"
        )
    return int(candidates[ok[0]])


def _series_argument(c: np.ndarray, variant: str) -> np.ndarray:
    if variant == "so3":
        return np.abs(c)
    if variant == "paper":
        return 2.0 * c * c - 1.0  # cos(2 arccos|c|)
    return c


def heat_series(x: np.ndarray, kappa: float, n_max: int, variant: Variant = "so3") -> np.ndarray:
    """Normalised truncated series ``S_N(x) / S_N(1)`` at Chebyshev arguments ``x`` in [-1, 1].

    Low-level helper (the kernels call it with ``x`` derived from quaternion inner products).
    Uses the three-term recurrence ``U_{n+1} = 2x U_n - U_{n-1}``, stable on ``[-1, 1]``.
    """
    t = 0.5 * _check_positive(kappa, "kappa") ** 2
    _check_variant(variant)
    x = np.clip(np.asarray(x, dtype=float), -1.0, 1.0)
    a = _coefficients(t, int(n_max), variant)
    u_prev = np.ones_like(x)
    total = a[0] * u_prev
    if n_max >= 1:
        u_cur = 2.0 * x
        for n in range(1, int(n_max) + 1):
            if a[n] != 0.0:
                total = total + a[n] * u_cur
            u_prev, u_cur = u_cur, 2.0 * x * u_cur - u_prev
    return total / float(np.sum(a * (np.arange(a.size) + 1.0)))


def s3_heat_kernel(
    qa: np.ndarray,
    qb: np.ndarray,
    kappa: float,
    *,
    variance: float = 1.0,
    variant: Variant = "so3",
    tol: float = 1e-12,
) -> np.ndarray:
    """Heat (SE) kernel on unit quaternions, ``(N, 4), (M, 4) -> (N, M)``; ``k(q, q) = variance``.

    ``kappa`` is the paper's length scale on the unit S3 (heat time ``t = kappa^2/2``); see the
    module doc for the meaning per ``variant``.  The series is truncated with
    :func:`heat_kernel_num_terms` so that the error of the normalised kernel is ``<= tol``.
    """
    variant = _check_variant(variant)
    variance = _check_positive(variance, "variance")
    n_max = heat_kernel_num_terms(kappa, tol, variant)
    x = _series_argument(quaternion_inner(qa, qb), variant)
    return variance * heat_series(x, kappa, n_max, variant)


def se_kernel_r3(
    pa: np.ndarray, pb: np.ndarray, lengthscale_m: float, *, variance: float = 1.0
) -> np.ndarray:
    """Squared-exponential kernel on positions, ``exp(-||pa - pb||^2 / (2 l^2))``, (N, M)."""
    a = _as_positions(pa, "pa")
    b = _as_positions(pb, "pb")
    ell = _check_positive(lengthscale_m, "lengthscale_m")
    variance = _check_positive(variance, "variance")
    d2 = np.sum(a * a, 1)[:, None] + np.sum(b * b, 1)[None, :] - 2.0 * a @ b.T
    return variance * np.exp(-np.maximum(d2, 0.0) / (2.0 * ell * ell))


def pose_product_kernel(
    poses_a: np.ndarray,
    poses_b: np.ndarray,
    *,
    kappa: float = 0.5,
    lengthscale_m: float = 0.3,
    variance: float = 1.0,
    variant: Variant = "so3",
    tol: float = 1e-12,
) -> np.ndarray:
    """Product kernel on S3 x R3: ``variance * k_S3(q_i, q_j) * k_SE(p_i, p_j)``, (N, M).

    ``poses_*`` are ``(N, 7)`` rows ``[qw qx qy qz px py pz]``.  Positive semi-definite as a
    product of PSD kernels (for ``variant="so3"`` and ``"s3"`` provably, see module doc).
    """
    a = _as_poses(poses_a, "poses_a")
    b = _as_poses(poses_b, "poses_b")
    k_rot = s3_heat_kernel(a[:, :4], b[:, :4], kappa, variant=variant, tol=tol)
    return (
        _check_positive(variance, "variance")
        * k_rot
        * se_kernel_r3(a[:, 4:], b[:, 4:], lengthscale_m)
    )


# ------------------------------------------------------------------------ naive kernels


def naive_geodesic_kernel(
    qa: np.ndarray, qb: np.ndarray, lengthscale_rad: float, *, variance: float = 1.0
) -> np.ndarray:
    """``variance * exp(-d_geo^2 / (2 l^2))`` with ``d_geo`` of eq. (1).  NOT positive definite
    in general (counter-example only)."""
    ell = _check_positive(lengthscale_rad, "lengthscale_rad")
    d = quaternion_geodesic_distance(qa, qb)
    return _check_positive(variance, "variance") * np.exp(-(d * d) / (2.0 * ell * ell))


def naive_se3_kernel(
    poses_a: np.ndarray,
    poses_b: np.ndarray,
    *,
    beta: float,
    gamma_pos: float = 0.1,
    gamma_rot: float = 0.9,
    sigma_f: float = 1.0,
) -> np.ndarray:
    """Paper eq. (5): ``sigma_f^2 exp(-d_SE3^2 / (2 beta^2))``,
    ``d_SE3 = ||[gamma_pos ||p_i - p_j||, gamma_rot d_S3(q_i, q_j)]||``.  NOT a valid kernel."""
    a = _as_poses(poses_a, "poses_a")
    b = _as_poses(poses_b, "poses_b")
    beta = _check_positive(beta, "beta")
    d_rot = quaternion_geodesic_distance(a[:, :4], b[:, :4])
    d_pos2 = np.maximum(
        np.sum(a[:, 4:] ** 2, 1)[:, None]
        + np.sum(b[:, 4:] ** 2, 1)[None, :]
        - 2.0 * a[:, 4:] @ b[:, 4:].T,
        0.0,
    )
    d2 = gamma_pos**2 * d_pos2 + gamma_rot**2 * d_rot**2
    return _check_positive(sigma_f, "sigma_f") ** 2 * np.exp(-d2 / (2.0 * beta * beta))
