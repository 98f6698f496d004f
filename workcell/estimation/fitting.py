"""Fit a recording with any method and evaluate it on a deterministic held-out split.

Every method returns a model with the FittedModel interface; this module owns the split, the
nominal baseline and the report (the keys `workcell fit --json` prints).
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from workcell.errors import UserError
from workcell.estimation.dh import (
    TRACKER_MPE_M,
    DHModel,
    fit_dh,
    nominal_registered,
    pose_sigma,
    pose_sigma_model,
)
from workcell.estimation.models import (
    RMS_INTERVAL_BASIS,
    FittedModel,
    aux_from_dataset,
    error_stats,
    note_joint_range,
    save_model,
    unexplained_error,
)
from workcell.kinematics.chain import (
    PARAMETER_FRAMES,
    joints_of,
    p_tracker,
    param_names,
    param_unit,
)
from workcell.recording.dataset import HOLDOUT_SEED, Dataset, distinct_poses, read_warnings

if TYPE_CHECKING:
    import os

MIN_TRAIN_POSES = 12  # a fit refuses fewer training poses (or distinct configurations)


def min_poses_for_fit(holdout: float = 0.25) -> int:
    """Fewest poses whose training part (after the held-out `holdout` fraction) a fit accepts."""
    n = MIN_TRAIN_POSES
    while n - int(round(holdout * n)) < MIN_TRAIN_POSES:
        n += 1
    return n


# method -> "module:function(ds_train, *, on, bounds, progress) -> (model, extra dict)"
FIT_METHODS: dict[str, str] = {
    "dh": "workcell.estimation.fitting:_fit_dh",
    "lddmm": "workcell.estimation.lddmm_fit:fit_method",
    "gp": "workcell.estimation.gp_residual:fit_method",
}


def _fit_dh(
    ds: Dataset, *, bounds=None, progress=None, tracker_mpe=TRACKER_MPE_M, **_
) -> tuple[DHModel, dict]:
    if bounds is not None:  # "" is refused by the bounds reader, not taken as no bounds
        from workcell.estimation.bounded import fit_dh_bounded  # experiment-design issue

        m = fit_dh_bounded(ds, bounds=bounds, tracker_mpe=tracker_mpe)
        # `converged` False makes `fit` warn (it was only in the model file's info)
        return m, {"qp_iterations": m.info["qp_iterations"], "converged": m.info["converged"]}
    return fit_dh(ds, tracker_mpe=tracker_mpe), {}


def parameter_std_basis(model: object) -> str:
    """What the `std` beside each fitted parameter is, for this model (and its base models)."""
    geo = getattr(model, "base", None) or model  # gp and lddmm sit on a DH model
    info = getattr(geo, "info", {}) or {}
    vf = info.get("variance_factor")
    parts = [
        "geometry (DH, offsets, base, SMR): 1 sigma, s0^2 (J^T W J)^-1 at the fit, W from the "
        "per-pose sigmas max(recorded, tracker MPE / 4)"
        + (
            f", s0^2 = {vf:.3g} the a posteriori variance factor (weighted residual variance; "
            "above 1 when the tracker or the model leave more scatter than those sigmas, which this "
            "std then carries)"
            if isinstance(vf, (int, float)) and np.isfinite(vf)
            else ""
        )
        + "; it holds for this model: an effect it leaves out biases beyond it"
    ]
    held = list(info.get("std_conditional_on") or info.get("active_bounds") or ())
    if held:
        parts.append(
            "conditional on the parameters a bound holds ("
            + ", ".join(held)
            + "), taken as exactly known at their bound values: with them estimated the "
            "others' stds would be larger (compare the fit without --bounds)"
        )
    if hasattr(model, "log_hyper_std"):
        parts.append(
            "gp_*: Laplace, the inverse Hessian of the negative log marginal likelihood in log "
            "space propagated to the value; none at a bound ('at bound') or where the likelihood "
            "has no proper maximum ('no peak': its Hessian is not positive definite)"
        )
    if hasattr(model, "lddmm"):
        parts.append(
            "lddmm_*: chosen by 5-fold cross-validation over a grid (extra.cv_grid), no Gaussian "
            "std"
        )
    return "; ".join(parts)


def stated_noise_floor(ds: Dataset) -> float:
    """Held-out RMS that the recording's stated per-axis sigmas alone would give (sqrt(sum var))."""
    return float(np.sqrt(np.mean(np.sum(ds.sigma_m**2, axis=1))))


def tracker_noise_floor(ds: Dataset, mpe: tuple[float, float] = TRACKER_MPE_M) -> float:
    """Held-out RMS that the tracker's errors alone would give: per-axis sigma
    max(recorded, (A + B * range) / 4) (`pose_sigma_model`), so the per-pose systematic error
    that averaging readings cannot remove is counted. The model's own estimation uncertainty is
    not included (`workcell diagnose` adds it for its geometry)."""
    return float(np.sqrt(np.mean(3.0 * pose_sigma_model(ds, mpe) ** 2)))


HELDOUT_OUTLIER_SIGMAS = 15.0  # robust sigmas, the band of the fits' robust pass (3 x 5)


def heldout_outliers(
    p_pred: np.ndarray, ev: Dataset, tracker_mpe: tuple[float, float] = TRACKER_MPE_M
) -> dict | None:
    """Held-out poses `ev` whose error (model prediction `p_pred` (N, 3) against the measured
    point) lies beyond 15 robust sigmas (MAD) of the held-out errors.
    One outlier reading there inflates the held-out RMS and what it says the model leaves
    unexplained; this names them (`pose_ids`, `errors_m`) and gives both figures without them
    (`heldout_rms_m`, `heldout_rms_ci95_m`, `unexplained`, the floor from the other poses).
    The error is not weighted: a bad reading among a pose's few also inflates its recorded sigma
    (its weighted error then looks ordinary). None when there are none, with fewer than 10
    held-out poses, or when more than 20 % would go (then it is the model's error)."""
    if len(ev) < 10:
        return None
    e = np.linalg.norm(p_pred - ev.p_tracker, axis=1)
    med = np.median(e)
    mad = 1.4826 * np.median(np.abs(e - med)) + 1e-12
    out = e > med + HELDOUT_OUTLIER_SIGMAS * mad
    if not out.any() or out.sum() > 0.2 * len(ev):
        return None
    rest = ev.subset(np.flatnonzero(~out))
    st = error_stats(p_pred[~out], rest.p_tracker, interval=True)
    floor = tracker_noise_floor(rest, tracker_mpe)
    return {
        "pose_ids": [int(ev.pose_id[i]) for i in np.flatnonzero(out)],
        "errors_m": e[out].tolist(),
        "rule": f"error beyond {HELDOUT_OUTLIER_SIGMAS:g} robust sigmas (MAD) of the held-out "
        "errors",
        "heldout_rms_m": st["rms_m"],
        "heldout_rms_ci95_m": st["rms_ci95_m"],
        "unexplained": unexplained_error(st["rms_m"], st["rms_ci95_m"], floor),
    }


HELD_FIGURES = ("rms_m", "rms_ci95_m", "max_m", "median_m")  # heldout_* (train_* without)


def fit_dataset(
    ds: Dataset,
    *,
    method: str = "dh",
    holdout: float = 0.25,
    on: str = "auto",
    bounds: str | None = None,
    tracker_mpe: tuple[float, float] = TRACKER_MPE_M,
    progress: Callable[[str], None] | None = None,
) -> tuple[FittedModel, dict]:
    if method not in FIT_METHODS:
        raise UserError(f"unknown method {method!r}; choose from {', '.join(FIT_METHODS)}")
    train, test = ds.holdout_split(holdout)
    if len(train) < MIN_TRAIN_POSES:
        raise UserError(
            f"only {len(train)} training poses (of {len(ds)} with {holdout:.0%} held out); a "
            f"fit needs at least {MIN_TRAIN_POSES}: "
            + (
                "hold fewer out (the held-out fraction, --holdout) or measure a campaign with "
                "more poses"
                if len(ds) >= MIN_TRAIN_POSES
                else f"measure a campaign with at least {min_poses_for_fit(holdout)} poses"
            )
        )
    n_distinct = distinct_poses(ds.q[train])
    if n_distinct < MIN_TRAIN_POSES:
        raise UserError(
            f"only {n_distinct} distinct joint configurations among the {len(train)} training "
            f"poses; a fit needs at least {MIN_TRAIN_POSES} different poses (the same pose "
            "measured again adds no geometry)"
        )
    dtr, dte = ds.subset(train), ds.subset(test)
    mod, fn = FIT_METHODS[method].split(":")
    try:
        fit_fn = getattr(importlib.import_module(mod), fn)
    except ModuleNotFoundError:
        raise UserError(f"method {method!r} is not available in this build") from None
    t0 = time.perf_counter()
    model, extra = fit_fn(dtr, on=on, bounds=bounds, progress=progress, tracker_mpe=tracker_mpe)
    fit_s = time.perf_counter() - t0
    note_joint_range(model, dtr.q)
    th_nom, base_nom = nominal_registered(dtr)
    ev = dte if len(dte) else dtr
    nominal = error_stats(
        np.asarray(p_tracker(th_nom, base_nom, ev.q)), ev.p_tracker, interval=True
    )
    pred = model.predict(ev.q, **aux_from_dataset(ev))
    held = error_stats(pred, ev.p_tracker, interval=True)
    train_stats = error_stats(model.predict(dtr.q, **aux_from_dataset(dtr)), dtr.p_tracker)
    params = model.parameters()
    info = getattr(model, "info", {}) or {}
    for n in info.get("pinned_by_bounds") or ():
        if n in params:  # a bound [v, v] fixes it at v: not estimated, no std
            params[n].update(std=None, at_bound=True, fixed_by_bound=True)
    report = {
        "method": method,
        **ds.provenance(),
        **({"chain": ds.chain_line} if ds.chain_line else {}),
        "robot": ds.robot.model,
        "train_poses": int(len(train)),
        "heldout_poses": int(len(test)),
        "split": f"seeded permutation (seed {HOLDOUT_SEED}), {holdout:.0%} held out"
        + (
            "; poses measured more than once trained on"
            if len(np.unique(ds.pose_groups())) < len(ds)
            else ""
        )
        if len(test)
        else "no hold-out: numbers are on the training poses",
        # with --holdout 0 the figures are on the training poses: train_*, heldout_* null
        # (until 2026-11-26 they were under the heldout_* keys, `evaluated_on` saying so)
        "evaluated_on": "held-out poses" if len(dte) else "training poses (no hold-out)",
        "nominal_rms_m": nominal["rms_m"],
        "nominal_rms_ci95_m": nominal["rms_ci95_m"],
        "nominal_max_m": nominal["max_m"],
        **{f"heldout_{k}": held[k] if len(dte) else None for k in HELD_FIGURES},
        **({} if len(dte) else {f"train_{k}": held[k] for k in HELD_FIGURES if k != "rms_m"}),
        "rms_interval_basis": RMS_INTERVAL_BASIS,
        "train_rms_m": train_stats["rms_m"],
        "stated_noise_floor_m": stated_noise_floor(ev),
        "tracker_noise_floor_m": (floor := tracker_noise_floor(ev, tracker_mpe)),
        "unexplained": unexplained_error(held["rms_m"], held["rms_ci95_m"], floor)
        if len(dte)
        else None,
        "heldout_outliers": heldout_outliers(pred, ev, tracker_mpe) if len(dte) else None,
        "tracker_mpe": {"a_m": float(tracker_mpe[0]), "b_m_per_m": float(tracker_mpe[1])},
        "tracker_noise_floor_basis": (
            f"per-pose sigma = max(recorded, tracker MPE ({tracker_mpe[0] * 1e6:g} um + "
            f"{tracker_mpe[1] * 1e6:g} um/m) / 4)"
        ),
        "fit_seconds": fit_s,
        "parameters": params,
        "parameter_std_basis": parameter_std_basis(model),
        "parameter_frames": PARAMETER_FRAMES,
        "unidentifiable": getattr(model, "unidentifiable", []),
        "identifiability": info.get("identifiability"),
        "outliers_rejected": info.get("outliers_rejected", 0),
        "extra": extra,
    }
    report["bounds"] = (
        bounds_summary(model, bounds, held["rms_m"], dtr, ev, tracker_mpe)
        if method == "dh" and bounds is not None
        else None
    )
    report["smr_change"] = smr_change(params)
    report["tracker_T_base"] = combined_base(model)
    report["heldout_model_std"] = (
        heldout_std_check(model, dte, tracker_mpe, pred=pred) if len(dte) else None
    )
    return model, report


def heldout_std_check(
    model: FittedModel,
    ds: Dataset,
    tracker_mpe: tuple[float, float] = TRACKER_MPE_M,
    *,
    pred: np.ndarray | None = None,
) -> dict | None:
    """The model's stated 1-sigma of its prediction at held-out poses `ds`, and how it holds
    their errors: e^T (C + s^2 I)^-1 e / 3 per pose, C the model's prediction covariance and s
    the tracker's per-pose sigma (max(recorded, MPE / 4), as the fits weight a pose). Its mean
    is 1 when the 1-sigma and the tracker's noise hold the errors; above 1 by what the model
    leaves out, or by a 1-sigma stated too small. `pred`: the model's prediction at `ds` when
    the caller has it. None for a model without a covariance of its prediction."""
    from scipy import stats

    from workcell.estimation.dh import pose_sigma_model

    f = getattr(model, "prediction_cov", None)
    C = None if f is None else f(ds.q, **aux_from_dataset(ds))
    if C is None or len(ds) < 3:
        return None
    C = np.asarray(C, float)
    if pred is None:
        pred = model.predict(ds.q, **aux_from_dataset(ds))
    e = ds.p_tracker - np.asarray(pred, float)
    s2 = pose_sigma_model(ds, tracker_mpe) ** 2
    try:
        z2 = np.einsum("ni,nij,nj->n", e, np.linalg.inv(C + s2[:, None, None] * np.eye(3)), e)
    except np.linalg.LinAlgError:
        return None
    s3 = np.sqrt(np.clip(np.einsum("nii->n", C), 0.0, None))
    n = len(z2)
    inside = int(np.sum(z2 < stats.chi2.ppf(0.95, 3)))
    return {
        "median_m": float(np.median(s3)),
        "max_m": float(s3.max()),
        "z2_mean_over_3": float(np.mean(z2) / 3),
        "inside_95": inside / n,
        # the two figures' chances if the 1-sigma and the tracker's noise held the errors:
        # sum z2 ~ chi2(3 n), and the count inside the 95 % ellipsoid ~ Binomial(n, 0.95).
        # Until 2026-11-29 the line passed any mean up to 1.5 and ignored the share inside, so
        # an augmented model's 1-sigma 1.5x too small (the tracker's noise beside it) passed
        "p_mean": float(stats.chi2.sf(float(np.sum(z2)), 3 * n)),
        "p_inside": float(stats.binom.cdf(inside, n, 0.95)),
        "poses": int(n),
        "basis": "3-D 1-sigma of the model's prediction (its covariance) at the held-out poses; "
        "z2_mean_over_3: mean of e^T (C + tracker sigma^2)^-1 e / 3 over them, 1 when the "
        "1-sigma and the tracker's noise hold the errors (inside_95: share inside the 95 % "
        "ellipsoid, 0.95 then); p_mean, p_inside: the chance of a mean as high (chi2 with 3 n "
        "dof) and of as few inside (binomial) if they held them: below 0.05, they do not",
    }


def combined_base(model: FittedModel) -> dict | None:
    """The model's tracker_T_base (its base_ref registration with the fitted base offsets) with
    the 1-sigma of its translation and rotation (`chain.base_pose_with_std`), from the geometric
    part of the model; None for a model without one. Two fits of one cell differ in how they
    split the base between base_ref and the offsets: compare this, not the offsets."""
    from workcell.estimation.models import geometric_cov, geometric_part
    from workcell.kinematics.chain import base_pose_with_std

    g = geometric_part(model)
    return None if g is None else base_pose_with_std(g.theta, g.base_ref, geometric_cov(g))


def bounds_summary(
    model: DHModel,
    bounds: str | dict,
    heldout_rms_m: float,
    dtr: Dataset,
    ev: Dataset,
    tracker_mpe: tuple[float, float],
) -> dict:
    """What the bounds of a bounded DH fit (`--bounds`) did: the estimated parameters held at
    a bound (`at_bound`: name, side (lower, upper, or fixed: a bound [v, v] fixes it at v),
    value, bound, unit), the bounds on parameters the fit does not estimate (`not_estimated`, no
    effect), and, when some bound holds, the held-out RMS of the unbounded fit of the same
    training poses (`heldout_rms_unbounded_m`: what `--method dh` without --bounds gives; one
    more fit, only then). `line` says it in one line."""
    info = getattr(model, "info", {}) or {}
    names = param_names(joints_of(model.theta))
    lim = info.get("bounds") or {}
    at = []
    pinned = set(info.get("pinned_by_bounds") or ())
    for n in info.get("active_bounds") or []:
        v = float(model.theta[names.index(n)])
        lo, hi = (lim.get(n) or [None, None])[:2]
        side = "lower" if lo is not None and (hi is None or abs(v - lo) <= abs(v - hi)) else "upper"
        if n in pinned:
            side = "fixed"  # lo == hi: the bound fixes it, it was never estimated
        at.append(
            {
                "name": n,
                "side": side,
                "value": v,
                "bound": lo if side in ("lower", "fixed") else hi,
                "unit": param_unit(n),
            }
        )
    ref = None
    if at:
        unb = fit_dh(dtr, tracker_mpe=tracker_mpe)
        ref = error_stats(unb.predict(ev.q), ev.p_tracker)["rms_m"]
    given = "a dict" if isinstance(bounds, dict) else str(bounds)
    out = {
        "given": given,
        "at_bound": at,
        "not_estimated": list(info.get("bounds_not_estimated") or []),
        "heldout_rms_m": heldout_rms_m,
        "heldout_rms_unbounded_m": ref,
        "evaluated_on": "held-out" if ev is not dtr else "train",  # --holdout 0: training poses
        "converged": info.get("converged"),
    }
    out["line"] = bounds_line(out)
    return out


def bounds_line(b: dict) -> str:
    """One line on what the bounds did (`bounds_summary`), for `fit` and its report."""
    if not b["at_bound"]:
        return (
            f"bounds ({b['given']}): none holds a parameter; the fit is the unbounded one "
            "(`--method dh` without --bounds)"
        )
    held = ", ".join(
        f"{a['name']} (fixed at {a['value']:.6g} {a.get('unit', '')} by its bound "
        f"[{a['value']:.6g}, {a['value']:.6g}])"
        if a["side"] == "fixed"
        else f"{a['name']} ({a['side']})"
        for a in b["at_bound"]
    )
    tool = [a["name"] for a in b["at_bound"] if a["name"].startswith("tool_")]
    n = len(b["at_bound"])
    line = (
        f"bounds ({b['given']}): {n} parameter{'s' if n > 1 else ''} held at a bound, not "
        f"estimated there (no std): {held}"
    )
    ref = b.get("heldout_rms_unbounded_m")
    if ref is not None:
        r = b["heldout_rms_m"]
        line += (
            f"; {b.get('evaluated_on', 'held-out')} RMS {r * 1e6:.1f} um with the bounds, "
            f"{ref * 1e6:.1f} um without (`--method dh` alone)"
        )
        if r > 1.05 * ref:
            line += (
                f": the bounds make the fit {r / ref:.2f}x worse, they hold parameters away from "
                "what the poses say; widen them"
            )
    if tool:
        line += (
            f"; the SMR offset ({', '.join(tool)}) is held by its bound: fit without --bounds for "
            "the offset to declare"
        )
    return line


def fit_recording(
    path: str | os.PathLike,
    *,
    method: str = "dh",
    holdout: float = 0.25,
    out: str | os.PathLike | None = None,
    on: str = "auto",
    bounds: str | None = None,
    tracker_mpe: tuple[float, float] = TRACKER_MPE_M,
    progress: Callable[[str], None] | None = None,
    warn=None,
    chain_missing: str = "refuse",
    smr_offset_m: npt.ArrayLike | None = None,
) -> dict:
    """`warn(line)` hears what the reader could not read (damaged chunk, cut-off end) before
    the fit starts; the report lists it as `recording_problems`. A resumed recording is fitted
    with every file it continues (`Dataset.from_recording`; `chain_missing` "ignore" leaves out
    a missing link and the files before it, with a warning). `smr_offset_m` (3,): the SMR
    offset on the flange (the controller's TCP) declared for this fit in place of the one the
    recording declares (`fit --smr-offset`); the report's `smr_declared` says which."""
    ds = Dataset.from_recording(path, chain_missing=chain_missing)
    for line in read_warnings(ds) if warn else ():
        warn(line)
    recorded_smr = np.asarray(ds.tool_offset_m, float).tolist()
    if smr_offset_m is not None:
        ds = replace(ds, tool_offset_m=np.asarray(smr_offset_m, float))
    model, report = fit_dataset(
        ds,
        method=method,
        holdout=holdout,
        on=on,
        bounds=bounds,
        tracker_mpe=tracker_mpe,
        progress=progress,
    )
    report["recording_problems"] = list(ds.read_problems)
    report["smr_declared"] = {
        "offset_m": np.asarray(ds.tool_offset_m, float).tolist(),
        "by": "recording" if smr_offset_m is None else "--smr-offset",
        "recording_m": recorded_smr,
    }
    b = report.get("bounds")
    if warn and b and b["not_estimated"]:
        ne = b["not_estimated"]
        it = "that bound has" if len(ne) == 1 else "those bounds have"
        warn(
            f"warning: --bounds {b['given']} bounds {', '.join(ne)}, which the fit does not "
            f"estimate (dependent or fixed at nominal): {it} no effect"
        )
    if out is not None:
        keep_in_model(model, ds, report)
        report["model"] = str(save_model(model, out))
    else:
        report["model"] = None
    return report


SMR_NOTE_M = 1e-3  # a fitted SMR this far (and 3 std) from the declared one gets a note


def smr_change(params: dict) -> dict | None:
    """The fitted SMR offset against the declared one (`tool_x/y/z` of a fit report's
    parameters), when they differ by more than SMR_NOTE_M and 3 std; else None (also when a
    bound of a bounded fit holds one of them: that value is the bound's, not an estimate)."""
    names = ("tool_x", "tool_y", "tool_z")
    if not all(n in params and "nominal" in params[n] for n in names):
        return None
    fitted = np.array([params[n]["value"] for n in names], float)
    declared = np.array([params[n]["nominal"] for n in names], float)
    d = fitted - declared
    change = float(np.linalg.norm(d))
    if any(params[n].get("at_bound") for n in names):
        return None  # held by a bound: no estimate to declare, nor a std (`bounds_summary`)
    stds = np.array([params[n].get("std") or 0.0 for n in names], float)
    std = float(np.sqrt(np.sum((d / max(change, 1e-12)) ** 2 * stds**2)))  # along the change
    if not (np.all(np.isfinite(fitted)) and change > SMR_NOTE_M and change > 3.0 * std):
        return None
    # what to declare: the sideways (flange x, y) components stay as declared when they differ
    # by no more than SMR_NOTE_M (the note's own threshold): a sideways offset of a fraction of
    # a millimetre makes {a5, theta5_offset} and {d5, alpha5} pass the structural test while
    # the poses barely tell them apart (series B: condition 118 -> 2.6e4, a5 11.4 +- 20.7 mm)
    side = float(np.linalg.norm(d[:2]))
    suggested = fitted.copy()
    if side <= SMR_NOTE_M:
        suggested[:2] = declared[:2]
    return {
        "change_m": change,
        "std_m": std,
        "declared_m": declared.tolist(),
        "fitted_m": fitted.tolist(),
        "suggested_m": suggested.tolist(),
        "sideways_kept_m": side if side <= SMR_NOTE_M else None,
        # its std along the sideways change (first order, as std_m along the whole change)
        "sideways_std_m": float(np.sqrt(np.sum((d[:2] / max(side, 1e-12)) ** 2 * stds[:2] ** 2))),
        "fitted_std_m": stds.tolist(),
    }


def keep_in_model(model: FittedModel, ds: Dataset, report: dict) -> None:
    """Put what the model file should carry into the model's `info`: its recording (path and
    sha256) and the held-out figures of `report` (RMS, its interval, what it leaves unexplained,
    and the same without named held-out outliers), which `export` states beside a table's
    1-sigma."""
    info = getattr(model, "info", None)
    if isinstance(info, dict):
        info.setdefault("recording", ds.source)
        if "active_bounds" in info and report.get("parameter_std_basis"):
            # a bounded fit: its stds are conditional on the parameters a bound holds
            info["parameter_std_basis"] = report["parameter_std_basis"]
        info.setdefault("recording_sha256", ds.source_sha256)
        if ds.chain:  # a resumed recording: every file of its chain
            info.setdefault("recording_chain", [dict(f) for f in ds.chain])
        if not report.get("heldout_poses"):
            # no held-out poses (--holdout 0): training figures say nothing of what the model
            # leaves unexplained elsewhere; `export` then states none
            for k in ("heldout_rms_m", "heldout_rms_ci95_m", "unexplained", "heldout_outliers"):
                info.pop(k, None)
            info["heldout"] = "none: fitted with --holdout 0"
            return
        info["heldout_rms_m"] = report["heldout_rms_m"]
        b = report.get("bounds")
        if b and b.get("heldout_rms_unbounded_m") is not None:
            info["heldout_rms_unbounded_m"] = b["heldout_rms_unbounded_m"]  # a bound held
        info["heldout_rms_ci95_m"] = report["heldout_rms_ci95_m"]
        info["unexplained"] = report["unexplained"]
        ho = report.get("heldout_outliers")
        if ho:
            # the same figures without the held-out poses `heldout_outliers` names (what `fit`
            # prints); `export` recomputes them too and states both
            info["heldout_outliers"] = {
                "pose_ids": ho["pose_ids"],
                "rule": ho["rule"],
                "heldout_rms_m": ho["heldout_rms_m"],
                "heldout_rms_ci95_m": ho["heldout_rms_ci95_m"],
                "floor_m": ho["unexplained"]["floor_m"],
            }
        else:
            info.pop("heldout_outliers", None)


__all__ = [
    "fit_dataset",
    "smr_change",
    "bounds_summary",
    "fit_recording",
    "keep_in_model",
    "heldout_outliers",
    "MIN_TRAIN_POSES",
    "min_poses_for_fit",
    "stated_noise_floor",
    "tracker_noise_floor",
    "pose_sigma",
    "FIT_METHODS",
]
