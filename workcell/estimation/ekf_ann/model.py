"""`EkfAnnModel`: the EKF-ANN estimate as a FittedModel (predict / parameters / save / load).

predict(q) = f(q; theta) + offset + R_tb(theta) . ANN(q; w)
with f the geometric chain (`workcell.kinematics.chain`), offset the paper mode's position-state
offset (zero in the adaptive mode) and the network in the base frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from workcell.estimation.ekf_ann import ann as A
from workcell.kinematics.chain import PARAM_NAMES, PARAM_UNITS, p_tracker, tracker_T_base
from workcell.kinematics.robots import DH


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

    def non_geometric(self, q: np.ndarray) -> np.ndarray:
        """The network's part (N, 3) in the tracker frame."""
        R = np.asarray(tracker_T_base(self.theta, self.base_ref))[:3, :3]
        return A.predict_base_m(self.w, np.atleast_2d(np.asarray(q, float)), self.spec) @ R.T

    def predict(self, q: np.ndarray, **aux) -> np.ndarray:
        q = np.atleast_2d(np.asarray(q, dtype=float))
        geo = np.asarray(p_tracker(self.theta, self.base_ref, q)) + self.offset_m
        return geo + self.non_geometric(q)

    def parameters(self) -> dict[str, dict]:
        out = {}
        for n, sd in self.geometric_std.items():
            if n in PARAM_NAMES:
                i = PARAM_NAMES.index(n)
                out[n] = {"value": float(self.theta[i]), "std": float(sd), "unit": PARAM_UNITS[n]}
            else:  # paper mode: position state components
                out[n] = {"value": float("nan"), "std": float(sd), "unit": "m"}
        for j, c in enumerate("xyz"):
            out[f"offset_{c}"] = {"value": float(self.offset_m[j]), "std": 0.0, "unit": "m"}
        sd = np.zeros_like(self.w) if self.w_std is None else self.w_std
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
            w_std=None if d.get("w_std") is None else np.asarray(d["w_std"], float),
            info=d.get("info", {}),
        )

    @classmethod
    def from_filter(cls, f, robot_model: str, nominal_dh: DH, info: dict | None = None):
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
            w_std=np.sqrt(np.clip(np.diag(f.P)[:K], 0, None)),
            info={"mode": f.cfg.mode, "samples": f.count, **(info or {})},
        )
