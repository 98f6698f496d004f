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
    # Laplace 1-sigma (6,) of each length scale (rad; delta method from the log-hyperparameters'
    # `gp_residual.laplace_log_std`), nan for one at a bound of its search range; None: not
    # computed (the drift check's fits, a model read from a file)
    lengthscale_std: np.ndarray | None = None

    def kernel(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        a = A / self.lengthscales
        b = B / self.lengthscales
        d2 = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T
        return self.signal_var * np.exp(-0.5 * np.clip(d2, 0.0, None))

    def predict(self, q: np.ndarray) -> np.ndarray:
        q = np.atleast_2d(np.asarray(q, float))
        return (self.kernel(q, self.X) @ self.alpha) * self.y_std + self.y_mean

    def predict_var(self, q: np.ndarray) -> np.ndarray:
        """Posterior variance (N, 3) of the residual at joints q (m^2, per axis)."""
        from scipy.linalg import cho_factor, cho_solve

        q = np.atleast_2d(np.asarray(q, float))
        K = self.kernel(self.X, self.X) + self.noise_var * np.eye(len(self.X))
        Ks = self.kernel(q, self.X)
        v = cho_solve(cho_factor(K, lower=True), Ks.T)
        var = np.clip(self.signal_var - np.einsum("ij,ji->i", Ks, v), 0.0, None)
        return var[:, None] * self.y_std[None, :] ** 2

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
    q = np.asarray(q, float)
    r = np.asarray(r, float)
    if q.ndim != 2 or q.shape[1] != 6 or r.shape != (len(q), 3):
        raise ValueError(f"fit_residual_gp: q {q.shape} and r {r.shape} must be (N, 6), (N, 3)")
    return _fit_ard_gp(q, r, max_points=max_points, seed=seed, laplace=True)


def _fit_ard_gp(
    X: np.ndarray, r: np.ndarray, *, max_points: int, seed: int, laplace: bool = False
) -> ResidualGP:
    """ARD-RBF + white-noise GP on inputs X (N, d) for residuals r (N, 3): hyperparameters by
    maximum marginal likelihood on at most `max_points` poses, weights on all of them."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    rng = np.random.default_rng(seed)
    sub = rng.permutation(len(X))[:max_points] if len(X) > max_points else np.arange(len(X))
    y_mean = r.mean(0)
    y_std = r.std(0) + 1e-12
    Y = (r - y_mean) / y_std
    k = ConstantKernel(0.5, (1e-3, 1e2)) * RBF(
        length_scale=np.full(X.shape[1], 1.0), length_scale_bounds=(0.05, 100.0)
    ) + WhiteKernel(0.5, (1e-3, 10.0))
    gp = GaussianProcessRegressor(k, normalize_y=False, n_restarts_optimizer=0, random_state=seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # bounds reached = no dependence on that input: expected
        gp.fit(X[sub], Y[sub])
    kk = gp.kernel_
    signal = float(kk.k1.k1.constant_value)
    ls = np.atleast_1d(np.asarray(kk.k1.k2.length_scale, float))
    noise = float(kk.k2.noise_level)
    # weights on all training poses with the fitted hyperparameters
    model = ResidualGP(X, np.zeros((len(X), 3)), ls, signal, noise, y_mean, y_std)
    K = model.kernel(X, X) + noise * np.eye(len(X))
    L = np.linalg.cholesky(K + 1e-10 * np.eye(len(X)))
    model.alpha = np.linalg.solve(L.T, np.linalg.solve(L, Y))
    if laplace:
        from workcell.estimation.gp_residual import laplace_log_std

        # kernel_.theta: log(signal), log(length scales) (d), log(noise)
        model.lengthscale_std = ls * laplace_log_std(gp)[1 : 1 + X.shape[1]]
    return model


def drift_check(
    q_tr: np.ndarray,
    t_tr: np.ndarray,
    r_tr: np.ndarray,
    q_te: np.ndarray,
    t_te: np.ndarray,
    r_te: np.ndarray,
    *,
    alpha: float = 0.01,
    max_points: int = 400,
    seed: int = 0,
    gp_joints: ResidualGP | None = None,
) -> dict | None:
    """Does a residual structure follow the joints or the recording order? When the arm sweeps
    a joint slowly through the recording, a drift in time (temperature, the tracker's set-up)
    looks like short-scale structure over that joint, and a correction over the joints would
    not carry to another day. The GP of `fit_residual_gp` is fitted on the joints, on the
    recording time alone (scaled to the training span), and on both (additive: a time GP on
    the joints GP's leave-one-out residuals), and the three are compared
    on the held-out poses, pose by pose (one-sided paired t-tests on the squared errors at
    `alpha`). `verdict`: "joints" (the joints predict better than the time), "time" (the
    reverse), or "either" (not told apart: the arm's path ties them together); `time_adds`: the
    time lowers the error further given the joints (a drift on top). Also the three held-out
    RMS (m), the one without any (`heldout_rms_m`) and the p-values (`p_time_helps`: the time
    GP against none). None without usable times. `gp_joints`: the joints GP already
    fitted to (q_tr, r_tr) by `fit_residual_gp`, if at hand."""
    from scipy import stats

    t_tr = np.asarray(t_tr, float)
    t_te = np.asarray(t_te, float)
    q_tr, q_te = np.asarray(q_tr, float), np.asarray(q_te, float)
    r_tr, r_te = np.asarray(r_tr, float), np.asarray(r_te, float)
    if not (np.all(np.isfinite(t_tr)) and np.all(np.isfinite(t_te))):
        return None
    t0, span = float(t_tr.min()), float(np.ptp(t_tr))
    if span <= 0.0 or len(t_tr) < 10 or len(t_te) < 3:
        return None
    s_tr, s_te = (t_tr - t0) / span, (t_te - t0) / span

    def predict(X_tr: np.ndarray, y: np.ndarray, X_te: np.ndarray) -> np.ndarray:
        return _fit_ard_gp(X_tr, y, max_points=max_points, seed=seed).predict(X_te)

    gp_j = gp_joints or _fit_ard_gp(q_tr, r_tr, max_points=max_points, seed=seed)
    f_te = gp_j.predict(q_te)
    g_te = predict(s_tr[:, None], r_tr, s_te[:, None])
    # both: additive, a field over the joints plus a drift in time; the drift is fitted to
    # what the joints GP leaves at each training pose without that pose (its leave-one-out
    # residual, one backfitting step)
    K = gp_j.kernel(q_tr, q_tr) + (gp_j.noise_var + 1e-10) * np.eye(len(q_tr))
    loo_j = (gp_j.alpha / np.diag(np.linalg.inv(K))[:, None]) * gp_j.y_std
    h_te = predict(s_tr[:, None], loo_j, s_te[:, None])
    e_j = np.sum((r_te - f_te) ** 2, axis=1)
    e_t = np.sum((r_te - g_te) ** 2, axis=1)
    e_b = np.sum((r_te - f_te - h_te) ** 2, axis=1)

    def p_less(a: np.ndarray, b: np.ndarray) -> float:  # H1: a's errors below b's
        p = float(stats.ttest_1samp(b - a, 0.0, alternative="greater").pvalue)
        return p if np.isfinite(p) else 1.0  # no difference at all: no evidence

    e_0 = np.sum(r_te**2, axis=1)
    p_j, p_t, p_add = p_less(e_j, e_t), p_less(e_t, e_j), p_less(e_b, e_j)
    verdict = "joints" if p_j < alpha else "time" if p_t < alpha else "either"
    return {
        "verdict": verdict,
        "time_adds": bool(p_add < alpha),
        "heldout_rms_joints_m": float(np.sqrt(e_j.mean())),
        "heldout_rms_time_m": float(np.sqrt(e_t.mean())),
        "heldout_rms_both_m": float(np.sqrt(e_b.mean())),
        "p_joints_better": p_j,
        "p_time_better": p_t,
        "p_time_adds": p_add,
        "heldout_rms_m": float(np.sqrt(e_0.mean())),  # without any of them
        "p_time_helps": p_less(e_t, e_0),
        "span_s": span,
        "alpha": alpha,
    }


def relevant_joints(model: ResidualGP, q_range: np.ndarray) -> list[tuple[int, float]]:
    """Joints (1-based) the residual depends on, with their length scale (rad), most relevant first.

    A joint counts when its length scale is shorter than twice the range the joint covered."""
    out = []
    for j in range(6):
        if model.lengthscales[j] < 2.0 * max(float(q_range[j]), 1e-6):
            out.append((j + 1, float(model.lengthscales[j])))
    return sorted(out, key=lambda t: t[1] / max(float(q_range[t[0] - 1]), 1e-6))
