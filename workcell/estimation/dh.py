"""Geometric calibration: simultaneous DH errors, joint offsets, base pose and SMR offset.

Steps (all on the training poses):
1. Rigid registration: the nominal chain's SMR positions in `base` are registered to the
   measurements (Kabsch). This gives `base_ref` (the recording's nominal base pose may be rough).
2. Identifiability: the weighted identification Jacobian at the nominal parameters is analysed;
   parameters that are not separately identifiable are fixed at nominal and reported by group.
3. Weighted nonlinear least squares (scipy least_squares, Levenberg-Marquardt/TRF) over the
   identifiable parameters. Per-pose isotropic weights 1/sigma_i with sigma_i the larger of
   the RMS of the recording's per-axis sigmas of that pose and the tracker's error model
   (MPE / 4, `pose_sigma_model`): a recorded sigma comes from the scatter of a few readings at
   the pose, which leaves out the per-pose systematic error and, from 2-5 readings, scatters
   itself (in simulation, weights from it made the estimates noisier and the covariance below
   about 1.2x too small).
4. Robust pass: poses whose residual exceeds `outlier_k` robust standard deviations are set
   aside (reported) and the fit is repeated once.
5. Uncertainty: Cov = s0^2 (J^T W J)^-1 with the a-posteriori variance factor s0^2 = chi2/dof,
   so the reported standard deviations do not depend on the stated sigmas being right.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from workcell.estimation.identifiability import (
    fit_identifiability,
    group_representatives,
)
from workcell.estimation.models import error_stats
from workcell.kinematics.chain import (
    IDX,
    N_PARAMS,
    base_pose_with_std,
    base_slice,
    jac_params,
    joints_of,
    p_tracker,
    pack,
    param_names,
    param_unit,
    tracker_T_base,
    unpack_dh,
)
from workcell.kinematics.frames import kabsch
from workcell.kinematics.robots import DH, RobotSpec, robot_by_name, robot_from_session
from workcell.recording.dataset import Dataset
from workcell.recording.tracker_spec import TRACKER_MPE_M, tracker_spec_sigma


def free_mask(v: object, n: int) -> np.ndarray:
    """A model file's `free` (which parameters the fit estimated): n true/false values (1/0
    accepted); anything else (text, NaN, another length) is a ValueError, not a mask that
    `np.asarray(v, bool)` would make of it."""
    if not (
        isinstance(v, list)
        and len(v) == n
        and all(isinstance(x, bool) or (isinstance(x, int) and x in (0, 1)) for x in v)
    ):
        raise ValueError(f"free must be {n} true/false values, got {str(v)[:60]}")
    return np.asarray(v, bool)


@dataclass
class DHModel:
    """A calibrated geometric model. `predict(q)` gives SMR positions in the tracker frame."""

    robot_model: str
    nominal_dh: DH
    theta: np.ndarray  # (39,)
    base_ref: np.ndarray  # (4, 4)
    cov: np.ndarray  # (39, 39); zero rows/cols for fixed parameters
    free: np.ndarray  # (39,) bool
    unidentifiable: list[list[str]] = field(default_factory=list)
    info: dict = field(default_factory=dict)
    method: str = "dh"

    def predict(self, q: np.ndarray, **aux: Any) -> np.ndarray:
        q = np.atleast_2d(np.asarray(q, dtype=float))
        return np.asarray(p_tracker(self.theta, self.base_ref, q))

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    def theta_cov(self) -> np.ndarray:
        """Covariance (39, 39) of `theta`; zero rows/columns for fixed parameters."""
        return self.cov

    def prediction_cov(self, q: np.ndarray, **aux: Any) -> np.ndarray:
        """Covariance (N, 3, 3) of `predict(q)` (tracker frame) from the parameter covariance,
        to first order: J cov J^T with J = d p / d theta."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        J = np.asarray(jac_params(self.theta, self.base_ref, q))
        return np.einsum("nip,pq,njq->nij", J, self.cov, J)

    @property
    def tracker_T_base(self) -> np.ndarray:
        return np.asarray(tracker_T_base(self.theta, self.base_ref))

    @property
    def dh(self) -> DH:
        return unpack_dh(self.theta)

    def parameters(self) -> dict[str, dict]:
        nom = pack(self.nominal_dh, tool=self.info.get("nominal_tool_m", (0.0, 0.0, 0.0)))
        n_j = joints_of(self.theta)
        base = base_slice(n_j)
        at_bound = set(self.info.get("active_bounds") or ())
        out = {}
        for i, n in enumerate(param_names(n_j)):
            out[n] = {
                "value": float(self.theta[i]),
                "std": float(self.std[i]) if self.free[i] else None,  # fixed: none (not 0)
                "unit": param_unit(n),
                "nominal": 0.0 if base.start <= i < base.stop else float(nom[i]),
                "estimated": bool(self.free[i]),
            }
            if self.free[i] and n in at_bound:  # held by its bound: no Gaussian std
                out[n].update(std=None, at_bound=True)
        # the one parameter of a dependent group kept free carries the group's combined effect
        # (the others are fixed at nominal): its value and std are the group's
        estimated = [n for n, v in out.items() if v["estimated"]]
        for n, g in group_representatives(self.unidentifiable, estimated).items():
            out[n]["stands_for"] = g
        return out

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "robot": self.robot_model,
            "nominal_dh": self.nominal_dh.to_dict(),
            "parameter_names": param_names(joints_of(self.theta)),
            "theta": self.theta.tolist(),
            "base_ref": self.base_ref.tolist(),
            "cov": self.cov.tolist(),
            "free": self.free.tolist(),
            "unidentifiable": self.unidentifiable,
            # with its 1-sigma from `cov` (first order): the base another tool or model compares
            "tracker_T_base": base_pose_with_std(self.theta, self.base_ref, self.cov),
            "info": self.info,
        }

    @classmethod
    def from_dict(cls, d: dict) -> DHModel:
        if not isinstance(d.get("robot"), str):
            raise ValueError(f"robot must be a model name, got {d.get('robot')!r}")
        return cls(
            robot_model=d["robot"],
            nominal_dh=DH.from_dict(d["nominal_dh"]),
            theta=np.asarray(d["theta"], float),
            base_ref=np.asarray(d["base_ref"], float),
            cov=np.asarray(d["cov"], float),
            free=free_mask(d["free"], len(d["theta"])),
            unidentifiable=d.get("unidentifiable", []),
            info=d.get("info", {}),
        )

    def robot_spec(self) -> RobotSpec:
        try:
            return robot_by_name(self.robot_model).with_dh(self.nominal_dh)
        except ValueError:
            return robot_from_session({"model": self.robot_model, "dh": self.nominal_dh.to_dict()})


def pose_sigma(ds: Dataset) -> np.ndarray:
    """Per-pose isotropic 1-sigma (N,) from the recording's per-axis sigmas."""
    return np.sqrt(np.mean(ds.sigma_m**2, axis=1))


def pose_sigma_model(ds: Dataset, mpe: tuple[float, float] = TRACKER_MPE_M) -> np.ndarray:
    """Per-pose isotropic 1-sigma per axis (N,): max(recorded, tracker MPE model / 4)."""
    return np.maximum(pose_sigma(ds), tracker_spec_sigma(ds.p_tracker, mpe))


def register_base(ds: Dataset, theta: np.ndarray) -> np.ndarray:
    """Rigid registration of the model's SMR positions (in base) to the measurements."""
    p_base = np.asarray(p_tracker(theta, np.eye(4), ds.q))
    return kabsch(p_base, ds.p_tracker)


def nominal_theta(ds: Dataset) -> np.ndarray:
    return pack(ds.robot.dh, tool=ds.tool_offset_m)


def fit_dh(
    ds: Dataset,
    *,
    fixed: list[str] | None = None,
    outlier_k: float = 5.0,
    max_nfev: int = 200,
    theta0: np.ndarray | None = None,
    base_ref: np.ndarray | None = None,
    tracker_mpe: tuple[float, float] = TRACKER_MPE_M,
) -> DHModel:
    """Fit the geometric model to all poses of `ds` (split before calling). `tracker_mpe`
    (A [m], B [m/m]) sets the floor of the per-pose sigmas that weight the poses."""
    t0 = time.perf_counter()
    if len(ds) < 12:
        raise ValueError(f"too few poses to fit the geometry: {len(ds)} (need at least 12)")
    th_nom = nominal_theta(ds)
    theta = th_nom.copy() if theta0 is None else np.asarray(theta0, float).copy()
    base_ref = register_base(ds, theta) if base_ref is None else base_ref
    w = 1.0 / pose_sigma_model(ds, tracker_mpe)
    J0 = np.asarray(jac_params(theta, base_ref, ds.q)) * w[:, None, None]
    ident = fit_identifiability(J0, w, ds.robot.dh, ds.tool_offset_m, fixed)
    free = np.zeros(N_PARAMS, bool)
    free[[IDX[n] for n in ident.identifiable]] = True
    solved = []

    def solve(keep, th):
        th, res = _solve(ds, keep, w, th, base_ref, free, max_nfev)
        solved.append(res)
        return th

    theta, keep = robust_solve(solve, ds, theta, base_ref, w, outlier_k)
    res, n_rejected = solved[-1], int((~keep).sum())
    cov, s0_2 = weighted_covariance(ds, theta, base_ref, w, keep, free, int(free.sum()))
    stats = error_stats(p_tracker(theta, base_ref, ds.q[keep]), ds.p_tracker[keep])
    info = {
        "nominal_tool_m": ds.tool_offset_m.tolist(),
        "train_poses": int(len(ds)),
        "outliers_rejected": n_rejected,
        "variance_factor": s0_2,
        "train_rms_m": stats["rms_m"],
        "identifiability": ident.to_dict(cov),
        "fit_seconds": time.perf_counter() - t0,
        "nfev": int(res.nfev),
        **ds.provenance(),  # the recording, and every file of a resumed one
    }
    return DHModel(
        robot_model=ds.robot.model,
        nominal_dh=ds.robot.dh,
        theta=theta,
        base_ref=base_ref,
        cov=cov,
        free=free,
        unidentifiable=ident.groups,
        info=info,
    )


def robust_solve(
    solve: Callable[[np.ndarray, np.ndarray], np.ndarray],
    ds: Dataset,
    theta: np.ndarray,
    base_ref: np.ndarray,
    w: np.ndarray,
    outlier_k: float,
    passes: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """`solve(keep, theta) -> theta` on all poses, then up to `passes` robust passes
    (`robust_keep`), each followed by a solve on the poses it keeps, so that the result is the
    fit of the poses returned. Returns (theta, keep). Shared by the fits (dh, bounded)."""
    keep = np.ones(len(ds), bool)
    theta = solve(keep, theta)
    for _ in range(passes):
        new_keep = robust_keep(ds, theta, base_ref, w, keep, outlier_k)
        if new_keep is None:
            break
        keep = new_keep
        theta = solve(keep, theta)
    return theta, keep


def robust_keep(
    ds: Dataset,
    theta: np.ndarray,
    base_ref: np.ndarray,
    w: np.ndarray,
    keep: np.ndarray,
    outlier_k: float,
) -> np.ndarray | None:
    """The robust pass shared by the fits: poses whose weighted residual lies beyond
    `3 * outlier_k` robust sigmas (MAD) of the kept ones are set aside. Returns the new mask, or
    None when nothing changes or more than 20 % of the poses would go."""
    e = np.linalg.norm(np.asarray(p_tracker(theta, base_ref, ds.q)) - ds.p_tracker, axis=1)
    sc = e * w
    med = np.median(sc[keep])
    mad = 1.4826 * np.median(np.abs(sc[keep] - med)) + 1e-12
    new_keep = sc < med + outlier_k * mad * 3.0  # 3-D norm: generous band
    if np.array_equal(new_keep, keep) or new_keep.sum() < 0.8 * len(ds):
        return None
    return new_keep


def weighted_covariance(
    ds: Dataset,
    theta: np.ndarray,
    base_ref: np.ndarray,
    w: np.ndarray,
    keep: np.ndarray,
    est: np.ndarray,
    n_free: int,
) -> tuple[np.ndarray, float]:
    """Cov = s0^2 (J^T W J)^-1 over the parameters `est` (mask), s0^2 = chi2 / (3N - n_free).
    Returns (cov (P, P) with zeros elsewhere, P = len(theta), s0^2)."""
    qk = ds.q[keep]
    r = (
        (np.asarray(p_tracker(theta, base_ref, qk)) - ds.p_tracker[keep]) * w[keep][:, None]
    ).ravel()
    s0_2 = float(r @ r / max(len(r) - n_free, 1))
    n_par = len(theta)
    cov = np.zeros((n_par, n_par))
    if np.any(est):
        Jw = (np.asarray(jac_params(theta, base_ref, qk)) * w[keep][:, None, None]).reshape(
            -1, n_par
        )[:, est]
        cov[np.ix_(est, est)] = s0_2 * np.linalg.pinv(Jw.T @ Jw)
    return cov, s0_2


def _solve(ds, keep, w, theta, base_ref, free, max_nfev):
    q, p, wk = ds.q[keep], ds.p_tracker[keep], w[keep]
    x0 = theta[free]

    def full(x):
        th = theta.copy()
        th[free] = x
        return th

    def fun(x):
        return ((np.asarray(p_tracker(full(x), base_ref, q)) - p) * wk[:, None]).ravel()

    def jac(x):
        J = np.asarray(jac_params(full(x), base_ref, q)) * wk[:, None, None]
        return J.reshape(-1, N_PARAMS)[:, free]

    res = least_squares(
        fun,
        x0,
        jac=jac,
        method="lm",
        x_scale="jac",
        max_nfev=max_nfev,
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
    )
    return full(res.x), res


def nominal_registered(ds_train: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """Nominal chain with the base registered on the training poses: (theta, base_ref)."""
    th = nominal_theta(ds_train)
    return th, register_base(ds_train, th)
