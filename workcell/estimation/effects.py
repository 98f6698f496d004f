"""Library of candidate physical effects and the augmented model (geometry + accepted effects).

Every effect has physical parameters with units and enters the forward kinematics where the
physics acts (not as a generic correction on the output):

| kind                | parameter (per)                  | unit       | model                         |
|---------------------|----------------------------------|------------|-------------------------------|
| joint_compliance    | c_j (joint j)                    | rad/(N m)  | q_link_j = q_enc_j + c_j tau_j |
| link_deflection     | f_L (link L = 2, 3)              | m/N        | cantilever under the carried  |
|                     |                                  |            | weight: tip shift f_L W_perp, |
|                     |                                  |            | tip slope 1.5 shift / L       |
| transmission_error  | s_jk, c_jk (joint j, order k)    | rad        | dq_j = s sin(k q_j) +         |
|                     |                                  |            |        c cos(k q_j)           |
| backlash            | b_j (joint j, full width)        | rad        | dq_j = b_j / 2 * approach_j   |
| thermal_drift       | k_T (whole arm)                  | 1/K        | a_i, d_i scale by             |
|                     |                                  | (or 1/h)   | 1 + k_T (T_link_i - T_ref_i)  |
| tracker_scale       | s                                | 1          | p_tracker scales by (1 + s)   |

tau_j is the torque gravity (links from the robot's inertial data + payload) puts on joint j
(`workcell.kinematics.gravity`), computed with the calibrated geometry; the link temperature is the
mean of the temperatures of the two joints it joins (the last link: joint 6). If the recording
has no joint temperatures, the ambient temperature is used, and failing that the elapsed time
(then k_T is a length drift per hour). Gravity is taken along -z of the robot base (an upright
robot), as in the recording format's `base` frame.

The geometric kinds (joint_offset, link_geometry, base_frame, tool_offset) are the 39 parameters
of `workcell.kinematics.chain` and are always estimated together with the effects.

`AugmentedModel` is the fitted model (method "augmented"): geometry + the accepted effects (+ an
optional non-parametric residual model), saved and replayed like any other model.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from workcell._jax import jax, jnp
from workcell.kinematics.chain import (
    I_TOOL,
    PARAM_NAMES,
    PARAM_UNITS,
    pack,
    tracker_T_base,
)
from workcell.kinematics.gravity import gravity_torques_nm
from workcell.kinematics.robots import DH, RobotSpec, has_inertia

G_BASE = np.array([0.0, 0.0, -9.80665])
N_ORDERS = 3  # harmonic orders of the transmission error in the library (1..N_ORDERS)

PHYSICAL_KINDS = (
    "joint_compliance",
    "link_deflection",
    "transmission_error",
    "backlash",
    "thermal_drift",
    "tracker_scale",
)
GEOMETRIC_KINDS = ("joint_offset", "link_geometry", "base_frame", "tool_offset")
# Kinds whose parameter has a sign fixed by the physics: a joint yields to the torque gravity puts
# on it (c_j >= 0: tau_j is that torque, positive towards increasing q) and a link bends the way
# its load pulls (f_L >= 0). A fitted value of the other sign is not that mechanism: the term
# stands in for something else. Backlash (its sign depends on where the encoder sits), thermal
# drift (the time source may carry a shrinking) and the harmonics have no fixed sign.
SIGN_FIXED_KINDS = {
    "joint_compliance": "a joint cannot stiffen against gravity's pull",
    "link_deflection": "a link cannot bend against its load",
}

# layout of the effect vector `eff` (52,)
SL_COMP = slice(0, 6)
SL_DEFL = slice(6, 8)  # links 2 and 3
SL_TE_SIN = slice(8, 8 + 6 * N_ORDERS)
SL_TE_COS = slice(8 + 6 * N_ORDERS, 8 + 12 * N_ORDERS)
SL_BL = slice(8 + 12 * N_ORDERS, 14 + 12 * N_ORDERS)
I_THERM = 14 + 12 * N_ORDERS
I_SCALE = 15 + 12 * N_ORDERS
N_EFF = 16 + 12 * N_ORDERS
N_FEAT = 20  # per-pose features: tau (6), approach sign (6), dT per link (6), link loads (2)


def _eff_names() -> tuple[list[str], list[str]]:
    names, units = [], []
    for j in range(6):
        names.append(f"joint{j + 1}_compliance")
        units.append("rad/(N m)")
    for link in (2, 3):
        names.append(f"link{link}_flexibility")
        units.append("m/N")
    for part in ("sin", "cos"):
        for j in range(6):
            for k in range(1, N_ORDERS + 1):
                names.append(f"joint{j + 1}_transmission_h{k}_{part}")
                units.append("rad")
    for j in range(6):
        names.append(f"joint{j + 1}_backlash")
        units.append("rad")
    names += ["thermal_expansion", "tracker_scale"]
    units += ["1/K", "1"]
    return names, units


EFF_NAMES, EFF_UNITS = _eff_names()


def te_index(joint0: int, order: int, part: str) -> int:
    base = SL_TE_SIN.start if part == "sin" else SL_TE_COS.start
    return base + joint0 * N_ORDERS + (order - 1)


@dataclass(frozen=True)
class Candidate:
    """One candidate of the library: an effect kind at one joint (and harmonic order)."""

    kind: str
    joint: int | None  # 1-based joint (for link_deflection: the link number), None: whole arm
    order: int | None = None
    idx: tuple[int, ...] = ()

    @property
    def key(self) -> str:
        s = self.kind
        if self.joint is not None:
            s += f"/{'link' if self.kind == 'link_deflection' else 'joint'}{self.joint}"
        if self.order is not None:
            s += f"/order{self.order}"
        return s

    def describe(self) -> str:
        if self.kind == "joint_compliance":
            return f"joint {self.joint} compliance"
        if self.kind == "link_deflection":
            return f"link {self.joint} deflection under gravity"
        if self.kind == "transmission_error":
            return f"joint {self.joint} transmission error (harmonic order {self.order})"
        if self.kind == "backlash":
            return f"joint {self.joint} backlash"
        if self.kind == "thermal_drift":
            return "thermal drift of the link lengths"
        if self.kind == "tracker_scale":
            return "tracker scale error"
        return self.key

    def to_list(self) -> list:
        return [self.kind, self.joint, self.order]


def library(orders: tuple[int, ...] = tuple(range(1, N_ORDERS + 1))) -> list[Candidate]:
    """Every candidate of the physical library (each is tested; unobservable ones are reported)."""
    out: list[Candidate] = []
    for j in range(6):
        out.append(Candidate("joint_compliance", j + 1, None, (SL_COMP.start + j,)))
    for i, link in enumerate((2, 3)):
        out.append(Candidate("link_deflection", link, None, (SL_DEFL.start + i,)))
    for j in range(6):
        for k in orders:
            out.append(
                Candidate(
                    "transmission_error",
                    j + 1,
                    k,
                    (te_index(j, k, "sin"), te_index(j, k, "cos")),
                )
            )
    for j in range(6):
        out.append(Candidate("backlash", j + 1, None, (SL_BL.start + j,)))
    out.append(Candidate("thermal_drift", None, None, (I_THERM,)))
    out.append(Candidate("tracker_scale", None, None, (I_SCALE,)))
    return out


def candidate_from_list(x: list) -> Candidate:
    kind, joint, order = x
    for c in library():
        if c.kind == kind and c.joint == joint and c.order == order:
            return c
    raise ValueError(f"unknown effect candidate {x!r}")


# ----------------------------------------------------------------------------- JAX forward model
def _rz(t):
    c, s = jnp.cos(t), jnp.sin(t)
    return jnp.array([[c, -s, 0.0, 0.0], [s, c, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0, 0, 0, 1.0]])


def _rx(t):
    c, s = jnp.cos(t), jnp.sin(t)
    return jnp.array([[1.0, 0.0, 0.0, 0.0], [0.0, c, -s, 0.0], [0.0, s, c, 0.0], [0, 0, 0, 1.0]])


def _ry(t):
    c, s = jnp.cos(t), jnp.sin(t)
    return jnp.array([[c, 0.0, s, 0.0], [0.0, 1.0, 0.0, 0.0], [-s, 0.0, c, 0.0], [0, 0, 0, 1.0]])


def _tr(x, y, z):
    return jnp.eye(4).at[0, 3].set(x).at[1, 3].set(y).at[2, 3].set(z)


def p_aug_single(theta: Any, eff: Any, base_ref: Any, q: Any, x: Any) -> Any:
    """SMR in the tracker frame for one pose: geometry theta (39,), effects eff (N_EFF,),
    joints q (6,), per-pose features x (N_FEAT,) = tau, approach sign, dT per link, link loads."""
    tau, sgn, dT, load = x[0:6], x[6:12], x[12:18], x[18:20]
    k = jnp.arange(1, N_ORDERS + 1, dtype=q.dtype)
    tes = eff[SL_TE_SIN].reshape(6, N_ORDERS)
    tec = eff[SL_TE_COS].reshape(6, N_ORDERS)
    kq = k[None, :] * q[:, None]
    dq = (
        eff[SL_COMP] * tau
        + jnp.sum(tes * jnp.sin(kq) + tec * jnp.cos(kq), axis=1)
        + 0.5 * eff[SL_BL] * sgn
    )
    ql = q + dq
    grow = 1.0 + eff[I_THERM] * dT
    a = theta[0:6] * grow
    d = theta[6:12] * grow
    alpha, off, beta = theta[12:18], theta[18:24], theta[24:30]
    g = jnp.asarray(G_BASE)
    T = jnp.eye(4)
    for i in range(6):
        A = _rz(ql[i] + off[i]) @ _tr(0.0, 0.0, d[i]) @ _tr(a[i], 0.0, 0.0)
        if i in (1, 2):
            T_end = T @ A
            g_link = T_end[:3, :3].T @ (load[i - 1] * g)
            L = jnp.maximum(jnp.abs(a[i]), 1e-3)
            f = eff[SL_DEFL.start + i - 1]
            sy, sz = f * g_link[1], f * g_link[2]
            A = A @ _tr(0.0, sy, sz) @ _ry(-1.5 * sz / L) @ _rz(1.5 * sy / L)
        T = T @ A @ _rx(alpha[i]) @ _ry(beta[i])
    p_base = T[:3, :3] @ theta[36:39] + T[:3, 3]
    Tb = tracker_T_base(theta, base_ref)
    return (1.0 + eff[I_SCALE]) * (Tb[:3, :3] @ p_base + Tb[:3, 3])


_p_aug = jax.jit(jax.vmap(p_aug_single, in_axes=(None, None, None, 0, 0)))
# reverse mode: 3 outputs per pose against 91 inputs (much cheaper than forward mode here)
_jac_aug = jax.jit(
    jax.vmap(jax.jacrev(p_aug_single, argnums=(0, 1)), in_axes=(None, None, None, 0, 0))
)

_MIN_BUCKET = [64]


@contextmanager
def batch_bucket(n: int) -> Iterator[None]:
    """Within this context every padded call uses at least the bucket of n poses, so one
    diagnosis compiles each jitted function once (train and held-out sets share a shape)."""
    old = _MIN_BUCKET[0]
    _MIN_BUCKET[0] = max(old, 1 << int(np.ceil(np.log2(max(n, 1)))))
    try:
        yield
    finally:
        _MIN_BUCKET[0] = old


def _pad(n: int) -> int:
    """Bucketed batch size (powers of two, at least the current bucket): few recompilations."""
    return max(_MIN_BUCKET[0], 1 << int(np.ceil(np.log2(max(n, 1)))))


def padded_call(fn: Callable[..., Any], q: np.ndarray, *args: Any, **kw: Any) -> np.ndarray:
    """fn(q_padded, ...) sliced back to len(q): for jitted per-pose functions of the foundation."""
    q = np.atleast_2d(np.asarray(q, float))
    n = len(q)
    m = _pad(n)
    qp = np.concatenate([q, np.repeat(q[:1], m - n, 0)]) if m > n else q
    return np.asarray(fn(qp, *args, **kw))[:n]


def _padded(q: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = len(q)
    m = _pad(n)
    if m == n:
        return q, x
    return (
        np.concatenate([q, np.repeat(q[:1], m - n, 0)]),
        np.concatenate([x, np.repeat(x[:1], m - n, 0)]),
    )


def p_aug(
    theta: npt.ArrayLike,
    eff: npt.ArrayLike,
    base_ref: npt.ArrayLike,
    q: np.ndarray,
    x: npt.ArrayLike,
) -> np.ndarray:
    """(N, 3) SMR positions in the tracker frame (padded internally to limit recompilations)."""
    n = len(q)
    qp, xp = _padded(np.asarray(q, float), np.asarray(x, float))
    return np.asarray(_p_aug(jnp.asarray(theta), jnp.asarray(eff), jnp.asarray(base_ref), qp, xp))[
        :n
    ]


def jac_aug(
    theta: npt.ArrayLike,
    eff: npt.ArrayLike,
    base_ref: npt.ArrayLike,
    q: np.ndarray,
    x: npt.ArrayLike,
) -> tuple[np.ndarray, np.ndarray]:
    """(d p / d theta (N, 3, 39), d p / d eff (N, 3, N_EFF))."""
    n = len(q)
    qp, xp = _padded(np.asarray(q, float), np.asarray(x, float))
    Jt, Je = _jac_aug(jnp.asarray(theta), jnp.asarray(eff), jnp.asarray(base_ref), qp, xp)
    return np.asarray(Jt)[:n], np.asarray(Je)[:n]


# ----------------------------------------------------------------------------- features
def link_loads_kg(spec: RobotSpec, payload_kg: np.ndarray) -> np.ndarray:
    """Mass carried at the tip of links 2 and 3 (half the link + everything distal + payload)."""
    m = spec.link_masses_kg
    loads = np.array([0.5 * m[1] + m[2:].sum(), 0.5 * m[2] + m[3:].sum()])
    return loads[None, :] + np.asarray(payload_kg, float)[:, None]


def thermal_source(temps: np.ndarray, ambient: np.ndarray, elapsed: np.ndarray) -> str:
    """Which signal drives thermal drift: 'joint', 'ambient', 'time' or 'none'."""
    if temps is not None and np.all(np.isfinite(temps)) and np.ptp(temps, axis=0).max() > 0.05:
        return "joint"
    if ambient is not None and np.all(np.isfinite(ambient)) and np.ptp(ambient) > 0.05:
        return "ambient"
    if elapsed is not None and np.all(np.isfinite(elapsed)) and np.ptp(elapsed) > 60.0:
        return "time"
    return "none"


def thermal_signal(
    source: str,
    temps: npt.ArrayLike | None,
    ambient: npt.ArrayLike | None,
    elapsed: npt.ArrayLike | None,
    n: int,
) -> np.ndarray:
    """(N, 6) per-link signal (K, or hours for 'time') before subtracting the reference."""
    if source == "joint":
        t = np.asarray(temps, float)
        return np.concatenate([0.5 * (t[:, :-1] + t[:, 1:]), t[:, -1:]], axis=1)
    if source == "ambient":
        return np.repeat(np.asarray(ambient, float)[:, None], 6, 1)
    if source == "time":
        return np.repeat(np.asarray(elapsed, float)[:, None] / 3600.0, 6, 1)
    return np.zeros((n, 6))


THERMAL_UNITS = {"joint": "1/K", "ambient": "1/K", "time": "1/h", "none": "1"}


@dataclass
class FeatureSpec:
    """What turns recorded aux data into per-pose effect features (stored in the model)."""

    spec: RobotSpec
    payload_com_m: np.ndarray
    thermal_source: str = "none"
    thermal_ref: np.ndarray = field(default_factory=lambda: np.zeros(6))
    payload_kg_default: float = 0.0

    def features(self, theta: np.ndarray, q: np.ndarray, **aux: Any) -> np.ndarray:
        q = np.atleast_2d(np.asarray(q, float))
        n = len(q)
        pay = aux.get("payload_kg")
        pay = np.full(n, self.payload_kg_default) if pay is None else np.asarray(pay, float)
        pay = np.where(np.isfinite(pay), pay, self.payload_kg_default)
        if has_inertia(self.spec):
            m = _pad(n)
            payp = np.concatenate([pay, np.repeat(pay[:1], m - n)]) if m > n else pay
            tau = padded_call(
                lambda qq: gravity_torques_nm(self.spec, qq, payp, self.payload_com_m, theta=theta),
                q,
            )
            loads = link_loads_kg(self.spec, pay)
        else:
            tau, loads = np.zeros((n, 6)), np.zeros((n, 2))
        sgn = aux.get("approach_sign")
        sgn = np.zeros((n, 6)) if sgn is None else np.sign(np.nan_to_num(np.asarray(sgn, float)))
        src = self.thermal_source
        sig = None
        if src == "joint" and aux.get("joint_temperature_c") is not None:
            sig = thermal_signal(src, aux["joint_temperature_c"], None, None, n)
        elif src == "ambient" and aux.get("ambient_temperature_c") is not None:
            sig = thermal_signal(src, None, aux["ambient_temperature_c"], None, n)
        elif src == "time" and aux.get("elapsed_s") is not None:
            sig = thermal_signal(src, None, None, aux["elapsed_s"], n)
        dT = np.zeros((n, 6)) if sig is None else sig - self.thermal_ref[None, :]
        dT = np.nan_to_num(dT)
        return np.concatenate([tau, sgn, dT, loads], axis=1)


def spec_to_dict(spec: RobotSpec) -> dict:
    return {
        "model": spec.model,
        "dh": spec.dh.to_dict(),
        "joint_limits_rad": spec.joint_limits_rad.tolist(),
        "link_masses_kg": spec.link_masses_kg.tolist(),
        "link_coms_m": spec.link_coms_m.tolist(),
    }


def spec_from_dict(d: dict) -> RobotSpec:
    return RobotSpec(
        model=d["model"],
        dh=DH.from_dict(d["dh"]),
        joint_limits_rad=np.asarray(d["joint_limits_rad"], float),
        link_masses_kg=np.asarray(d["link_masses_kg"], float),
        link_coms_m=np.asarray(d["link_coms_m"], float),
    )


# ----------------------------------------------------------------------------- the model
@dataclass
class AugmentedModel:
    """Geometry + accepted physical effects (+ optional non-parametric residual model)."""

    features_spec: FeatureSpec
    theta: np.ndarray  # (39,)
    base_ref: np.ndarray  # (4, 4)
    eff: np.ndarray  # (N_EFF,), zero for effects not accepted
    accepted: list[Candidate]
    free: np.ndarray  # (39,) bool: estimated geometric parameters
    cov: np.ndarray  # covariance of [theta[free], eff[active]]
    nominal_tool_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    residual: dict | None = None  # serialised non-parametric residual model (discovery_np)
    info: dict = field(default_factory=dict)
    method: str = "augmented"

    # ------------------------------------------------------------ prediction
    @property
    def active(self) -> np.ndarray:
        idx = sorted({i for c in self.accepted for i in c.idx})
        return np.asarray(idx, int)

    def features(self, q: np.ndarray, **aux: Any) -> np.ndarray:
        return self.features_spec.features(self.theta, q, **aux)

    def predict_parametric(self, q: np.ndarray, **aux: Any) -> np.ndarray:
        q = np.atleast_2d(np.asarray(q, float))
        return p_aug(self.theta, self.eff, self.base_ref, q, self.features(q, **aux))

    def predict(self, q: np.ndarray, **aux: Any) -> np.ndarray:
        p = self.predict_parametric(q, **aux)
        if self.residual is not None:
            from workcell.estimation.discovery_np import ResidualGP

            p = p + ResidualGP.from_dict(self.residual).predict(np.atleast_2d(q))
        return p

    # ------------------------------------------------------------ reporting
    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    def theta_cov(self) -> np.ndarray:
        """Marginal covariance (39, 39) of the geometric `theta` (the effects estimated with it
        are marginalised out); zero rows/columns for fixed parameters."""
        idx = np.flatnonzero(self.free)
        out = np.zeros((len(self.theta), len(self.theta)))
        out[np.ix_(idx, idx)] = self.cov[: len(idx), : len(idx)]
        return out

    def prediction_jacobian(self, q: np.ndarray, **aux: Any) -> np.ndarray:
        """Jacobian (N, 3, P) of the parametric `predict(q, **aux)` (tracker frame) with respect
        to the estimated parameters, in `cov`'s order (free geometry, then accepted effects)."""
        q = np.atleast_2d(np.asarray(q, float))
        Jt, Je = jac_aug(self.theta, self.eff, self.base_ref, q, self.features(q, **aux))
        return np.concatenate([Jt[:, :, self.free], Je[:, :, self.active]], axis=2)

    def prediction_cov(self, q: np.ndarray, **aux: Any) -> np.ndarray | None:
        """Covariance (N, 3, 3) of `predict(q, **aux)` (tracker frame) from the covariance of the
        geometry and the accepted effects, to first order (features held at their values). With
        a residual GP, plus its posterior variance per axis, added as if independent of the
        parametric part (the GP was fitted to its residuals): an upper estimate."""
        q = np.atleast_2d(np.asarray(q, float))
        J = self.prediction_jacobian(q, **aux)
        C = np.einsum("nip,pq,njq->nij", J, self.cov, J)
        if self.residual is not None:
            from workcell.estimation.discovery_np import ResidualGP

            v = ResidualGP.from_dict(self.residual).predict_var(q)
            C = C + v[:, :, None] * np.eye(3)[None]
        return C

    def _std_of(self) -> tuple[np.ndarray, np.ndarray]:
        s = self.std
        nf = int(self.free.sum())
        st = np.zeros(39)
        st[self.free] = s[:nf]
        se = np.zeros(N_EFF)
        se[self.active] = s[nf:]
        return st, se

    def effect_parameters(self, c: Candidate) -> dict[str, dict]:
        """Physical parameters of one accepted candidate: name -> {value, std, unit}."""
        _, se = self._std_of()
        unit = self.effect_unit(c)
        out: dict[str, dict] = {}
        if c.kind == "transmission_error":
            i_s, i_c = c.idx
            s, co = float(self.eff[i_s]), float(self.eff[i_c])
            amp = float(np.hypot(s, co))
            ph = float(np.arctan2(co, s))
            C = self.cov_of([i_s, i_c])
            if amp > 0:
                g = np.array([s, co]) / amp
                amp_sd = float(np.sqrt(max(g @ C @ g, 0.0)))
                gp = np.array([-co, s]) / amp**2
                ph_sd = float(np.sqrt(max(gp @ C @ gp, 0.0)))
            else:
                amp_sd = ph_sd = 0.0
            out["amplitude"] = {"value": amp, "std": amp_sd, "unit": "rad"}
            out["phase"] = {"value": ph, "std": ph_sd, "unit": "rad"}
            out["order"] = {"value": int(c.order), "std": 0.0, "unit": "1"}
            out["sin_coefficient"] = {"value": s, "std": float(se[i_s]), "unit": "rad"}
            out["cos_coefficient"] = {"value": co, "std": float(se[i_c]), "unit": "rad"}
            return out
        (i,) = c.idx
        name = {
            "joint_compliance": "compliance",
            "link_deflection": "flexibility",
            "backlash": "backlash_width",
            "thermal_drift": "expansion_coefficient",
            "tracker_scale": "scale",
        }[c.kind]
        out[name] = {"value": float(self.eff[i]), "std": float(se[i]), "unit": unit}
        return out

    def effect_unit(self, c: Candidate) -> str:
        if c.kind == "thermal_drift":
            return THERMAL_UNITS[self.features_spec.thermal_source]
        return EFF_UNITS[c.idx[0]]

    def cov_of(self, eff_idx: list[int]) -> np.ndarray:
        nf = int(self.free.sum())
        act = list(self.active)
        pos = [nf + act.index(i) for i in eff_idx]
        return self.cov[np.ix_(pos, pos)]

    def parameters(self) -> dict[str, dict]:
        st, _ = self._std_of()
        nom = pack(self.features_spec.spec.dh, tool=self.nominal_tool_m)
        out: dict[str, dict] = {}
        for i, n in enumerate(PARAM_NAMES):
            out[n] = {
                "value": float(self.theta[i]),
                "std": float(st[i]),
                "unit": PARAM_UNITS[n],
                "nominal": float(nom[i]) if i < 30 or i >= 36 else 0.0,
                "estimated": bool(self.free[i]),
            }
        for c in self.accepted:
            for k, v in self.effect_parameters(c).items():
                out[f"{c.key}:{k}"] = v
        return out

    # ------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict:
        fs = self.features_spec
        return {
            "method": self.method,
            "robot": spec_to_dict(fs.spec),
            "payload_com_m": np.asarray(fs.payload_com_m, float).tolist(),
            "payload_kg_default": float(fs.payload_kg_default),
            "thermal": {"source": fs.thermal_source, "ref": np.asarray(fs.thermal_ref).tolist()},
            "parameter_names": PARAM_NAMES,
            "theta": self.theta.tolist(),
            "base_ref": self.base_ref.tolist(),
            "effect_names": EFF_NAMES,
            "eff": self.eff.tolist(),
            "accepted": [c.to_list() for c in self.accepted],
            "free": self.free.tolist(),
            "cov": self.cov.tolist(),
            "nominal_tool_m": np.asarray(self.nominal_tool_m).tolist(),
            "residual": self.residual,
            "effects": {c.key: self.effect_parameters(c) for c in self.accepted},
            "info": self.info,
        }

    @classmethod
    def from_dict(cls, d: dict) -> AugmentedModel:
        from workcell.estimation.dh import free_mask

        if list(d.get("effect_names", EFF_NAMES)) != EFF_NAMES:
            raise ValueError("augmented model: effect layout differs from this build's library")
        fs = FeatureSpec(
            spec=spec_from_dict(d["robot"]),
            payload_com_m=np.asarray(d.get("payload_com_m", [0, 0, 0]), float),
            thermal_source=d.get("thermal", {}).get("source", "none"),
            thermal_ref=np.asarray(d.get("thermal", {}).get("ref", [0.0] * 6), float),
            payload_kg_default=float(d.get("payload_kg_default", 0.0)),
        )
        # what `export` states as the recording's conditions: checked here, not where it fails
        if fs.thermal_ref.shape != (6,) or not np.all(np.isfinite(fs.thermal_ref)):
            raise ValueError(f"thermal.ref must be 6 finite temperatures, got {fs.thermal_ref}")
        if not (np.isfinite(fs.payload_kg_default) and fs.payload_kg_default >= 0.0):
            raise ValueError(
                f"payload_kg_default must be a mass >= 0 kg, got {fs.payload_kg_default:g}"
            )
        if fs.payload_com_m.shape != (3,) or not np.all(np.isfinite(fs.payload_com_m)):
            raise ValueError(f"payload_com_m must be 3 finite numbers (m), got {fs.payload_com_m}")
        return cls(
            features_spec=fs,
            theta=np.asarray(d["theta"], float),
            base_ref=np.asarray(d["base_ref"], float),
            eff=np.asarray(d["eff"], float),
            accepted=[candidate_from_list(x) for x in d.get("accepted", [])],
            free=free_mask(d["free"], len(d["theta"])),
            cov=np.asarray(d["cov"], float),
            nominal_tool_m=np.asarray(d.get("nominal_tool_m", [0, 0, 0]), float),
            residual=d.get("residual"),
            info=d.get("info", {}),
        )

    @property
    def tool_m(self) -> np.ndarray:
        return self.theta[I_TOOL]


__all__ = [
    "AugmentedModel",
    "Candidate",
    "FeatureSpec",
    "EFF_NAMES",
    "EFF_UNITS",
    "GEOMETRIC_KINDS",
    "N_EFF",
    "PHYSICAL_KINDS",
    "SIGN_FIXED_KINDS",
    "candidate_from_list",
    "jac_aug",
    "library",
    "p_aug",
    "p_aug_single",
]
