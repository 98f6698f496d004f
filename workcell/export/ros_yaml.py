"""The geometric part of a calibrated model as the UR ROS drivers' calibration YAML.

Convention (the one `ur_calibration` writes and `ur_description` reads; see
Universal_Robots_ROS2_Driver ur_calibration/src/calibration.cpp and
Universal_Robots_ROS2_Description config/<type>/default_kinematics.yaml):
- each DH link i splits into seg1_i = Rz(theta_i) Tz(d_i) and seg2_i = Tx(a_i) Rx(alpha_i);
- the six YAML frames are shoulder = seg1_1, upper_arm = seg2_1 seg1_2, forearm = seg2_2 seg1_3,
  wrist_1 = seg2_3 seg1_4, wrist_2 = seg2_4 seg1_5, wrist_3 = seg2_5 seg1_6; the last seg2_6
  (a6, alpha6) is not written;
- the description composes base_link_inertia -> [frame_i (x, y, z, rpy), then Rz(q_i)] for the
  six joints, then wrist_3 -> flange -> tool0 (fixed rpy (0,-pi/2,-pi/2) and (pi/2,0,pi/2), whose
  product is the identity). URDF rpy means R = Rz(yaw) Ry(pitch) Rx(roll).
- base_link_inertia is the frame the controller's kinematics work in (ROS `base_link` is it
  turned by pi about z); here it is the model's `base_ref` (see `workcell.export.frame`).

What this export adds and what it cannot carry:
- Hayati tilts beta_i (Ry after Rx(alpha_i)) go into seg2_i, hence into the next frame: carried.
- The calibrated base offset (relative to the registered nominal base) goes into `shoulder`:
  carried. The base is the model's registered base (the frame of the correction table).
- a6, alpha6, beta6 (seg2_6) cannot be written in the six frames; with the SMR offset they form
  the TCP (`tcp_in_tool0` in the header comment), which reproduces the SMR exactly.
- Anything non-geometric (compliance, backlash, thermal, data-driven residuals of lddmm/gp models)
  cannot be carried: use the correction table or URScript export for those. The header states
  its size: RMS and max of the model's prediction minus its geometric part's over the poses of
  the recording the model was fitted on, at their recorded conditions (the YAML has no volume:
  the export takes no --volume).
- A TCP farther than `TCP_MAX_M` from the flange, or a link length beyond `DH_LENGTH_MAX_M`,
  is a model in the wrong unit (millimetres): refused, not written for a controller.
- Euler angles: ur_calibration writes Eigen's eulerAngles(0, 1, 2) (R = Rx Ry Rz) as roll, pitch,
  yaw. That agrees with URDF rpy only when the rotation is about one axis (all nominal frames); we
  keep its numbers where they are a valid URDF rpy (so the nominal file matches the published one)
  and write the URDF-correct rpy elsewhere.
"""

from __future__ import annotations

import hashlib
import math
import re
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from workcell.atomic import write_text
from workcell.errors import UserError
from workcell.export.frame import base_correction, base_correction_line, base_ref_line
from workcell.recording.checks import SMR_OFFSET_MAX_M as TCP_MAX_M  # the recordings' limit

if TYPE_CHECKING:
    import os

    from workcell.estimation.models import FittedModel

LINKS = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")
KEYS = ("x", "y", "z", "roll", "pitch", "yaw")


def _rz(t: float) -> np.ndarray:
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rx(t: float) -> np.ndarray:
    c, s = math.cos(t), math.sin(t)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(t: float) -> np.ndarray:
    c, s = math.cos(t), math.sin(t)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _T(R: np.ndarray, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t
    return M


def _axis_angle(t: float, axis: int) -> np.ndarray:
    """Rotation matrix as Eigen's AngleAxis::toRotationMatrix computes it (same rounding)."""
    u = np.zeros(3)
    u[axis] = 1.0
    s, c = math.sin(t), math.cos(t)
    sa, ca = s * u, (1.0 - c) * u
    R = np.empty((3, 3))
    R[0, 1] = ca[0] * u[1] - sa[2]
    R[1, 0] = ca[0] * u[1] + sa[2]
    R[0, 2] = ca[0] * u[2] + sa[1]
    R[2, 0] = ca[0] * u[2] - sa[1]
    R[1, 2] = ca[1] * u[2] - sa[0]
    R[2, 1] = ca[1] * u[2] + sa[0]
    for i in range(3):
        R[i, i] = ca[i] * u[i] + c
    return R


def segments(theta: np.ndarray, base_T: np.ndarray | None = None) -> list[np.ndarray]:
    """The seven simplified-chain transforms (4x4): six YAML frames and the unwritten seg2_6."""
    th = np.asarray(theta, float)
    a, d, al, off, be = th[0:6], th[6:12], th[12:18], th[18:24], th[24:30]
    seg1 = [_T(_axis_angle(off[i], 2), (0.0, 0.0, d[i])) for i in range(6)]
    seg2 = []
    for i in range(6):
        R = _axis_angle(al[i], 0)
        if be[i] != 0.0:
            R = R @ _ry(be[i])
        seg2.append(_T(R, (a[i], 0.0, 0.0)))
    out = [seg1[0] if base_T is None else np.asarray(base_T, float) @ seg1[0]]
    out += [seg2[i] @ seg1[i + 1] for i in range(5)]
    out.append(seg2[5])
    return out


def eigen_euler_xyz(R: np.ndarray) -> np.ndarray:
    """Eigen's MatrixBase::eulerAngles(0, 1, 2): R = Rx(a) Ry(b) Rz(c), a in [0, pi]."""
    i, j, k = 0, 1, 2
    res = np.zeros(3)
    res[0] = math.atan2(R[j, k], R[k, k])
    c2 = math.hypot(R[i, i], R[i, j])
    if res[0] > 0.0:  # (!odd && res0 > 0) branch
        res[0] -= math.pi
        res[1] = math.atan2(-R[i, k], -c2)
    else:
        res[1] = math.atan2(-R[i, k], c2)
    s1, c1 = math.sin(res[0]), math.cos(res[0])
    res[2] = math.atan2(s1 * R[k, i] - c1 * R[j, i], c1 * R[j, j] - s1 * R[k, j])
    return -res


def rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """URDF rpy: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    return _rz(yaw) @ _ry(pitch) @ _rx(roll)


def urdf_rpy(R: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) with rpy_matrix(...) == R; ur_calibration's numbers where valid."""
    r, p, y = eigen_euler_xyz(R)
    if np.max(np.abs(rpy_matrix(r, p, y) - R)) < 1e-12:
        return float(r), float(p), float(y)
    p = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    r = math.atan2(R[2, 1], R[2, 2])
    y = math.atan2(R[1, 0], R[0, 0])
    return r, p, y


def ros_kinematics(theta: np.ndarray, base_T: np.ndarray | None = None) -> dict:
    """{link: {x, y, z, roll, pitch, yaw}} for a parameter vector (39,) (DH part used)."""
    segs = segments(theta, base_T)
    out = {}
    for name, S in zip(LINKS, segs[:6], strict=True):
        r, p, y = urdf_rpy(S[:3, :3])
        out[name] = {"x": S[0, 3], "y": S[1, 3], "z": S[2, 3], "roll": r, "pitch": p, "yaw": y}
    return {k: {kk: float(vv) for kk, vv in v.items()} for k, v in out.items()}


# wrist_3_link -> flange -> tool0 as fixed in ur_description (their product is the identity)
WRIST3_T_TOOL0 = _T(rpy_matrix(0.0, -math.pi / 2, -math.pi / 2)) @ _T(
    rpy_matrix(math.pi / 2, 0.0, math.pi / 2)
)


def fk_tool0(kin: dict, q: np.ndarray) -> np.ndarray:
    """tool0 poses (N, 4, 4) in base_link_inertia, as the ROS description composes them."""
    q = np.atleast_2d(np.asarray(q, float))
    F = [
        _T(
            rpy_matrix(kin[n]["roll"], kin[n]["pitch"], kin[n]["yaw"]),
            (kin[n]["x"], kin[n]["y"], kin[n]["z"]),
        )
        for n in LINKS
    ]
    out = np.empty((len(q), 4, 4))
    for m, qq in enumerate(q):
        T = np.eye(4)
        for i in range(6):
            T = T @ F[i] @ _T(_rz(qq[i]))
        out[m] = T @ WRIST3_T_TOOL0
    return out


def _fmt(x: float) -> str:
    if x == 0.0:
        return "0"
    return repr(float(x))


def to_yaml(
    kin: dict,
    *,
    comments: list[str] | None = None,
    hash_: str | None = None,
    std: dict | None = None,
    fixed: dict | None = None,
) -> str:
    """The calibration YAML; `std` ({link: {key: 1-sigma}}) goes beside each value as a comment,
    which every YAML reader ignores (the drivers read the values only); a value in `fixed`
    ({link: {key: [parameter names]}}, `fixed_values`) is marked not estimated instead."""
    if hash_ is None:
        h = hashlib.sha256(repr([[kin[n][k] for k in KEYS] for n in LINKS]).encode()).digest()
        hash_ = f"calib_{int.from_bytes(h[:8], 'big')}"
    lines = [f"# {' '.join(str(c).split())}" for c in (comments or [])]  # one line each
    lines.append("kinematics:")
    for n in LINKS:
        lines.append(f"  {n}:")
        for k in KEYS:
            line = f"    {k}: {_fmt(kin[n][k])}"
            held = (fixed or {}).get(n, {}).get(k)
            if held is not None:
                why = ", ".join(_held_how(x) for x in held) or "no parameter moves it"
                line = f"{line:<33} # fixed, not estimated ({why})"
            elif std is not None:
                unit = "m" if k in "xyz" else "rad"
                line = f"{line:<33} # +- {std[n][k]:.2g} {unit}"
            lines.append(line)
    lines.append(f"  hash: {hash_}")
    return "\n".join(lines) + "\n"


def read_ros_yaml(text: str) -> dict:
    """Parse the calibration YAML shape above (enough for tests and round trips)."""
    kin: dict = {}
    cur = None
    seen_root = False
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].rstrip()
        if not line.strip():
            continue
        if line == "kinematics:":
            seen_root = True
            continue
        m2 = re.match(r"^  (\w+):\s*(\S*)$", line)
        m4 = re.match(r"^    (\w+):\s*(\S+)$", line)
        if m2 and seen_root:
            if m2[2]:
                kin[m2[1]] = m2[2]
                cur = None
            else:
                cur = kin.setdefault(m2[1], {})
        elif m4 and cur is not None:
            cur[m4[1]] = float(m4[2])
        else:
            raise ValueError(f"line {n}: unexpected {raw!r}")
    for name in LINKS:
        if name not in kin or set(kin[name]) != set(KEYS):
            raise ValueError(f"calibration YAML: link {name!r} missing or incomplete")
    return kin


def _geometric_part(model) -> tuple[object, str | None]:
    """(the object holding the model's geometry (`theta`, `base_ref`), the attribute it is
    under, None for the model itself); refuses models without one."""
    for attr in (None, "base", "base_model", "dh_model", "geometric"):
        m = model if attr is None else getattr(model, attr, None)
        if m is not None and hasattr(m, "theta") and hasattr(m, "base_ref"):
            return m, attr
    raise UserError(
        f"model {getattr(model, 'method', '?')!r} has no geometric (DH) part to write as ROS "
        "calibration YAML; use --format table or urscript"
    )


def model_geometry(model: FittedModel) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """(theta (39,), base offset (4x4, registered base -> calibrated base), base_ref, note) of the
    geometric part of a model; refuses models without one."""
    from workcell.kinematics.chain import tracker_T_base

    m, attr = _geometric_part(model)
    th = np.asarray(m.theta, float)
    base_ref = np.asarray(m.base_ref, float)
    B = np.linalg.solve(base_ref, np.asarray(tracker_T_base(th, base_ref)))
    note = "" if attr is None else f"geometric part ({attr}) of a {model.method} model"
    return th, B, base_ref, note


def _flat(kin: dict) -> np.ndarray:
    return np.array([kin[n][k] for n in LINKS for k in KEYS], float)


def kinematics_std(model: FittedModel, step: float = 1e-7) -> dict | None:
    """1-sigma of every YAML value ({link: {key: std}}), the geometric part's parameter
    covariance propagated to first order (central differences, angles wrapped); None when the
    model carries no covariance."""
    th, _, base_ref, _ = model_geometry(model)
    cov = _geometry_cov(model, th)
    if cov is None:
        return None
    J = _yaml_jacobian(th, base_ref, np.flatnonzero(np.diag(cov) > 0), step)
    sd = np.sqrt(np.clip(np.einsum("ij,jk,ik->i", J, cov, J), 0.0, None))
    it = iter(sd)
    return {n: {k: float(next(it)) for k in KEYS} for n in LINKS}


def _geometry_cov(model, th: np.ndarray) -> np.ndarray | None:
    """The geometric part's parameter covariance (len(th), len(th)), or None."""
    from workcell.estimation.models import geometric_cov, geometric_part

    g = geometric_part(model)
    c = None if g is None else geometric_cov(g)
    return c if c is not None and c.shape == (len(th), len(th)) else None


def tcp_in_tool0(th: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The SMR in tool0 (4x4): segment 6 then the tool offset (incl. a6/alpha6/beta6)."""
    return segments(th, B)[6] @ _T(np.eye(3), th[36:39])


def tcp_std_m(
    model: FittedModel, th: np.ndarray, B: np.ndarray, step: float = 1e-7
) -> np.ndarray | None:
    """1-sigma (3,) of tcp_in_tool0's translation, the parameter covariance propagated to first
    order (central differences); None without a covariance."""
    cov = _geometry_cov(model, th)
    if cov is None:
        return None
    J = np.zeros((3, len(th)))
    for j in np.flatnonzero(np.diag(cov) > 0):
        d = np.zeros(len(th))
        d[j] = step
        J[:, j] = (tcp_in_tool0(th + d, B)[:3, 3] - tcp_in_tool0(th - d, B)[:3, 3]) / (2 * step)
    return np.sqrt(np.clip(np.einsum("ij,jk,ik->i", J, cov, J), 0.0, None))


def _yaml_jacobian(th: np.ndarray, base_ref: np.ndarray, cols, step: float = 1e-7) -> np.ndarray:
    """d(YAML values, `_flat` order) / d(theta[cols]) (36, len(theta)), zero in the other
    columns: central differences, angles wrapped."""
    from workcell.kinematics.chain import tracker_T_base

    def f(t):
        B = np.linalg.solve(base_ref, np.asarray(tracker_T_base(t, base_ref)))
        return _flat(ros_kinematics(t, B))

    J = np.zeros((len(LINKS) * len(KEYS), len(th)))
    ang = np.tile([False, False, False, True, True, True], len(LINKS))
    for i in cols:
        e = np.zeros(len(th))
        e[i] = step
        d = f(th + e) - f(th - e)
        d[ang] = (d[ang] + np.pi) % (2 * np.pi) - np.pi
        J[:, i] = d / (2 * step)
    return J


def _estimated_mask(g, n: int) -> np.ndarray | None:
    """Which of the n geometric parameters the model estimated: its `free` mask (dh, augmented
    and the dh base of lddmm/gp), else those with a variance in its covariance (ekf-ann); None
    when it says neither."""
    free = getattr(g, "free", None)
    if free is not None and np.shape(free) == (n,):
        return np.asarray(free, bool)
    c = g.theta_cov() if hasattr(g, "theta_cov") else None
    if c is not None and np.shape(c) == (n, n) and np.all(np.isfinite(c)):
        return np.diag(np.asarray(c, float)) > 0
    return None


# a parameter a bounded fit held at one of its bounds (`info["active_bounds"]`), as
# `fixed_values` names it: not estimated there, its value set by the bound
AT_BOUND = " (at its bound)"


def _held_how(name: str) -> str:
    """'a4 (at its bound)' -> 'a4 at its bound'; 'd5' -> 'd5 at nominal'."""
    if name.endswith(AT_BOUND):
        return f"{name.removesuffix(AT_BOUND)} at its bound"
    return f"{name} at nominal"


def _at_bound(g) -> set[str]:
    info = getattr(g, "info", None)
    return set((info or {}).get("active_bounds") or ()) if isinstance(info, dict) else set()


def fixed_values(model: FittedModel) -> tuple[dict | None, list[str]]:
    """The YAML values the model did not estimate -> ({link: {key: [parameter names]}}, the
    fixed parameters named): a value is fixed when it moves one for one (|derivative| >= 0.5)
    with a parameter held at its nominal value (unidentifiable, or left out of the fit) and
    with no estimated one, or when no estimated parameter moves it at all. Its propagated +-
    (0, or a by-product of a small rotation of it, 2e-8 m) is no measurement. (None, []) when
    the model does not say which parameters it estimated."""
    from workcell.kinematics.chain import joints_of, param_names

    th, _, base_ref, _ = model_geometry(model)
    g, _ = _geometric_part(model)
    est = _estimated_mask(g, len(th))
    if est is None:
        return None, []
    names = param_names(joints_of(th))
    bound = _at_bound(g)
    if bound:  # held at a bound by a bounded fit: not estimated, whatever its `free` says
        est = est & np.array([x not in bound for x in names])
        names = [x + AT_BOUND if x in bound else x for x in names]
    J = np.abs(_yaml_jacobian(th, base_ref, range(len(th))))
    out: dict = {}
    used: set[str] = set()
    it = iter(J)
    for n in LINKS:
        for k in KEYS:
            row = next(it)
            held = [j for j in np.flatnonzero(row >= 0.5) if not est[j]]
            if any(row[est] >= 0.5) or (not held and np.any(row[est] > 1e-6)):
                continue  # estimated (through a parameter that moves it, however little)
            held = held or [j for j in np.flatnonzero(row > 1e-6) if not est[j]]
            out.setdefault(n, {})[k] = [names[j] for j in held]
            used.update(names[j] for j in held)
    return out, [x for x in names if x in used]


# a calibration moves the nominal DH by tenths of a millimetre and milliradians: a model this
# far from it is another arm's, or the session declared the wrong arm
LINK_MOVE_MAX_M = 0.02
ANGLE_MOVE_MAX_RAD = 0.05


def check_nominal_distance(model: FittedModel) -> None:
    """Refuse (one line) a geometry whose link lengths moved more than `LINK_MOVE_MAX_M` or
    whose angles (alpha, joint offsets, tilts) moved more than `ANGLE_MOVE_MAX_RAD` from the
    nominal chain of the arm the model names: a controller would take it as given (the table
    and URScript exports refuse such a model by its correction's size)."""
    from workcell.kinematics.chain import joints_of, pack, param_names
    from workcell.kinematics.robots import robot_by_name

    g, _ = _geometric_part(model)
    spec = getattr(getattr(g, "features_spec", None), "spec", None)  # augmented
    nd = getattr(g, "nominal_dh", None)
    nd = getattr(spec, "dh", None) if nd is None else nd
    robot = getattr(g, "robot_model", None) or getattr(spec, "model", None) or "?"
    if nd is None:
        try:
            nd = robot_by_name(robot).dh
        except ValueError:
            return  # no nominal to compare with
    th = np.asarray(g.theta, float)
    n = joints_of(th)
    nom = pack(nd)
    if nom.shape != th.shape:
        return
    d = th - nom
    d[2 * n : 5 * n] = (d[2 * n : 5 * n] + np.pi) % (2 * np.pi) - np.pi
    names = param_names(n)
    method = getattr(model, "method", "?")
    for sl, lim, scale, unit in (
        (slice(0, 2 * n), LINK_MOVE_MAX_M, 1e3, "mm"),
        (slice(2 * n, 5 * n), ANGLE_MOVE_MAX_RAD, 1.0, "rad"),
    ):
        i = sl.start + int(np.argmax(np.abs(d[sl])))
        if abs(d[i]) > lim:
            raise UserError(
                f"refused: the {method} model's {names[i]} moved {abs(d[i]) * scale:.3g} {unit} "
                f"from the {robot} nominal ({nom[i]:.6g} -> {th[i]:.6g}; more than "
                f"{lim * scale:g} {unit}): is the session's robot model right? A calibration "
                "moves it by far less; fit a recording of this arm"
            )


# Universal Robots arm model names (CB3, e-Series and later), lower case
UR_ARMS = frozenset(
    "ur3 ur5 ur10 ur3e ur5e ur7e ur10e ur12e ur16e ur8long ur15 ur18 ur20 ur30".split()
)


def check_ur_arm(model: FittedModel) -> None:
    """The UR ROS driver's calibration file is for a Universal Robots arm: refuse a model whose
    robot field names another (a hand-edited "kuka" over a UR chain was written as one)."""
    g, _ = _geometric_part(model)
    spec = getattr(getattr(g, "features_spec", None), "spec", None)  # augmented
    robot = getattr(g, "robot_model", None) or getattr(spec, "model", None) or ""
    if str(robot).strip().lower() in UR_ARMS:
        return
    raise UserError(
        f"the model is of a {str(robot)[:40]!r} (its robot field), and the ros-yaml export is "
        "the UR ROS driver's calibration file, for Universal Robots arms (ur3, ur5e, ur10, ...); "
        "export a table (--format table, or targets), or fit a recording of a UR arm"
    )


def check_std(model: FittedModel, std: dict | None, tcp_sd: np.ndarray | None) -> None:
    """Refuse a geometry whose values the measured poses do not determine: a position (of a
    link or the TCP) whose 1-sigma exceeds the default correction bound (5 mm), which a
    controller would take as given (series D's DH model, {base_ty, tool_z} weakly identified,
    was written with a 27 mm 1-sigma in y while its table was refused)."""
    from workcell.export.table import DEFAULT_MAX_CORRECTION_M, weak_hint

    worst = max(
        [(v, f"{link}.{k}") for link, d in (std or {}).items() for k, v in d.items() if k in ("x", "y", "z")]
        + [(float(v), f"the TCP's {'xyz'[i]}") for i, v in enumerate([] if tcp_sd is None else tcp_sd)],
        default=None,
    )  # fmt: skip
    if worst is None or not worst[0] > DEFAULT_MAX_CORRECTION_M:
        return
    raise UserError(
        f"refused: {worst[1]} has a 1-sigma of {worst[0] * 1e3:.3g} mm (more than "
        f"{DEFAULT_MAX_CORRECTION_M * 1e3:g} mm): the measured poses do not determine it"
        + (weak_hint(model) or "; measure poses that spread the tool's orientation, then fit again")
    )


def check_units(th: np.ndarray, tcp: np.ndarray, method: str) -> None:
    """Refuse a geometry in the wrong unit (one line): a link length beyond any arm or a TCP
    (SMR) farther than `TCP_MAX_M` from the flange, which a controller would use as given."""
    from workcell.recording.checks import DH_LENGTH_MAX_M

    again = (
        "it looks like millimetres; the model file wants metres: fit it again with `workcell fit`"
    )
    lengths = np.abs(np.r_[th[0:6], th[6:12]])
    i = int(np.argmax(lengths))
    if lengths[i] > DH_LENGTH_MAX_M:
        name = f"{'ad'[i // 6]}{i % 6 + 1}"
        raise UserError(
            f"the {method} model's link length {name} is {lengths[i]:.4g} m (more than "
            f"{DH_LENGTH_MAX_M:g} m): {again}"
        )
    r = float(np.linalg.norm(tcp[:3, 3]))
    if not r <= TCP_MAX_M:
        raise UserError(
            f"the {method} model puts the SMR/TCP {r:.4g} m from the flange (more than "
            f"{TCP_MAX_M:g} m), which the controller would use as its TCP: "
            + (again if r <= 1000 * TCP_MAX_M else "a corrupt value; fit it again")
        )


def dropped_part(
    model: FittedModel, th: np.ndarray, base_ref: np.ndarray
) -> tuple[dict | None, str]:
    """Size of what the YAML does not carry: the model's prediction minus its geometric part's
    (`p_tracker(th, base_ref, q)`, which the YAML reproduces), over the poses of the recording
    the model was fitted on, at their recorded conditions (approach, temperatures, payload,
    time) -> ({"rms_m", "max_m", "poses"}, "") or (None, why it could not be evaluated)."""
    from workcell.estimation.models import aux_from_dataset
    from workcell.kinematics.chain import p_tracker
    from workcell.recording.dataset import Dataset

    info = getattr(model, "info", None)
    info = info if isinstance(info, dict) else {}
    rec = info.get("recording")
    if not rec:
        why = info.get("recording_unusable") or "the model names no recording"
        return None, f"{why}; put the recording beside the model to have it stated"
    try:
        ds = Dataset.from_recording(rec)
        p_full = np.asarray(model.predict(ds.q, **aux_from_dataset(ds)), float)
        p_geo = np.asarray(p_tracker(th, base_ref, ds.q), float)
    except Exception as e:  # noqa: BLE001 - the figure is a comment; the geometry is written
        return None, f"the model's recording {rec} could not be evaluated ({str(e)[:120]})"
    d = np.linalg.norm(p_full - p_geo, axis=1)
    if len(d) == 0 or not np.all(np.isfinite(d)):
        return None, f"the model does not predict finite positions on its recording {rec}"
    return {"rms_m": float(np.sqrt(np.mean(d**2))), "max_m": float(d.max()), "poses": len(d)}, ""


def _dropped_line(model, th: np.ndarray, base_ref: np.ndarray) -> tuple[str, dict | None]:
    what = (
        "not carried: non-geometric effects (compliance, backlash, thermal, data-driven residuals)"
    )
    if getattr(model, "method", None) == "dh":
        return "not carried: no term of the model (a dh model is geometric only)", None
    size, why = dropped_part(model, th, base_ref)
    if size is None:
        return f"{what}; their size could not be evaluated: {why}", None
    return (
        f"{what}: model prediction minus its geometric part, over the {size['poses']} poses of "
        f"the recording it was fitted on at their recorded conditions (the YAML has no volume), "
        f"RMS {size['rms_m'] * 1e6:.1f} um, max {size['max_m'] * 1e6:.1f} um; the table or "
        "URScript export carries them",
        size,
    )


def export_ros_yaml(
    model: FittedModel, path: str | os.PathLike, meta: dict | None = None
) -> tuple[Path, dict]:
    from workcell.export.correction import matrix_to_rotvec

    th, B, base_ref, note = model_geometry(model)
    kin = ros_kinematics(th, B)
    tcp = tcp_in_tool0(th, B)
    tcp_sd = tcp_std_m(model, th, B)
    check_units(th, tcp, getattr(model, "method", "?"))
    check_ur_arm(model)
    check_nominal_distance(model)
    dropped, size = _dropped_line(model, th, base_ref)
    unexplained, u = _unexplained_lines(model)
    meta = meta or {}
    bc = base_correction(model)
    bc_line = base_correction_line(bc)
    comments = [
        "UR calibration kinematics generated by workcell (ur_description kinematics_params_file)",
        f"model: {meta.get('model', '?')} ({getattr(model, 'method', '?')}) {note}".rstrip(),
        f"recording sha256: {meta.get('recording_sha256', '?')}",
        "frame: base_link_inertia = base_ref, the model's rigid registration of its nominal "
        "chain to the tracker (p_tracker = tracker_T_base @ p_base, tracker_T_base = base_ref "
        "below); the fitted base correction is folded into `shoulder`, so the kinematics put "
        "tool0 in base_ref, as the table/URScript corrections take targets in it; map tracker "
        "coordinates into it with the inverse of this file's tracker_T_base (each model "
        "registers its own)",
        base_ref_line(base_ref),
        bc_line,
        f"tcp_in_tool0 (SMR, incl. a6/alpha6/beta6): xyz {np.round(tcp[:3, 3], 9).tolist()} m"
        + (
            ""
            if tcp_sd is None
            else f" (1-sigma {np.round(tcp_sd, 9).tolist()} m, the fit's covariance)"
        )
        + ", "
        f"rotvec {np.round(matrix_to_rotvec(tcp[:3, :3]), 12).tolist()} rad",
        dropped,
        *unexplained,
    ]
    std = kinematics_std(model)
    check_std(model, std, tcp_sd)
    fixed, held = fixed_values(model)
    method = getattr(model, "method", "?")
    if std is not None:
        basis = {
            "augmented": "the fit's covariance of the geometry, the effects fitted with it "
            "marginalised out",
            "ekf-ann": "the filter's final state covariance of the geometric states it estimated "
            "times max(1, s0^2), s0^2 its innovation variance factor",
        }.get(method, "the fit's parameter covariance (see `workcell fit` for its basis)")
        comments.append(f"+- beside a value: 1 sigma, {basis}, propagated to first order")
        if method == "ekf-ann":
            comments.append(
                "that +- is the uncertainty of the geometry alone, not a 1-sigma of the model's "
                "prediction: the model file keeps no covariance of its network's weights with "
                "the geometric states, so the table and targets exports give no correction "
                "1-sigma for this model"
            )
    else:
        comments.append(
            f"no uncertainty beside the values: this {method} model carries no covariance of its "
            "geometry (an ekf-ann model in paper mode does not estimate it)"
        )
    if fixed:
        comments.append(_fixed_line(model, held))
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    write_text(p, to_yaml(kin, comments=comments, std=std, fixed=fixed))
    return p, {
        "kinematics": kin,
        "kinematics_std": std,
        "kinematics_fixed": fixed,  # {link: {key: [parameter names]}}: values not estimated
        "tcp_in_tool0": tcp.tolist(),
        "base_ref": base_ref.tolist(),
        "base_correction": bc,
        "base_correction_line": bc_line,
        "not_carried": size,  # {"rms_m", "max_m", "poses"} or None (dh, or not evaluated)
        **u,  # model_unexplained (and without outliers): the model file's held-out figure
    }


def _unexplained_lines(model) -> tuple[list[str], dict]:
    """What the model itself leaves unexplained on its held-out poses (the model file's figure,
    `export` prints it beside a table's 1-sigma): in neither the YAML's values nor their +-."""
    from workcell.estimation.models import unexplained_text
    from workcell.export.build import model_unexplained

    u = model_unexplained(model)
    if u is None:
        return [
            "unexplained by the model: not stated (the model file has no held-out figure); "
            "it is in neither the values nor their +-"
        ], {}
    lines = [
        f"unexplained by the model: {unexplained_text(u)} on its held-out poses, in neither the "
        "values nor their +-"
    ]
    out = {"model_unexplained": u}
    w = model_unexplained(model, without_outliers=True)
    if w is not None:
        ids = ", ".join(str(i) for i in w["pose_ids"])
        lines.append(f"without the held-out outlier pose(s) {ids}: {unexplained_text(w)}")
        out["model_unexplained_without_outliers"] = w
    return lines, out


def _fixed_line(model, held: list[str]) -> str:
    """The header line saying what `fixed` beside a value means, naming the parameters."""
    g, _ = _geometric_part(model)
    groups = [
        gr
        for gr in (getattr(g, "unidentifiable", None) or [])
        if isinstance(gr, list | tuple) and set(gr) & set(held)
    ]
    why = (
        " (not identifiable apart on the recording's poses: "
        + ", ".join("{" + ", ".join(map(str, gr)) + "}" for gr in groups)
        + "; or left out of the fit)"
        if groups
        else " (unidentifiable on the recording's poses, or left out of the fit)"
    )
    nominal = [x for x in held if not x.endswith(AT_BOUND)]
    at_bound = [x.removesuffix(AT_BOUND) for x in held if x.endswith(AT_BOUND)]
    bound_part = (
        f"; or held at a bound of the bounded fit (`fit --bounds`): {', '.join(at_bound)}"
        if at_bound
        else ""
    )
    if not nominal and at_bound:
        why = ""
    return (
        f"fixed beside a value: not estimated; it follows parameters held at their nominal "
        f"value: {', '.join(nominal) or 'none'}{why}{bound_part}; no 1-sigma is given for it "
        "(it would be 0 or a by-product of other parameters, not a measurement)"
    )
