"""How far the real arm is from the nominal kinematics the envelope checks use, from a fitted
model: the basis for an envelope's `kinematic_margin_m` once a cell has been calibrated.

Every envelope check (SMR box, floor) runs on the controller's nominal chain. The real SMR is off
by the model's deviation from that chain (millimetres on a real UR10), plus what the model itself
leaves unexplained (its held-out RMS). This module measures the first over joint configurations
the envelope allows and suggests a margin that covers both.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from workcell.campaign.envelope import Envelope
    from workcell.estimation.models import FittedModel
    from workcell.kinematics.robots import RobotSpec

SAMPLES = 4000
# the largest deviation is taken over samples; between them it can be larger: this factor on top
SAFETY_FACTOR = 1.25
# the model's own unexplained error, as a multiple of its held-out RMS
UNEXPLAINED_SIGMAS = 3.0


def model_deviation(
    model: FittedModel, env: Envelope, spec: RobotSpec, *, samples: int = SAMPLES, seed: int = 0
) -> dict:
    """The model's SMR minus the nominal chain's SMR over `samples` joint configurations drawn
    uniformly inside the envelope's joint ranges and kept when the nominal checks pass (where the
    margin matters).

    The controller's base frame, in which the envelope is drawn, is not observable from tracker
    data, so the deviation is measured in the two frames the fit gives and the larger counts:
    - `registered`: the base the nominal chain fits best to the measured poses (the frame of the
      correction table);
    - `calibrated`: that base moved by the model's fitted base offset (models with a geometric
      part only).

    Returns, per frame, max / 99th percentile / RMS (metres); the model's held-out RMS (if
    recorded); and the suggested margin (metres, rounded up to the next millimetre) with its
    basis in words."""
    from workcell.errors import UserError
    from workcell.export.build import nominal_for_model
    from workcell.export.correction import Corrector
    from workcell.export.ros_yaml import model_geometry

    nominal = nominal_for_model(model)
    corr = Corrector(model, nominal)
    lim = np.asarray(env.joint_limits_rad, float)
    rng = np.random.default_rng(seed)
    q = rng.uniform(lim[:, 0], lim[:, 1], (samples, len(lim)))
    ok = np.array([v is None for v in env.violations(spec, q, nominal.tool_m)])
    q = q[ok]
    if len(q) == 0:
        raise ValueError("no configuration inside the envelope's joint ranges passes its checks")
    p_nom, _ = nominal.fk(q)
    p_reg = corr.real_base(q)
    frames = {"registered": p_reg}
    try:
        _, B, _, _ = model_geometry(model)
    except UserError:
        pass  # no geometric part: no fitted base offset
    else:
        Bi = np.linalg.inv(B)
        frames["calibrated"] = p_reg @ Bi[:3, :3].T + Bi[:3, 3]
    out_frames = {}
    for name, p in frames.items():
        d = np.linalg.norm(p - p_nom, axis=1)
        out_frames[name] = {
            "max_m": float(d.max()),
            "p99_m": float(np.percentile(d, 99)),
            "rms_m": float(np.sqrt(np.mean(d**2))),
        }
    worst = max(f["max_m"] for f in out_frames.values())
    info = getattr(model, "info", {}) or {}
    rms_model = info.get("heldout_rms_m")
    rms_model = float(rms_model) if isinstance(rms_model, (int, float)) else None
    unexplained = UNEXPLAINED_SIGMAS * rms_model if rms_model else 0.0
    suggested = SAFETY_FACTOR * (worst + unexplained)
    if not math.isfinite(suggested):
        raise UserError(
            "the model's deviation from the nominal chain is not finite anywhere in the envelope "
            "(a parameter of the model file is out of range); refit it"
        )
    return {
        "configurations": int(len(q)),
        "frames": out_frames,
        "max_m": worst,
        "model_heldout_rms_m": rms_model,
        "model_heldout_rms_ci95_m": info.get("heldout_rms_ci95_m") if rms_model else None,
        "suggested_margin_m": math.ceil(suggested * 1e3 - 1e-9) / 1e3,
        "basis": (
            f"{SAFETY_FACTOR:g} x (largest deviation over {len(q)} allowed configurations, "
            f"in the worse of the {' and '.join(out_frames)} base frames"
            + (f", + {UNEXPLAINED_SIGMAS:g} x the model's held-out RMS" if rms_model else "")
            + "), rounded up to the next mm; measured at the SMR, the box check's point (the "
            "floor check's link frames are not measured; the same parameters move them)"
        ),
    }
