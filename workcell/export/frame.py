"""The frame a correction export's targets are in, stated the same way by every format.

Every correction (table, URScript, targets, and the ROS YAML's `base_link_inertia`) is for
targets expressed in `base_ref`: the model's rigid (Kabsch) registration of the nominal chain to
the tracker, `p_tracker = tracker_T_base @ p_base` with `tracker_T_base = base_ref`. `validate`
defines its goals through it too. The fit also estimates a base correction relative to it (the
model's `base_tx..base_rz`), which the correction folds in: a target expressed in another
estimate of the robot base (the controller's own base frame, or another model's `base_ref`)
differs from `base_ref` by that much, and the correction does not remove that difference.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from workcell.estimation.models import FittedModel

FRAME_TEXT = (
    "base_ref, the model's rigid registration of its nominal chain to the tracker (p_tracker = "
    "tracker_T_base @ p_base, tracker_T_base = base_ref below): desired and commanded targets "
    "are SMR/TCP positions in it; map tracker coordinates into it with the inverse of this "
    "file's tracker_T_base (each model registers its own); validate defines its goals in it"
)
NO_BASE_BASIS = (
    "none: the model has no base parameters (base_tx..base_rz), so the size of the difference "
    "between base_ref and another estimate of the robot base is not known to it"
)
# what the fitted base correction does not hold (the audit's simulated UR5e: the fitted base
# 0.6 mm from base_ref, the true base 0.8 mm RMS from it over the table's volume)
NOT_ALL = (
    "the controller's own base may differ from base_ref by more: position measurements do not "
    "tell a base rotation about joint 1's axis and a shift along it from theta1_offset and d1"
)
BASE_BASIS = (
    "the model's fitted base offsets from base_ref (base_tx, base_ty, base_tz in m, base_rx, "
    "base_ry, base_rz as a rotation vector in rad; tracker_T_fitted_base = base_ref @ Trans(t) "
    "@ Rot(r)), which the correction folds in; max_shift_m: how far that moves a point of the "
    "exported positions"
)


STD_BASIS = (
    "1-sigma of each base offset from the fit's parameter covariance (first order, conditional "
    "on the model; 0 for a parameter the fit held fixed)"
)


def _base_std(g, th: np.ndarray) -> np.ndarray | None:
    """1-sigma (6,) of the base offsets from the model's parameter covariance, or None."""
    from workcell.estimation.models import geometric_cov
    from workcell.kinematics.chain import base_slice, joints_of

    cov = geometric_cov(g)
    if cov is None:
        return None
    var = np.diag(cov)[base_slice(joints_of(th))]
    return np.sqrt(var) if var.shape == (6,) and np.all(var >= 0) else None


def _rotvec_matrix(r: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(r, float)).as_matrix()


def base_correction(model: FittedModel, points: np.ndarray | None = None) -> dict:
    """The model's fitted base correction relative to its base_ref (`BASE_BASIS`), with
    `max_shift_m` over `points` (N, 3, base_ref) when given; {"basis": NO_BASE_BASIS} for a
    model without base parameters."""
    from workcell.estimation.models import geometric_part
    from workcell.kinematics.chain import base_slice, joints_of

    g = geometric_part(model)
    if g is None:
        return {"basis": NO_BASE_BASIS}
    th = np.asarray(g.theta, float)
    try:
        b = th[base_slice(joints_of(th))]
    except (ValueError, IndexError):
        return {"basis": NO_BASE_BASIS}
    if b.shape != (6,) or not np.all(np.isfinite(b)):
        return {"basis": NO_BASE_BASIS}
    t, r = b[:3], b[3:]
    out = {
        "translation_m": t.tolist(),
        "rotation_rad": r.tolist(),
        "translation_norm_m": float(np.linalg.norm(t)),
        "rotation_angle_rad": float(np.linalg.norm(r)),
        "basis": BASE_BASIS,
    }
    std = _base_std(g, th)
    if std is not None:
        out["translation_std_m"] = std[:3].tolist()
        out["rotation_std_rad"] = std[3:].tolist()
        out["std_basis"] = STD_BASIS
    if points is not None:
        P = np.asarray(points, float).reshape(-1, 3)
        if len(P):
            d = P @ _rotvec_matrix(r).T + t - P
            out["max_shift_m"] = float(np.linalg.norm(d, axis=1).max())
    return out


def frame_meta(model: FittedModel, base_ref: np.ndarray, points: np.ndarray | None = None) -> dict:
    """The frame keys an export's metadata carries: `frame`, `base_ref` (tracker_T_base, 4x4,
    m) and `base_correction`."""
    return {
        "frame": FRAME_TEXT,
        "base_ref": np.asarray(base_ref, float).tolist(),
        "base_correction": base_correction(model, points),
    }


def base_ref_line(base_ref: npt.ArrayLike) -> str:
    """tracker_T_base's 16 values, row-major, SI."""
    M = np.asarray(base_ref, float).reshape(4, 4)
    rows = "; ".join(", ".join(repr(float(x)) for x in row) for row in M)
    return f"tracker_T_base (base_ref, 4x4 row-major, rotation 1, translation m): [{rows}]"


def base_correction_line(bc: dict | None, where: str = "the exported positions") -> str:
    """One line: targets in another estimate of the robot base differ from base_ref by the
    fitted base correction, which the correction does not remove (its size from `bc`)."""
    head = (
        "base correction: targets expressed in another estimate of the robot base (e.g. the "
        "controller's own base frame) differ from base_ref by the fitted base correction, "
        "which this correction does not remove"
    )
    if not isinstance(bc, dict) or "translation_m" not in bc:
        return f"{head}; its size is unknown: the model has no base parameters"
    t = np.asarray(bc["translation_m"], float) * 1e3
    r = np.asarray(bc["rotation_rad"], float) * 1e3
    ts, rs = bc.get("translation_std_m"), bc.get("rotation_std_rad")
    if ts is not None and rs is not None:
        ts, rs = np.asarray(ts, float) * 1e3, np.asarray(rs, float) * 1e3
        tt = ", ".join(f"{x:.3f} +- {e:.3f}" for x, e in zip(t, ts, strict=True))
        rr = ", ".join(f"{x:.3f} +- {e:.3f}" for x, e in zip(r, rs, strict=True))
        sig = " (+- 1-sigma from the fit's covariance)"
    else:
        tt, rr = ", ".join(f"{x:.3f}" for x in t), ", ".join(f"{x:.3f}" for x in r)
        sig = " (no covariance in the model: no 1-sigma)"
    line = (
        f"{head}: {np.linalg.norm(t):.3f} mm (base_tx, base_ty, base_tz {tt} mm) and "
        f"{np.linalg.norm(r):.3f} mrad (base_rx, base_ry, base_rz {rr} mrad){sig}"
    )
    if bc.get("max_shift_m") is not None:
        line += f", up to {bc['max_shift_m'] * 1e3:.3f} mm over {where}"
    return line + f"; {NOT_ALL}; express targets in base_ref"


def frame_lines(meta: dict, where: str = "the exported positions") -> list[str]:
    """The header lines (without `# `) stating the frame, tracker_T_base and the base
    correction, from an export's metadata (`frame_meta`)."""
    out = [f"frame: {meta.get('frame') or FRAME_TEXT}"]
    if meta.get("base_ref") is not None:
        out.append(base_ref_line(meta["base_ref"]))
    else:
        out.append("tracker_T_base (base_ref): not recorded in this file")
    out.append(base_correction_line(meta.get("base_correction"), where))
    return out
