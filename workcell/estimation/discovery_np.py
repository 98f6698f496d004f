"""A small Gaussian-process model of a residual field over joint space (non-parametric fallback).

Used by discovery when a structured residual remains that no physical candidate explains. Inputs
are the six joint angles (rad); outputs the three components of the position residual in the
tracker frame (m). Kernel: signal^2 * RBF with one length scale per joint (ARD) + white noise;
hyperparameters by maximum marginal likelihood (scikit-learn, on at most `max_points` poses).
Prediction needs only numpy, so a saved model replays without scikit-learn.

The ARD length scales locate the residual in joint space: a joint with a short length scale is
one the residual depends on; a length scale much longer than the joint's range means no
dependence.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np


@dataclass
class ResidualGP:
    X: np.ndarray  # (n, 6) training joints
    alpha: np.ndarray  # (n, 3) weights (normalised targets)
    lengthscales: np.ndarray  # (6,) rad
    signal_var: float
    noise_var: float
    y_mean: np.ndarray  # (3,)
    y_std: np.ndarray  # (3,)

    def kernel(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        a = A / self.lengthscales
        b = B / self.lengthscales
        d2 = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T
        return self.signal_var * np.exp(-0.5 * np.clip(d2, 0.0, None))

    def predict(self, q: np.ndarray) -> np.ndarray:
        q = np.atleast_2d(np.asarray(q, float))
        return (self.kernel(q, self.X) @ self.alpha) * self.y_std + self.y_mean

    def to_dict(self) -> dict:
        return {
            "kind": "ard-rbf-gp",
            "inputs": "q_rad",
            "X": self.X.tolist(),
            "alpha": self.alpha.tolist(),
            "lengthscales": self.lengthscales.tolist(),
            "signal_var": self.signal_var,
            "noise_var": self.noise_var,
            "y_mean": self.y_mean.tolist(),
            "y_std": self.y_std.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> ResidualGP:
        return cls(
            X=np.asarray(d["X"], float),
            alpha=np.asarray(d["alpha"], float),
            lengthscales=np.asarray(d["lengthscales"], float),
            signal_var=float(d["signal_var"]),
            noise_var=float(d["noise_var"]),
            y_mean=np.asarray(d["y_mean"], float),
            y_std=np.asarray(d["y_std"], float),
        )


def fit_residual_gp(
    q: np.ndarray, r: np.ndarray, *, max_points: int = 400, seed: int = 0
) -> ResidualGP:
    """Fit the GP to residuals r (N, 3) at joints q (N, 6)."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    q = np.asarray(q, float)
    r = np.asarray(r, float)
    if q.ndim != 2 or q.shape[1] != 6 or r.shape != (len(q), 3):
        raise ValueError(f"fit_residual_gp: q {q.shape} and r {r.shape} must be (N, 6), (N, 3)")
    rng = np.random.default_rng(seed)
    sub = rng.permutation(len(q))[:max_points] if len(q) > max_points else np.arange(len(q))
    y_mean = r.mean(0)
    y_std = r.std(0) + 1e-12
    Y = (r - y_mean) / y_std
    k = ConstantKernel(0.5, (1e-3, 1e2)) * RBF(
        length_scale=np.full(6, 1.0), length_scale_bounds=(0.05, 100.0)
    ) + WhiteKernel(0.5, (1e-3, 10.0))
    gp = GaussianProcessRegressor(k, normalize_y=False, n_restarts_optimizer=0, random_state=seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # bounds reached = no dependence on that joint: expected
        gp.fit(q[sub], Y[sub])
    kk = gp.kernel_
    signal = float(kk.k1.k1.constant_value)
    ls = np.atleast_1d(np.asarray(kk.k1.k2.length_scale, float))
    noise = float(kk.k2.noise_level)
    # weights on all training poses with the fitted hyperparameters
    model = ResidualGP(q, np.zeros((len(q), 3)), ls, signal, noise, y_mean, y_std)
    K = model.kernel(q, q) + noise * np.eye(len(q))
    L = np.linalg.cholesky(K + 1e-10 * np.eye(len(q)))
    model.alpha = np.linalg.solve(L.T, np.linalg.solve(L, Y))
    return model


def relevant_joints(model: ResidualGP, q_range: np.ndarray) -> list[tuple[int, float]]:
    """Joints (1-based) the residual depends on, with their length scale (rad), most relevant first.

    A joint counts when its length scale is shorter than twice the range the joint covered."""
    out = []
    for j in range(6):
        if model.lengthscales[j] < 2.0 * max(float(q_range[j]), 1e-6):
            out.append((j + 1, float(model.lengthscales[j])))
    return sorted(out, key=lambda t: t[1] / max(float(q_range[t[0] - 1]), 1e-6))
