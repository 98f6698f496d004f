"""6-joint calibration by diffeomorphisms: k = psi o k0 o phi^-1 with X = joint space (rad),
Y = SMR position in the tracker frame (m), k0 = a geometric model (the DH fit by default, or the
nominal chain with its base registered). Fitting and evaluation are in `workcell.estimation.lddmm`.

Model selection uses the training poses only: the kernel widths and the data weight sigma by
5-fold linearised cross-validation (`linear_cv_scores`), and `--on auto` keeps the base with
the lower CV RMS (the same CV, so `auto` costs one more grid search, no extra nonlinear fit).
The JSON `extra` reports the widths, sigma, CV scores, minimum Jacobian determinants of phi and
psi at the training poses and the evaluation settings (RK4 steps, float32) with their measured
deviation from the reference evaluation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from workcell.estimation.dh import TRACKER_MPE_M, DHModel, fit_dh, nominal_registered
from workcell.estimation.lddmm import LddmmModel, fit_lddmm, linear_cv_scores
from workcell.estimation.lddmm.model import linear_cv_errors
from workcell.estimation.models import (
    interval_um,
    model_from_dict,
    rms_interval,
    rms_ratio_interval,
)
from workcell.kinematics.chain import p_tracker_and_jacobian_single, p_tracker_single
from workcell.recording.checks import is_finite_number

if TYPE_CHECKING:
    from workcell.recording.dataset import Dataset


class _ChainK0:
    """k0(q) = p_tracker_single(theta, base_ref, q) as a hashable callable: the jitted LDDMM
    kernels take k0 as a static argument, so models with the same base (a model loaded twice,
    repeated predictions) share one compilation instead of recompiling for each new closure."""

    def __init__(self, theta: np.ndarray, base_ref: np.ndarray) -> None:
        from workcell._jax import jnp

        self._key = (np.asarray(theta, float).tobytes(), np.asarray(base_ref, float).tobytes())
        self._th, self._br = jnp.asarray(theta, float), jnp.asarray(base_ref, float)

    def __call__(self, q):
        return p_tracker_single(self._th, self._br, q)

    def value_and_jacobian(self, q):
        """(k0(q), Dk0(q)) analytically (the LDDMM evaluation needs both at every point)."""
        return p_tracker_and_jacobian_single(self._th, self._br, q)

    def __hash__(self) -> int:
        return hash(self._key)

    def __eq__(self, other) -> bool:
        return isinstance(other, _ChainK0) and self._key == other._key


def _k0(theta: np.ndarray, base_ref: np.ndarray) -> _ChainK0:
    return _ChainK0(theta, base_ref)


@dataclass
class LddmmCalibration:
    base: DHModel
    lddmm: LddmmModel
    on: str
    info: dict = field(default_factory=dict)
    method: str = "lddmm"
    # tau^2 (m^2) of the deformation's linearised posterior (`LddmmModel.posterior_scale`);
    # None (a model file from before 2026-11-27): no covariance of the prediction
    posterior_scale_m2: float | None = None

    @property
    def unidentifiable(self) -> list[list[str]]:
        return self.base.unidentifiable if self.on == "dh" else []

    def predict(self, q: np.ndarray, **aux: Any) -> np.ndarray:
        return self.lddmm.predict(np.atleast_2d(np.asarray(q, float)))

    def prediction_cov(self, q: np.ndarray, **aux: Any) -> np.ndarray | None:
        """Covariance (N, 3, 3) of `predict(q)` (tracker frame): the base's (a DH fit's, from its
        parameter covariance; none for the registered nominal chain) plus the deformation's
        linearised Gaussian-process posterior (`LddmmModel.linear_posterior_cov`, scale tau^2
        by maximum likelihood on the training poses), added as if independent (the deformation
        was fitted to the base's residual: an upper estimate). None for a model file without
        tau^2."""
        if self.posterior_scale_m2 is None:
            return None
        q = np.atleast_2d(np.asarray(q, float))
        C = self.lddmm.linear_posterior_cov(q, self.posterior_scale_m2)
        if self.on == "dh":
            Cb = self.base.prediction_cov(q)
            if Cb is not None:
                C = C + np.asarray(Cb, float)
        return C

    def min_jacobian_det(self, q: np.ndarray) -> tuple[float, float]:
        return self.lddmm.min_jacobian_det(np.atleast_2d(np.asarray(q, float)))

    def parameters(self) -> dict[str, dict]:
        out = dict(self.base.parameters()) if self.on == "dh" else {}
        kp = self.lddmm.kp
        # chosen from a grid by 5-fold cross-validation: a discrete choice, no Gaussian std
        cv = "5-fold cross-validation over a grid (cv_grid: in the fit report's extra, the model's info)"
        out["lddmm_sigma_v"] = {"value": kp.sigma_v, "std": None, "unit": "rad", "chosen_by": cv}
        out["lddmm_sigma_w"] = {"value": kp.sigma_w, "std": None, "unit": "m", "chosen_by": cv}
        out["lddmm_sigma"] = {"value": self.lddmm.sigma, "std": None, "unit": "1", "chosen_by": cv}
        return out

    def to_dict(self) -> dict:
        out = {
            "method": self.method,
            "on": self.on,
            "base": self.base.to_dict(),
            "lddmm": self.lddmm.to_dict(),
            "info": self.info,
        }
        if self.posterior_scale_m2 is not None:
            out["posterior_scale_m2"] = float(self.posterior_scale_m2)
        return out

    @classmethod
    def from_dict(cls, d: dict) -> LddmmCalibration:
        base = model_from_dict(d["base"])
        lm = LddmmModel.from_dict(d["lddmm"], _k0(base.theta, base.base_ref))
        on = d.get("on", "dh")
        fitted = bool(np.any(np.asarray(base.free, bool)))  # the registered nominal has none
        want = "dh" if fitted else "nominal"
        if on != want:  # "on" decides whether the base's covariance enters the 1-sigma
            raise ValueError(f"on must be {want!r} (the base this file holds), got {on!r}")
        tau2 = d.get("posterior_scale_m2")
        if tau2 is not None and not (is_finite_number(tau2) and 0.0 <= tau2 < 1.0):
            raise ValueError(f"posterior_scale_m2 must be a variance in m^2 (0 to 1), got {tau2!r}")
        return cls(
            base=base,
            lddmm=lm,
            on=on,
            info=d.get("info", {}),
            posterior_scale_m2=None if tau2 is None else float(tau2),
        )


def _nominal_as_model(ds) -> DHModel:
    th, base = nominal_registered(ds)
    return DHModel(
        robot_model=ds.robot.model,
        nominal_dh=ds.robot.dh,
        theta=th,
        base_ref=base,
        cov=np.zeros((len(th), len(th))),
        free=np.zeros(len(th), bool),
        info={"nominal_tool_m": ds.tool_offset_m.tolist()},
    )


# CV grids for 6-joint recordings (X in rad, Y in m): widths as multiples of the RMS spread of
# the training joints (s_x) / of k0 at them (s_y); the data weight sigma (dimensionless ridge).
SIGMAS = (0.03, 0.1, 0.3)
WIDTH_FACTORS_V = (1.0, 2.0, 4.0)
WIDTH_FACTORS_W = (1.0, 2.0, 4.0, 8.0)
EVAL_TOL_M = 1e-8  # a cheaper evaluation is used only within 10 nm of the reference one
N_CHECK = 256  # extra random configurations (in the training box) for that check


def fit_lddmm_on(base: DHModel, ds: Dataset, **kw: Any) -> LddmmModel:
    return fit_lddmm(_k0(base.theta, base.base_ref), ds.q, ds.p_tracker, **kw)


def cv_scores_on(base: DHModel, ds: Dataset, *, k_folds: int = 5, seed: int = 0) -> dict:
    """Linearised k-fold CV RMS of the deformation of `base` over the (sigma_v, sigma_w, sigma)
    grid (coordinate search: widths, then sigma, then widths again if sigma moved), on the
    poses of ds only (the training poses)."""
    return linear_cv_scores(
        _k0(base.theta, base.base_ref),
        ds.q,
        ds.p_tracker,
        sigma=SIGMAS,
        width_factors=(WIDTH_FACTORS_V, WIDTH_FACTORS_W),
        k_folds=k_folds,
        seed=seed,
        search="coordinate",
    )


def cv_errors_on(base: DHModel, ds: Dataset, sv: float, sw: float, sigma: float) -> np.ndarray:
    """Per-pose error norms (N,) of `cv_scores_on`'s CV at one configuration (same folds)."""
    return linear_cv_errors(
        _k0(base.theta, base.base_ref), ds.q, ds.p_tracker, sigma_v=sv, sigma_w=sw, sigma=sigma
    )


def fit_method(
    ds: Dataset,
    *,
    on: str = "auto",
    progress: Callable[[str], None] | None = None,
    tracker_mpe: tuple[float, float] = TRACKER_MPE_M,
    **_: Any,
) -> tuple[LddmmCalibration, dict]:
    """`workcell fit --method lddmm [--on dh|nominal|auto]` on the training poses.

    Everything is chosen on the training poses: kernel widths and sigma by 5-fold linearised CV
    (grid above); `auto` takes the base (DH fit or registered nominal) with the lower CV RMS
    (note: the DH base is fitted on all training poses, so its CV score is slightly optimistic
    - 39 parameters against 3 N coordinates). The evaluation is then tuned (fewest RK4 steps,
    float32 kernels) within EVAL_TOL_M of the reference evaluation.
    """
    if on not in ("auto", "dh", "nominal"):
        raise ValueError(f"--on must be dh, nominal or auto, got {on!r}")
    bases = {}
    if on in ("auto", "dh"):
        bases["dh"] = fit_dh(ds, tracker_mpe=tracker_mpe)
    if on in ("auto", "nominal"):
        bases["nominal"] = _nominal_as_model(ds)
    scores = {}
    cv_best = {}
    cv_ci = {}
    cv_err = {}
    for name, b in bases.items():
        scores[name] = cv_scores_on(b, ds)
        cv_best[name] = min(scores[name].values())
        cv_err[name] = cv_errors_on(b, ds, *min(scores[name], key=scores[name].get))
        cv_ci[name] = list(rms_interval(cv_err[name]))
        if progress:
            progress(
                f"lddmm on {name}: 5-fold linearised CV RMS {cv_best[name] * 1e6:.1f} um "
                f"({interval_um(cv_ci[name]) or 'no interval'}; at the best of its grid)"
            )
    on = min(cv_best, key=cv_best.get)
    choice = None
    if len(bases) == 2:  # auto: how clearly the CV prefers one base, paired over the poses
        other = "nominal" if on == "dh" else "dh"
        ratio_ci = rms_ratio_interval(cv_err[other], cv_err[on])
        choice = {
            "kept": on,
            "other": other,
            "cv_rms_ratio_other_to_kept": cv_best[other] / max(cv_best[on], 1e-300),
            "ratio_ci95": list(ratio_ci),
            "basis": "paired BCa bootstrap over the training poses' CV errors, each base at the "
            "best of its grid (the selection itself is not in the interval)",
        }
        if progress:
            lo, hi = ratio_ci
            progress(
                f"lddmm: kept {on}; {other}'s CV RMS is {choice['cv_rms_ratio_other_to_kept']:.2f}x "
                f"(95 % CI {lo:.2f}-{hi:.2f}x, paired over the poses)"
                + ("; the two are not told apart" if lo <= 1.0 else "")
            )
    sv, sw, sigma = min(scores[on], key=scores[on].get)
    lm = fit_lddmm_on(bases[on], ds, sigma_v=sv, sigma_w=sw, sigma=sigma)
    det_phi, det_psi = lm.min_jacobian_det(ds.q)
    rng = np.random.default_rng(0)
    lo, hi = ds.q.min(0), ds.q.max(0)
    q_check = np.concatenate([ds.q, rng.uniform(lo, hi, size=(N_CHECK, ds.q.shape[1]))])
    ev = lm.tune_evaluation(q_check, tol_m=EVAL_TOL_M)
    fi = lm.info
    info = {
        "on": on,
        "cv_rms_m": cv_best,
        # 95 % interval of each CV RMS over the training poses (at the best of its grid: the
        # selection makes the figure somewhat optimistic, which the interval does not hold)
        "cv_rms_ci95_m": cv_ci,
        **({"cv_choice": choice} if choice is not None else {}),
        "cv_grid": {
            "sigma": list(SIGMAS),
            "sigma_v_factors": list(WIDTH_FACTORS_V),
            "sigma_w_factors": list(WIDTH_FACTORS_W),
            "folds": 5,
        },
        "sigma_v_rad": lm.kp.sigma_v,
        "sigma_w_m": lm.kp.sigma_w,
        "sigma": lm.sigma,
        "min_jacobian_det_phi": det_phi,
        "min_jacobian_det_psi": det_psi,
        "train_rms_before_m": fi.rms_train_before if fi else None,
        "train_rms_linear_m": fi.rms_train_linear if fi else None,
        "train_rms_after_m": fi.rms_train_after if fi else None,
        "iterations": fi.n_iter if fi else None,
        # L-BFGS-B's own verdict: False when it stopped at its iteration or evaluation limit
        "converged": (fi.message.upper().startswith("CONVERGENCE")) if fi else None,
        "optimizer_message": fi.message if fi else None,
        "lddmm_fit_seconds": fi.fit_seconds if fi else None,
        "evaluation": ev,
        "identifiability": bases[on].info.get("identifiability"),
    }
    tau2 = lm.posterior_scale(ds.p_tracker)
    # what the linearised posterior reads as measurement noise (tau sigma) beside the tracker's
    info["posterior_noise_std_m"] = float(np.sqrt(tau2) * lm.sigma)
    model = LddmmCalibration(base=bases[on], lddmm=lm, on=on, info=info, posterior_scale_m2=tau2)
    return model, {k: v for k, v in info.items() if k != "identifiability"}
