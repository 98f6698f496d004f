"""GP regression over poses on S3 x R3 and GP-UCB pose selection (seed 002, Algorithm 1).

The paper (Das, Touma & Burdick) models a scalar calibration objective ``f(p, q)`` over
end-effector poses with a GP whose kernel is the product of a heat kernel on S3 and an SE kernel
on R3 (:mod:`workcell.estimation.design.kernels`), and picks the next measurement pose by
GP-UCB, ``x_k = argmax_x mu_{k-1}(x) + sqrt(beta_k) sigma_{k-1}(x)`` (their Sec. III, eq. after
(7)).  Here the argmax runs over a finite candidate set (reachable poses supplied by the caller).

Objective (paper eq. 6-7), see :func:`pose_error_objective`::

    f(p, q) = -( a1 * ||p - p~|| / sup||p - p~||  +  a2 * d_S3(q, q~) / sup d_S3(q, q~) )

with ``p~, q~`` the pose predicted by the current calibrated model at the measured joint angles
and ``a1 + a2 = 1``.  Note the sign: the paper maximises ``f``, i.e. minus the normalised error,
so the exploitation term of GP-UCB favours poses the current model already predicts well and
the exploration term ``sqrt(beta) sigma`` carries the design.  We keep the paper's sign by default;
``pose_error_objective(..., negate=False)`` gives the "measure where the model is worst" variant.

Hyperparameters are chosen by maximising the log marginal likelihood over a small bounded grid
(``kappa`` x position length scale x noise/signal ratio), with the signal variance profiled out
in closed form (``s^2 = r^T R^-1 r / n`` for the correlation matrix ``R``).  The prior mean is the
sample mean of the observations.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import cho_solve, cholesky, solve_triangular

from workcell.estimation.design.kernels import (
    Variant,
    _as_poses,
    _check_positive,
    _check_variant,
    _series_argument,
    heat_kernel_num_terms,
    heat_series,
    quaternion_inner,
)

try:  # small matrices: BLAS threading only adds contention (300x slower on a loaded 2-core box)
    from threadpoolctl import threadpool_limits as _threadpool_limits
except ImportError:  # pragma: no cover - threadpoolctl comes with scikit-learn
    _threadpool_limits = None


def _single_thread_blas() -> contextlib.AbstractContextManager:
    if _threadpool_limits is None:
        return contextlib.nullcontext()
    return _threadpool_limits(limits=1, user_api="blas")


DEFAULT_KAPPA_GRID: tuple[float, ...] = (0.1, 0.17, 0.3, 0.5, 0.85, 1.5)
DEFAULT_LENGTHSCALE_GRID_M: tuple[float, ...] = (0.05, 0.09, 0.16, 0.3, 0.55, 1.0, 2.0)
DEFAULT_NOISE_RATIO_GRID: tuple[float, ...] = (1e-6, 1e-4, 1e-3, 1e-2, 1e-1, 0.5)


@dataclass(frozen=True)
class GPHyperparameters:
    """Kernel ``signal_var * k_S3(kappa) * k_SE(lengthscale_m)`` plus ``noise_var`` on the diagonal.

    ``kappa``: the paper's S3 length scale (heat time ``kappa^2/2``); with the default
    ``variant="so3"`` the rotation-angle length scale is ``2 kappa`` rad.
    """

    kappa: float = 0.5
    lengthscale_m: float = 0.3
    signal_var: float = 1.0
    noise_var: float = 1e-4
    variant: Variant = "so3"

    def __post_init__(self) -> None:
        _check_positive(self.kappa, "kappa")
        _check_positive(self.lengthscale_m, "lengthscale_m")
        _check_positive(self.signal_var, "signal_var")
        if not (math.isfinite(self.noise_var) and self.noise_var >= 0.0):
            raise ValueError(f"noise_var must be finite and >= 0, got {self.noise_var!r}")
        _check_variant(self.variant)


def _correlation(
    qa_qb_inner: np.ndarray,
    sq_dist_m2: np.ndarray,
    kappa: float,
    ell_m: float,
    variant: str,
    tol: float,
) -> np.ndarray:
    n_max = heat_kernel_num_terms(kappa, tol, variant)
    k_rot = heat_series(_series_argument(qa_qb_inner, variant), kappa, n_max, variant)
    return k_rot * np.exp(-sq_dist_m2 / (2.0 * ell_m * ell_m))


def _sq_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d2 = np.sum(a * a, 1)[:, None] + np.sum(b * b, 1)[None, :] - 2.0 * a @ b.T
    return np.maximum(d2, 0.0)


class PoseGP:
    """Exact GP regression on poses ``(N, 7) = [qw qx qy qz px py pz]`` (Cholesky based).

    Usage::

        gp = PoseGP().fit(measured_poses, y)          # ML hyperparameters over a grid
        mean, var = gp.predict(candidate_poses)         # latent f, var excludes noise
        scores = gp.ucb(candidate_poses, beta=4.0)      # mean + sqrt(beta) * std
    """

    def __init__(self, hyper: GPHyperparameters | None = None, *, tol: float = 1e-10) -> None:
        self.hyper = hyper if hyper is not None else GPHyperparameters()
        self.tol = _check_positive(tol, "tol")
        self._poses: np.ndarray | None = None
        self._mean = 0.0
        self._alpha: np.ndarray | None = None
        self._chol: np.ndarray | None = None
        self._lml = float("nan")

    # ------------------------------------------------------------------ fitting

    def fit(
        self,
        poses: np.ndarray,
        y: np.ndarray,
        *,
        optimize: bool = True,
        kappa_grid: Sequence[float] = DEFAULT_KAPPA_GRID,
        lengthscale_grid_m: Sequence[float] = DEFAULT_LENGTHSCALE_GRID_M,
        noise_ratio_grid: Sequence[float] = DEFAULT_NOISE_RATIO_GRID,
    ) -> PoseGP:
        """Condition on ``(poses (N, 7), y (N,))``; with ``optimize`` (and N >= 3) pick
        ``kappa``, ``lengthscale_m`` and the noise/signal ratio maximising the log marginal
        likelihood over the grids, the signal variance profiled in closed form.  Returns self."""
        with _single_thread_blas():
            return self._fit(
                poses,
                y,
                optimize=optimize,
                kappa_grid=kappa_grid,
                lengthscale_grid_m=lengthscale_grid_m,
                noise_ratio_grid=noise_ratio_grid,
            )

    def _fit(
        self,
        poses: np.ndarray,
        y: np.ndarray,
        *,
        optimize: bool,
        kappa_grid: Sequence[float],
        lengthscale_grid_m: Sequence[float],
        noise_ratio_grid: Sequence[float],
    ) -> PoseGP:
        x = _as_poses(poses, "poses")
        y = np.asarray(y, dtype=float)
        if y.ndim != 1 or y.shape[0] != x.shape[0]:
            raise ValueError(f"y must have shape ({x.shape[0]},), got {y.shape}")
        if not np.all(np.isfinite(y)):
            raise ValueError("y contains non-finite values")
        self._poses = x
        n = x.shape[0]
        if n == 0:
            self._mean, self._alpha, self._chol, self._lml = 0.0, np.zeros(0), None, 0.0
            return self
        self._mean = float(np.mean(y))
        r = y - self._mean
        inner = quaternion_inner(x[:, :4], x[:, :4])
        d2 = _sq_dist(x[:, 4:], x[:, 4:])
        if optimize and n >= 3:
            self.hyper = self._grid_search(
                inner, d2, r, kappa_grid, lengthscale_grid_m, noise_ratio_grid
            )
        h = self.hyper
        k = h.signal_var * _correlation(inner, d2, h.kappa, h.lengthscale_m, h.variant, self.tol)
        k[np.diag_indices_from(k)] += h.noise_var + 1e-12 * h.signal_var
        self._chol = cholesky(k, lower=True)
        self._alpha = cho_solve((self._chol, True), r)
        self._lml = float(
            -0.5 * r @ self._alpha
            - np.sum(np.log(np.diag(self._chol)))
            - 0.5 * n * math.log(2.0 * math.pi)
        )
        return self

    def _grid_search(
        self,
        inner: np.ndarray,
        d2: np.ndarray,
        r: np.ndarray,
        kappa_grid: Sequence[float],
        lengthscale_grid_m: Sequence[float],
        noise_ratio_grid: Sequence[float],
    ) -> GPHyperparameters:
        n = r.size
        variant = self.hyper.variant
        # Floor for the profiled signal variance: flat data would give s^2 = 0, and the UCB
        # needs standard deviations well above the float resolution of the mean.
        s2_floor = 1e-12 * float(np.mean(r * r)) + (1e-6 * abs(self._mean)) ** 2 + 1e-300
        best: tuple[float, GPHyperparameters] | None = None
        pos_corr = {
            ell: np.exp(-d2 / (2.0 * _check_positive(ell, "lengthscale_m") ** 2))
            for ell in lengthscale_grid_m
        }
        for kappa in kappa_grid:
            n_max = heat_kernel_num_terms(kappa, self.tol, variant)
            k_rot = heat_series(_series_argument(inner, variant), kappa, n_max, variant)
            for ell, k_pos in pos_corr.items():
                corr = k_rot * k_pos
                for ratio in noise_ratio_grid:
                    ratio = _check_positive(ratio, "noise ratio")
                    mat = corr.copy()
                    mat[np.diag_indices_from(mat)] += ratio + 1e-12
                    try:
                        chol = cholesky(mat, lower=True)
                    except np.linalg.LinAlgError:
                        continue
                    quad = float(r @ cho_solve((chol, True), r))
                    s2 = max(quad / n, s2_floor)
                    lml = (
                        -0.5 * quad / s2
                        - np.sum(np.log(np.diag(chol)))
                        - 0.5 * n * math.log(2.0 * math.pi * s2)
                    )
                    if best is None or lml > best[0]:
                        best = (
                            float(lml),
                            replace(
                                self.hyper,
                                kappa=float(kappa),
                                lengthscale_m=float(ell),
                                signal_var=s2,
                                noise_var=ratio * s2,
                            ),
                        )
        if best is None:
            raise ValueError("hyperparameter grid search failed: no grid point gave a PD matrix")
        return best[1]

    # --------------------------------------------------------------- prediction

    @property
    def log_marginal_likelihood(self) -> float:
        """Log marginal likelihood of the fitted data under the current hyperparameters."""
        return self._lml

    def predict(
        self, poses: np.ndarray, *, include_noise: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """Posterior mean and variance at ``poses (M, 7)`` -> ``(M,), (M,)``.

        The variance is that of the latent ``f`` unless ``include_noise``.  Before ``fit`` (or
        with no data) this is the prior: mean 0, variance ``signal_var``."""
        with _single_thread_blas():
            return self._predict(poses, include_noise)

    def _predict(self, poses: np.ndarray, include_noise: bool) -> tuple[np.ndarray, np.ndarray]:
        xs = _as_poses(poses, "poses")
        h = self.hyper
        prior_var = np.full(xs.shape[0], h.signal_var)
        if self._poses is None or self._poses.shape[0] == 0:
            mean = np.full(xs.shape[0], self._mean)
            var = prior_var
        else:
            k_star = h.signal_var * _correlation(
                quaternion_inner(xs[:, :4], self._poses[:, :4]),
                _sq_dist(xs[:, 4:], self._poses[:, 4:]),
                h.kappa,
                h.lengthscale_m,
                h.variant,
                self.tol,
            )
            mean = self._mean + k_star @ self._alpha
            v = solve_triangular(self._chol, k_star.T, lower=True)
            var = np.maximum(prior_var - np.sum(v * v, axis=0), 0.0)
        if include_noise:
            var = var + h.noise_var
        return mean, var

    def ucb(self, candidates: np.ndarray, beta: float) -> np.ndarray:
        """GP-UCB score ``mu(x) + sqrt(beta) * sigma(x)`` at ``candidates (M, 7)`` -> ``(M,)``."""
        beta = float(beta)
        if not (math.isfinite(beta) and beta >= 0.0):
            raise ValueError(f"beta must be finite and >= 0, got {beta!r}")
        mean, var = self.predict(candidates)
        return mean + math.sqrt(beta) * np.sqrt(var)


# --------------------------------------------------------------------------- beta schedule


def srinivas_beta(iteration: int, n_candidates: int, delta: float = 0.1) -> float:
    """GP-UCB exploration weight for a finite domain (Srinivas et al. 2010, Thm. 1):
    ``beta_t = 2 log(|D| t^2 pi^2 / (6 delta))``, ``t >= 1`` the index of the query."""
    if iteration < 1:
        raise ValueError(f"iteration must be >= 1, got {iteration}")
    if n_candidates < 1:
        raise ValueError(f"n_candidates must be >= 1, got {n_candidates}")
    if not (0.0 < delta < 1.0):
        raise ValueError(f"delta must be in (0, 1), got {delta!r}")
    return 2.0 * math.log(n_candidates * iteration**2 * math.pi**2 / (6.0 * delta))


BetaSchedule = str | float | Callable[[int, int], float]


def _resolve_beta(schedule: BetaSchedule, iteration: int, n_candidates: int, delta: float) -> float:
    if callable(schedule):
        beta = float(schedule(iteration, n_candidates))
    elif isinstance(schedule, str):
        if schedule != "srinivas":
            raise ValueError(
                f"beta_schedule must be 'srinivas', a float or a callable, got {schedule!r}"
            )
        beta = srinivas_beta(iteration, n_candidates, delta)
    else:
        beta = float(schedule)
    if not (math.isfinite(beta) and beta >= 0.0):
        raise ValueError(f"beta must be finite and >= 0, got {beta!r}")
    return beta


def select_next_pose(
    candidate_poses: np.ndarray,
    measured_poses: np.ndarray,
    objective_values: np.ndarray,
    **kw: object,
) -> int:
    """Index into ``candidate_poses (M, 7)`` of the next pose to measure (GP-UCB, Algorithm 1):
    the argmax of :func:`ucb_scores` (same arguments; first index on ties)."""
    return int(np.argmax(ucb_scores(candidate_poses, measured_poses, objective_values, **kw)))


def ucb_scores(
    candidate_poses: np.ndarray,
    measured_poses: np.ndarray,
    objective_values: np.ndarray,
    *,
    beta_schedule: BetaSchedule = "srinivas",
    delta: float = 0.1,
    iteration: int | None = None,
    hyperparameters: GPHyperparameters | None = None,
    optimize_hyperparameters: bool = True,
) -> np.ndarray:
    """GP-UCB scores ``(M,)`` of ``candidate_poses (M, 7)`` (Algorithm 1); the next pose to
    measure is the best-scored one (or, when a motion constraint rules it out, the best allowed).

    Fits a :class:`PoseGP` on ``(measured_poses (N, 7), objective_values (N,))`` and returns
    ``mu(x_i) + sqrt(beta_t) sigma(x_i)`` for every candidate.  The objective is
    maximised as given: pass the paper's ``f`` from :func:`pose_error_objective` (minus the
    normalised error) to reproduce the paper, or ``negate=False`` there to seek large errors.

    Beta schedule.  The paper only states that ``beta_k > 0`` is "an iteration-varying parameter"
    and cites GP-UCB (Srinivas et al. 2010); it gives no formula or values.  We default to
    ``"srinivas"``: the finite-domain schedule of that paper's Theorem 1,
    ``beta_t = 2 log(|D| t^2 pi^2 / (6 delta))`` with ``|D| = M`` candidates,
    ``t = iteration`` (default ``N + 1``, the index of the query being chosen) and
    ``delta = 0.1``.  It grows like ``log t``, so exploration weight increases slowly; it is
    known to be conservative (explorative) in practice.  A float gives a constant beta, a
    callable ``(t, M) -> beta`` any other schedule.

    With ``N = 0`` the posterior is the prior (flat mean, equal variance), all scores are
    equal and :func:`select_next_pose` returns index 0: seed the campaign with a few spread
    poses first, as the paper does.
    Hyperparameters are fitted by marginal likelihood when ``optimize_hyperparameters`` and
    ``N >= 3``; otherwise ``hyperparameters`` (or the defaults) are used as given.
    """
    cands = _as_poses(candidate_poses, "candidate_poses")
    if cands.shape[0] == 0:
        raise ValueError("candidate_poses is empty")
    measured = np.asarray(measured_poses, dtype=float)
    if measured.size == 0:
        measured = measured.reshape(0, 7)
    measured = _as_poses(measured, "measured_poses")
    n = measured.shape[0]
    t = n + 1 if iteration is None else int(iteration)
    beta = _resolve_beta(beta_schedule, t, cands.shape[0], delta)
    gp = PoseGP(hyperparameters)
    gp.fit(measured, objective_values, optimize=optimize_hyperparameters)
    return gp.ucb(cands, beta)


# ------------------------------------------------------------------------------ objective


def pose_error_objective(
    pos_err_m: np.ndarray,
    rot_err_rad: np.ndarray | None = None,
    w_pos: float = 0.5,
    w_rot: float = 0.5,
    *,
    pos_scale_m: float | None = None,
    rot_scale_rad: float | None = None,
    negate: bool = True,
) -> np.ndarray:
    """Paper eq. (6)-(7): ``-(a1 e_p / sup e_p + a2 e_r / sup e_r)``, one value per pose.

    ``pos_err_m``: ``(N,)`` position error norms ``||p_measured - p_model||`` in m, or ``(N, 3)``
    error vectors (their norms are used).  ``rot_err_rad``: ``(N,)`` orientation errors
    ``d_S3(q_measured, q_model) = 2 arccos|<q, q~>|`` in rad, or ``None`` when the tracker
    measures position only (then ``f = -e_p / sup e_p`` and the weights are unused).
    ``w_pos, w_rot > 0`` are the paper's ``a1, a2``; they are rescaled to sum to 1.

    The paper normalises by the supremum of each error over the workspace, which is unknown;
    by default we use the largest value among the supplied poses (empirical sup, so the values
    are in ``[-1, 0]``), or the fixed ``pos_scale_m`` / ``rot_scale_rad`` when given (use fixed
    scales if values must stay comparable as data accumulate).  ``negate=False`` returns the
    positive weighted error instead (GP-UCB then seeks poses where the model is worst).
    """
    e_p = np.asarray(pos_err_m, dtype=float)
    if e_p.ndim == 2 and e_p.shape[1] == 3:
        e_p = np.linalg.norm(e_p, axis=1)
    if e_p.ndim != 1:
        raise ValueError(f"pos_err_m must have shape (N,) or (N, 3), got {np.shape(pos_err_m)}")
    if not np.all(np.isfinite(e_p)) or np.any(e_p < 0.0):
        raise ValueError("pos_err_m must be finite and non-negative (error norms)")
    cost = _normalised(e_p, pos_scale_m, "pos_scale_m")
    if rot_err_rad is not None:
        e_r = np.asarray(rot_err_rad, dtype=float)
        if e_r.shape != e_p.shape:
            raise ValueError(f"rot_err_rad must have shape {e_p.shape}, got {e_r.shape}")
        if not np.all(np.isfinite(e_r)) or np.any(e_r < 0.0):
            raise ValueError("rot_err_rad must be finite and non-negative (angles)")
        a1 = _check_positive(w_pos, "w_pos")
        a2 = _check_positive(w_rot, "w_rot")
        cost = (a1 * cost + a2 * _normalised(e_r, rot_scale_rad, "rot_scale_rad")) / (a1 + a2)
    return -cost if negate else cost


def _normalised(e: np.ndarray, scale: float | None, name: str) -> np.ndarray:
    if scale is None:
        top = float(np.max(e)) if e.size else 0.0
        return e / top if top > 0.0 else np.zeros_like(e)
    return e / _check_positive(scale, name)
