"""Bounded geometric identification: the linearised least squares with parameter bounds solved
as a QP and iterated to convergence (seed 002, Das, Touma & Burdick, eq. 11).

    delta* = argmin_delta || W (Delta_n - J_n delta) ||^2   s.t.  lb - theta <= delta <= ub - theta
    theta <- theta + delta*,   repeated until the step is below `xtol`

Bounded linear least squares *is* a convex QP (objective 1/2 d^T J^T W J d - (J^T W r)^T d with
box constraints); it is solved exactly by `scipy.optimize.lsq_linear(method="bvls")` on
column-scaled variables. If a full step does not lower the weighted cost it is halved (the
halved steps stay feasible: the box is convex and contains both ends).

Before the iteration, local identifiability (Theorem 1 of the paper: rank of the identification
Jacobian) is checked with :func:`workcell.estimation.identifiability.analyse` exactly as in the
unbounded fit (:func:`workcell.estimation.dh.fit_dh`): dependent parameters are fixed at nominal
and reported by group. The rigid registration of the base, the weights (1/sigma per pose), the
robust pass and the covariance follow `fit_dh` too, so with inactive bounds the two fits agree
(the iterated QP is then Gauss-Newton on the same problem).

Bounds
------
``bounds="default"`` (:func:`default_bounds`): bounds on the DH corrections only, as in the
paper (its bounds are on the 4 n_j DH parameters; it states no values, and its simulated errors,
up to 150 mm and 1.3 rad, were inside them), around the nominal value of each parameter:
  - DH lengths a_i, d_i: +-5 mm;  DH angles alpha_i, theta_i offset, beta_i: +-10 mrad.
    Physically plausible manufacturing and assembly errors with a margin: the unbounded fit of
    the real UR10 (series B and D) finds at most 1.3 mm (a2, std 0.04 mm) and 1.9 mrad
    (alpha3), about a quarter and a fifth of the bounds, and the simulator draws errors of
    sigma 0.3 mm and 0.5-1 mrad. An identifiable parameter also absorbs the error of the
    parameters dependent on it (e.g. d4 carries d2 + d3), which is one reason for the margin;
  - base (tracker placement, offsets from the rigid registration) and tool (the SMR in the
    flange, around the declared offset): unbounded. They are no manufacturing tolerance: the
    tracker stands where it was put, and the declared SMR offset can be centimetres off (series
    B: the SMR sits 15.8 mm nearer the flange than declared); a bound there holds the fit away
    from the data and the DH corrections absorb the difference (with +-10 mm on the tool the
    held-out RMS of series B doubled, 446 -> 946 um). Bound them in a file if wanted.
``bounds=path``: a JSON object ``{name: [lo, hi], ...}`` with absolute parameter values in SI
units (m, rad; base_* are the offsets from the registered base, like the values `workcell fit`
reports). Parameters not listed keep their default bound. Optionally
``{"mode": "delta", "bounds": {name: [lo, hi]}}`` gives bounds on the correction from nominal.
``bounds=None`` or ``"none"``: no bounds (the QP is then plain Gauss-Newton). An empty string
is refused (it used to mean no bounds, silently).
A dict of the same forms is accepted too. A bound on a parameter the fit does not estimate
(dependent, fixed at nominal) has no effect; `info["bounds_not_estimated"]` names them.
A bound [v, v] fixes the parameter at v (v must be the nominal value, where the fit starts):
it is not estimated, and is reported like a parameter held at a bound (`active_bounds`, also
`pinned_by_bounds`); the other parameters' stds are then conditional on the held ones
(`std_conditional_on`). A file is refused in one line when a bound is not a number, empty,
excludes the nominal value, or reaches further from the nominal than any calibration correction:
0.1 m for lengths (DH a_i, d_i, base translation, SMR offset; read as millimetres) and 0.5 rad
(29 deg) for angles (read as degrees); also a key given twice, and "mode" without a "bounds"
object.

Shapes: all Jacobians are evaluated on pose arrays padded to a few fixed sizes (powers of two),
so that JAX compiles each kernel once per size class instead of once per pose count.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from scipy.optimize import lsq_linear

from workcell import strict_json
from workcell.errors import UserError
from workcell.estimation.dh import (
    TRACKER_MPE_M,
    DHModel,
    nominal_theta,
    pose_sigma_model,
    register_base,
    robust_solve,
    weighted_covariance,
)
from workcell.estimation.identifiability import Identifiability, fit_identifiability
from workcell.estimation.models import error_stats
from workcell.kinematics.chain import (
    jac_params,
    joints_of,
    p_tracker,
    param_index,
    param_names,
)
from workcell.recording.dataset import Dataset

LENGTH_BOUND_M = 5e-3  # DH lengths a_i, d_i (see the module docstring for why)
ANGLE_BOUND_RAD = 10e-3  # DH angles alpha_i, theta_i offset, beta_i
BASE_T_BOUND_M = np.inf  # tracker placement: not a manufacturing tolerance, unbounded
BASE_R_BOUND_RAD = np.inf
TOOL_BOUND_M = np.inf  # declared SMR offset: can be centimetres off, unbounded


# ----------------------------------------------------------------------- padded evaluation


def _bucket(n: int) -> int:
    return max(16, 1 << int(np.ceil(np.log2(max(n, 1)))))


def predict_padded(theta: np.ndarray, base_ref: np.ndarray, q: np.ndarray) -> np.ndarray:
    """`p_tracker` as numpy (the foundation pads batch sizes to buckets itself)."""
    return np.asarray(
        p_tracker(
            np.asarray(theta, float),
            np.asarray(base_ref, float),
            np.atleast_2d(np.asarray(q, float)),
        )
    )


def jacobian_padded(theta: np.ndarray, base_ref: np.ndarray, q: np.ndarray) -> np.ndarray:
    """`jac_params` (N, 3, 5 n + 9) as numpy (39 columns for 6 joints)."""
    return np.asarray(
        jac_params(
            np.asarray(theta, float),
            np.asarray(base_ref, float),
            np.atleast_2d(np.asarray(q, float)),
        )
    )


# ----------------------------------------------------------------------------------- bounds


def default_bounds(theta_nominal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) arrays (5 n + 9,) of the documented default bounds around `theta_nominal`."""
    th = np.asarray(theta_nominal, float)
    if th.ndim != 1:
        raise ValueError(f"theta_nominal: expected a vector (5 n + 9,), got shape {th.shape}")
    half = np.empty(len(th))
    for n, i in param_index(joints_of(th)).items():
        if n[0] in "ad" and n[1:].isdigit():
            half[i] = LENGTH_BOUND_M
        elif n.startswith(("alpha", "theta", "beta")):
            half[i] = ANGLE_BOUND_RAD
        elif n in ("base_tx", "base_ty", "base_tz"):
            half[i] = BASE_T_BOUND_M
        elif n.startswith("base_r"):
            half[i] = BASE_R_BOUND_RAD
        else:  # tool
            half[i] = TOOL_BOUND_M
    return th - half, th + half


def resolve_bounds(
    bounds: str | Path | dict | None, theta_nominal: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) absolute bounds (5 n + 9,) from "default", None/"none", a JSON path or a dict."""
    lo, hi, _ = _resolve(bounds, theta_nominal)
    return lo, hi


PLAUSIBLE_LENGTH_M = 0.1  # a bound reaching further from nominal than this is not metres
PLAUSIBLE_ANGLE_RAD = 0.5  # ~29 deg: a bound reaching further than this is not radians


def _kind(name: str) -> str:
    """'m' for lengths (DH a_i, d_i, base translations, the SMR offset), else 'rad'."""
    if (name[0] in "ad" and name[1:].isdigit()) or name.startswith(("base_t", "tool")):
        return "m"
    return "rad"


def _check_bound(where, name, a, b, nominal, mode) -> None:
    """Refuse, in one line, a bound [a, b] (absolute, or offsets from `nominal` in delta mode)
    that is not a number, is empty, excludes the nominal value (where the fit starts) or reaches
    further from the nominal than any calibration correction (PLAUSIBLE_LENGTH_M,
    PLAUSIBLE_ANGLE_RAD): millimetres or degrees given for metres or radians."""
    if np.isnan(a) or np.isnan(b):
        raise UserError(
            f"{where}: {name} bound [{a:g}, {b:g}] is not a number (NaN; JSON files may "
            "carry NaN): give two numbers [lo, hi] in SI units (m, rad)"
        )
    if a > b:
        raise UserError(f"{where}: {name} bound [{a:g}, {b:g}] is empty (need lo <= hi)")
    unit = _kind(name)
    off = nominal if mode == "delta" else 0.0
    lo, hi = a + off, b + off
    contains = lo <= nominal <= hi
    reach = max((abs(x - nominal) for x in (lo, hi) if np.isfinite(x)), default=0.0)
    if unit == "m":
        limit, factor, big, small = PLAUSIBLE_LENGTH_M, 1e-3, "millimetres", "metres"
        limit_s = f"{PLAUSIBLE_LENGTH_M:g} m"
    else:
        limit, factor, big, small = PLAUSIBLE_ANGLE_RAD, np.pi / 180.0, "degrees", "radians"
        limit_s = f"{PLAUSIBLE_ANGLE_RAD:g} rad = {np.degrees(PLAUSIBLE_ANGLE_RAD):.0f} deg"
    sa, sb = a * factor, b * factor  # the bound read as millimetres or degrees
    converted = f"[{sa:.6g}, {sb:.6g}] {unit}"
    given = f"{name} bound [{a:g}, {b:g}] {unit} ({mode})"
    if not contains:
        read_small = (sa + off <= nominal <= sb + off) if mode == "absolute" else False
        old_mm = unit == "m" and max(abs(a), abs(b)) > 300 * max(abs(nominal), 0.01)
        if read_small:
            raise UserError(
                f"{where}: {given} does not contain the nominal value {nominal:.6g} {unit}, "
                f"which {converted}, the same numbers read as {big}, does; it looks like "
                f"{big}, give {small}"
            )
        if old_mm:
            raise UserError(
                f"{where}: {given} does not contain the nominal value {nominal:.6g} {unit}, "
                f"where the fit starts, and reaches {reach:.3g} m from it; it looks like "
                "millimetres, give metres"
                + (
                    " (and include 0: delta bounds are offsets from nominal)"
                    if mode == "delta"
                    else ""
                )
            )
        advice = (
            "widen it to include 0 (delta bounds are offsets from nominal, where the fit starts)"
            if mode == "delta"
            else 'widen it, or give offsets from nominal with {"mode": "delta"}'
        )
        far = (
            f", and reaches {reach:.3g} {unit} from it, beyond any calibration correction "
            f"({limit_s}): check its sign and units ({small}, not {big})"
            if reach > limit
            else ""
        )
        raise UserError(
            f"{where}: {given} does not contain the nominal value {nominal:.6g} {unit}, where "
            f"the fit starts{far}; {advice}"
        )
    if reach > limit:
        if mode == "delta" or sa <= nominal <= sb:
            hint = f"{'offsets ' if mode == 'delta' else ''}{converted} if {big} were meant"
        else:
            hint = f"if {small} were meant, keep it within {limit_s} of the nominal"
        if name.startswith(("base_", "tool")):
            hint += "; leave it out to keep it unbounded"
        raise UserError(
            f"{where}: {given} reaches {reach:.3g} {unit} from the nominal value "
            f"{nominal:.6g} {unit}, beyond any calibration correction ({limit_s}); it looks "
            f"like {big}, give {small} ({hint})"
        )


def _resolve(bounds, theta_nominal) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """`resolve_bounds` and the names the file or dict lists (none for default and none)."""
    th = np.asarray(theta_nominal, float)
    index = param_index(joints_of(th))
    if isinstance(bounds, str) and not bounds.strip():
        raise UserError(
            "--bounds is empty: give a JSON file of bounds or 'default' (leave --bounds out, "
            "or give 'none', for the unbounded fit)"
        )
    if bounds is None or (isinstance(bounds, str) and bounds.strip().lower() == "none"):
        return np.full(len(th), -np.inf), np.full(len(th), np.inf), []
    lo, hi = default_bounds(th)
    if isinstance(bounds, str) and bounds.strip().lower() == "default":
        return lo, hi, []
    if isinstance(bounds, dict):
        spec, where = bounds, "bounds"
    else:
        path = Path(bounds)
        if path.is_dir():
            raise UserError(
                f"bounds file {path} is a directory: give a JSON file of bounds, 'default' or "
                "'none'"
            )
        if not path.is_file():
            raise UserError(f"bounds file {path} not found (give a JSON file or 'default')")
        try:
            spec = strict_json.loads(path.read_text(encoding="utf-8-sig"))
        except strict_json.DuplicateKey as e:
            raise UserError(
                f"bounds file {path}: key {e.args[0]!r} is given twice (JSON readers keep only "
                "the last): give each once"
            ) from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise UserError(f"bounds file {path}: not valid JSON ({e})") from None
        where = str(path)
    form = '{name: [lo, hi]} or {"mode": "delta", "bounds": {name: [lo, hi]}}'
    if not isinstance(spec, dict):
        raise UserError(f"{where}: expected a JSON object {form}")
    mode = "absolute"
    if "bounds" in spec:
        if not isinstance(spec["bounds"], dict):
            raise UserError(
                f'{where}: "bounds" must be an object {{name: [lo, hi]}}, got '
                f"{type(spec['bounds']).__name__} {spec['bounds']!r:.40}"
            )
        mode = spec.get("mode", "absolute")
        extra = set(spec) - {"bounds", "mode"}
        if extra:
            raise UserError(
                f'{where}: unexpected keys {sorted(extra)} beside "bounds" (only "mode" '
                'goes there; put parameter bounds inside "bounds")'
            )
        spec = spec["bounds"]
    elif "mode" in spec:
        raise UserError(
            f'{where}: "mode" goes with a "bounds" object: {{"mode": "delta", "bounds": '
            '{name: [lo, hi]}} (the parameter bounds inside "bounds")'
        )
    if mode not in ("absolute", "delta"):
        raise UserError(f"{where}: mode must be 'absolute' or 'delta', got {mode!r}")
    for name, v in spec.items():
        if name not in index:
            raise UserError(f"{where}: unknown parameter {name!r} (names as in `workcell fit`)")
        if (
            not isinstance(v, (list, tuple))
            or len(v) != 2
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
        ):
            raise UserError(f"{where}: {name} must be [lo, hi] (two numbers), got {v!r}")
        try:
            a, b = float(v[0]), float(v[1])
        except OverflowError:
            raise UserError(f"{where}: {name} bound {v!r:.60} is too large a number") from None
        i = index[name]
        _check_bound(where, name, a, b, float(th[i]), mode)
        off = th[i] if mode == "delta" else 0.0
        lo[i], hi[i] = a + off, b + off
    return lo, hi, list(spec)


# -------------------------------------------------------------------------------------- fit


def fit_dh_bounded(
    ds: Dataset,
    bounds: str | Path | dict | None = "default",
    *,
    fixed: list[str] | None = None,
    theta0: np.ndarray | None = None,
    base_ref: np.ndarray | None = None,
    free: np.ndarray | None = None,
    outlier_k: float = 5.0,
    robust: bool = True,
    max_iter: int = 50,
    xtol: float = 1e-11,
    min_poses: int = 12,
    tracker_mpe: tuple[float, float] = TRACKER_MPE_M,
) -> DHModel:
    """Fit the geometric model to all poses of `ds` by the iterated bounded QP (eq. 11).

    `theta0`/`base_ref` warm-start the iteration (default: nominal, rigid registration);
    `free` (bool (5 n + 9,)) skips the identifiability analysis and estimates exactly those
    parameters (used by adaptive plans that refit after every pose). Returns a `DHModel`
    (method "dh") whose `info` adds `bounds` (for the estimated parameters), `active_bounds`
    (the estimated parameters held at a bound, and those a bound [v, v] fixes at v, which
    `pinned_by_bounds` names: their std is not given; the other stds are conditional on them,
    `std_conditional_on`), `qp_iterations`,
    `converged` and `bounds_not_estimated` (parameters a bounds file lists that the fit does
    not estimate: dependent or fixed, so the bound has no effect).
    """
    t0 = time.perf_counter()
    if len(ds) < min_poses:
        raise ValueError(
            f"too few poses to fit the geometry: {len(ds)} (need at least {min_poses})"
        )
    th_nom = nominal_theta(ds)
    n_par = len(th_nom)
    names = param_names(joints_of(th_nom))
    index = param_index(joints_of(th_nom))
    lo, hi, listed = _resolve(bounds, th_nom)
    theta = th_nom.copy() if theta0 is None else np.asarray(theta0, float).copy()
    if theta.shape != (n_par,):
        raise ValueError(f"theta0: expected shape ({n_par},), got {theta.shape}")
    base_ref = register_base(ds, theta) if base_ref is None else np.asarray(base_ref, float)
    w = 1.0 / pose_sigma_model(ds, tracker_mpe)  # as fit_dh
    ident: Identifiability | None = None
    if free is None:
        J0 = jacobian_padded(theta, base_ref, ds.q) * w[:, None, None]
        ident = fit_identifiability(J0, w, ds.robot.dh, ds.tool_offset_m, fixed)
        free = np.zeros(n_par, bool)
        free[[index[n] for n in ident.identifiable]] = True
    else:
        free = np.asarray(free, bool).copy()
        if free.shape != (n_par,):
            raise ValueError(f"free: expected shape ({n_par},), got {free.shape}")
    # a parameter pinned by lo == hi is fixed at that value by its bound: not estimated (the QP
    # leaves it out), but reported like a parameter held at a bound (`active_bounds`, no std,
    # the unbounded fit's held-out RMS beside the bounded one), and named in `pinned_by_bounds`
    pinned = free & (hi - lo <= 0)
    theta[pinned] = lo[pinned]
    # listed bounds on parameters that are neither estimated nor pinned by them do nothing
    not_estimated = [n for n in listed if not free[index[n]]]
    est = free & ~pinned  # what the QP estimates
    bad = (theta < lo) | (theta > hi)
    theta[est] = np.clip(theta[est], lo[est], hi[est])  # feasible start
    if np.any(bad & ~est):
        out = [names[i] for i in np.where(bad & ~est)[0]]
        raise UserError(
            f"bounds exclude the nominal value of parameters that are not estimated: {out}"
        )
    runs = []  # (iterations, converged) of each solve

    def solve(keep, th):
        th, it, conv = _iterate_qp(ds, keep, w, th, base_ref, est, lo, hi, max_iter, xtol)
        runs.append((it, conv))
        return th

    theta, keep = robust_solve(solve, ds, theta, base_ref, w, outlier_k, passes=2 if robust else 0)
    iters, converged = sum(r[0] for r in runs), runs[-1][1]
    n_rejected = int((~keep).sum())
    span = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
    at_lo = est & np.isfinite(lo) & (theta - lo <= 1e-9 * np.maximum(span, 1e-12))
    at_hi = est & np.isfinite(hi) & (hi - theta <= 1e-9 * np.maximum(span, 1e-12))
    active = at_lo | at_hi | pinned
    # uncertainty of the parameters not held by a bound (as in fit_dh): conditional on the held
    # ones, which it takes as exactly known at their bound values (`std_conditional_on`)
    qk = ds.q[keep]
    cov, s0_2 = weighted_covariance(ds, theta, base_ref, w, keep, est & ~active, int(est.sum()))
    stats = error_stats(predict_padded(theta, base_ref, qk), ds.p_tracker[keep])
    finite = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
    info = {
        "nominal_tool_m": ds.tool_offset_m.tolist(),
        "train_poses": int(len(ds)),
        "outliers_rejected": n_rejected,
        "variance_factor": s0_2,
        "train_rms_m": stats["rms_m"],
        "identifiability": ident.to_dict(cov) if ident is not None else None,
        "fit_seconds": time.perf_counter() - t0,
        "solver": "iterated bounded linear least squares (QP, eq. 11 of seed 002)",
        "qp_iterations": iters,
        "converged": bool(converged),
        "bounds": {names[i]: [finite(lo[i]), finite(hi[i])] for i in np.where(free)[0]},
        "active_bounds": [names[i] for i in np.where(active)[0]],
        "pinned_by_bounds": [names[i] for i in np.where(pinned)[0]],
        "std_conditional_on": [names[i] for i in np.where(active)[0]],
        "bounds_not_estimated": not_estimated,
        **ds.provenance(),  # the recording, and every file of a resumed one
    }
    return DHModel(
        robot_model=ds.robot.model,
        nominal_dh=ds.robot.dh,
        theta=theta,
        base_ref=base_ref,
        cov=cov,
        free=free,
        unidentifiable=ident.groups if ident is not None else [],
        info=info,
    )


def _iterate_qp(ds, keep, w, theta, base_ref, free, lo, hi, max_iter, xtol):
    """Iterate the bounded linearised least squares from `theta`; returns (theta, iters, ok)."""
    q, p, wk = ds.q[keep], ds.p_tracker[keep], w[keep]
    theta = theta.copy()
    idx = np.where(free)[0]
    if len(idx) == 0:
        return theta, 0, True

    def residual(th):
        return ((p - predict_padded(th, base_ref, q)) * wk[:, None]).ravel()

    r = residual(theta)
    cost = float(r @ r)
    for it in range(1, max_iter + 1):
        J = (jacobian_padded(theta, base_ref, q) * wk[:, None, None]).reshape(-1, len(theta))
        J = J[:, idx]
        s = np.linalg.norm(J, axis=0)
        s = np.where(s > 0, s, 1.0)
        lb = (lo[idx] - theta[idx]) * s
        ub = (hi[idx] - theta[idx]) * s
        # lsq_linear needs lb < ub; a parameter sitting on a zero-width range cannot move
        ub = np.maximum(ub, lb + 1e-300)
        sol = lsq_linear(J / s, r, bounds=(lb, ub), method="bvls", tol=1e-12)
        delta = sol.x / s
        step = 1.0
        while True:
            cand = theta.copy()
            cand[idx] = np.clip(theta[idx] + step * delta, lo[idx], hi[idx])
            r_new = residual(cand)
            c_new = float(r_new @ r_new)
            if c_new <= cost * (1 + 1e-12) or step < 1e-4:
                break
            step *= 0.5
        moved = np.max(np.abs(cand[idx] - theta[idx]))
        theta, r, cost = cand, r_new, c_new
        if moved < xtol:
            return theta, it, True
    return theta, max_iter, False


__all__ = [
    "default_bounds",
    "fit_dh_bounded",
    "jacobian_padded",
    "predict_padded",
    "resolve_bounds",
]
