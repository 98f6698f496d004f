"""6-joint calibration by diffeomorphisms: k = psi o k0 o phi^-1 with X = joint space (rad),
Y = SMR position in the tracker frame (m), k0 = a geometric model (the DH fit by default, or the
nominal chain with its base registered). Fitting and evaluation are in `workcell.estimation.lddmm`.

`--on auto` fits both bases on the training poses and keeps the one with the lower
cross-validated error of the deformation (5-fold on the training poses, linearised CV inside
fit_lddmm picks the kernel widths).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from workcell.estimation.dh import DHModel, fit_dh, nominal_registered
from workcell.estimation.lddmm import LddmmModel, fit_lddmm
from workcell.estimation.models import model_from_dict
from workcell.kinematics.chain import p_tracker_single


def _k0(theta: np.ndarray, base_ref: np.ndarray):
    from workcell._jax import jnp

    th, br = jnp.asarray(theta), jnp.asarray(base_ref)
    return lambda q: p_tracker_single(th, br, q)


@dataclass
class LddmmCalibration:
    base: DHModel
    lddmm: LddmmModel
    on: str
    info: dict = field(default_factory=dict)
    method: str = "lddmm"

    @property
    def unidentifiable(self):
        return self.base.unidentifiable if self.on == "dh" else []

    def predict(self, q: np.ndarray, **aux) -> np.ndarray:
        return self.lddmm.predict(np.atleast_2d(np.asarray(q, float)))

    def min_jacobian_det(self, q: np.ndarray) -> tuple[float, float]:
        return self.lddmm.min_jacobian_det(np.atleast_2d(np.asarray(q, float)))

    def parameters(self) -> dict[str, dict]:
        out = dict(self.base.parameters()) if self.on == "dh" else {}
        kp = self.lddmm.kp
        out["lddmm_sigma_v"] = {"value": kp.sigma_v, "std": None, "unit": "rad"}
        out["lddmm_sigma_w"] = {"value": kp.sigma_w, "std": None, "unit": "m"}
        out["lddmm_sigma"] = {"value": self.lddmm.sigma, "std": None, "unit": "1"}
        return out

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "on": self.on,
            "base": self.base.to_dict(),
            "lddmm": self.lddmm.to_dict(),
            "info": self.info,
        }

    @classmethod
    def from_dict(cls, d: dict) -> LddmmCalibration:
        base = model_from_dict(d["base"])
        lm = LddmmModel.from_dict(d["lddmm"], _k0(base.theta, base.base_ref))
        return cls(base=base, lddmm=lm, on=d.get("on", "dh"), info=d.get("info", {}))


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


def fit_lddmm_on(base: DHModel, ds, **kw) -> LddmmModel:
    return fit_lddmm(_k0(base.theta, base.base_ref), ds.q, ds.p_tracker, **kw)


def _cv_rms(base: DHModel, ds, k: int = 4, seed: int = 0, **kw) -> float:
    rng = np.random.default_rng(seed)
    folds = np.array_split(rng.permutation(len(ds)), k)
    se = 0.0
    for f in folds:
        tr = np.setdiff1d(np.arange(len(ds)), f)
        m = fit_lddmm_on(base, ds.subset(tr), **kw)
        se += float(np.sum((m.predict(ds.q[f]) - ds.p_tracker[f]) ** 2))
    return float(np.sqrt(se / len(ds)))


def fit_method(ds, *, on: str = "auto", progress=None, **_) -> tuple[LddmmCalibration, dict]:
    """`workcell fit --method lddmm [--on dh|nominal|auto]` on the training poses."""
    if on not in ("auto", "dh", "nominal"):
        raise ValueError(f"--on must be dh, nominal or auto, got {on!r}")
    bases = {}
    if on in ("auto", "dh"):
        bases["dh"] = fit_dh(ds)
    if on in ("auto", "nominal"):
        bases["nominal"] = _nominal_as_model(ds)
    cv = {}
    if len(bases) > 1:
        for name, b in bases.items():
            cv[name] = _cv_rms(b, ds, max_iter=60)
            if progress:
                progress(f"lddmm on {name}: 4-fold CV RMS {cv[name] * 1e6:.1f} um")
        on = min(cv, key=cv.get)
    else:
        on = next(iter(bases))
    lm = fit_lddmm_on(bases[on], ds)
    det_phi, det_psi = lm.min_jacobian_det(ds.q)
    fi = lm.info
    info = {
        "on": on,
        "cv_rms_m": cv,
        "sigma_v_rad": lm.kp.sigma_v,
        "sigma_w_m": lm.kp.sigma_w,
        "sigma": lm.sigma,
        "min_jacobian_det_phi": det_phi,
        "min_jacobian_det_psi": det_psi,
        "train_rms_before_m": fi.rms_train_before if fi else None,
        "train_rms_after_m": fi.rms_train_after if fi else None,
        "iterations": fi.n_iter if fi else None,
        "identifiability": bases[on].info.get("identifiability"),
    }
    model = LddmmCalibration(base=bases[on], lddmm=lm, on=on, info=info)
    return model, {k: v for k, v in info.items() if k != "identifiability"}
