"""Calibration by diffeomorphisms (LDDMM landmark shooting), Orozco & Ratajczak.

Real kinematics k = psi o k0 o phi^-1; phi, psi are flows of time-varying Gaussian-RKHS vector
fields on joint space X and task space Y. See `shooting` for the equations (and the documented
deviations from the printed eq. 28) and `model` for fitting, scaling and width selection.

Public API:
    fit_lddmm(k0, X_train, Y_train, *, sigma_v=None, sigma_w=None, sigma=0.1 (or a CV list),
              n_steps=10,
              max_iter=200, lam_v=1.0, lam_w=1.0, ...) -> LddmmModel
    linear_cv_scores(k0, X_train, Y_train, *, sigma=..., width_factors=...) -> {(sv, sw, s): rms}
    LddmmModel.predict(X) -> (M, dy)
    LddmmModel.set_evaluation(n_steps, float32) / tune_evaluation(X, tol_m=1e-8) -> dict
    LddmmModel.min_jacobian_det(X) -> (min det D phi_1, min det D psi_1)
    LddmmModel.to_dict() / LddmmModel.from_dict(d, k0)
"""

from workcell.estimation.lddmm.model import FitInfo, LddmmModel, fit_lddmm, linear_cv_scores
from workcell.estimation.lddmm.shooting import KernelParams, State

__all__ = ["FitInfo", "KernelParams", "LddmmModel", "State", "fit_lddmm", "linear_cv_scores"]
