"""`EkfAnnModel`: the EKF-ANN estimate as a FittedModel (predict / parameters / save / load).

predict(q) = f(q; theta) + offset + R_tb(theta) . ANN(q; w)
with f the geometric chain (`workcell.kinematics.chain`), offset the paper mode's position-state
offset (zero in the adaptive mode) and the network in the base frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from workcell.estimation.ekf_ann import ann as A
from workcell.kinematics.chain import PARAM_NAMES, PARAM_UNITS, p_tracker, tracker_T_base
from workcell.kinematics.robots import DH

if TYPE_CHECKING:
    from workcell.estimation.ekf_ann.filter import EkfAnnFilter


@dataclass
class EkfAnnModel:
    robot_model: str
    nominal_dh: DH
    theta: np.ndarray  # (39,)
    base_ref: np.ndarray  # (4, 4)
    offset_m: np.ndarray  # (3,)
    spec: A.AnnSpec
    w: np.ndarray
    geometric_std: dict = field(default_factory=dict)  # estimated geometric state -> std
    # covariance of the estimated geometric states, in `geometric_std`'s order (None: unknown)
    geometric_cov: np.ndarray | None = None
    w_std: np.ndarray | None = None
    info: dict = field(default_factory=dict)
    method: str = "ekf-ann"

    def __post_init__(self) -> None:
        self.theta = np.asarray(self.theta, float)
        self.base_ref = np.asarray(self.base_ref, float)
        self.offset_m = np.asarray(self.offset_m, float)
        self.w = np.asarray(self.w, float)
        if self.theta.shape != (len(PARAM_NAMES),) or self.base_ref.shape != (4, 4):
            raise ValueError(f"theta {self.theta.shape} / base_ref {self.base_ref.shape} malformed")
        if self.w.shape != (self.spec.n_weights,):
            raise ValueError(f"w: expected {self.spec.n_weights} weights, got {self.w.shape}")
        if self.geometric_cov is not None:
            self.geometric_cov = np.asarray(self.geometric_cov, float)
            n = len(self.geometric_std)
            if self.geometric_cov.shape != (n, n):
                raise ValueError(
                    f"geometric_cov: expected ({n}, {n}) for {n} geometric states, "
                    f"got {self.geometric_cov.shape}"
                )

    @property
    def std_scale(self) -> float:
        """sqrt(max(1, s0^2)), s0^2 the innovation variance factor the live filter recorded in
        `info["variance_factor"]` (1 when absent or not finite): the filter's P is right only if
        the stated measurement noise is, so its stds are scaled up when the innovations are
        larger than stated (as `replay --json` reports them)."""
        s0 = self.info.get("variance_factor")
        if s0 is None or not np.isfinite(s0):
            return 1.0
        return float(np.sqrt(max(float(s0), 1.0)))

    def theta_cov(self) -> np.ndarray | None:
        """Covariance (39, 39) of `theta`: the filter's final state covariance of the geometric
        states times `std_scale`^2 (zero for parameters the filter did not estimate); None when
        the geometry was not estimated (paper mode) or the model file predates the covariance."""
        names = list(self.geometric_std)
        if self.geometric_cov is None or not all(n in PARAM_NAMES for n in names):
            return None
        idx = [PARAM_NAMES.index(n) for n in names]
        out = np.zeros((len(PARAM_NAMES), len(PARAM_NAMES)))
        out[np.ix_(idx, idx)] = self.geometric_cov * self.std_scale**2
        return out

    def non_geometric(self, q: np.ndarray) -> np.ndarray:
        """The network's part (N, 3) in the tracker frame."""
        R = np.asarray(tracker_T_base(self.theta, self.base_ref))[:3, :3]
        return A.predict_base_m(self.w, np.atleast_2d(np.asarray(q, float)), self.spec) @ R.T

    def predict(self, q: np.ndarray, **aux: Any) -> np.ndarray:
        q = np.atleast_2d(np.asarray(q, dtype=float))
        geo = np.asarray(p_tracker(self.theta, self.base_ref, q)) + self.offset_m
        return geo + self.non_geometric(q)

    def parameters(self) -> dict[str, dict]:
        """Each estimated state: value and std (the filter's, times `std_scale`), unit."""
        k = self.std_scale
        out = {}
        for n, sd in self.geometric_std.items():
            if n in PARAM_NAMES:
                i = PARAM_NAMES.index(n)
                out[n] = {
                    "value": float(self.theta[i]),
                    "std": float(sd) * k,
                    "unit": PARAM_UNITS[n],
                }
            else:  # paper mode: position state components
                out[n] = {"value": float("nan"), "std": float(sd) * k, "unit": "m"}
        for j, c in enumerate("xyz"):
            out[f"offset_{c}"] = {"value": float(self.offset_m[j]), "std": 0.0, "unit": "m"}
        sd = np.zeros_like(self.w) if self.w_std is None else self.w_std * k
        for k, v in enumerate(self.w):
            out[f"ann_w{k:03d}"] = {"value": float(v), "std": float(sd[k]), "unit": "1"}
        return out

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "robot": self.robot_model,
            "nominal_dh": self.nominal_dh.to_dict(),
            "parameter_names": PARAM_NAMES,
            "theta": self.theta.tolist(),
            "base_ref": self.base_ref.tolist(),
            "offset_m": self.offset_m.tolist(),
            "ann": {**self.spec.to_dict(), "w": self.w.tolist()},
            "w_std": None if self.w_std is None else np.asarray(self.w_std).tolist(),
            "geometric_std": {k: float(v) for k, v in self.geometric_std.items()},
            "geometric_cov": None
            if self.geometric_cov is None
            else np.asarray(self.geometric_cov).tolist(),
            "info": self.info,
        }

    @classmethod
    def from_dict(cls, d: dict) -> EkfAnnModel:
        if not isinstance(d.get("robot"), str):
            raise ValueError(f"robot must be a model name, got {d.get('robot')!r}")
        return cls(
            robot_model=d["robot"],
            nominal_dh=DH.from_dict(d["nominal_dh"]),
            theta=np.asarray(d["theta"], float),
            base_ref=np.asarray(d["base_ref"], float),
            offset_m=np.asarray(d["offset_m"], float),
            spec=A.AnnSpec.from_dict(d["ann"]),
            w=np.asarray(d["ann"]["w"], float),
            geometric_std=dict(d.get("geometric_std", {})),
            geometric_cov=None
            if d.get("geometric_cov") is None
            else np.asarray(d["geometric_cov"], float),
            w_std=None if d.get("w_std") is None else np.asarray(d["w_std"], float),
            info=d.get("info", {}),
        )

    @classmethod
    def from_filter(
        cls, f: EkfAnnFilter, robot_model: str, nominal_dh: DH, info: dict | None = None
    ) -> EkfAnnModel:
        K = f.n_weights
        return cls(
            robot_model=robot_model,
            nominal_dh=nominal_dh,
            theta=f.theta,
            base_ref=f.base_ref,
            offset_m=f.offset_m(),
            spec=f.spec,
            w=f.w.copy(),
            geometric_std=f.geometric_std(),
            geometric_cov=np.array(f.P[K:, K:], float),
            w_std=np.sqrt(np.clip(np.diag(f.P)[:K], 0, None)),
            info={"mode": f.cfg.mode, "samples": f.count, **(info or {})},
        )
