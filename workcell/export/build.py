"""Glue shared by `workcell export`, `workcell validate` and the demo: model -> nominal chain,
corrector and table with its metadata."""

from __future__ import annotations

import numpy as np

from workcell.errors import UserError
from workcell.export.correction import Conditions, Corrector, Nominal, nominal_for
from workcell.export.table import (
    DEFAULT_INTERP_ERROR_M,
    DEFAULT_MAX_CORRECTION_M,
    CorrectionTable,
    build_table,
    default_volume,
)
from workcell.kinematics.robots import robot_by_name

DEFAULT_ORIENTATION = (0.0, np.pi, 0.0)  # tool pointing down (flange z = -z of base)


def model_recording(model) -> tuple[str | None, str | None]:
    info = getattr(model, "info", {}) or {}
    return info.get("recording"), info.get("recording_sha256")


def nominal_for_model(model, recording: str | None = None) -> Nominal:
    """nominal_for(model), falling back on the model's (or the given) recording."""
    try:
        return nominal_for(model)
    except UserError:
        rec = recording or model_recording(model)[0]
        unusable = (getattr(model, "info", {}) or {}).get("recording_unusable")
        if not rec and unusable:
            raise UserError(
                f"{unusable}; this model needs it for its nominal chain: give it with --recording"
            ) from None
        if not rec:
            raise
    from workcell.recording.dataset import Dataset, file_sha256

    sha = model_recording(model)[1]
    if recording and sha and file_sha256(recording) != sha:
        raise UserError(
            f"{recording} is not the model's recording (its sha256 differs from the one the "
            "model was fitted on); give that one"
        )

    ds = Dataset.from_recording(rec)
    train, _ = ds.holdout_split(0.25)
    return nominal_for(model, ds.subset(train))


def parse_vec(text: str, n: int, what: str) -> np.ndarray:
    try:
        v = np.array([float(x) for x in text.replace(" ", "").split(",") if x], float)
    except ValueError:
        raise UserError(f"{what}: expected {n} comma-separated numbers, got {text!r}") from None
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise UserError(f"{what}: expected {n} comma-separated numbers, got {text!r}")
    return v


def make_table(
    model,
    *,
    model_path: str = "",
    volume: np.ndarray | None = None,
    orientations: list | None = None,
    conditions: Conditions | None = None,
    target_error_m: float = DEFAULT_INTERP_ERROR_M,
    max_correction_m: float = DEFAULT_MAX_CORRECTION_M,
    spacing_m: float | None = None,
    recording: str | None = None,
    log=None,
) -> tuple[CorrectionTable, Corrector]:
    nominal = nominal_for_model(model, recording)
    corr = Corrector(model, nominal, conditions)
    if volume is None:
        try:
            spec = robot_by_name(nominal.robot)
        except ValueError:
            raise UserError(
                f"no default volume for robot {nominal.robot!r}; give --volume"
            ) from None
        lo, hi = default_volume(spec)
    else:
        lo, hi = np.asarray(volume[:3], float), np.asarray(volume[3:], float)
        check_volume(lo, hi, nominal)
    rv = np.asarray(orientations or [DEFAULT_ORIENTATION], float).reshape(-1, 3)
    rec, sha = model_recording(model)
    meta = {
        "model": model_path or "(in memory)",
        "method": getattr(model, "method", "?"),
        "recording": rec,
        "recording_sha256": sha,
        "robot": nominal.robot,
    }
    tab = build_table(
        corr,
        lo,
        hi,
        rv,
        target_error_m=target_error_m,
        max_correction_m=max_correction_m,
        spacing_m=spacing_m,
        meta=meta,
        log=log,
    )
    return tab, corr


def reach_of(nominal: Nominal) -> float:
    """Upper bound (m) of the SMR/TCP's distance from the base over all joint angles."""
    from workcell.kinematics.chain import unpack_dh
    from workcell.recording.checks import reach_m

    return reach_m(unpack_dh(nominal.theta), nominal.tool_m)


def check_volume(lo: np.ndarray, hi: np.ndarray, nominal: Nominal) -> None:
    """A table volume (base frame, m) must lie within the arm's reach: a corner farther than
    that cannot be corrected (no joint solution), and a volume typed in millimetres would ask
    for ~10^12 nodes."""
    from workcell.recording.checks import millimetre_hint

    r = reach_of(nominal)
    far = float(np.max(np.abs(np.r_[lo, hi])))
    if np.all(np.isfinite(np.r_[lo, hi])) and far > r:
        raise UserError(
            f"--volume {np.r_[lo, hi].tolist()}: a bound {far:.4g} m from the base is beyond the "
            f"{nominal.robot}'s reach of {r:.3g} m; "
            + millimetre_hint(far, r, "give the volume in metres, within reach")
        )
