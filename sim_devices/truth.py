"""The simulated "true" workcell: a robot whose real geometry differs from nominal and that carries
physical effects, plus a laser tracker with a realistic noise model.

Written independently of `workcell.estimation` and of `workcell.kinematics.chain`: its own forward
kinematics (elementary rotations/translations composed link by link), its own gravity model. It
imports only the nominal robot catalogue. Estimators must never import this module; tests may,
only to score.

Effects (each switchable, each with its own parameters, all SI):
- geometry: every DH parameter (a, d, alpha, theta zero offset) differs from nominal; base pose;
  SMR offset on the flange.
- joint_compliance: link-side angle = encoder + c_i * tau_i, tau_i the gravity + payload torque
  on joint i [rad/(N m)].
- link_deflection: links 2 and 3 bend as cantilevers under the perpendicular load of their own
  weight and everything they carry: tip shift = flex_m_per_n * W_perp, tip slope = 1.5 shift / L.
- transmission_error: dq_i = sum_k A_ik sin(k q_i + phi_ik) (gear eccentricity, ripple).
- backlash: dq_i = +- b_i / 2 depending on the direction the joint approached its target.
- thermal_drift: link lengths grow with alpha * dT; joint temperatures follow a warm-up curve
  T_i(t) = T_amb + dT_i (1 - exp(-t / tau)) that the joint temperature sensors show.
- tracker_scale: the tracker reports (1 + s) * p_true about its own origin.
- tracker_drift (outside the library, not in "all"): the tracker's stand settles, so every
  reading creeps by v * t (tracker frame, t the simulated time): a drift that follows time, not
  the arm, which no model of the arm can explain and a re-measured pose shows.

Inertia: the true link masses differ from the catalogue's by a few per cent (sigma 8 %) and their
centres of mass by about a centimetre (sigma 10 mm); the payload differs from what the operator
declares (`declared_payload_kg`, what the cell setup and the controller are told) by sigma 3 % in
mass and 3 mm in centre of mass. So the gravity torques the estimation computes from the
catalogue and the declaration are close to, not equal to, the ones that bend the simulated arm.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from workcell.kinematics.robots import RobotSpec, robot_by_name

G = 9.80665
EFFECT_KINDS = (
    "joint_compliance",
    "link_deflection",
    "transmission_error",
    "backlash",
    "thermal_drift",
    "tracker_scale",
)


# ----------------------------------------------------------------- elementary transforms
def _rot_z(t: float) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    M = np.eye(4)
    M[0, 0], M[0, 1], M[1, 0], M[1, 1] = c, -s, s, c
    return M


def _rot_x(t: float) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    M = np.eye(4)
    M[1, 1], M[1, 2], M[2, 1], M[2, 2] = c, -s, s, c
    return M


def _rot_y(t: float) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    M = np.eye(4)
    M[0, 0], M[0, 2], M[2, 0], M[2, 2] = c, s, -s, c
    return M


def _trans(x: float, y: float, z: float) -> np.ndarray:
    M = np.eye(4)
    M[:3, 3] = (x, y, z)
    return M


def _euler_zyx(yaw: float, pitch: float, roll: float) -> np.ndarray:
    return _rot_z(yaw) @ _rot_y(pitch) @ _rot_x(roll)


# ----------------------------------------------------------------- configuration
@dataclass
class TrackerNoise:
    """Tracker errors. MPE about +-(15 um + 6 um/m * range); typical error half the MPE.

    A reading's error = a per-pose systematic part (does not average out over readings at one
    pose) + a per-reading random part. Per-axis 1-sigma of the total = (a + b * range) / 4.
    """

    a_m: float = 15e-6
    b_m_per_m: float = 6e-6
    systematic_share: float = 0.8  # fraction of the sigma that is per pose (not averaging)
    beam_break_prob: float = 0.0
    outlier_prob: float = 0.0
    outlier_scale_m: float = 1e-3

    def sigma_axis(self, range_m: float) -> float:
        return (self.a_m + self.b_m_per_m * range_m) / 4.0

    def sigma_parts(self, range_m: float) -> tuple[float, float]:
        s = self.sigma_axis(range_m)
        sys_ = self.systematic_share * s
        rnd = np.sqrt(max(s**2 - sys_**2, 0.0))
        return sys_, rnd

    def sigma_of_mean(self, range_m: float, n_readings: int) -> float:
        """Per-axis 1-sigma of the error of a mean over n readings at one pose."""
        sys_, rnd = self.sigma_parts(range_m)
        return float(np.sqrt(sys_**2 + rnd**2 / max(n_readings, 1)))


@dataclass
class TrueWorkcell:
    """Ground truth of the simulated cell. Build with `make_truth`."""

    nominal: RobotSpec
    a: np.ndarray
    d: np.ndarray
    alpha: np.ndarray
    theta_offset: np.ndarray
    tracker_T_base: np.ndarray  # (4, 4)
    smr_flange_m: np.ndarray  # (3,)
    link_masses_kg: np.ndarray
    link_coms_m: np.ndarray
    payload_kg: float = 0.0  # true
    payload_com_m: np.ndarray = field(default_factory=lambda: np.zeros(3))  # true, flange frame
    declared_payload_kg: float = 0.0  # what the operator declares (cell setup, controller)
    declared_payload_com_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    effects: dict = field(default_factory=dict)
    beta: np.ndarray = field(default_factory=lambda: np.zeros(6))  # tilt about y_i of link i
    noise: TrackerNoise = field(default_factory=TrackerNoise)
    ambient_c: float = 21.0

    # ------------------------------------------------------------ temperatures and time
    def joint_temperatures_c(self, t_s: float) -> np.ndarray:
        th = self.effects.get("thermal_drift")
        if th is None:
            # joints still warm up; the effect on geometry is what is switched off
            dT = (
                np.array([6.0, 8.0, 7.0, 4.0, 4.0, 3.0])
                if len(self.a) == 6
                else np.full(len(self.a), 5.0)
            )
            tau = 1200.0
        else:
            dT, tau = np.asarray(th["warmup_k"], float), float(th["tau_s"])
        return self.ambient_c + dT * (1.0 - np.exp(-max(t_s, 0.0) / tau))

    # ------------------------------------------------------------ gravity (own model)
    def _frames(self, q_link: np.ndarray, a: np.ndarray, d: np.ndarray) -> list[np.ndarray]:
        Ts = [np.eye(4)]
        for i in range(len(a)):
            A = (
                _rot_z(q_link[i] + self.theta_offset[i])
                @ _trans(0.0, 0.0, d[i])
                @ _trans(a[i], 0.0, 0.0)
                @ _rot_x(self.alpha[i])
                @ _rot_y(self.beta[i])
            )
            Ts.append(Ts[-1] @ A)
        return Ts

    def gravity_torques(self, q: np.ndarray) -> np.ndarray:
        """Torque gravity applies about each joint axis (N m), positive towards increasing q."""
        n = len(self.a)
        Ts = self._frames(q, self.a, self.d)
        g = np.array([0.0, 0.0, -G])
        pts = [Ts[j + 1][:3, :3] @ self.link_coms_m[j] + Ts[j + 1][:3, 3] for j in range(n)]
        ms = list(self.link_masses_kg)
        pts.append(Ts[n][:3, :3] @ self.payload_com_m + Ts[n][:3, 3])
        ms.append(self.payload_kg)
        tau = np.zeros(n)
        for i in range(n):
            z, o = Ts[i][:3, 2], Ts[i][:3, 3]
            tot = np.zeros(3)
            for j in range(i, n + 1):
                tot += np.cross(pts[j] - o, ms[j] * g)
            tau[i] = tot @ z
        return tau

    # ------------------------------------------------------------ the physics
    def link_angles(self, q_enc: np.ndarray, approach_sign: np.ndarray) -> np.ndarray:
        """Link-side joint angles from encoder angles and the approach direction."""
        q = np.array(q_enc, dtype=float)
        e = self.effects
        dq = np.zeros(len(q))
        if "joint_compliance" in e:
            dq += np.asarray(e["joint_compliance"]["c_rad_per_nm"], float) * self.gravity_torques(q)
        if "transmission_error" in e:
            for j, harmonics in e["transmission_error"]["harmonics"].items():
                for k, amp, ph in harmonics:
                    dq[int(j)] += amp * np.sin(k * q[int(j)] + ph)
        if "backlash" in e:
            dq += 0.5 * np.asarray(e["backlash"]["b_rad"], float) * np.sign(approach_sign)
        return q + dq

    def smr_in_base(self, q_enc: np.ndarray, approach_sign: np.ndarray, t_s: float) -> np.ndarray:
        q = self.link_angles(q_enc, approach_sign)
        a, d = self.a.copy(), self.d.copy()
        th = self.effects.get("thermal_drift")
        if th is not None:
            temps = self.joint_temperatures_c(t_s)
            # link i spans joints i and i+1: its temperature is their mean
            t_link = np.append(0.5 * (temps[:-1] + temps[1:]), temps[-1])
            grow = 1.0 + float(th["alpha_per_k"]) * (t_link - self.ambient_c)
            a, d = a * grow, d * grow
        Ts = [np.eye(4)]
        defl = self.effects.get("link_deflection")
        g_base = np.array([0.0, 0.0, -G])
        for i in range(len(a)):
            A = (
                _rot_z(q[i] + self.theta_offset[i])
                @ _trans(0.0, 0.0, d[i])
                @ _trans(a[i], 0.0, 0.0)
            )
            T_end = Ts[-1] @ A  # end of link i before the twist
            if defl is not None and i in (1, 2):
                flex = float(defl["flex_m_per_n"][i - 1])
                # load carried by the link tip: half its own mass + all distal masses + payload
                m_load = 0.5 * self.link_masses_kg[i] + self.link_masses_kg[i + 1 :].sum()
                m_load += self.payload_kg
                g_link = T_end[:3, :3].T @ (m_load * g_base)  # in the link-end frame
                L = abs(a[i])
                w_perp = np.array([0.0, g_link[1], g_link[2]])  # perpendicular to the link (x)
                shift = flex * w_perp
                slope_y = -1.5 * shift[2] / L  # rotation about y bends towards z
                slope_z = 1.5 * shift[1] / L
                A = A @ _trans(*shift) @ _rot_y(slope_y) @ _rot_z(slope_z)
            Ts.append(Ts[-1] @ A @ _rot_x(self.alpha[i]) @ _rot_y(self.beta[i]))
        T_flange = Ts[-1]
        return T_flange[:3, :3] @ self.smr_flange_m + T_flange[:3, 3]

    def overturning_moment(self, q: np.ndarray) -> np.ndarray:
        """Moment gravity puts on the base about its origin (N m, base frame; horizontal)."""
        n = len(self.a)
        Ts = self._frames(q, self.a, self.d)
        g = np.array([0.0, 0.0, -G])
        m = np.zeros(3)
        for j in range(n):
            m += np.cross(Ts[j + 1][:3, :3] @ self.link_coms_m[j] + Ts[j + 1][:3, 3],
                          self.link_masses_kg[j] * g)  # fmt: skip
        p_pay = Ts[n][:3, :3] @ self.payload_com_m + Ts[n][:3, 3]
        return m + np.cross(p_pay, self.payload_kg * g)

    def pedestal_tilt(self, q: np.ndarray, p_b: np.ndarray) -> np.ndarray:
        """`pedestal_tilt` (outside the estimation library): the pedestal the arm stands on
        yields to the arm's overturning moment, turning the whole arm by k * M about a pivot
        `pivot_below_m` under the base origin (its foot)."""
        pt = self.effects["pedestal_tilt"]
        rotvec = float(pt["k_rad_per_nm"]) * self.overturning_moment(np.asarray(q, float))
        from scipy.spatial.transform import Rotation

        c = np.array([0.0, 0.0, -float(pt["pivot_below_m"])])
        return Rotation.from_rotvec(rotvec).apply(p_b - c) + c

    def smr_in_tracker(
        self, q_enc: np.ndarray, approach_sign: np.ndarray, t_s: float
    ) -> np.ndarray:
        """Noise-free SMR position as the tracker would report it (includes tracker scale)."""
        p_b = self.smr_in_base(q_enc, approach_sign, t_s)
        if "pedestal_tilt" in self.effects:
            p_b = self.pedestal_tilt(self.link_angles(q_enc, approach_sign), p_b)
        p = self.tracker_T_base[:3, :3] @ p_b + self.tracker_T_base[:3, 3]
        ts = self.effects.get("tracker_scale")
        if ts is not None:
            p = p * (1.0 + float(ts["scale"]))
        td = self.effects.get("tracker_drift")
        if td is not None:
            p = p + np.asarray(td["velocity_m_per_s"], float) * float(t_s)
        return p

    def session_nominal(self, rng: np.random.Generator, rough_base: bool = True) -> dict:
        """What the operator believes: nominal chain, nominal SMR, a rough base pose."""
        T = self.tracker_T_base.copy()
        if rough_base:
            ang = rng.normal(0, np.deg2rad(2.0), 3)
            T = T @ _euler_zyx(*ang)
            T[:3, 3] += rng.normal(0, 0.02, 3)
        from scipy.spatial.transform import Rotation

        x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
        return {"translation_m": T[:3, 3].tolist(), "quaternion_wxyz": [w, x, y, z]}


# ----------------------------------------------------------------- factories
DEFAULT_MAGNITUDES = {
    "joint_compliance": {"c_rad_per_nm": [3e-6, 6e-6, 6e-6, 1e-5, 1e-5, 1e-5]},
    "link_deflection": {"flex_m_per_n": [3.0e-7, 2.5e-7]},
    "transmission_error": {
        "harmonics": {1: [(1, 30e-6, 0.4), (2, 15e-6, 1.1)], 2: [(1, 25e-6, -0.7), (2, 10e-6, 2.0)]}
    },
    "backlash": {"b_rad": [40e-6, 60e-6, 60e-6, 40e-6, 40e-6, 40e-6]},
    "thermal_drift": {
        "alpha_per_k": 23e-6,
        "warmup_k": [6.0, 8.0, 7.0, 4.0, 4.0, 3.0],
        "tau_s": 1200.0,
    },
    "tracker_scale": {"scale": 15e-6},
    # outside the library (not in "all"): about 60 urad under the UR5e's largest moment
    "pedestal_tilt": {"k_rad_per_nm": 1e-6, "pivot_below_m": 0.5},
    # outside the library: a settling tripod, about 1.4 um a minute (80 um an hour)
    "tracker_drift": {"velocity_m_per_s": [1.0e-8, -0.5e-8, -2.0e-8]},
}

REALISTIC = ("joint_compliance", "transmission_error", "backlash", "thermal_drift")
# Effects whose form no candidate of the estimation library has (`workcell diagnose` must not
# name them; the test is what it says instead). Not part of "all", which is every library form.
OUT_OF_LIBRARY = ("pedestal_tilt", "tracker_drift")


def parse_effects(spec: str | None) -> dict:
    """`none`, `dh` (geometry only), `realistic`, `all`, or a comma list of effect kinds."""
    if spec is None or spec.strip() in ("", "none", "dh", "geometry"):
        return {}
    s = spec.strip()
    kinds = {"realistic": REALISTIC, "all": EFFECT_KINDS}.get(s)
    if kinds is None:
        kinds = tuple(k.strip() for k in s.split(",") if k.strip())
    out = {}
    for k in kinds:
        if k in ("none", "dh", "geometry", "realistic", "all"):
            raise ValueError(
                f"effect set {k!r} cannot be combined with others in a comma list; give it alone, "
                f"or a list of effect kinds ({', '.join(EFFECT_KINDS + OUT_OF_LIBRARY)})"
            )
        if k not in DEFAULT_MAGNITUDES:
            raise ValueError(
                f"unknown effect {k!r}; known: none, realistic, all, "
                f"{', '.join(EFFECT_KINDS + OUT_OF_LIBRARY)}"
            )
        out[k] = copy.deepcopy(DEFAULT_MAGNITUDES[k])
    return out


def _random_base_pose(rng: np.random.Generator) -> np.ndarray:
    """tracker_T_base: the base 1.8-2.6 m from the tracker at a random yaw, not quite level."""
    yaw = rng.uniform(-np.pi, np.pi)
    T = _trans(*rng.uniform([1.8, -1.0, -0.6], [2.6, 1.0, 0.0])) @ _euler_zyx(yaw, 0.0, 0.0)
    return T @ _euler_zyx(*rng.normal(0, 0.003, 3))  # base not perfectly level


def _inertia(spec: RobotSpec, payload_kg: float, payload_com_m: np.ndarray, seed: int) -> dict:
    """True link and payload inertia near the catalogue and the declaration (module docstring).
    Its own random stream, so the geometry a seed draws does not depend on it."""
    rng = np.random.default_rng([seed, 0x1E4])
    n = len(spec.link_masses_kg)
    return {
        "link_masses_kg": spec.link_masses_kg * np.clip(1.0 + rng.normal(0, 0.08, n), 0.7, 1.3),
        "link_coms_m": spec.link_coms_m + rng.normal(0, 0.01, (n, 3)),
        "payload_kg": float(payload_kg * (1.0 + rng.normal(0, 0.03))),
        "payload_com_m": payload_com_m + rng.normal(0, 0.003, 3),
        "declared_payload_kg": float(payload_kg),
        "declared_payload_com_m": payload_com_m.copy(),
    }


def make_truth(
    robot: str | RobotSpec = "ur5e",
    effects: dict | str | None = "realistic",
    seed: int = 0,
    *,
    dh_error_scale: float = 1.0,
    payload_kg: float = 0.5,
    noise: TrackerNoise | None = None,
) -> TrueWorkcell:
    """A random true cell: DH errors (sigma 0.3 mm, 0.5 mrad), base ~2.5 m from the tracker."""
    spec = robot_by_name(robot) if isinstance(robot, str) else robot
    rng = np.random.default_rng(seed)
    s = dh_error_scale
    eff = parse_effects(effects) if (effects is None or isinstance(effects, str)) else effects
    T = _random_base_pose(rng)
    return TrueWorkcell(
        nominal=spec,
        a=spec.dh.a + s * rng.normal(0, 3e-4, 6),
        d=spec.dh.d + s * rng.normal(0, 3e-4, 6),
        alpha=spec.dh.alpha + s * rng.normal(0, 5e-4, 6),
        theta_offset=spec.dh.theta_offset + s * rng.normal(0, 1e-3, 6),
        tracker_T_base=T,
        smr_flange_m=np.array([0.0, 0.0, 0.06]) + s * rng.normal(0, 3e-4, 3),
        **_inertia(spec, payload_kg, np.array([0.0, 0.0, 0.03]), seed),
        effects=eff,
        beta=np.array([0.0, 1.0, 1.0, 0.0, 0.0, 0.0]) * s * rng.normal(0, 3e-4, 6),
        noise=noise or TrackerNoise(beam_break_prob=0.01, outlier_prob=0.005),
    )


NOMINAL_SMR_M = np.array([0.0, 0.0, 0.06])

# Seed 002 (Das, Touma & Burdick), section V-A: the DH errors set in their WAM simulation.
# delta theta = [0 ... 0 1.3] rad, delta alpha = [0 0.4 0 ...] rad, delta a = [0 0 0.01 0 ...] m,
# delta d = [0 0 0.15 0 ...] m.
WAM_SMR_M = np.array([0.05, 0.0, 0.06])  # nominal SMR in the WAM's flange frame
PAPER_WAM_ERRORS = {
    "theta_offset": {6: 1.3},
    "alpha": {1: 0.4},
    "a": {2: 0.01},
    "d": {2: 0.15},
}


def make_paper_wam_truth(
    seed: int = 0, *, small_errors: bool = False, noise: TrackerNoise | None = None
) -> TrueWorkcell:
    """The paper's simulated setting on our tracker: a 7-joint WAM-like arm whose DH parameters
    carry seed 002's four errors (`PAPER_WAM_ERRORS`), everything else nominal unless
    `small_errors` (then also the UR cell's small random DH errors: sigma 0.3 mm, 0.5 mrad,
    1 mrad). The base stands 1.8-2.6 m from the tracker at a random yaw (as in `make_truth`);
    the SMR sits on a bracket off the flange axis (`WAM_SMR_M`, like the paper's scoop), so the
    joint-7 offset error moves it, with a small random offset error. No physical effects; the
    tracker measures position only (the paper's camera measured full pose)."""
    from workcell.kinematics.robots import WAM7

    spec = WAM7
    n = spec.n_joints
    rng = np.random.default_rng(seed)
    T = _random_base_pose(rng)
    s = 1.0 if small_errors else 0.0
    dh = {
        "a": spec.dh.a + s * rng.normal(0, 3e-4, n),
        "d": spec.dh.d + s * rng.normal(0, 3e-4, n),
        "alpha": spec.dh.alpha + s * rng.normal(0, 5e-4, n),
        "theta_offset": spec.dh.theta_offset + s * rng.normal(0, 1e-3, n),
    }
    for name, errs in PAPER_WAM_ERRORS.items():
        for j, v in errs.items():
            dh[name][j] += v
    return TrueWorkcell(
        nominal=spec,
        a=dh["a"],
        d=dh["d"],
        alpha=dh["alpha"],
        theta_offset=dh["theta_offset"],
        tracker_T_base=T,
        smr_flange_m=WAM_SMR_M + rng.normal(0, 3e-4, 3),
        link_masses_kg=spec.link_masses_kg.copy(),
        link_coms_m=spec.link_coms_m.copy(),
        payload_kg=0.0,
        effects={},
        beta=np.zeros(n),
        noise=noise or TrackerNoise(beam_break_prob=0.0, outlier_prob=0.0),
    )
