"""Calibration by diffeomorphisms: fitting (cost 27 by L-BFGS) and the fitted model (eq. 29).

Units and scaling. X is used as given (joint angles in rad), Y as given (positions in m); the
kernel widths are in those units. The momenta P carry the units of Y (the kernels are
dimensionless), so the weight `sigma` of the data term in (27) is dimensionless: linearised, the
fit is kernel ridge regression with ridge sigma^2 on a Gram matrix whose diagonal is ~1
(default sigma = 0.1, ridge 1e-2: much smaller sigma gives huge, cancelling momenta
with the wide kernels CV prefers, and the nonlinear flow then blows up).

Conditioning. The optimiser works on z with P0 = sigma (G + sigma^2 I)^-1 z, where G (N m x N m)
is the Gram matrix of the linearised flow at t=0:
    G_ij = lam_w K_W(k0(x_i), k0(x_j)) I_m + lam_v K_V(x_i, x_j) Dk0(x_i) Dk0(x_j)^T.
This whitens the Hessian of (27) (eigenvalues g/(g+sigma^2)) and z0 = (y - k0(x))/sigma is the
exact linearised optimum, so L-BFGS starts at the kernel-ridge solution and only has to fix the
nonlinear part. The cost is normalised by its value at z = 0.

Width selection (sigma_v / sigma_w = None). k-fold (default 5) cross-validation over the grid
    sigma_v in s_x * (0.25, 0.5, 1, 2),   sigma_w in s_y * (0.25, 0.5, 1, 2)
where s_x = RMS over coordinates of the std of X_train, s_y = the same for k0(X_train). The
score is the held-out RMS error of the linearised model (the t=0 kernel-ridge solution above),
which costs one Cholesky per fold and grid point; `cv="full"` instead runs the nonlinear fit
(with max_iter capped at 30) for each fold - far slower.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.linalg
import scipy.optimize

from workcell._jax import jax, jnp
from workcell.estimation.lddmm.shooting import (
    KernelParams,
    State,
    evaluate_lagrangian,
    evolve_kinematics,
    flow_phi,
    flow_psi,
    hamiltonian,
    shoot,
)

K0 = Callable[[jnp.ndarray], jnp.ndarray]

WIDTH_FACTORS = (0.25, 0.5, 1.0, 2.0)
_FORMAT = "workcell.lddmm/1"


def _check_xy(X: Any, Y: Any | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    X = np.asarray(X, dtype=float)
    if X.ndim != 2 or X.shape[0] < 1:
        raise ValueError(f"X must have shape (N, dx) with N >= 1, got {X.shape}")
    if not np.all(np.isfinite(X)):
        raise ValueError("X contains non-finite values")
    if Y is None:
        return X, None
    Y = np.asarray(Y, dtype=float)
    if Y.ndim != 2 or Y.shape[0] != X.shape[0]:
        raise ValueError(f"Y must have shape (N, dy) with N = {X.shape[0]}, got {Y.shape}")
    if not np.all(np.isfinite(Y)):
        raise ValueError("Y contains non-finite values")
    return X, Y


def _k0_and_jac(k0: K0) -> Callable:
    return functools.partial(_k0j_jit, k0)


@functools.partial(jax.jit, static_argnums=0)
def _k0j_jit(k0, X):
    """k0 and Dk0 at X (B, n): by k0.value_and_jacobian when k0 has one (an analytic Jacobian),
    else by forward-mode autodiff."""
    vj = getattr(k0, "value_and_jacobian", None)
    if vj is not None:
        return jax.vmap(vj)(X)
    return jax.vmap(k0)(X), jax.vmap(jax.jacfwd(k0))(X)


# Module-level jitted kernels: the kernel parameters are traced (a pytree of floats), k0 and the
# step count are static, so repeated fits / models with the same shapes reuse the compilation.


@functools.partial(jax.jit, static_argnums=(2, 3))
def _shoot_record(s0, x, n_steps, div_term, kp):
    return shoot(s0, x, kp, n_steps, div_term=div_term, record=True)


@functools.partial(jax.jit, static_argnums=(0, 5, 6))
def _pred_jit(k0, xi, sd, x, kp, f32=False, frozen=False):
    if frozen == "lagrangian":
        return evaluate_lagrangian(xi, jax.vmap(k0), x, sd, kp, f32=f32)
    kx, dkx = _k0j_jit(k0, xi)
    return evolve_kinematics(xi, kx, dkx, x, sd, kp, f32=f32, frozen_jacobian=frozen)


MIN_BUCKET = 64
# Points per evaluation call: the kernel matrices (batch x landmarks, float32) of a 1024-point
# batch stay in cache. Measured on the 500-landmark model of `workcell bench lddmm` (2 cores):
# 1024 points 165,000-180,000 /s, 4096 points 105,000-114,000 /s, 256 points ~90,000 /s.
PREDICT_BATCH = 1024


def _bucket(nb: int, batch: int) -> int:
    """Padded batch size: the next power of two >= nb (at least MIN_BUCKET, at most batch), so
    calls with any batch size reuse a handful of compilations."""
    b = MIN_BUCKET
    while b < nb:
        b *= 2
    return min(b, max(batch, nb))


@functools.partial(jax.jit, static_argnums=0)
def _dets_jit(k0, xi, sd, x, kp):
    kx, _ = _k0j_jit(k0, xi)
    _, dphi = flow_phi(xi, x, sd, kp)
    _, dpsi = flow_psi(kx, sd, kp)
    return dphi, dpsi


def _fit_cost(z, chol, q0, J0, x, y, kp, sigma, c_ref, n_steps, div_term):
    N, m = q0.shape
    P = (sigma * jax.scipy.linalg.cho_solve((chol, True), z)).reshape(N, m)
    s0 = State(q0, J0, P)
    fin = shoot(s0, x, kp, n_steps, div_term=div_term)
    r = fin.q - y
    return (sigma**2 * hamiltonian(s0, x, kp) + 0.5 * jnp.sum(r * r)) / c_ref


_fit_vg = jax.jit(jax.value_and_grad(_fit_cost), static_argnums=(9, 10))


def _gauss_np(a: np.ndarray, b: np.ndarray, width: float) -> np.ndarray:
    d = a[:, None, :] - b[None, :, :]
    return np.exp(-np.einsum("ijk,ijk->ij", d, d) / (2.0 * width * width))


def _gram_cross(xs, qs, Js, x, q0, J0, kp: KernelParams) -> np.ndarray:
    """Linearised flow Gram matrix (numpy): response at (xs, qs, Js) (M points) to momenta at
    the landmarks (x, q0, J0): lam_w K_W I_m + lam_v K_V J_s J^T, shape (M m, N m)."""
    M, m = qs.shape
    N = q0.shape[0]
    kw = _gauss_np(qs, q0, kp.sigma_w)
    kv = _gauss_np(xs, x, kp.sigma_v)
    jj = np.einsum("ian,jbn->iajb", Js, J0)
    g = kp.lam_v * kv[:, None, :, None] * jj
    g += kp.lam_w * kw[:, None, :, None] * np.eye(m)[None, :, None, :]
    return g.reshape(M * m, N * m)


def _gram(x, q0, J0, kp: KernelParams) -> np.ndarray:
    return _gram_cross(x, q0, J0, x, q0, J0, kp)


def _cho(G: np.ndarray, sigma: float):
    return scipy.linalg.cho_factor(G + sigma**2 * np.eye(G.shape[0]), lower=True)


@dataclass
class FitInfo:
    fit_seconds: float
    n_iter: int
    n_fev: int
    cost_start: float
    cost_end: float
    rms_train_before: float
    rms_train_linear: float
    rms_train_after: float
    message: str
    cv_scores: dict[str, float] = field(default_factory=dict)


class LddmmModel:
    """Fitted calibration k = psi o k0 o phi^-1, encoded by (x_i, P0_i) and the kernels.

    `predict(X)` integrates eq. (29) (by default with the same RK4 steps/stages as the fit, so at
    the training configurations it returns exactly the fitted k_1(x_i)). `set_evaluation`
    / `tune_evaluation` select a cheaper evaluation (fewer RK4 steps: the landmark system is
    re-shot with that many steps; float32 kernels), `tune_evaluation` only within a stated
    tolerance of the reference evaluation.
    """

    def __init__(
        self,
        k0: K0,
        x: np.ndarray,
        P0: np.ndarray,
        kp: KernelParams,
        sigma: float,
        n_steps: int,
        div_term: bool = False,
        info: FitInfo | None = None,
    ) -> None:
        self.k0 = k0
        self.x = np.asarray(x, dtype=float)
        self.P0 = np.asarray(P0, dtype=float)
        self.kp = KernelParams(*(float(v) for v in kp))
        self.sigma = float(sigma)
        self.n_steps = int(n_steps)
        self.div_term = bool(div_term)
        self.info = info
        self._lin_cho = None  # Cholesky of the linearised Gram (`linear_posterior_cov`)
        self._k0j = _k0_and_jac(k0)
        q0, J0 = self._k0j(jnp.asarray(self.x))
        self.dx = self.x.shape[1]
        self.dy = int(q0.shape[1])
        if self.P0.shape != (self.x.shape[0], self.dy):
            raise ValueError(
                f"P0 must have shape {(self.x.shape[0], self.dy)}, got {self.P0.shape}"
            )
        self._xj = jnp.asarray(self.x)
        self._kpj = KernelParams(*(jnp.asarray(v) for v in self.kp))
        s0 = State(q0, J0, jnp.asarray(self.P0))
        self._final, self._sd, _ = _shoot_record(
            s0, self._xj, self.n_steps, self.div_term, self._kpj
        )
        self.energy = float(hamiltonian(s0, self._xj, self._kpj))
        self._pred = functools.partial(_pred_jit, k0)
        self._dets = functools.partial(_dets_jit, k0)
        self._s0 = s0
        self.eval_steps = self.n_steps
        self.eval_float32 = False
        self.eval_frozen_jacobian = False
        self._sd_eval = self._sd

    def set_evaluation(
        self, n_steps: int | None = None, float32: bool = False, frozen_jacobian: bool = False
    ) -> None:
        """Evaluate `predict` with `n_steps` RK4 steps (None: the fit's), float32 kernels and the
        scheme: frozen_jacobian=False eq. (29) (Eulerian, evolving Dk), True the frozen-Jacobian
        approximation (shooting.evolve_kinematics), "lagrangian" psi_1 o k0 o phi_1^-1 by the two
        flows (shooting.evaluate_lagrangian, no Dk0)."""
        n = self.n_steps if n_steps is None else int(n_steps)
        if n < 1:
            raise ValueError(f"n_steps must be >= 1, got {n_steps}")
        if n == self.n_steps:
            self._sd_eval = self._sd
        elif n != self.eval_steps:
            _, self._sd_eval, _ = _shoot_record(self._s0, self._xj, n, self.div_term, self._kpj)
        self.eval_steps = n
        self.eval_float32 = bool(float32)
        if frozen_jacobian not in (False, True, "lagrangian"):
            raise ValueError(
                f"frozen_jacobian must be a bool or 'lagrangian', got {frozen_jacobian!r}"
            )
        self.eval_frozen_jacobian = frozen_jacobian

    def tune_evaluation(
        self,
        X: Any,
        tol_m: float = 1e-8,
        steps: Sequence[int] = (1, 2, 3, 5),
    ) -> dict[str, Any]:
        """Pick the cheapest evaluation (fewest steps; then Lagrangian float32 / float64, frozen
        Jacobian float32, Eulerian float32, float64) whose predictions at X stay within tol_m (max Euclidean deviation) of the
        reference (fit steps, float64, evolving Jacobian).

        Returns {"eval_steps", "eval_float32", "eval_frozen_jacobian", "tol_m",
        "deviation_m": {candidate: max deviation}}.
        """
        X, _ = _check_xy(X)
        self.set_evaluation(None, False, False)
        ref = self.predict(X)
        devs: dict[str, float] = {}
        choice = (self.n_steps, False, False)
        ns = sorted({int(v) for v in steps if 0 < int(v) <= self.n_steps} | {self.n_steps})
        modes = (
            (True, "lagrangian"),
            (False, "lagrangian"),
            (True, True),
            (True, False),
            (False, False),
        )
        cands = [(n, f, fr) for n in ns for (f, fr) in modes]
        for cand in cands:
            self.set_evaluation(*cand)
            d = float(np.max(np.linalg.norm(self.predict(X) - ref, axis=1)))
            tag = {"lagrangian": "_lagrangian", True: "_frozenJ", False: ""}[cand[2]]
            devs[f"{cand[0]}{'_f32' if cand[1] else ''}{tag}"] = d
            if d <= tol_m:
                choice = cand
                break
        self.set_evaluation(*choice)
        return {
            "eval_steps": choice[0],
            "eval_float32": choice[1],
            "eval_frozen_jacobian": choice[2],
            "tol_m": tol_m,
            "deviation_m": devs,
        }

    # ---------------------------------------------------------------------------------------
    @property
    def fitted_landmarks(self) -> np.ndarray:
        """k_1(x_i) at the training configurations (N, dy)."""
        return np.asarray(self._final.q)

    def _batched(self, fn, X: np.ndarray, batch: int):
        M = X.shape[0]
        outs = []
        for s in range(0, M, batch):
            chunk = X[s : s + batch]
            nb = chunk.shape[0]
            nbp = _bucket(nb, batch)
            if nbp > nb:  # pad to a bucket size: a few compiled shapes for any M
                chunk = np.concatenate([chunk, np.repeat(chunk[-1:], nbp - nb, 0)])
            r = fn(jnp.asarray(chunk))
            outs.append(jax.tree_util.tree_map(lambda a, nb=nb: np.asarray(a)[:nb], r))
        return jax.tree_util.tree_map(lambda *a: np.concatenate(a), *outs)

    def predict(self, X: Any, batch: int = PREDICT_BATCH) -> np.ndarray:
        """Calibrated kinematics k_1 at configurations X (M, dx) -> (M, dy), eq. (29)."""
        X, _ = _check_xy(X)
        if X.shape[1] != self.dx:
            raise ValueError(f"X must have {self.dx} columns, got {X.shape[1]}")
        sd, f32, fr = self._sd_eval, self.eval_float32, self.eval_frozen_jacobian
        return self._batched(lambda c: self._pred(c, sd, self._xj, self._kpj, f32, fr), X, batch)

    def jacobian_dets(self, X: Any, batch: int = PREDICT_BATCH) -> tuple[np.ndarray, np.ndarray]:
        """det D phi_1 at X and det D psi_1 at k0(X) (flows of v_t on X and w_t on Y)."""
        X, _ = _check_xy(X)
        if X.shape[1] != self.dx:
            raise ValueError(f"X must have {self.dx} columns, got {X.shape[1]}")
        return self._batched(lambda c: self._dets(c, self._sd, self._xj, self._kpj), X, batch)

    def min_jacobian_det(self, X: Any) -> tuple[float, float]:
        """(min det D phi_1 over X, min det D psi_1 over k0(X)); both > 0 for a diffeomorphism."""
        dphi, dpsi = self.jacobian_dets(X)
        return float(np.min(dphi)), float(np.min(dpsi))

    # ------------------------------------------------------------------ linearised posterior
    def _linear_factor(self):
        """Cholesky of the landmarks' linearised Gram G + sigma^2 I (cached)."""
        if getattr(self, "_lin_cho", None) is None:
            q0, J0 = (np.asarray(a) for a in (self._s0.q, self._s0.J))
            self._lin_cho = _cho(_gram(self.x, q0, J0, self.kp), self.sigma)
        return self._lin_cho

    def posterior_scale(self, Y: Any) -> float:
        """tau^2 (dy units squared): the maximum-likelihood scale of the linearised model read as
        a Gaussian process, residual r = Y - k0(x) ~ N(0, tau^2 (G + sigma^2 I)) over the
        landmarks (the kernel ridge regression the cross-validation scores is its posterior
        mean): tau^2 = r^T (G + sigma^2 I)^-1 r / (N dy). Y (N, dy): the training targets."""
        _, Y = _check_xy(self.x, Y)
        r = (Y - np.asarray(self._s0.q)).ravel()
        return float(r @ scipy.linalg.cho_solve(self._linear_factor(), r) / len(r))

    def linear_posterior_cov(self, X: Any, scale2: float, batch: int = 512) -> np.ndarray:
        """Covariance (M, dy, dy) of the deformation at X (M, dx): the linearised model's
        Gaussian-process posterior, tau^2 (G(x*, x*) - G(x*, x) (G + sigma^2 I)^-1 G(x, x*)),
        linearised at k0 (zero momentum) as the cross-validation is, tau^2 = `scale2`. Small
        where the landmarks are, growing to the prior's tau^2 G(x*, x*) away from them."""
        X, _ = _check_xy(X)
        if X.shape[1] != self.dx:
            raise ValueError(f"X must have {self.dx} columns, got {X.shape[1]}")
        cho = self._linear_factor()
        q0, J0 = (np.asarray(a) for a in (self._s0.q, self._s0.J))
        m, kp = self.dy, self.kp
        out = np.empty((len(X), m, m))
        for s in range(0, len(X), batch):
            xs = X[s : s + batch]
            qs, Js = (np.asarray(a) for a in self._k0j(jnp.asarray(xs)))
            Gc = _gram_cross(xs, qs, Js, self.x, q0, J0, kp).reshape(len(xs), m, -1)
            V = scipy.linalg.cho_solve(cho, Gc.reshape(len(xs) * m, -1).T)
            V = V.T.reshape(len(xs), m, -1)
            prior = kp.lam_v * np.einsum("ian,ibn->iab", Js, Js) + kp.lam_w * np.eye(m)
            out[s : s + len(xs)] = scale2 * (prior - np.einsum("iak,ibk->iab", Gc, V))
        return 0.5 * (out + np.swapaxes(out, 1, 2))

    # ---------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-able description (lists of floats). k0 is not stored: pass it to from_dict."""
        return {
            "format": _FORMAT,
            "x_landmarks": self.x.tolist(),
            "P0": self.P0.tolist(),
            "sigma_v": self.kp.sigma_v,
            "sigma_w": self.kp.sigma_w,
            "lam_v": self.kp.lam_v,
            "lam_w": self.kp.lam_w,
            "sigma": self.sigma,
            "n_steps": self.n_steps,
            "div_term": self.div_term,
            "dx": self.dx,
            "dy": self.dy,
            "eval_steps": self.eval_steps,
            "eval_float32": self.eval_float32,
            "eval_frozen_jacobian": self.eval_frozen_jacobian,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], k0: K0) -> LddmmModel:
        if d.get("format") != _FORMAT:
            raise ValueError(f"unknown LDDMM model format {d.get('format')!r}; want {_FORMAT!r}")
        kp = KernelParams(d["sigma_v"], d["sigma_w"], d["lam_v"], d["lam_w"])
        _check_saved_params(d)
        m = cls(
            k0,
            np.asarray(d["x_landmarks"], float),
            np.asarray(d["P0"], float),
            kp,
            d["sigma"],
            d["n_steps"],
            d.get("div_term", False),
        )
        if m.dy != d["dy"] or m.dx != d["dx"]:
            raise ValueError(
                f"k0 maps R^{m.dx} -> R^{m.dy}, model was fitted for R^{d['dx']} -> R^{d['dy']}"
            )
        m.set_evaluation(
            d.get("eval_steps"),
            bool(d.get("eval_float32", False)),
            d.get("eval_frozen_jacobian", False),
        )
        return m


def _check_saved_params(d: dict[str, Any]) -> None:
    """ValueError unless a saved model's kernel and data weights are ones a fit makes: widths
    and sigma finite and positive, lam_v / lam_w finite, >= 0 and not both 0, n_steps a whole
    number >= 1. A hand-edited lam_v = -1 otherwise loaded and failed inside numpy ("not
    positive definite") at the first 1-sigma, without the file's name."""
    for k in ("sigma_v", "sigma_w", "sigma", "lam_v", "lam_w"):
        v = d[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise ValueError(f"lddmm.{k} must be a finite number, got {v!r}")
    for k in ("sigma_v", "sigma_w", "sigma"):
        if d[k] <= 0:
            raise ValueError(f"lddmm.{k} must be positive, got {d[k]!r}")
    if d["lam_v"] < 0 or d["lam_w"] < 0 or d["lam_v"] + d["lam_w"] == 0:
        raise ValueError(
            f"lddmm.lam_v and lam_w must be >= 0 and not both 0, got {d['lam_v']!r}, {d['lam_w']!r}"
        )
    n = d["n_steps"]
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= 10_000:
        raise ValueError(f"lddmm.n_steps must be a whole number 1..10000, got {n!r}")


# ---------------------------------------------------------------------------------------------
# Fitting
# ---------------------------------------------------------------------------------------------


def _rms_scale(A: np.ndarray) -> float:
    s = float(np.sqrt(np.mean(np.var(A, axis=0))))
    return s if s > 0 else 1.0


def _cv_splits(N: int, m: int, k_folds: int, seed: int) -> list:
    """The CV folds: [(train rows, held-out rows of the stacked (N m) system, held-out points)]
    from one seeded permutation (the CV scores and the per-point errors share them)."""
    folds = np.array_split(np.random.default_rng(seed).permutation(N), k_folds)
    idx = np.arange(N * m).reshape(N, m)
    return [(idx[np.setdiff1d(np.arange(N), f)].ravel(), idx[f].ravel(), f) for f in folds]


def _linear_cv(x, q0, J0, y, grid, sigmas, lam_v, lam_w, k_folds, seed):
    """Linearised k-fold CV: {(sigma_v, sigma_w, sigma): held-out RMS of the kernel-ridge model}.

    One Gram matrix per width pair on all N points; each fold uses its sub-blocks (the train
    block and the cross block), and one Cholesky per fold and sigma.
    """
    N, m = q0.shape
    r_all = (y - q0).ravel()
    splits = [(itr, ite) for itr, ite, _ in _cv_splits(N, m, k_folds, seed)]
    scores = {}
    for sv, sw in grid:
        G = _gram(x, q0, J0, KernelParams(sv, sw, lam_v, lam_w))
        se = dict.fromkeys(sigmas, 0.0)
        for itr, ite in splits:
            Gtr = G[np.ix_(itr, itr)]
            Gc = G[np.ix_(ite, itr)]
            for s in sigmas:
                c = _cho(Gtr, s)
                pred = Gc @ scipy.linalg.cho_solve(c, r_all[itr])
                se[s] += float(np.sum((pred - r_all[ite]) ** 2))
        for s in sigmas:
            scores[(sv, sw, s)] = math.sqrt(se[s] / N)
    return scores


def linear_cv_errors(
    k0: K0,
    X_train: Any,
    Y_train: Any,
    *,
    sigma_v: float,
    sigma_w: float,
    sigma: float,
    lam_v: float = 1.0,
    lam_w: float = 1.0,
    k_folds: int = 5,
    seed: int = 0,
) -> np.ndarray:
    """Per-point held-out error norms (N,) of the linearised k-fold CV at one configuration,
    with the folds `linear_cv_scores` uses (same seed): their RMS is its score there."""
    X, Y = _check_xy(X_train, Y_train)
    N = X.shape[0]
    if N < 2 * k_folds:
        raise ValueError(f"need at least {2 * k_folds} points for {k_folds}-fold CV, got {N}")
    q0, J0 = (np.asarray(a) for a in _k0_and_jac(k0)(jnp.asarray(X)))
    m = q0.shape[1]
    G = _gram(X, q0, J0, KernelParams(sigma_v, sigma_w, lam_v, lam_w))
    r_all = (Y - q0).ravel()
    err = np.empty((N, m))
    for itr, ite, f in _cv_splits(N, m, k_folds, seed):
        c = _cho(G[np.ix_(itr, itr)], sigma)
        pred = G[np.ix_(ite, itr)] @ scipy.linalg.cho_solve(c, r_all[itr])
        err[f] = (pred - r_all[ite]).reshape(len(f), m)
    return np.linalg.norm(err, axis=1)


def linear_cv_scores(
    k0: K0,
    X_train: Any,
    Y_train: Any,
    *,
    sigma: float | Sequence[float] = 0.1,
    sigma_v: float | None = None,
    sigma_w: float | None = None,
    width_factors: tuple[Sequence[float], Sequence[float]] = (WIDTH_FACTORS, WIDTH_FACTORS),
    lam_v: float = 1.0,
    lam_w: float = 1.0,
    k_folds: int = 5,
    seed: int = 0,
    search: str = "grid",
) -> dict[tuple[float, float, float], float]:
    """Linearised k-fold CV RMS {(sigma_v, sigma_w, sigma): rms} (see module doc).

    Cheap (Cholesky factorisations only): used by fit_lddmm and to compare nominal models k0.
    search="grid": every (widths, sigma) combination. search="coordinate": the width grid at
    the middle sigma, then all sigmas at the best widths, then (if sigma moved) the width grid
    again at the new sigma - about half the factorisations for a 3-value sigma list. The
    returned dict holds the points evaluated; its minimum is the selection.
    """
    if search not in ("grid", "coordinate"):
        raise ValueError(f"search must be 'grid' or 'coordinate', got {search!r}")
    X, Y = _check_xy(X_train, Y_train)
    sigmas = [float(v) for v in np.atleast_1d(np.asarray(sigma, dtype=float))]
    if not sigmas or any(v <= 0 or not math.isfinite(v) for v in sigmas):
        raise ValueError(f"sigma must be > 0 (a number or a non-empty sequence), got {sigma}")
    N = X.shape[0]
    if N < 2 * k_folds:
        raise ValueError(f"need at least {2 * k_folds} points for {k_folds}-fold CV, got {N}")
    q0, J0 = (np.asarray(a) for a in _k0_and_jac(k0)(jnp.asarray(X)))
    if q0.shape != Y.shape:
        raise ValueError(f"k0 maps to R^{q0.shape[1]} but Y_train has shape {Y.shape}")
    fv, fw = width_factors
    svs = [sigma_v] if sigma_v is not None else [_rms_scale(X) * f for f in fv]
    sws = [sigma_w] if sigma_w is not None else [_rms_scale(q0) * f for f in fw]
    grid = [(a, b) for a in svs for b in sws]

    def cv(g, ss):
        return _linear_cv(X, q0, J0, Y, g, ss, lam_v, lam_w, k_folds, seed)

    if search == "grid" or len(sigmas) == 1:
        return cv(grid, sigmas)
    s_mid = sorted(sigmas)[len(sigmas) // 2]
    scores = cv(grid, [s_mid])
    sv, sw, _ = min(scores, key=scores.get)
    scores.update(cv([(sv, sw)], [s for s in sigmas if s != s_mid]))
    s_best = min(scores, key=scores.get)[2]
    if s_best != s_mid:
        scores.update(cv([g for g in grid if g != (sv, sw)], [s_best]))
    return scores


def fit_lddmm(
    k0: K0,
    X_train: Any,
    Y_train: Any,
    *,
    sigma_v: float | None = None,
    sigma_w: float | None = None,
    sigma: float | Sequence[float] = 0.1,
    n_steps: int = 10,
    max_iter: int = 200,
    tol: float = 1e-9,
    lam_v: float = 1.0,
    lam_w: float = 1.0,
    div_term: bool = False,
    cv: str = "linear",
    k_folds: int = 5,
    seed: int = 0,
    width_factors: tuple[Sequence[float], Sequence[float]] = (WIDTH_FACTORS, WIDTH_FACTORS),
    verbose: bool = False,
) -> LddmmModel:
    """Fit k = psi o k0 o phi^-1 to measurements (X_train (N,dx), Y_train (N,dy)).

    k0: JAX-differentiable nominal kinematics (dx,) -> (dy,).
    sigma_v / sigma_w: Gaussian widths on X / Y (None -> k-fold CV, see module docstring).
    sigma: dimensionless data weight of (27) (ridge sigma^2); a sequence -> chosen by the same
    linearised k-fold CV as the widths (jointly over the grid). n_steps: RK4 steps on [0,1].
    width_factors: the CV grids of sigma_v / sigma_w as multiples of s_x / s_y.
    max_iter: L-BFGS iterations; tol: L-BFGS-B ftol on the cost normalised by its value at
    P0 = 0 (stop when an iteration lowers it by less than tol). lam_v / lam_w: weights of the phi / psi fields
    (lam_v=0: psi only; lam_w=0: phi only).
    """
    X, Y = _check_xy(X_train, Y_train)
    sigmas = [float(v) for v in np.atleast_1d(np.asarray(sigma, dtype=float))]
    if not sigmas or any(v <= 0 or not math.isfinite(v) for v in sigmas):
        raise ValueError(f"sigma must be > 0 (a number or a non-empty sequence), got {sigma}")
    if n_steps < 1:
        raise ValueError(f"n_steps must be >= 1, got {n_steps}")
    if lam_v < 0 or lam_w < 0 or lam_v + lam_w == 0:
        raise ValueError(f"need lam_v, lam_w >= 0 and not both 0, got {lam_v}, {lam_w}")
    if cv not in ("linear", "full"):
        raise ValueError(f"cv must be 'linear' or 'full', got {cv!r}")
    t0 = time.perf_counter()
    k0j = _k0_and_jac(k0)
    xj = jnp.asarray(X)
    q0, J0 = k0j(xj)
    q0 = np.asarray(q0)
    J0 = np.asarray(J0)
    if q0.shape != Y.shape:
        raise ValueError(f"k0 maps to R^{q0.shape[1]} but Y_train has shape {Y.shape}")
    N, m = Y.shape

    cv_scores: dict[str, float] = {}
    if sigma_v is None or sigma_w is None or len(sigmas) > 1:
        if N < 2 * k_folds:
            raise ValueError(f"need at least {2 * k_folds} points for {k_folds}-fold CV, got {N}")
        fv, fw = width_factors
        svs = [sigma_v] if sigma_v is not None else [_rms_scale(X) * f for f in fv]
        sws = [sigma_w] if sigma_w is not None else [_rms_scale(q0) * f for f in fw]
        grid = [(a, b) for a in svs for b in sws]
        if cv == "linear":
            scores = _linear_cv(X, q0, J0, Y, grid, sigmas, lam_v, lam_w, k_folds, seed)
        else:
            scores = {
                (a, b, s): v
                for s in sigmas
                for (a, b), v in _full_cv(
                    k0, X, Y, grid, s, n_steps, lam_v, lam_w, div_term, k_folds, seed
                ).items()
            }
        sigma_v, sigma_w, sigma = min(scores, key=scores.get)
        cv_scores = {f"{a:.6g},{b:.6g},{s:.6g}": v for (a, b, s), v in scores.items()}
        if verbose:
            print(
                f"[lddmm] CV picked sigma_v={sigma_v:.4g} sigma_w={sigma_w:.4g} sigma={sigma:.3g}"
            )
    else:
        sigma = sigmas[0]
    if sigma_v <= 0 or sigma_w <= 0:
        raise ValueError(f"kernel widths must be > 0, got {sigma_v}, {sigma_w}")
    kp = KernelParams(float(sigma_v), float(sigma_w), float(lam_v), float(lam_w))

    G = _gram(X, q0, J0, kp)
    c_np = _cho(G, sigma)
    delta = Y - q0
    z0 = (delta / sigma).ravel()
    c_ref = max(float(0.5 * np.sum(delta**2)), 1e-300)
    kpj = KernelParams(*(jnp.asarray(v) for v in kp))
    args = (
        jnp.asarray(c_np[0]),
        jnp.asarray(q0),
        jnp.asarray(J0),
        jnp.asarray(X),
        jnp.asarray(Y),
        kpj,
        sigma,
        c_ref,
        n_steps,
        div_term,
    )

    def P_of(z):
        return (sigma * scipy.linalg.cho_solve(c_np, np.asarray(z))).reshape(N, m)

    def fun(z):
        v, g = _fit_vg(jnp.asarray(z), *args)
        v = float(v)
        g = np.asarray(g, dtype=float)
        if not (math.isfinite(v) and np.all(np.isfinite(g))):
            # the flow blew up for this trial step: report a large cost so the line search
            # backtracks (L-BFGS-B stops with ABNORMAL on NaN)
            return 1e6, np.zeros_like(z)
        return v, g

    cost_start = fun(z0)[0]
    res = scipy.optimize.minimize(
        fun,
        z0,
        jac=True,
        method="L-BFGS-B",
        options={"maxiter": int(max_iter), "ftol": tol, "gtol": 1e-12, "maxcor": 20},
    )
    P0 = P_of(res.x)
    fit_s = time.perf_counter() - t0
    model = LddmmModel(k0, X, P0, kp, sigma, n_steps, div_term)
    lin = q0 + (G @ scipy.linalg.cho_solve(c_np, delta.ravel())).reshape(N, m)
    model.info = FitInfo(
        fit_seconds=fit_s,
        n_iter=int(res.nit),
        n_fev=int(res.nfev),
        cost_start=float(cost_start),
        cost_end=float(res.fun),
        rms_train_before=float(np.sqrt(np.mean(np.sum(delta**2, 1)))),
        rms_train_linear=float(np.sqrt(np.mean(np.sum((lin - Y) ** 2, 1)))),
        rms_train_after=float(np.sqrt(np.mean(np.sum((model.fitted_landmarks - Y) ** 2, 1)))),
        message=str(res.message),
        cv_scores=cv_scores,
    )
    if verbose:
        i = model.info
        print(
            f"[lddmm] N={N} sv={kp.sigma_v:.4g} sw={kp.sigma_w:.4g} iters={i.n_iter} "
            f"fev={i.n_fev} cost {i.cost_start:.3e}->{i.cost_end:.3e} rms train "
            f"{i.rms_train_before:.3e}->{i.rms_train_after:.3e} ({fit_s:.2f}s) {i.message}"
        )
    return model


def _full_cv(k0, X, Y, grid, sigma, n_steps, lam_v, lam_w, div_term, k_folds, seed):
    N = X.shape[0]
    rng = np.random.default_rng(seed)
    folds = np.array_split(rng.permutation(N), k_folds)
    scores = {}
    for sv, sw in grid:
        se = 0.0
        for f in folds:
            tr = np.setdiff1d(np.arange(N), f)
            mdl = fit_lddmm(
                k0,
                X[tr],
                Y[tr],
                sigma_v=sv,
                sigma_w=sw,
                sigma=sigma,
                n_steps=n_steps,
                max_iter=30,
                lam_v=lam_v,
                lam_w=lam_w,
                div_term=div_term,
            )
            se += float(np.sum((mdl.predict(X[f]) - Y[f]) ** 2))
        scores[(sv, sw)] = math.sqrt(se / N)
    return scores
