"""The small interface every fitted model shares, and saving/loading model files.

A model file is JSON: {"method": ..., "format": "workcell-model/1", ...}. `load_model` dispatches
on `method` to the class registered for it.
"""

from __future__ import annotations

import importlib
import json
import math
import os
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from workcell import strict_json
from workcell.errors import REPLACE_REMEDY, UserError, folder_problem, replace_or_refuse

if TYPE_CHECKING:
    from workcell.recording.dataset import Dataset

MODEL_FORMAT = "workcell-model/1"

# method -> "module:Class" with a classmethod from_dict(d) -> model
REGISTRY: dict[str, str] = {
    "dh": "workcell.estimation.dh:DHModel",
    "lddmm": "workcell.estimation.lddmm_fit:LddmmCalibration",
    "gp": "workcell.estimation.gp_residual:GPResidualModel",
    "ekf-ann": "workcell.estimation.ekf_ann.model:EkfAnnModel",
    "augmented": "workcell.estimation.effects:AugmentedModel",
}


@runtime_checkable
class FittedModel(Protocol):
    method: str

    def predict(self, q: np.ndarray, **aux: Any) -> np.ndarray:
        """SMR positions in the tracker frame (N, 3) for joints q (N, 6).

        aux (optional, per pose): approach_sign (N, 6), joint_temperature_c (N, 6),
        elapsed_s (N,), payload_kg (N,). Models that do not need them ignore them.
        """
        ...

    def parameters(self) -> dict[str, dict]:
        """name -> {"value", "std", "unit"} for every estimated parameter."""
        ...

    def to_dict(self) -> dict: ...


def aux_from_dataset(ds: Dataset) -> dict:
    """A dataset's operating conditions as the models' `predict(q, **aux)` takes them (an
    augmented model's thermal term reads the joint or the ambient temperature, or the time)."""
    return {
        "approach_sign": ds.approach_sign,
        "joint_temperature_c": ds.joint_temperature_c,
        "ambient_temperature_c": ds.ambient_temperature_c,
        "elapsed_s": ds.elapsed_s,
        "payload_kg": ds.payload_kg,
    }


def note_joint_range(model: FittedModel, q: np.ndarray) -> None:
    """Record in the model's `info["joint_range_rad"]` the per-joint [min, max] of the joints
    q (N, 6) it was fitted on: `export` warns about table nodes outside it (extrapolation)."""
    info = getattr(model, "info", None)
    q = np.atleast_2d(np.asarray(q, float))
    if isinstance(info, dict) and len(q) and np.all(np.isfinite(q)):
        info["joint_range_rad"] = np.stack([q.min(0), q.max(0)], 1).tolist()


def default_model_out(recording: str | os.PathLike, suffix: str) -> tuple[Path, str | None]:
    """Where a model of `recording` goes when no output is named: beside it, with `suffix`; or,
    when that folder takes no new file (an archive of recordings: kept as it is), under the same
    name in the current folder, with the line that says so (else None)."""
    out = Path(recording).with_suffix(suffix)
    if folder_problem(out.parent):
        return Path(out.name), (
            f"the recording's folder {out.parent} is read-only: the model file goes to "
            f"{out.name} here"
        )
    return out, None


def check_model_output(
    path: str | os.PathLike,
    recording: str | os.PathLike,
    *,
    force: bool = False,
    say: Callable[[str], None] | None = None,
    remedy: str = REPLACE_REMEDY,
) -> None:
    """Refuse, before any work, to write a model over an existing file, except an earlier model
    of the same recording (same sha256): the recording re-creates that one, so nothing is lost.
    `force` replaces anything but a recording (see `errors.refuse_overwrite`); `say(line)` is told
    what is being replaced; `remedy` ends a refusal (what to do instead)."""
    from workcell.recording.dataset import file_sha256

    p = Path(path)
    if not p.is_file() or not Path(recording).is_file():
        return  # nothing to replace, or the command refuses the missing recording itself
    try:
        d = strict_json.loads(p.read_text(encoding="utf-8-sig"))
    except PermissionError:
        raise UserError(
            f"model file {p} exists and cannot be read (permissions), so it cannot be checked "
            "before writing over it; "
            + ("choose another name" if remedy == REPLACE_REMEDY else remedy)
        ) from None
    except (OSError, ValueError, UnicodeDecodeError):
        d = None
    is_model = isinstance(d, dict) and d.get("format") == MODEL_FORMAT
    info = d.get("info") if is_model and isinstance(d.get("info"), dict) else {}
    same = is_model and info.get("recording_sha256") == file_sha256(recording)
    replace_or_refuse(
        "model file",
        p,
        f"an earlier {d.get('method')} model of this recording" if same else None,
        "a model of another recording" if is_model else "not a workcell model",
        force=force,
        say=say,
        remedy=remedy,
    )


def save_model(model: FittedModel, path: str | os.PathLike) -> Path:
    from workcell.atomic import write_text

    d = {"format": MODEL_FORMAT, **model.to_dict(), "conventions": model_conventions()}
    # whole or not at all: a temporary name beside the output, then an atomic rename
    return write_text(path, json.dumps(d, indent=1, allow_nan=False))


def model_conventions() -> dict:
    """Units and frames of a model file's arrays, written beside them (readers ignore it)."""
    from workcell.kinematics.chain import PARAM_NAMES, PARAM_UNITS, PARAMETER_FRAMES

    return {
        "theta": "geometric parameters in the order of parameter_names; units in theta_units",
        "theta_units": {n: PARAM_UNITS[n] for n in PARAM_NAMES},
        "parameter_frames": PARAMETER_FRAMES,
        "cov": "covariance of the estimated parameters, in the products of their units (m^2, "
        "m rad, rad^2; effects in the units `workcell fit`/`diagnose` print beside them)",
        "base_ref": "4x4 homogeneous transform tracker_T_base_ref (rotation, translation in m)",
        "nominal_dh": "a, d in m; alpha, theta_offset in rad",
        "thermal.ref": "reference link temperature in degC (source joint or ambient), hours "
        "(source time)",
        "positions": "SMR positions in m, tracker frame unless named otherwise",
    }


def model_fingerprint(model: FittedModel) -> str:
    """sha256 of what the model predicts with: its serialised form without `info` (which holds
    where its recording is and its held-out figures). Equal for a model and its saved and
    reloaded copy; different for another fit, even of the same recording and method."""
    import hashlib

    d = _fingerprinted({k: v for k, v in model.to_dict().items() if k != "info"})
    return hashlib.sha256(json.dumps(d, sort_keys=True, allow_nan=True).encode()).hexdigest()


# the keys of a derived `tracker_T_base` the fingerprint has always covered: its 1-sigma, added
# to model files on 2026-11-27, is left out, so tables exported before still match their model
_POSE_KEYS = ("translation_m", "quaternion_wxyz")


def _fingerprinted(d):
    """`d` as `model_fingerprint` hashes it: every `tracker_T_base` reduced to `_POSE_KEYS`."""
    if isinstance(d, dict):
        return {
            k: (
                {p: v[p] for p in _POSE_KEYS if p in v}
                if k == "tracker_T_base" and isinstance(v, dict)
                else _fingerprinted(v)
            )
            for k, v in d.items()
        }
    return d


def load_model(path: str | os.PathLike) -> FittedModel:
    p = Path(path)
    if not p.exists():
        raise UserError(f"{p}: no such model file; fit one with `workcell fit REC --out {p}`")
    if not p.is_file():  # a directory, or a pipe (reading it would wait forever)
        raise UserError(f"{p}: not a regular file; give a model file (.json)")
    try:
        d = strict_json.loads(p.read_text(encoding="utf-8-sig"))
    except strict_json.DuplicateKey as e:
        raise UserError(
            f"{p}: the key {e.args[0]!r} is given twice in one object (edited by hand?); a "
            "model file has each key once: fit it again with `workcell fit`"
        ) from None
    except (ValueError, UnicodeDecodeError) as e:
        why = getattr(e, "msg", "")
        why = why if why.startswith("nested too deeply") else "not JSON"
        raise UserError(f"{p}: not a workcell model file ({why})") from None
    if not isinstance(d, dict) or d.get("format") != MODEL_FORMAT:
        raise UserError(f"{p}: not a workcell model file (format is not {MODEL_FORMAT})")
    model = model_from_dict(d, source=str(p))
    _find_recording(model, p)
    return model


def _find_recording(model: FittedModel, model_path: Path) -> None:
    """Point the model's `info["recording"]` at the file it was fitted on: as stored (fit stores
    it absolute; older models stored it as typed, relative to wherever fit ran), else relative to
    the model's folder, else the same file name beside the model; a candidate whose sha256
    differs from the stored one is not it. When none is, `info["recording"]` becomes None and
    `info["recording_unusable"]` says why, for the commands that need it."""
    info = getattr(model, "info", None)
    rec = info.get("recording") if isinstance(info, dict) else None
    if not rec:
        return
    from workcell.recording.dataset import file_sha256

    sha = info.get("recording_sha256")
    here = model_path.parent
    seen = []
    for cand in (Path(rec), here / rec, here / Path(rec).name):
        if cand.is_file() and cand.resolve() not in seen:
            seen.append(cand.resolve())
            try:
                same = not sha or file_sha256(cand) == sha
            except OSError:
                continue
            if same:
                info["recording"] = str(cand)
                return
    info["recording"] = None
    info["recording_unusable"] = f"the model's recording {rec} " + (
        "has changed since the fit (its sha256 differs; so does any same-named file beside "
        "the model)"
        if seen
        else "was not found where it was fitted or beside the model"
    )


# joints inside every catalogue arm's range: a loaded model must predict finite positions there
_PROBE_Q = np.array([[0.0, -1.2, 1.0, -0.5, 0.4, 0.3], [0.5, -0.6, -0.8, 0.7, -1.1, -0.9]])


def model_from_dict(d: dict, source: str = "model") -> FittedModel:
    """Build a model from its file's dict; a malformed file is one UserError line.

    Besides the class's own parsing, the model must report its parameters and predict finite
    positions (N, 3) for two probe configurations: a file edited by hand or cut short fails here,
    not halfway through an export."""
    method = d.get("method") if isinstance(d, dict) else None
    if not isinstance(method, str) or method not in REGISTRY:
        raise UserError(f"{source}: unknown model method {method!r}")
    mod, cls = REGISTRY[method].split(":")
    try:
        klass = getattr(importlib.import_module(mod), cls)
    except ModuleNotFoundError:
        raise UserError(f"{source}: method {method!r} is not available in this build") from None
    info = d.get("info", {})
    if not isinstance(info, dict):
        raise UserError(f"{source}: malformed {method} model file (info is not an object)")
    if info.get("recording") is not None and not isinstance(info.get("recording"), str):
        raise UserError(f"{source}: malformed {method} model file (recording is not a path)")
    if (where := _number_as_text(d)) is not None:
        raise UserError(
            f"{source}: the {method} model file has a number written as text ({where}): edited "
            "by hand? write it as a number, or fit it again with `workcell fit`"
        )
    if (why := info_problem(info)) is not None:
        raise UserError(
            f"{source}: the {method} model file's info.{why}: edited by hand? restore the file "
            "or fit it again with `workcell fit`"
        )
    try:
        model = klass.from_dict(d)
        _check_base_ref(model, source, method)
        model.parameters()
        p = np.asarray(model.predict(_PROBE_Q), dtype=float)
    except UserError:
        raise
    except Exception as e:  # noqa: BLE001 - a hand-edited file may break any step (JAX too)
        if os.environ.get("WORKCELL_DEBUG"):
            raise
        raise UserError(
            f"{source}: malformed {method} model file ({type(e).__name__}: "
            f"{' '.join(str(e).split())[:100]}); "
            "fit it again with `workcell fit`"
        ) from None
    if p.shape != (len(_PROBE_Q), 3) or not np.all(np.isfinite(p)):
        raise UserError(
            f"{source}: the {method} model does not predict finite positions (shape {p.shape}); "
            "fit it again with `workcell fit`"
        )
    if np.abs(p).max() > MAX_PREDICTED_M:
        raise UserError(
            f"{source}: the {method} model puts the SMR {np.abs(p).max():.3g} m from the tracker "
            "(a parameter of the file is out of range); fit it again with `workcell fit`"
        )
    _check_joint_count(model, source, method)
    _check_derived_fields(d, model, source, method)
    _check_nominal_units(model, source, method)
    # a std may be "not given" (None/NaN: a hyperparameter at its bound, a CV-chosen one), but
    # a covariance with a negative variance (beyond rounding) is malformed, and so is one that
    # is not positive semi-definite: some combination of its parameters would have a negative
    # variance, and the 1-sigma propagated from it is wrong (larger or smaller)
    for m, where in ((model, ""), (getattr(model, "base", None), "base ")):
        for attr in ("cov", "geometric_cov"):
            c = getattr(m, attr, None) if m is not None else None
            if c is None or isinstance(m, np.ndarray):
                continue
            _check_covariance(np.asarray(c, dtype=float), source, method, where + attr)
    return model


def _check_base_ref(model: FittedModel, source: str, method: str) -> None:
    """A model's `base_ref` (the tracker_T_base its base parameters are offsets from) must be one
    rigid transform (`frames.check_transform`). Until 2026-11-28 a (3, 4) or (5, 4) matrix, or
    an inf in the bottom row, loaded (the prediction reads the top rows only) and failed later
    in an export."""
    from workcell.kinematics.frames import check_transform

    for m in (model, getattr(model, "base", None)):
        ref = getattr(m, "base_ref", None) if m is not None else None
        if ref is None:
            continue
        T = np.asarray(ref, dtype=float)
        try:
            if T.shape != (4, 4):
                raise ValueError(f"shape {T.shape}, not (4, 4)")
            check_transform(T)
        except ValueError as e:
            raise UserError(
                f"{source}: the {method} model's base_ref is not a rigid transform ({e}): "
                "edited by hand? restore the file or fit it again with `workcell fit`"
            ) from None


# text fields of a model file whose value may read as a number ("unit": "1", a hash, a path, a
# robot's name such as "1200": `robot` in dh/ekf-ann/gp/lddmm bases, `robot.model` in augmented)
_TEXT_KEYS = frozenset(
    {"unit", "units", "recording", "recording_sha256", "model_fingerprint", "robot", "model"}
)


def _number_as_text(x, path: str = "", key: str = "") -> str | None:
    """Where a model file holds a number as a string ("-0.425", in a list or as a value), or
    None: numpy's and Python's float conversion would read it as the number, though the file is
    not what fit wrote. Text fields (`_TEXT_KEYS`) and words ("nan" in a note) are not numbers."""
    if isinstance(x, dict):
        for k, v in x.items():
            if not path and k == "free":  # true/false values: its own check says so
                continue
            if (w := _number_as_text(v, f"{path}.{k}" if path else str(k), str(k))) is not None:
                return w
    elif isinstance(x, list):
        for i, v in enumerate(x):
            if (w := _number_as_text(v, f"{path}[{i}]", key)) is not None:
                return w
    elif isinstance(x, str) and key not in _TEXT_KEYS and any(c.isdigit() for c in x):
        try:
            float(x)
        except ValueError:
            return None
        return f"{path} = {x[:20]!r}"
    return None


def _number(v) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _metres(v, *, allow_nan: bool = False) -> bool:
    """A length in metres a model file states: a finite number >= 0 (NaN: none, where allowed)."""
    if not _number(v):
        return False
    return (allow_nan and math.isnan(v)) or (math.isfinite(v) and v >= 0.0)


def info_problem(info: dict) -> str | None:
    """What is wrong with the figures a model file's `info` states, which export, envelope and
    validate act on (a negative held-out RMS made `envelope --model` suggest a 1 mm margin where
    the model needs 5 mm; a 10**400 one was a traceback), or None. Absent keys are fine."""
    from workcell.recording.checks import is_finite_list

    for key in ("heldout_rms_m", "heldout_rms_unbounded_m"):
        v = info.get(key)
        if v is not None and not _metres(v):
            return f"{key} must be a finite number >= 0 (metres), got {str(v)[:40]}"
    ci = info.get("heldout_rms_ci95_m")
    if ci is not None:
        ok = isinstance(ci, list) and len(ci) == 2
        ok = ok and all(v is None or _metres(v, allow_nan=True) for v in ci)
        if ok and all(_metres(v) for v in ci):
            ok = ci[0] <= ci[1]
        if not ok:
            return f"heldout_rms_ci95_m must be [low, high] in metres, got {str(ci)[:60]}"
        rms = info.get("heldout_rms_m")
        if (
            rms is not None
            and all(_metres(v) for v in ci)
            and not (ci[0] * (1 - 1e-9) <= rms <= ci[1] * (1 + 1e-9))
        ):  # the interval fit writes always holds its RMS (its chi-square part does)
            return (
                f"heldout_rms_m {rms:.6g} m lies outside its own 95 % interval "
                f"[{ci[0]:.6g}, {ci[1]:.6g}] m"
            )
    u = info.get("unexplained")
    if u is not None:
        if not isinstance(u, dict):
            return "unexplained must be an object"
        for k, v in u.items():
            if k.endswith("_m") and v is not None and not _metres(v):
                return f"unexplained.{k} must be a finite number >= 0 (metres), got {str(v)[:40]}"
    jr = info.get("joint_range_rad")
    if jr is not None:
        ok = isinstance(jr, list) and all(
            is_finite_list(r, 2) and r[0] <= r[1] and max(map(abs, r)) <= 4 * math.pi for r in jr
        )
        if not ok:
            return "joint_range_rad must be [low, high] radians per joint, within +-4 pi"
    tool = info.get("nominal_tool_m")
    if tool is not None and not is_finite_list(tool, 3):  # its size: `_check_nominal_units`
        return f"nominal_tool_m must be 3 finite numbers (metres), got {str(tool)[:60]}"
    sha = info.get("recording_sha256")
    if sha is not None and not isinstance(sha, str):
        return f"recording_sha256 must be a text hash, got {str(sha)[:40]}"
    return None


GEOMETRY_ATTRS = (None, "base", "base_model", "dh_model", "geometric")


def geometric_part(model: FittedModel) -> Any:
    """The object holding a model's geometry: `theta` (5 n + 9,) with the base parameters and
    `base_ref` (4x4): the model itself or the geometric model it wraps (`GEOMETRY_ATTRS`); None
    for a model without one."""
    for attr in GEOMETRY_ATTRS:
        g = model if attr is None else getattr(model, attr, None)
        if g is None or isinstance(g, np.ndarray):
            continue
        th, ref = getattr(g, "theta", None), getattr(g, "base_ref", None)
        if th is not None and ref is not None and np.ndim(th) == 1 and np.shape(ref) == (4, 4):
            return g
    return None


def geometric_cov(g: Any) -> np.ndarray | None:
    """`g.theta_cov()` of a `geometric_part` as a finite (P, P) array, P = len(g.theta); None
    when it has none (or one of another shape, or not finite)."""
    get = getattr(g, "theta_cov", None)
    if not callable(get):
        return None
    try:
        c = get()
    except Exception:  # noqa: BLE001 - a model without a usable covariance states none
        return None
    if c is None:
        return None
    c = np.asarray(c, float)
    n = len(g.theta)
    return c if c.shape == (n, n) and np.all(np.isfinite(c)) else None


def _check_joint_count(model, source: str, method: str) -> None:
    """Campaigns, recordings, exports and validation are for the 6-joint arms: a model of
    another chain (the design bench's 7-joint one) is refused, not folded into a UR's six."""
    from workcell.kinematics.chain import N_JOINTS, joints_of

    g = geometric_part(model)
    if g is None:
        return
    try:
        n = joints_of(np.asarray(g.theta))
    except (ValueError, TypeError):
        n = None
    if n != N_JOINTS:
        raise UserError(
            f"{source}: the {method} model has {len(g.theta)} geometric parameters, not the "
            f"{5 * N_JOINTS + 9} of a {N_JOINTS}-joint arm: exports, envelopes and "
            "validation are for the 6-joint UR arms (a 7-joint chain is the design bench's "
            "only); fit a model of this arm's recording"
        )


COV_PSD_RTOL = 1e-9  # eigenvalues down to -this x the largest are rounding


MAX_GEOMETRIC_VARIANCE = 100.0  # (10 m or 10 rad)^2: beyond any geometric parameter's std


def _check_covariance(c: np.ndarray, source: str, method: str, attr: str) -> None:
    """Refuse a covariance that is not square, not finite, has a negative variance or (once
    symmetrised) an eigenvalue below -COV_PSD_RTOL x its largest: not a covariance."""
    again = "fit it again with `workcell fit`"
    v = np.diag(c) if c.ndim == 2 else np.array([np.nan])
    if not np.all(np.isfinite(c)) or np.any(v < -COV_PSD_RTOL * np.abs(v).max()):
        raise UserError(
            f"{source}: the {method} model's {attr} has a negative or non-finite variance; {again}"
        )
    if c.shape[0] != c.shape[1] or not c.size:
        raise UserError(f"{source}: the {method} model's {attr} is not a square matrix; {again}")
    if c.shape[0] % 5 == 4 and v.max() > MAX_GEOMETRIC_VARIANCE:  # a geometric (5 n + 9) one
        j = int(np.argmax(v))
        raise UserError(
            f"{source}: the {method} model's {attr} gives parameter {j} a standard deviation of "
            f"{np.sqrt(v[j]):.3g} (metres or radians): no calibration is that uncertain; edited "
            f"by hand? {again}"
        )
    w = np.linalg.eigvalsh(0.5 * (c + c.T))
    if w[0] < -COV_PSD_RTOL * max(float(w[-1]), 0.0):
        raise UserError(
            f"{source}: the {method} model's {attr} is not a covariance (not positive "
            f"semi-definite: eigenvalue {w[0]:.3g} against the largest {w[-1]:.3g}), so the "
            f"1-sigma propagated from it would be wrong; edited by hand? {again}"
        )


MAX_PREDICTED_M = 1e3  # a laser tracker measures within ~100 m


def _check_derived_fields(d: dict, model: FittedModel, source: str, method: str) -> None:
    """A model file also writes fields derived from its parameters, for people to read (the
    parameter names, the tracker_T_base pose). Loading ignores them, so an edit of one would
    change nothing while seeming to: refuse a file where they no longer match."""
    ref = model.to_dict()
    edit = "edited by hand? it is written for reading and derived from the parameters"
    names = d.get("parameter_names")
    if names is not None and names != ref.get("parameter_names", names):
        raise UserError(
            f"{source}: the {method} model's parameter_names do not match its parameters ({edit}); "
            "restore the file or fit it again with `workcell fit`"
        )
    pose, want = d.get("tracker_T_base"), ref.get("tracker_T_base")
    if pose is None or want is None:
        return
    try:
        t = np.asarray(pose["translation_m"], dtype=float)
        q = np.asarray(pose["quaternion_wxyz"], dtype=float)
        ok = (
            t.shape == (3,)
            and q.shape == (4,)
            and np.allclose(t, want["translation_m"], rtol=0, atol=1e-9)
            and abs(abs(float(q @ np.asarray(want["quaternion_wxyz"]))) - 1.0) < 1e-9
        )
    except (KeyError, TypeError, ValueError):
        ok = False
    if not ok:
        raise UserError(
            f"{source}: the {method} model's tracker_T_base does not match its parameters ({edit}); "
            "restore the file or fit it again with `workcell fit`"
        )


def rms(e: np.ndarray) -> float:
    """RMS of 3-D position errors (N, 3) -> metres."""
    e = np.asarray(e)
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1)))) if len(e) else float("nan")


RMS_INTERVAL_LEVEL = 0.95
RMS_INTERVAL_RESAMPLES = 2000
RMS_INTERVAL_BASIS = (
    "95 % interval of the RMS over the evaluated poses: the wider of a BCa bootstrap (2,000 "
    "resamples, seed 0) and a chi-square interval for the mean square with Satterthwaite's "
    "degrees of freedom (at most 3 a pose); the bootstrap alone covered the true RMS only "
    "75-78 % of the time on 10-20 held-out poses of simulated fits "
    "(docs/rms_interval_coverage.py). How much the figure depends on which poses were "
    "measured; it does not cover a bias shared by all poses (tracker scale, temperature)"
)


def _rms(x, axis=-1):
    """sqrt(mean(x^2)) along `axis`, scaled by max|x| so huge errors do not overflow."""
    x = np.asarray(x, float)
    s = np.max(np.abs(x), axis=axis, keepdims=True)
    s = np.where(np.isfinite(s) & (s > 0), s, 1.0)
    return np.squeeze(s, axis=axis) * np.sqrt(np.mean((x / s) ** 2, axis=axis))


def _bootstrap_interval(data: tuple, stat, level: float, seed: int) -> tuple[float, float]:
    """scipy.stats.bootstrap over the poses (paired when several arrays): BCa, percentile when
    BCa is degenerate, the point value twice when there is no spread to resample at all."""
    from scipy.stats import bootstrap

    for method in ("BCa", "percentile"):
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = bootstrap(
                data,
                stat,
                paired=len(data) > 1,
                confidence_level=level,
                n_resamples=RMS_INTERVAL_RESAMPLES,
                method=method,
                rng=np.random.default_rng(seed),
            )
        lo, hi = float(res.confidence_interval.low), float(res.confidence_interval.high)
        if np.isfinite(lo) and np.isfinite(hi):
            return lo, hi
    v = float(stat(*data))
    return v, v


def _chi2_rms_interval(e: np.ndarray, level: float, dims: int = 3) -> tuple[float, float]:
    """Interval of the RMS from its mean square taken as a scaled chi-square whose degrees of
    freedom come from the sample (Satterthwaite: nu = 2 n m^2 / var(e^2)), at most `dims` a
    pose (exact for isotropic Gaussian errors in `dims` axes)."""
    from scipy.stats import chi2

    # the interval scales with the errors: work on e / max|e| so that squares neither overflow
    # (errors of 1e200 m from a diverged fit) nor underflow
    scale = float(np.max(np.abs(e))) if len(e) else 0.0
    if not (np.isfinite(scale) and scale > 0.0):
        r = float(np.sqrt(np.mean(e * e))) if len(e) else float("nan")
        return r, r
    d2 = (e / scale) ** 2
    n, m, v = len(d2), float(d2.mean()), float(d2.var(ddof=1))
    if m <= 0.0 or v <= (1e-9 * m) ** 2:  # no spread to go by (as the bootstrap)
        return scale * float(np.sqrt(m)), scale * float(np.sqrt(m))
    nu = min(2.0 * n * m * m / v, float(dims * n))
    a = (1.0 - level) / 2.0
    return (
        scale * float(np.sqrt(nu * m / chi2.ppf(1.0 - a, nu))),
        scale * float(np.sqrt(nu * m / chi2.ppf(a, nu))),
    )


def rms_interval(
    e_norm: np.ndarray, level: float = RMS_INTERVAL_LEVEL, seed: int = 0
) -> tuple[float, float]:
    """Confidence interval of sqrt(mean(e^2)) over the poses, from the per-pose 3-D error norms
    `e_norm` (N,): the wider of a BCa bootstrap (scipy.stats.bootstrap, seeded so a report is
    reproducible) and a Satterthwaite chi-square interval (`RMS_INTERVAL_BASIS`). The bootstrap
    alone undercovers with few poses. (nan, nan) for fewer than 3 poses or a non-finite error."""
    e = np.asarray(e_norm, float).ravel()
    if len(e) < 3 or not np.all(np.isfinite(e)):
        return float("nan"), float("nan")
    b_lo, b_hi = _bootstrap_interval((e,), _rms, level, seed)
    c_lo, c_hi = _chi2_rms_interval(e, level)
    return min(b_lo, c_lo), max(b_hi, c_hi)


def _paired_interval(a, b, stat, level: float, seed: int) -> tuple[float, float]:
    """`_bootstrap_interval` of stat(a, b) over paired values; (nan, nan) for fewer than 3 pairs
    or a non-finite value; ValueError for arrays of other shapes."""
    a = np.asarray(a, float).ravel()
    b = np.asarray(b, float).ravel()
    if a.shape != b.shape:
        raise ValueError(f"paired values need the same shape, got {a.shape} and {b.shape}")
    if len(a) < 3 or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return float("nan"), float("nan")
    return _bootstrap_interval((a, b), stat, level, seed)


def rms_gain_interval(
    e_without: np.ndarray, e_with: np.ndarray, level: float = RMS_INTERVAL_LEVEL, seed: int = 0
) -> tuple[float, float]:
    """Confidence interval of RMS(e_without) - RMS(e_with) over the same poses (paired BCa
    bootstrap): the held-out gain of adding something to a model, with the pose-to-pose spread
    that a point comparison hides. (nan, nan) for fewer than 3 poses."""
    return _paired_interval(
        e_without, e_with, lambda x, y, axis=-1: _rms(x, axis) - _rms(y, axis), level, seed
    )


def rms_ratio_interval(
    e_before: np.ndarray, e_after: np.ndarray, level: float = RMS_INTERVAL_LEVEL, seed: int = 0
) -> tuple[float, float]:
    """Confidence interval of RMS(e_before) / RMS(e_after) over the same poses (paired BCa
    bootstrap): an improvement factor with its pose-to-pose spread. (nan, nan) for fewer than 3
    poses or a non-finite error."""

    def ratio(x, y, axis=-1):
        return _rms(x, axis) / np.maximum(_rms(y, axis), 1e-300)

    return _paired_interval(e_before, e_after, ratio, level, seed)


def mean_ratio_interval(
    a: np.ndarray, b: np.ndarray, level: float = RMS_INTERVAL_LEVEL, seed: int = 0
) -> tuple[float, float]:
    """Confidence interval of mean(a) / mean(b) over paired observations (paired bootstrap: BCa,
    percentile when BCa is degenerate). (nan, nan) for fewer than 3 pairs or a non-finite
    value."""

    def ratio(x, y, axis=-1):
        return np.mean(x, axis) / np.maximum(np.mean(y, axis), 1e-300)

    return _paired_interval(a, b, ratio, level, seed)


def interval_um(ci: Sequence[float] | np.ndarray | None, label: bool = True) -> str:
    """'95 % CI 88.2-115.3 um' (or without the label '88.2-115.3 um') for an interval [low,
    high] in metres; '' when there is none (an older report, too few poses)."""
    if ci is None or len(ci) != 2 or not all(np.isfinite(ci)):
        return ""
    return ("95 % CI " if label else "") + f"{ci[0] * 1e6:.1f}-{ci[1] * 1e6:.1f} um"


UNEXPLAINED_BASIS = (
    "held-out RMS above the noise floor, in quadrature: sqrt(max(RMS^2 - floor^2, 0)); the "
    "upper figure uses the upper end of the RMS's 95 % interval (resampling the held-out poses) "
    "with the floor taken as exact. It is what the model leaves out at the measured poses, "
    "beyond the tracker's noise: not part of the model's own 1-sigma"
)


def unexplained_error(
    rms_m: float, rms_ci95_m: Sequence[float] | np.ndarray | None, floor_m: float
) -> dict | None:
    """What a model leaves unexplained beyond the noise floor, from its held-out RMS:
    `{"rms_m", "upper_m", "floor_m", "basis"}` (metres; `upper_m` from the upper end of the
    RMS's 95 % interval, None without one), or None when the figures are missing or not finite.

    Below the floor the estimate is 0 and `upper_m` says how large an unexplained part the
    held-out poses could still hide under the tracker's noise."""
    try:
        rms, floor = float(rms_m), float(floor_m)
    except (TypeError, ValueError):
        return None
    if not (np.isfinite(rms) and np.isfinite(floor) and rms >= 0.0 and floor >= 0.0):
        return None

    def above(x: float) -> float:  # sqrt(max(x^2 - floor^2, 0)), without overflow
        return float(np.sqrt(max((x - floor) * (x / 2.0 + floor / 2.0), 0.0)) * np.sqrt(2.0))

    upper = None
    if rms_ci95_m is not None and len(rms_ci95_m) == 2 and np.isfinite(rms_ci95_m[1]):
        upper = above(float(rms_ci95_m[1]))
        upper = upper if np.isfinite(upper) else None
    excess = above(rms)
    if not np.isfinite(excess):
        return None
    return {
        "rms_m": excess,
        "upper_m": upper,
        "floor_m": floor,
        "basis": UNEXPLAINED_BASIS,
    }


def unexplained_text(u: dict | None) -> str:
    """'3.1 um above the noise floor (up to 5.7 um at the upper end of the 95 % interval)', or
    '' for None."""
    if not u:
        return ""
    txt = f"{u['rms_m'] * 1e6:.1f} um above the noise floor"
    if u.get("upper_m") is None:
        return txt
    if u["upper_m"] > 0.0:
        return txt + f" (up to {u['upper_m'] * 1e6:.1f} um at the upper end of the 95 % interval)"
    return txt + " (the upper end of the 95 % interval is below the floor too)"


def error_stats(p_pred: np.ndarray, p_meas: np.ndarray, *, interval: bool = False) -> dict:
    """RMS, mean, median and max of the 3-D position error per pose; with `interval`, also
    `rms_ci95_m` ([low, high], `rms_interval`)."""
    e = np.linalg.norm(np.asarray(p_pred) - np.asarray(p_meas), axis=1)
    if not len(e):
        out = {
            "rms_m": float("nan"),
            "mean_m": float("nan"),
            "max_m": float("nan"),
            "median_m": float("nan"),
        }
    else:
        out = {
            "rms_m": float(np.sqrt(np.mean(e**2))),
            "mean_m": float(e.mean()),
            "median_m": float(np.median(e)),
            "max_m": float(e.max()),
        }
    if interval:
        out["rms_ci95_m"] = list(rms_interval(e))
    return out


def _check_robot_chain(m, nd, source: str, method: str, where: str) -> None:
    """A model's `robot` must be the arm its nominal chain is of (a catalogue arm's link lengths
    within `CHAIN_TOL_M`): `export` scales its default volume and `validate` picks the arm
    by that name, while the IK uses the chain; one edited without the other is refused."""
    from workcell.kinematics.robots import catalogue_mismatch

    name = getattr(m, "robot_model", None)
    if (why := catalogue_mismatch(name, nd.a, nd.d)) is not None:
        raise UserError(
            f"{source}: the {method} model says robot {name!r} but its {where}nominal chain is "
            f"not a {name}'s: {why}; edited by hand? restore the file or fit it again with "
            "`workcell fit`"
        )


def _check_nominal_units(model, source: str, method: str) -> None:
    """The nominal chain and SMR a model file carries (what `export` and `validate` command the
    arm with: `export.correction.nominal_for`) in the format's units, with the recording's
    limits (`recording.checks`): link lengths and the SMR offset in metres, angles in radians.
    A file in millimetres or degrees otherwise fails later as "no finite correction ... shrink
    the volume", or exports a 60 m TCP."""
    from workcell.kinematics.chain import N_JOINTS
    from workcell.recording.checks import DH_LENGTH_MAX_M, SMR_OFFSET_MAX_M, _length_hint

    again = "fit it again with `workcell fit`"
    # a dh model carries its nominal chain; gp and lddmm models carry it in their dh `base`;
    # augmented and ekf-ann models take theirs from the recording, checked when it was read
    for m, where in ((model, ""), (getattr(model, "base", None), "base ")):
        nd = getattr(m, "nominal_dh", None)
        if nd is None:
            continue
        sizes = {k: np.asarray(getattr(nd, k)).size for k in ("a", "d", "alpha", "theta_offset")}
        if set(sizes.values()) != {N_JOINTS}:  # the 6-joint fit beside it reads the first six
            raise UserError(
                f"{source}: the {method} model's {where}nominal_dh has "
                + ", ".join(f"{v} {k}" for k, v in sizes.items())
                + f", not {N_JOINTS} of each (a {N_JOINTS}-joint arm's): edited by hand? restore "
                f"the file or {again}"
            )
        for name, lim, unit, other in (
            ("a", DH_LENGTH_MAX_M, "m", "millimetres; the format wants metres"),
            ("d", DH_LENGTH_MAX_M, "m", "millimetres; the format wants metres"),
            ("alpha", 2 * np.pi, "rad", "degrees; the format wants radians"),
            ("theta_offset", 2 * np.pi, "rad", "degrees; the format wants radians"),
        ):
            v = np.abs(np.asarray(getattr(nd, name), float))
            if v.size and np.any(v > lim):
                j = int(np.argmax(v))
                raise UserError(
                    f"{source}: the {method} model's {where}nominal_dh {name}[{j}] is "
                    f"{v[j]:.4g} {unit} (more than {lim:.4g} {unit}): it looks like {other}; "
                    f"{again}"
                )
        _check_robot_chain(m, nd, source, method, where)
        info = getattr(m, "info", None)
        tool = info.get("nominal_tool_m") if isinstance(info, dict) else None
        if tool is not None:
            try:
                tv = np.asarray(tool, float)
            except (TypeError, ValueError):
                tv = None
            if tv is None or tv.shape != (3,) or not np.all(np.isfinite(tv)):
                raise UserError(
                    f"{source}: the {method} model's {where}nominal_tool_m must be 3 finite "
                    f"numbers (the SMR on the flange, m), got {tool!r}; {again}"
                )
            r = float(np.linalg.norm(tv))
            if r > SMR_OFFSET_MAX_M:
                raise UserError(
                    f"{source}: the {method} model's {where}nominal_tool_m is {r:.4g} m from "
                    f"the flange (more than {SMR_OFFSET_MAX_M:g} m): "
                    f"{_length_hint(r, SMR_OFFSET_MAX_M)}; {again}"
                )
        th = getattr(m, "theta", None)
        th = None if th is None else np.asarray(th, float)
        if th is not None and th.shape == (39,):  # the fitted geometry: lengths and SMR too
            lengths = np.abs(np.r_[th[0:6], th[6:12]])
            j = int(np.argmax(lengths))
            if lengths[j] > DH_LENGTH_MAX_M:
                raise UserError(
                    f"{source}: the {method} model's {where}theta {'ad'[j // 6]}{j % 6 + 1} is "
                    f"{lengths[j]:.4g} m (more than {DH_LENGTH_MAX_M:g} m): "
                    f"{_length_hint(lengths[j], DH_LENGTH_MAX_M)}; {again}"
                )
            # angles: a fit starts at the nominal chain and corrects it by milliradians, so no
            # fit makes one beyond a turn; alphas in degrees (90 for pi/2) loaded and moved the
            # SMR by metres, found only by the ros-yaml export
            angles = np.abs(th[12:30])
            k = int(np.argmax(angles))
            if angles[k] > 2 * np.pi:
                from workcell.kinematics.chain import PARAM_NAMES

                hint = (
                    "it looks like degrees; the format wants radians"
                    if angles[k] <= 400.0
                    else "beyond any angle a fit makes (edited by hand?)"
                )
                raise UserError(
                    f"{source}: the {method} model's {where}theta {PARAM_NAMES[12 + k]} is "
                    f"{angles[k]:.4g} rad (more than 2 pi: no fit turns a joint's geometry that "
                    f"far): {hint}; {again}"
                )
            r = float(np.linalg.norm(th[36:39]))
            if r > SMR_OFFSET_MAX_M:
                raise UserError(
                    f"{source}: the {method} model's {where}fitted SMR offset (theta 36..38) is "
                    f"{r:.4g} m from the flange (more than {SMR_OFFSET_MAX_M:g} m): "
                    f"{_length_hint(r, SMR_OFFSET_MAX_M)}; {again}"
                )


def evaluated_figure(report: dict, name: str) -> Any:
    """A fit report's figure `name` ("rms_m", "rms_ci95_m", "max_m", "median_m") on the poses it
    was evaluated on: the held-out ones, or the training ones for a fit without a hold-out."""
    held_out = bool(report.get("heldout_poses", 1))
    return report.get(f"{'heldout' if held_out else 'train'}_{name}")
