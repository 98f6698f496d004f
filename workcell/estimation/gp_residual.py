"""Non-parametric peer: Gaussian-process regression of the residual of a geometric model.

p_tracker(q) = k_dh(q) + r(q), r ~ GP(0, s^2 ARD-RBF(q) + noise). Inputs are the six joint angles
(radians, each scaled by its training spread), outputs the three residual components (shared
kernel, independent outputs). Hyperparameters by marginal likelihood (scikit-learn, restarts).
Prediction uses the stored training inputs and dual coefficients, so a model file is plain JSON.
The predictive standard deviation is available (`predict_std`) as the uncertainty of the
correction. The hyperparameters carry a Laplace standard deviation: the inverse Hessian of the
negative log marginal likelihood in log-hyperparameter space at the optimum (central differences of
its analytic gradient), mapped to each value by the delta method. A hyperparameter at a bound of
its search range (a length scale at the upper bound: that joint does not matter) has no Gaussian
uncertainty and is reported as `at_bound` without a std.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from workcell.estimation.dh import TRACKER_MPE_M, DHModel, fit_dh
from workcell.estimation.models import model_from_dict

if TYPE_CHECKING:
    from sklearn.gaussian_process import GaussianProcessRegressor

    from workcell.recording.dataset import Dataset


@dataclass
class GPResidualModel:
    base: DHModel
    X: np.ndarray  # (N, 6) training joints
    alpha: np.ndarray  # (N, 3) dual coefficients
    scale: np.ndarray  # (6,) input scaling (divide q by it)
    lengthscales: np.ndarray  # (6,) in scaled units
    signal_var: float
    noise_var: float
    y_mean: np.ndarray  # (3,)
    L: np.ndarray | None = None  # Cholesky of K + noise (for predict_std)
    # Laplace std of log(signal_var), log(lengthscales) (6), log(noise_var); nan at a bound
    log_hyper_std: np.ndarray | None = None
    info: dict = field(default_factory=dict)
    method: str = "gp"

    @property
    def unidentifiable(self) -> list[list[str]]:
        return self.base.unidentifiable

    def _k(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        a = A / self.scale / self.lengthscales
        b = B / self.scale / self.lengthscales
        d2 = (a**2).sum(1)[:, None] + (b**2).sum(1)[None, :] - 2 * a @ b.T
        return self.signal_var * np.exp(-0.5 * np.maximum(d2, 0.0))

    def residual(self, q: np.ndarray) -> np.ndarray:
        q = np.atleast_2d(np.asarray(q, float))
        out = np.empty((len(q), 3))
        for s in range(0, len(q), 4096):
            out[s : s + 4096] = self._k(q[s : s + 4096], self.X) @ self.alpha + self.y_mean
        return out

    def predict(self, q: np.ndarray, **aux: Any) -> np.ndarray:
        return self.base.predict(q) + self.residual(q)

    def predict_std(self, q: np.ndarray) -> np.ndarray:
        """Predictive 1-sigma of each residual component (N,) (same for x, y, z)."""
        from scipy.linalg import cho_solve

        q = np.atleast_2d(np.asarray(q, float))
        if self.L is None:
            K = self._k(self.X, self.X) + self.noise_var * np.eye(len(self.X))
            self.L = np.linalg.cholesky(K)
        Ks = self._k(q, self.X)
        v = cho_solve((self.L, True), Ks.T)
        var = self.signal_var - np.einsum("ij,ji->i", Ks, v)
        return np.sqrt(np.clip(var, 0.0, None))

    def prediction_cov(self, q: np.ndarray, **aux: Any) -> np.ndarray:
        """Covariance (N, 3, 3) of `predict(q)` (tracker frame): the geometry's from its parameter
        covariance plus the GP's posterior variance of the residual on each axis. The two are
        added as if independent (the GP was fitted to that geometry's residuals, so their errors
        are partly opposed): an upper estimate."""
        C = self.base.prediction_cov(q)
        return C + (self.predict_std(q) ** 2)[:, None, None] * np.eye(3)

    def parameters(self) -> dict[str, dict]:
        out = dict(self.base.parameters())
        ls = np.full(8, np.nan) if self.log_hyper_std is None else self.log_hyper_std

        def entry(value: float, s_log: float, power: float, unit: str) -> dict:
            # value = exp(power * log_hyper): std(value) ~ value * power * std(log_hyper)
            ok = bool(np.isfinite(s_log))
            e = {
                "value": value,
                "std": float(value * power * s_log) if ok else None,
                "unit": unit,
                "at_bound": self.log_hyper_std is not None and not ok,
            }
            if ok:  # the approximation is Gaussian in the log: a factor either way
                f = float(np.exp(min(1.96 * power * s_log, 700.0)))  # no overflow: >1000 shown
                e["factor_95"], e["range_95"] = f, [value / f, value * f]
                if power * s_log > 0.5:  # a std beyond half the value says nothing
                    e["std"] = None
            return e

        for j in range(6):
            out[f"gp_lengthscale_q{j + 1}"] = entry(
                float(self.lengthscales[j] * self.scale[j]), ls[1 + j], 1.0, "rad"
            )
        out["gp_signal_std"] = entry(float(np.sqrt(self.signal_var)), ls[0], 0.5, "m")
        out["gp_noise_std"] = entry(float(np.sqrt(self.noise_var)), ls[7], 0.5, "m")
        at = self.info.get("hyper_at_bound")  # (8,) in log_hyper_std's order; older models: none
        if at is not None and len(at) == 8:
            names = [
                "gp_signal_std",
                *(f"gp_lengthscale_q{j + 1}" for j in range(6)),
                "gp_noise_std",
            ]
            for name, b in zip(names, at, strict=True):
                e = out[name]
                e["at_bound"] = bool(b) and e["std"] is None
                if e["std"] is None and not b and "factor_95" not in e:
                    e["no_std"] = (
                        "the log marginal likelihood's Hessian over the free hyperparameters is "
                        "not positive definite: no proper maximum, no Gaussian approximation"
                    )
        return out

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "base": self.base.to_dict(),
            "X": self.X.tolist(),
            "alpha": self.alpha.tolist(),
            "scale": self.scale.tolist(),
            "lengthscales": self.lengthscales.tolist(),
            "signal_var": self.signal_var,
            "noise_var": self.noise_var,
            "y_mean": self.y_mean.tolist(),
            "log_hyper_std": None
            if self.log_hyper_std is None
            else [None if not np.isfinite(x) else float(x) for x in self.log_hyper_std],
            "info": self.info,
        }

    @classmethod
    def from_dict(cls, d: dict) -> GPResidualModel:
        for k in ("signal_var", "noise_var"):  # a variance: positive, finite
            v = float(d[k])
            if not (np.isfinite(v) and v > 0.0):
                raise ValueError(f"{k} must be a variance > 0, got {v:g}")
        _check_arrays(d)
        return cls(
            base=model_from_dict(d["base"]),
            X=np.asarray(d["X"], float),
            alpha=np.asarray(d["alpha"], float),
            scale=np.asarray(d["scale"], float),
            lengthscales=np.asarray(d["lengthscales"], float),
            signal_var=float(d["signal_var"]),
            noise_var=float(d["noise_var"]),
            y_mean=np.asarray(d["y_mean"], float),
            log_hyper_std=None
            if d.get("log_hyper_std") is None
            else np.array([np.nan if x is None else x for x in d["log_hyper_std"]], float),
            info=d.get("info", {}),
        )


def _check_arrays(d: dict) -> None:
    """The shapes and ranges a GP model file's arrays must have: a hand edit gave a matmul
    error's text, and training joints X in degrees were read, the GP's residual vanishing from
    the exported table without a word (fuzz audit, 2026-11-29)."""
    X = np.asarray(d["X"], float)
    if X.ndim != 2 or not len(X) or not np.all(np.isfinite(X)):
        raise ValueError(f"X must be finite joint angles (poses x joints), got shape {X.shape}")
    if np.abs(X).max() > 4 * np.pi:
        raise ValueError(
            f"X reaches {np.abs(X).max():.4g}, beyond +-4 pi: joint angles in degrees? the file "
            "wants radians"
        )
    jr = (d.get("info") or {}).get("joint_range_rad")
    if jr is not None and np.shape(jr) == (X.shape[1], 2):
        lo, hi = np.asarray(jr, float).T
        if np.any(X < lo - 1e-9) or np.any(X > hi + 1e-9):
            raise ValueError("X lies outside the model's own fitted joint range (joint_range_rad)")
    shapes = {
        "alpha": (len(X), None),
        "scale": (X.shape[1],),
        "lengthscales": (X.shape[1],),
    }
    for k, want in shapes.items():
        a = np.asarray(d[k], float)
        if a.ndim != len(want) or any(
            w is not None and n != w for n, w in zip(a.shape, want, strict=True)
        ):
            raise ValueError(f"{k} has shape {a.shape}, X {X.shape}: they do not belong together")
        if not np.all(np.isfinite(a)) or (k != "alpha" and not np.all(a > 0)):
            raise ValueError(f"{k} must be finite" + ("" if k == "alpha" else " and > 0"))


def fit_gp_residual(
    base: DHModel,
    q: np.ndarray,
    p: np.ndarray,
    *,
    restarts: int = 2,
    seed: int = 0,
    sigma_m: np.ndarray | None = None,
) -> GPResidualModel:
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    r = p - base.predict(q)
    y_mean = r.mean(0)
    scale = np.maximum(q.std(0), 1e-3)
    X = q / scale
    s2 = float(np.var(r - y_mean)) + 1e-18
    # the white noise cannot be below the stated measurement noise of one component
    noise_lo = float(np.median(sigma_m) ** 2) if sigma_m is not None else s2 * 1e-4
    kern = ConstantKernel(s2, (s2 * 1e-4, s2 * 1e2)) * RBF(np.ones(6), (1e-2, 1e2)) + WhiteKernel(
        s2 * 0.3, (noise_lo, max(s2 * 2, noise_lo * 10))
    )
    gpr = GaussianProcessRegressor(
        kern, normalize_y=False, n_restarts_optimizer=restarts, random_state=seed
    )
    import warnings

    from sklearn.exceptions import ConvergenceWarning

    with warnings.catch_warnings():  # a length scale at its bound means "irrelevant joint"
        warnings.simplefilter("ignore", ConvergenceWarning)
        gpr.fit(X, r - y_mean)
    k = gpr.kernel_
    signal_var = float(k.k1.k1.constant_value)
    ls = np.asarray(k.k1.k2.length_scale, float)
    noise_var = float(k.k2.noise_level)
    K = signal_var * np.exp(
        -0.5 * ((X[:, None, :] - X[None, :, :]) ** 2 / ls**2).sum(-1)
    ) + noise_var * np.eye(len(X))
    L = np.linalg.cholesky(K)
    from scipy.linalg import cho_solve

    alpha = cho_solve((L, True), r - y_mean)
    return GPResidualModel(
        log_hyper_std=laplace_log_std(gpr),
        base=base,
        X=np.asarray(q, float),
        alpha=alpha,
        scale=scale,
        lengthscales=ls,
        signal_var=signal_var,
        noise_var=noise_var,
        y_mean=y_mean,
        L=L,
        info={
            "log_marginal_likelihood": float(gpr.log_marginal_likelihood_value_),
            "train_poses": int(len(q)),
            "identifiability": base.info.get("identifiability"),
            "outliers_rejected": base.info.get("outliers_rejected", 0),
            "hyper_at_bound": _at_bound(gpr).tolist(),
        },
    )


def _at_bound(gpr, rel_bound: float = 1e-2) -> np.ndarray:
    """Which log-hyperparameters sit within `rel_bound` of their search range (laplace_log_std
    holds these fixed)."""
    theta = np.asarray(gpr.kernel_.theta, float)
    bounds = np.asarray(gpr.kernel_.bounds, float)
    return ~((theta - bounds[:, 0] > rel_bound) & (bounds[:, 1] - theta > rel_bound))


def laplace_log_std(gpr: GaussianProcessRegressor, rel_bound: float = 1e-2) -> np.ndarray:
    """Laplace standard deviations of a fitted scikit-learn GP's log-hyperparameters.

    The Hessian of the negative log marginal likelihood comes from central differences of its
    analytic gradient. Hyperparameters within `rel_bound` (in log units) of a bound of their
    search range are held fixed (nan); so is everything when the Hessian of the free ones is not
    positive definite (the optimum is not a proper maximum: no Gaussian approximation)."""
    theta = np.asarray(gpr.kernel_.theta, float)
    free = ~_at_bound(gpr, rel_bound)
    out = np.full(len(theta), np.nan)
    idx = np.where(free)[0]
    if idx.size == 0:
        return out
    h = 1e-4
    H = np.empty((idx.size, idx.size))
    for a, i in enumerate(idx):
        tp, tm = theta.copy(), theta.copy()
        tp[i] += h
        tm[i] -= h
        gp = gpr.log_marginal_likelihood(tp, eval_gradient=True, clone_kernel=False)[1]
        gm = gpr.log_marginal_likelihood(tm, eval_gradient=True, clone_kernel=False)[1]
        H[a] = -(gp[idx] - gm[idx]) / (2 * h)
    H = 0.5 * (H + H.T)
    w = np.linalg.eigvalsh(H)
    if not np.all(np.isfinite(w)) or w.min() <= 0:
        return out
    out[idx] = np.sqrt(np.diag(np.linalg.inv(H)))
    return out


def fit_method(
    ds: Dataset,
    *,
    on: str = "auto",
    progress: Callable[[str], None] | None = None,
    tracker_mpe: tuple[float, float] = TRACKER_MPE_M,
    **_: Any,
) -> tuple[GPResidualModel, dict]:
    """`workcell fit --method gp`: DH fit, then a GP on its residual (training poses only)."""
    if on == "nominal":
        from workcell.errors import UserError

        raise UserError(
            "--method gp always sits on the DH fit (its GP models the DH fit's residual); drop "
            "--on nominal, or use --method lddmm --on nominal"
        )
    base = fit_dh(ds, tracker_mpe=tracker_mpe)
    model = fit_gp_residual(base, ds.q, ds.p_tracker, sigma_m=ds.sigma_m)
    extra = {
        "on": "dh",
        "gp_lengthscales_rad": (model.lengthscales * model.scale).round(4).tolist(),
        "gp_signal_std_m": float(np.sqrt(model.signal_var)),
        "gp_noise_std_m": float(np.sqrt(model.noise_var)),
    }
    return model, extra
