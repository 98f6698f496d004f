"""Glue shared by `workcell export`, `workcell validate` and the demo: model -> nominal chain,
corrector and table with its metadata."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from workcell.errors import UserError
from workcell.estimation.models import model_fingerprint, unexplained_text
from workcell.export.correction import Conditions, Corrector, Nominal, nominal_for
from workcell.export.table import (
    DEFAULT_INTERP_ERROR_M,
    DEFAULT_MAX_CORRECTION_M,
    CorrectionTable,
    build_table,
    default_volume,
)
from workcell.kinematics.robots import robot_by_name

if TYPE_CHECKING:
    from workcell.campaign.envelope import Envelope
    from workcell.estimation.models import FittedModel

DEFAULT_ORIENTATION = (0.0, np.pi, 0.0)  # tool pointing down (flange z = -z of base)


def model_recording(model: FittedModel) -> tuple[str | None, str | None]:
    info = getattr(model, "info", {}) or {}
    return info.get("recording"), info.get("recording_sha256")


def model_session(model: FittedModel) -> tuple[dict, str]:
    """The session of the recording the model was fitted on -> (session, why not): {} and a
    reason when the model names none or it cannot be read (the recording is optional to
    `validate`: it gives the simulated truth and the cell's envelope)."""
    rec, _ = model_recording(model)
    missing = (getattr(model, "info", {}) or {}).get("recording_unusable", "")
    if not rec:
        return {}, missing
    try:
        from workcell.recording.reader import read_recording

        return read_recording(rec).session, ""
    except Exception as e:  # noqa: BLE001 - the recording is optional here
        return {}, f"the model's recording {rec} is unreadable: {e}"[:300]


def nominal_for_model(model: FittedModel, recording: str | None = None) -> Nominal:
    """nominal_for(model), falling back on the model's (or the given) recording. A given
    `recording` must be the model's (same sha256), also for a model that carries its chain and
    does not need it: one that was silently ignored (another arm's recording, a model file)."""
    from workcell.recording.dataset import Dataset, file_sha256

    own: Nominal | None = None  # the chain the model carries, if it does
    try:
        own = nominal_for(model)
    except UserError as e:
        missing = e
    sha = model_recording(model)[1]
    if recording and sha and file_sha256(recording) != sha:
        raise UserError(
            f"{recording} is not the model's recording (its sha256 differs from the one the "
            "model was fitted on); give that one"
            + (
                ", or leave --recording out: this model carries its nominal chain"
                if own is not None
                else ""
            )
        )
    if recording and not sha and own is not None:
        raise UserError(
            f"--recording {recording} would not be used: the model carries its nominal chain, "
            "and it names no recording to check this one against; leave --recording out"
        )
    if own is not None:
        return own
    rec = recording or model_recording(model)[0]
    unusable = (getattr(model, "info", {}) or {}).get("recording_unusable")
    if not rec and unusable:
        raise UserError(
            f"{unusable}; this model needs it for its nominal chain: give it with --recording"
        )
    if not rec:
        raise missing  # no chain in the model and no recording to register one on
    ds = Dataset.from_recording(rec)
    train, _ = ds.holdout_split(0.25)
    return nominal_for(model, ds.subset(train))


def parse_vec(text: str, n: int, what: str) -> np.ndarray:
    fields = text.replace(" ", "").split(",")
    if any(not x for x in fields):  # an empty field is a typo, not a number left out
        raise UserError(f"{what}: expected {n} comma-separated numbers, got {text!r}")
    try:
        v = np.array([float(x) for x in fields], float)
    except ValueError:
        raise UserError(f"{what}: expected {n} comma-separated numbers, got {text!r}") from None
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise UserError(f"{what}: expected {n} comma-separated numbers, got {text!r}")
    return v


COMPLIANCE_KINDS = ("joint_compliance", "link_deflection")
PAYLOAD_MAX_KG = 50.0  # the largest UR arm carries 30 kg
JOINT_TEMPERATURE_RANGE_C = (-30.0, 100.0)
ELAPSED_MAX_S = 30 * 24 * 3600.0


def parse_conditions(
    approach: str,
    payload: str | None = None,
    joint_temperature: str | None = None,
    elapsed: str | None = None,
) -> Conditions:
    """The export's operating conditions from the command-line strings, checked for units."""
    sign = parse_vec(approach, 6, "--approach")
    if not np.all(np.isin(sign, (-1.0, 0.0, 1.0))):
        raise UserError(
            f"--approach {approach}: each joint's approach sign is -1, 0 or 1 (the direction the "
            "joint moves into its target from)"
        )
    cond = Conditions(approach_sign=sign)
    if payload is not None:
        (kg,) = parse_vec(payload, 1, "--payload")
        if not 0.0 <= kg <= PAYLOAD_MAX_KG:
            raise UserError(
                f"--payload {kg:g} kg is outside 0..{PAYLOAD_MAX_KG:g} kg; give kilograms"
            )
        cond.payload_kg = float(kg)
    if joint_temperature is not None:
        t = parse_vec(joint_temperature, 6, "--joint-temperature")
        lo, hi = JOINT_TEMPERATURE_RANGE_C
        if np.any(t < lo) or np.any(t > hi):
            raise UserError(
                f"--joint-temperature {np.round(t, 1).tolist()}: outside {lo:g}..{hi:g} degC "
                "(kelvin or Fahrenheit?); give degrees Celsius, as the recording does"
            )
        cond.joint_temperature_c = t
    if elapsed is not None:
        (sec,) = parse_vec(elapsed, 1, "--elapsed")
        if not 0.0 <= sec <= ELAPSED_MAX_S:
            raise UserError(f"--elapsed {sec:g} s is outside 0..{ELAPSED_MAX_S:g} s; give seconds")
        cond.elapsed_s = float(sec)
    return cond


def residual_drift_note(model: FittedModel) -> str | None:
    """A line when the model's non-parametric residual (a GP over the joints) may be a drift
    during the recording: `diagnose` found the joints and the recording order not told apart,
    or the order predicting better (`residual_drift_check` in the model file)."""
    info = getattr(model, "info", None)
    dc = info.get("residual_drift_check") if isinstance(info, dict) else None
    if getattr(model, "residual", None) is None or not isinstance(dc, dict):
        return None
    verdict = dc.get("verdict")
    why = {
        "time": "it followed the recording order more than the joints",
        "either": "the joints and the recording order could not be told apart on its poses",
    }.get(verdict if isinstance(verdict, str) else "")
    if why is None:
        return None
    return (
        f"the model's GP residual may be a drift during the recording, not an error of the "
        f"joints (diagnose: {why}); the table carries it as a function of the joints: check "
        "the correction on another day's measurements"
    )


def conditions_note(model: FittedModel, cond: Conditions, strict: bool = False) -> list[str]:
    """What the table assumes about the conditions the model's accepted effects depend on, one
    line each; `strict` (a user's options): refuses a given condition that does not drive the
    model's thermal drift."""
    accepted = getattr(model, "accepted", None)
    fs = getattr(model, "features_spec", None)
    kinds = {c.kind for c in accepted} if accepted is not None and fs is not None else set()
    lines = []
    drift = residual_drift_note(model)
    if drift:
        lines.append(drift)
    if kinds & set(COMPLIANCE_KINDS):
        if cond.payload_kg is not None:
            lines.append(f"payload {cond.payload_kg:g} kg (given), for the compliance terms")
        else:
            lines.append(
                f"payload {fs.payload_kg_default:g} kg, the recording's, for the compliance terms "
                "(--payload KG for another)"
            )
    elif cond.payload_kg is not None:
        lines.append("--payload changes nothing: the model has no payload-dependent effect")
    if "backlash" in kinds:
        sg = np.asarray(cond.approach_sign, int).tolist()
        lines.append(
            f"approach {sg} per joint (the direction each joint moves into its target from): "
            "the model's backlash terms hold for that approach only; command a pre-pose so "
            "every joint arrives that way (--approach for another)"
        )
    src = fs.thermal_source if fs is not None and "thermal_drift" in kinds else None
    if src is None:
        if cond.joint_temperature_c is not None or cond.elapsed_s is not None:
            lines.append(
                "--joint-temperature/--elapsed change nothing: the model has no thermal drift"
            )
        return lines
    # a given condition that does not drive this drift would be silently ignored: refuse it
    drives = {
        "joint": ("--joint-temperature", "the joint temperatures; give --joint-temperature"),
        "time": ("--elapsed", "the time since the campaign's start; give --elapsed"),
    }
    settable, driven_by = drives.get(
        src,
        (
            None,
            "the ambient temperature, which export cannot set (the table is for the "
            "recording's mean); leave the option out",
        ),
    )
    for opt, value in (
        ("--joint-temperature", cond.joint_temperature_c),
        ("--elapsed", cond.elapsed_s),
    ):
        if strict and value is not None and opt != settable:
            raise UserError(
                f"{opt} does not set the model's thermal drift: it is driven by {driven_by}"
            )
    ref = np.asarray(fs.thermal_ref, float)
    if src == "joint" and cond.joint_temperature_c is not None:
        lines.append(
            f"thermal state: joint temperatures {np.round(cond.joint_temperature_c, 1).tolist()} "
            "degC (given)"
        )
    elif src == "time" and cond.elapsed_s is not None:
        lines.append(f"thermal state: {cond.elapsed_s:g} s after the campaign's start (given)")
    else:
        mean = {
            "joint": f"link temperatures {np.round(ref, 1).tolist()} degC",
            "time": f"{ref[0] * 3600:.0f} s after the campaign's start",
            "ambient": f"ambient {ref[0]:.1f} degC",
        }.get(src, "")
        how = {"joint": " (--joint-temperature T1,..,T6 for another)", "time": " (--elapsed S)"}
        lines.append(
            f"thermal state: the recording's mean, {mean}{how.get(src, '')}: the thermal "
            "drift term is zero there"
        )
    return lines


def make_table(
    model: FittedModel,
    *,
    model_path: str = "",
    volume: np.ndarray | None = None,
    orientations: list | None = None,
    conditions: Conditions | None = None,
    target_error_m: float = DEFAULT_INTERP_ERROR_M,
    max_correction_m: float = DEFAULT_MAX_CORRECTION_M,
    spacing_m: float | None = None,
    recording: str | None = None,
    envelope: tuple | None = None,
    check_envelope: bool = True,
    nominal: Nominal | None = None,
    log: Callable[[str], None] | None = None,
) -> tuple[CorrectionTable, Corrector]:
    """The table of `model` over `volume` (default: `default_volume`). A table for a controller
    (`check_envelope`) is refused when its volume reaches outside the envelope
    (`check_volume_box`, `check_table_envelope`): `envelope` (Envelope, what it is), default
    the one the model's recording ran in (`table_envelope`)."""
    nominal = nominal if nominal is not None else nominal_for_model(model, recording)
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
    if check_envelope:
        env, env_what = envelope if envelope is not None else table_envelope(model, nominal)
        what = "--volume" if volume is not None else "the default volume (give --volume)"
        check_volume_box(lo, hi, env, env_what, what)  # before any IK: a box typed outside it
    rv = np.asarray(orientations or [DEFAULT_ORIENTATION], float).reshape(-1, 3)
    rec, sha = model_recording(model)
    meta = {
        "model": model_path or "(in memory)",
        "method": getattr(model, "method", "?"),
        "model_fingerprint": model_fingerprint(model),
        "recording": rec,
        "recording_sha256": sha,
        "robot": nominal.robot,
        "conditions_note": conditions_note(model, corr.conditions),
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
    if check_envelope:
        tab.meta["envelope_check"] = check_table_envelope(tab, nominal, env, env_what, what)
        if log:
            log(f"  {tab.meta['envelope_check']}")
    note_unexplained(model, tab.meta, log)
    return tab, corr


def table_envelope(model: FittedModel, nominal: Nominal) -> tuple[Envelope | None, str]:
    """The envelope a table's commanded positions must lie in -> (Envelope or None, what it is):
    the one the model's recording ran in (the cell's configured one), as `export --format
    targets` checks its commanded joints; None (with why) when the recording records none or
    is not readable: then the nodes are checked against the arm's joint ranges only."""
    from workcell.campaign.envelope import envelope_of_session

    try:
        spec = robot_by_name(nominal.robot)
    except ValueError:
        return None, f"unknown arm {nominal.robot!r}, whose envelope is not known"
    session, why = model_session(model)
    rec = model_recording(model)[0]
    env = envelope_of_session(session.get("campaign") or {}, spec, str(rec)) if session else None
    if env is None:
        return None, why or f"the model's recording {rec} records no envelope"
    return env, f"the envelope the model's recording {rec} ran in"


def check_volume_box(
    lo: np.ndarray, hi: np.ndarray, env: Envelope | None, env_what: str, what: str
) -> None:
    """Refuse a table volume (SMR positions, base) reaching outside the envelope's workspace box
    less its kinematic margin: the controller would be handed corrections for places the arm
    must not go (one line, before any IK)."""
    if env is None:
        return
    m = env.kinematic_margin_m
    blo, bhi = np.asarray(env.box_min_m) + m, np.asarray(env.box_max_m) - m
    out = (np.asarray(lo) < blo - 1e-12) | (np.asarray(hi) > bhi + 1e-12)
    if out.any():
        a = int(np.flatnonzero(out)[0])
        raise UserError(
            f"{what} {np.round(np.r_[lo, hi], 4).tolist()} m reaches outside {env_what}: its "
            f"{'xyz'[a]} range {lo[a]:.4g}..{hi[a]:.4g} m leaves the workspace box "
            f"({blo[a]:.4g}..{bhi[a]:.4g} m inside its {m * 1e3:g} mm kinematic margin); give a "
            "volume inside it"
        )


def check_table_envelope(
    tab: CorrectionTable, nominal: Nominal, env: Envelope | None, env_what: str, what: str
) -> str:
    """Refuse a table one of whose nodes' corrected joints (what the controller is sent there)
    leaves the envelope (`Envelope.violations`: joint ranges, the workspace box, the floor under
    the link frames), or, without an envelope, the arm's joint ranges. -> the line saying what
    the nodes were checked against."""
    try:
        spec = robot_by_name(nominal.robot)
    except ValueError:
        return "nodes not checked against an envelope: unknown arm (its controller checks)"
    q = np.asarray(tab.q_nodes, float).reshape(-1, 6)
    X = np.broadcast_to(tab.node_positions(), (*np.shape(tab.q_nodes)[:-1], 3)).reshape(-1, 3)
    if env is None:
        lim = np.asarray(spec.joint_limits_rad, float)
        bad = np.any((q < lim[:, 0]) | (q > lim[:, 1]), axis=1)
        why = [None if not b else "joints outside the arm's ranges" for b in bad]
        said = (
            f"nodes' corrected joints checked against the arm's joint ranges only: {env_what}; "
            "check the volume against the cell's envelope before using the table"
        )
    else:
        why = env.violations(spec, q, nominal.tool_m)
        said = f"nodes' corrected joints inside {env_what}"
    i = next((i for i, v in enumerate(why) if v is not None), None)
    if i is not None:
        n = sum(v is not None for v in why)
        raise UserError(
            f"{what} reaches outside {env_what if env is not None else 'the arm'}: "
            f"{n} node(s), first at {np.round(X[i], 4).tolist()} m (base): {why[i]}; give a "
            "volume the arm may go to"
        )
    return said


def note_unexplained(model, meta: dict, log: Callable[[str], None] | None = None) -> None:
    """Put the model file's figure of what it leaves unexplained on its held-out poses (not in
    the correction's 1-sigma) in `meta` (`model_unexplained`, and `..._without_outliers` when
    `fit` named held-out outliers) and tell `log` (the lines `export` prints)."""
    u = model_unexplained(model)
    if u is None:
        if log:  # said, as the table's files say it (before 2026-11-26 only the files did)
            from workcell.export.table import unexplained_lines

            for line in unexplained_lines(meta):
                log(f"  {line}")
            why = (getattr(model, "info", {}) or {}).get("heldout")
            if isinstance(why, str):
                log(f"  (held-out poses: {why}; fit with a hold-out to know what it leaves out)")
        return
    meta["model_unexplained"] = u
    if log:
        from workcell.export.table import unexplained_lines

        log(f"  {unexplained_lines(meta)[0]}")  # its line without the outliers comes below
        if isinstance(sel := model.info.get("heldout_selection"), str):
            log(f"  ({sel})")
    w = model_unexplained(model, without_outliers=True)
    if w is not None:
        meta["model_unexplained_without_outliers"] = w
        if log:
            ids = ", ".join(str(i) for i in w["pose_ids"])
            log(
                f"  without the held-out outlier pose(s) {ids} ({w['rule']}): {unexplained_text(w)}"
            )


def model_unexplained(model: FittedModel, *, without_outliers: bool = False) -> dict | None:
    """The model file's held-out figure of what it leaves unexplained (`fit` and `diagnose`
    store it), recomputed from the stored RMS, interval and floor so a hand-edited entry cannot
    put a wrong figure in a table; None when the model has none or it does not parse.
    With `without_outliers`, the same figure without the held-out poses `fit` named as outliers
    (`heldout_outliers` in the model file), with their `pose_ids` and `rule`; None when none
    were named."""
    from workcell.estimation.models import unexplained_error

    info = getattr(model, "info", None)
    if not isinstance(info, dict) or not isinstance(info.get("unexplained"), dict):
        return None
    src, floor = info, info["unexplained"].get("floor_m")
    if without_outliers:
        src = info.get("heldout_outliers")
        if not isinstance(src, dict):
            return None
        floor = src.get("floor_m")
    ci = src.get("heldout_rms_ci95_m")
    try:
        ci = [float(c) for c in ci] if ci is not None else None
    except (TypeError, ValueError):
        ci = None
    u = unexplained_error(src.get("heldout_rms_m"), ci, floor)
    if u is None or not without_outliers:
        return u
    ids = src.get("pose_ids")
    if not isinstance(ids, list) or not ids:
        return None
    try:
        u["pose_ids"] = [int(i) for i in ids]
    except (TypeError, ValueError):
        return None
    u["rule"] = str(src.get("rule", "named by fit"))
    return u


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
