"""Robot catalogue: nominal standard-DH chains with joint limits and link inertial data.

Standard DH, joint i: A_i = Rz(q_i + theta_offset_i) Tz(d_i) Tx(a_i) Rx(alpha_i).
Link centres of mass are expressed in the link's own DH frame i (the frame at the end of link i),
as Universal Robots publish them. All values SI.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

PI = np.pi


@dataclass(frozen=True)
class DH:
    """Standard DH parameters of an n-joint serial chain, each an array of shape (n,).

    The catalogue's arms have 6 joints; the design bench also builds a 7-joint WAM-like arm."""

    a: np.ndarray
    d: np.ndarray
    alpha: np.ndarray
    theta_offset: np.ndarray

    def __post_init__(self) -> None:
        n = np.shape(self.a)
        if len(n) != 1 or n[0] < 1:
            raise ValueError(f"DH.a: expected one value per joint, got shape {n}")
        for name in ("a", "d", "alpha", "theta_offset"):
            try:
                v = np.asarray(getattr(self, name), dtype=float)
            except (TypeError, ValueError):
                raise ValueError(
                    f"DH.{name}: expected numbers, got {getattr(self, name)!r}"
                ) from None
            if v.shape != n:
                raise ValueError(f"DH.{name}: expected {n[0]} values, got shape {v.shape}")
            if not np.all(np.isfinite(v)):
                raise ValueError(f"DH.{name}: non-finite value in {v.tolist()}")
            object.__setattr__(self, name, v)

    def to_dict(self) -> dict:
        return {k: getattr(self, k).tolist() for k in ("a", "d", "alpha", "theta_offset")}

    @property
    def n_joints(self) -> int:
        return len(self.a)

    @classmethod
    def from_dict(cls, d: dict) -> DH:
        try:
            return cls(
                a=d["a"],
                d=d["d"],
                alpha=d["alpha"],
                theta_offset=d.get("theta_offset", [0.0] * len(d["a"])),
            )
        except KeyError as e:
            raise ValueError(f"DH parameters: missing field {e.args[0]!r}") from None


# no revolute joint of a serial arm turns more than two turns each way (UR: +-2 pi)
JOINT_LIMIT_MAX_RAD = 4 * PI + 1e-6


@dataclass(frozen=True)
class RobotSpec:
    """An n-joint arm (n = 6 for the catalogue): nominal geometry, limits and inertial data used
    for gravity torques."""

    model: str
    dh: DH
    joint_limits_rad: np.ndarray  # (n, 2)
    link_masses_kg: np.ndarray  # (n,)
    link_coms_m: np.ndarray  # (n, 3), in DH frame i
    max_joint_speed_rad_s: np.ndarray | None = None  # (n,), default pi rad/s
    max_torque_nm: np.ndarray | None = None  # (n,), default 150 N m
    max_payload_kg: float = 5.0

    def __post_init__(self) -> None:
        n = self.dh.n_joints
        lim = np.asarray(self.joint_limits_rad, dtype=float)
        if lim.shape != (n, 2):
            raise ValueError(
                f"joint_limits_rad: expected {n} [lo, hi] pairs, got shape {lim.shape}"
            )
        if not np.all(np.isfinite(lim)):
            raise ValueError("joint_limits_rad: every limit must be a finite number (radians)")
        if np.any(lim[:, 0] >= lim[:, 1]):
            j = int(np.argmax(lim[:, 0] >= lim[:, 1]))
            raise ValueError(
                f"joint_limits_rad: joint {j + 1}'s pair is [{lim[j, 0]:.4g}, {lim[j, 1]:.4g}]; "
                "write [lo, hi] with lo < hi"
            )
        if np.max(np.abs(lim)) > JOINT_LIMIT_MAX_RAD:
            hint = (
                "it looks like degrees; the format wants radians"
                if np.max(np.abs(lim)) <= 1080.0
                else "not an angle in radians"
            )
            raise ValueError(
                f"joint_limits_rad: a limit of {np.max(np.abs(lim)):.4g} is beyond two turns "
                f"({JOINT_LIMIT_MAX_RAD:.4g} rad): {hint}"
            )
        object.__setattr__(self, "joint_limits_rad", lim)
        if self.max_joint_speed_rad_s is None:
            object.__setattr__(self, "max_joint_speed_rad_s", np.full(n, PI))
        if self.max_torque_nm is None:
            object.__setattr__(self, "max_torque_nm", np.full(n, 150.0))
        for name, shape in (("link_masses_kg", (n,)), ("link_coms_m", (n, 3))):
            v = np.asarray(getattr(self, name), dtype=float)
            if v.shape != shape:
                raise ValueError(f"{name}: expected shape {shape}, got {v.shape}")
            object.__setattr__(self, name, v)
        object.__setattr__(
            self, "max_joint_speed_rad_s", np.asarray(self.max_joint_speed_rad_s, dtype=float)
        )
        object.__setattr__(self, "max_torque_nm", np.asarray(self.max_torque_nm, dtype=float))

    @property
    def n_joints(self) -> int:
        return self.dh.n_joints

    def with_dh(self, dh: DH) -> RobotSpec:
        return replace(self, dh=dh)


_LIM_UR = np.array([[-2 * PI, 2 * PI]] * 2 + [[-PI, PI]] + [[-2 * PI, 2 * PI]] * 3)

UR5E = RobotSpec(
    model="ur5e",
    dh=DH(
        a=[0.0, -0.425, -0.3922, 0.0, 0.0, 0.0],
        d=[0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996],
        alpha=[PI / 2, 0.0, 0.0, PI / 2, -PI / 2, 0.0],
        theta_offset=[0.0] * 6,
    ),
    joint_limits_rad=_LIM_UR,
    link_masses_kg=[3.761, 8.058, 2.846, 1.37, 1.3, 0.365],
    link_coms_m=[
        [0.0, -0.02561, 0.00193],
        [0.2125, 0.0, 0.11336],
        [0.15, 0.0, 0.0265],
        [0.0, -0.0018, 0.01634],
        [0.0, 0.0018, 0.01634],
        [0.0, 0.0, -0.001159],
    ],
    max_joint_speed_rad_s=np.full(6, PI),
    max_torque_nm=[150.0, 150.0, 150.0, 28.0, 28.0, 28.0],
    max_payload_kg=5.0,
)

UR10 = RobotSpec(
    model="ur10",
    dh=DH(
        a=[0.0, -0.612, -0.5723, 0.0, 0.0, 0.0],
        d=[0.1273, 0.0, 0.0, 0.163941, 0.1157, 0.0922],
        alpha=[PI / 2, 0.0, 0.0, PI / 2, -PI / 2, 0.0],
        theta_offset=[0.0] * 6,
    ),
    joint_limits_rad=_LIM_UR,
    link_masses_kg=[7.1, 12.7, 4.27, 2.0, 2.0, 0.365],
    link_coms_m=[
        [0.021, 0.0, 0.027],
        [0.38, 0.0, 0.158],
        [0.24, 0.0, 0.068],
        [0.0, 0.007, 0.018],
        [0.0, 0.007, 0.018],
        [0.0, 0.0, -0.026],
    ],
    max_joint_speed_rad_s=[2 * PI / 3, 2 * PI / 3, PI, PI, PI, PI],
    max_torque_nm=[330.0, 330.0, 150.0, 54.0, 54.0, 54.0],
    max_payload_kg=10.0,
)

CATALOGUE: dict[str, RobotSpec] = {"ur5e": UR5E, "ur10": UR10}

# A 7-joint Barrett-WAM-like arm, the setting of seed 002's simulation (Das, Touma & Burdick,
# section V-A). Standard DH as Barrett publishes it (shoulder centre at the base origin); joint
# limits from Barrett's WAM data sheet. Not in the catalogue: no simulated controller or driver
# speaks for it. Used by `workcell bench design --robot wam7` only. No inertial data (the bench's
# cell has no gravity effects).
WAM7 = RobotSpec(
    model="wam7",
    dh=DH(
        a=[0.0, 0.0, 0.045, -0.045, 0.0, 0.0, 0.0],
        d=[0.0, 0.0, 0.55, 0.0, 0.3, 0.0, 0.06],
        alpha=[-PI / 2, PI / 2, -PI / 2, PI / 2, -PI / 2, PI / 2, 0.0],
        theta_offset=[0.0] * 7,
    ),
    joint_limits_rad=np.array(
        [
            [-2.6, 2.6],
            [-2.0, 2.0],
            [-2.8, 2.8],
            [-0.9, 3.1],
            [-4.76, 1.24],
            [-1.6, 1.6],
            [-3.0, 3.0],
        ]
    ),
    link_masses_kg=np.zeros(7),
    link_coms_m=np.zeros((7, 3)),
    max_payload_kg=3.0,
)


CHAIN_TOL_M = 0.02  # a controller's own calibration moves a nominal length by mm, not cm


def catalogue_mismatch(name: object, a_m: Sequence[float], d_m: Sequence[float]) -> str | None:
    """When `name` is a catalogue arm whose link lengths the chain (a, d) is not, within
    CHAIN_TOL_M: what differs, e.g. "a2 is 0.425 m, a ur10's 0.612 m (it is a ur5e's)"; None
    when it is that arm's, or `name` is no catalogue arm."""
    spec = CATALOGUE.get(name.strip().lower()) if isinstance(name, str) else None
    if spec is None:
        return None
    lengths = np.r_[np.asarray(a_m, float), np.asarray(d_m, float)]
    want = np.r_[spec.dh.a, spec.dh.d]
    if lengths.shape != want.shape:
        return None
    j = int(np.argmax(np.abs(lengths - want)))
    if abs(lengths[j] - want[j]) <= CHAIN_TOL_M:
        return None
    other = [
        k
        for k, sp in CATALOGUE.items()
        if np.allclose(lengths, np.r_[sp.dh.a, sp.dh.d], rtol=0, atol=CHAIN_TOL_M)
    ]
    is_ = f" (it is a {other[0]}'s)" if other else ""
    return f"{'ad'[j // 6]}{j % 6 + 1} is {lengths[j]:.4g} m, a {name}'s {want[j]:.4g} m{is_}"


def robot_by_name(name: str) -> RobotSpec:
    key = name.strip().lower()
    if key not in CATALOGUE:
        raise ValueError(f"unknown robot {name!r}; known: {', '.join(sorted(CATALOGUE))}")
    return CATALOGUE[key]


def robot_from_session(robot: dict) -> RobotSpec:
    """Build the nominal chain a recording's session message declares.

    The DH chain in the session wins over the catalogue (it is what the controller believes);
    inertial data comes from the catalogue when the model is known, else gravity torques are
    unavailable (masses zero) and the caller is told through `has_inertia`.
    """
    model = str(robot.get("model", "unknown"))
    if "dh" not in robot:
        return robot_by_name(model)
    raw = robot["dh"]
    for name in ("a", "d", "alpha", "theta_offset"):
        v = raw.get(name, [0.0] * 6) if isinstance(raw, dict) else None
        if np.shape(v) != (6,):
            raise ValueError(
                f"DH.{name}: expected 6 values (recordings describe 6-joint arms), "
                f"got shape {np.shape(v)}"
            )
    dh = DH.from_dict(raw)
    base = CATALOGUE.get(model.strip().lower())
    lim = robot.get("joint_limits_rad")
    try:
        lim = np.asarray(lim, dtype=float) if lim is not None else _LIM_UR
    except (TypeError, ValueError):
        raise ValueError("joint_limits_rad: expected 6 [lo, hi] pairs in radians") from None
    if base is not None:
        return replace(base, dh=dh, joint_limits_rad=lim)
    return RobotSpec(
        model=model,
        dh=dh,
        joint_limits_rad=lim,
        link_masses_kg=np.zeros(6),
        link_coms_m=np.zeros((6, 3)),
    )


def has_inertia(spec: RobotSpec) -> bool:
    return bool(np.any(spec.link_masses_kg > 0))
