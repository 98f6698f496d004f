"""Identifiability of geometric parameters from a set of poses.

The identification Jacobian J (3 m rows for m poses, P columns, d p_tracker / d theta, weighted
when the caller weights it) is analysed:
- rank: a greedy column selection in a stated priority order keeps a maximal identifiable
  subset; every other parameter is reported with the kept parameters it is a combination of (its
  group). Singular values and condition number are those of the kept columns scaled to unit norm
  over this pose set (column equilibration, which makes the condition number nearly the smallest
  any column scaling gives; van der Sluis 1969);
- observability indices (the names of Sun & Hollerbach 2008, "Observability index selection for
  robot calibration", and Joubair & Bonev 2013, seed 002's refs [16] and [13]; seed 002 itself
  names no index), of the Jacobian with a FIXED column scaling (`parameter_units`: metres for
  lengths, angles as the arc they sweep at `ANGLE_LENGTH_M` = 1 m, so the scaled Jacobian is J in
  SI units with 1 rad counted as 1 m) over the L parameters that can be identified at all
  (`structural_identifiable`: the structurally dependent ones removed, a property of the chain,
  not of the poses):
  O1 = (sigma_1 ... sigma_L)^(1/L) / sqrt(m) (Borm & Menq 1991), and
  O3 = sigma_L, the minimum singular value (Nahvi, Hollerbach & Hayward 1994).
  Both are 0 when the poses do not identify all L parameters. O1 estimates det(E[J_k^T J_k])^(1/2L)
  (J_k: one pose's 3 rows), so it does not grow or shrink with the pose count for poses drawn
  from one distribution (it is lower when 3 m is close to L: such sets identify poorly); O3 grows
  like sqrt(m). A change of units multiplies O1 by the same factor for every pose set (det of a
  diagonally rescaled matrix), so O1 ranks pose sets the same whatever the units; O3 does not.
  D-optimal design (`--plan dopt`) maximises log det(Js^T Js) = 2 L log(O1 sqrt(m)): at a given
  pose count and L, the same ordering as O1 (see `workcell.campaign.adaptive`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from workcell.kinematics.chain import N_JOINTS, joints_of, param_names

if TYPE_CHECKING:
    from workcell.kinematics.robots import DH


def priority_for(n: int) -> list[str]:
    """The column order of the greedy selection for an n-joint chain.

    Base and tool parameters first (they are what a user sets), then DH lengths/twists, so that
    dependent DH parameters are the ones fixed at nominal. For the 6-joint UR arms: theta1 goes
    with base_rz, d1 with base_tz, d2/d3 with d4, a6/d6/alpha6/theta6 with the tool."""
    r = range(1, n)
    return (
        ["base_tx", "base_ty", "base_tz", "base_rx", "base_ry", "base_rz"]
        + ["tool_x", "tool_y", "tool_z"]
        + [f"a{i}" for i in r]
        + [f"alpha{i}" for i in r]
        + [f"theta{i}_offset" for i in range(2, n)]
        + [f"beta{i}" for i in r]
        + [f"d{n - 2}", f"d{n - 1}", "d1"]
        + [f"d{i}" for i in range(2, n - 2)]
        + [f"d{n}", f"a{n}", f"alpha{n}", "theta1_offset", f"theta{n}_offset", f"beta{n}"]
    )


PRIORITY = priority_for(6)


def candidates_for(dh: DH, fixed: Iterable[str] | None = ()) -> list[str]:
    """The parameters a fit may estimate for the chain `dh`: all 5 n + 9 but the Hayati tilts of
    links whose next axis is not nominally parallel, and those in `fixed`."""
    from workcell.kinematics.chain import parallel_beta_names

    betas = set(parallel_beta_names(dh))
    fixed = set(fixed or ())
    return [
        n
        for n in param_names(len(dh.a))
        if n not in fixed and (not n.startswith("beta") or n in betas)
    ]


ANGLE_LENGTH_M = 1.0  # an angle counts as the arc it sweeps at this distance (O1, O3)
ANGLE_PREFIXES = ("alpha", "beta", "theta", "base_r")

OBSERVABILITY_BASIS = (
    "O1 = (sigma_1 ... sigma_L)^(1/L) / sqrt(m) (Borm & Menq 1991) and O3 = sigma_L, the minimum "
    "singular value (Nahvi, Hollerbach & Hayward 1994), of the identification Jacobian of the m "
    "poses (3 rows a pose) over the L parameters the chain can identify at all (structurally "
    "dependent ones removed), columns in fixed units: metres for lengths, angles as the arc they "
    f"sweep at {ANGLE_LENGTH_M:g} m (J in SI units, 1 rad counted as 1 m); both 0 when the poses "
    "leave one of the L dependent. O1 does not depend on the pose count for poses drawn alike; "
    "O3 grows like sqrt(m)"
)


def parameter_units(names: Iterable[str], angle_length_m: float = ANGLE_LENGTH_M) -> np.ndarray:
    """The fixed column scaling of the observability indices: the step of each parameter that
    counts as one unit, (P,). Lengths 1 m; angles (alpha*, beta*, theta*, base_r*) 1 m /
    `angle_length_m` rad, the angle that moves a point `angle_length_m` away by 1 m; any other
    name 1 (the Jacobian's own unit). The scaled Jacobian is J * parameter_units(names)."""
    return np.array(
        [1.0 / angle_length_m if str(n).startswith(ANGLE_PREFIXES) else 1.0 for n in names]
    )


STRUCTURAL_POSES = 60  # generic configurations that reveal the chain's structural dependencies
_STRUCTURAL: dict[tuple, list[str]] = {}


def structural_identifiable(
    dh: DH, tool_m: npt.ArrayLike, fixed: Iterable[str] | None = ()
) -> list[str]:
    """The parameters of the chain `dh` (SMR at `tool_m` on the flange) that a point tracker can
    identify at all, in `analyse`'s priority order: the rank analysis of `candidates_for(dh,
    fixed)` at `STRUCTURAL_POSES` seeded configurations uniform over every joint's full turn
    (generic poses: a parameter dependent there is dependent at every pose set, a property of
    the chain). L of the observability indices: 25 for the UR arms with the SMR on the flange
    axis (27 off it: d5 and theta5_offset then separate)."""
    from workcell.kinematics.chain import jac_params, pack

    tool_m = np.asarray(tool_m, float)
    key = tuple(
        tuple(np.asarray(v, float).round(12))
        for v in (dh.a, dh.d, dh.alpha, dh.theta_offset, tool_m)
    ) + (tuple(sorted(fixed or ())),)
    if key not in _STRUCTURAL:
        n_j = len(dh.a)
        names = param_names(n_j)
        q = np.random.default_rng(0).uniform(-np.pi, np.pi, (STRUCTURAL_POSES, n_j))
        J = np.asarray(jac_params(pack(dh, tool=tool_m), np.eye(4), q)).reshape(-1, len(names))
        order = priority_for(n_j)
        ident = analyse(J, names, priority=order, candidates=candidates_for(dh, fixed))
        _STRUCTURAL[key] = sorted(ident.identifiable, key=order.index)
    return list(_STRUCTURAL[key])


@dataclass
class Identifiability:
    names: list[str]
    rank: int
    singular_values: np.ndarray
    condition: float
    o1: float  # Borm & Menq, see OBSERVABILITY_BASIS
    min_singular_value: float  # O3, same scaling and parameters as o1
    identifiable: list[str]
    dependent: dict[str, list[str]]  # dependent param -> kept params it combines
    groups: list[list[str]]
    observability_parameters: list[str] | None = None  # the L parameters of o1 and O3
    # what Jacobian `singular_values` and `condition` are of (short label, see to_dict)
    jacobian_label: str = "the Jacobian as given"
    # a fit's: the condition of its unweighted (SI) Jacobian, columns scaled the same way, the
    # dry run's definition (`pose_set_report`); None when not computed
    condition_unweighted: float | None = None

    def to_dict(self, cov: np.ndarray | None = None) -> dict:
        """The analysis as a report; with the fit's covariance `cov` (over `names`), also the
        groups the poses barely tell apart (`weakly_identified`, see `weak_directions`)."""
        weak = {}
        if cov is not None:
            weak = {
                "weakly_identified": weak_directions(cov, self.names),
                "weakly_identified_basis": WEAK_BASIS,
                "correlated_pairs": correlated_pairs(cov, self.names),
            }
        sv_basis = (
            f"of the identification Jacobian ({self.jacobian_label}) over the {self.rank} "
            "parameters the rank test keeps, each column scaled to unit norm over these poses "
            "(column equilibration); condition = largest / smallest of them"
        )
        cu = {}
        if self.condition_unweighted is not None:
            cu = {
                "condition_unweighted": self.condition_unweighted,
                "condition_unweighted_basis": "the same for the unweighted Jacobian (SI units), "
                "unit-norm columns: the dry run's `condition` (`workcell campaign --dry-run`, "
                "there at the nominal chain and the planned poses)",
            }
        return {
            "rank": self.rank,
            "n_parameters": len(self.names),
            "condition": self.condition,
            "condition_label": f"{self.jacobian_label}, unit-norm columns",
            "condition_basis": sv_basis,
            **cu,
            "o1": self.o1,
            "min_singular_value": self.min_singular_value,
            "observability_parameters": len(self.observability_parameters or self.identifiable),
            "observability_basis": OBSERVABILITY_BASIS
            if self.observability_parameters is not None
            else OBSERVABILITY_BASIS + "; here of the Jacobian as the caller gave it (a fit's is "
            "weighted by 1 / sigma), and L = the parameters these poses identify (the chain's "
            "structural set was not given), so a rank-deficient set is not scored 0",
            "min_singular_value_basis": "O3 (observability_basis): fixed units over the "
            "observability parameters, not unit-norm columns, so not the smallest of "
            "singular_values",
            "singular_values": self.singular_values.tolist(),
            "singular_values_basis": sv_basis,
            "identifiable": self.identifiable,
            "unidentifiable": self.groups,
        } | weak


def observability(Js: np.ndarray, n_poses: int | None = None, *, rank: int | None = None) -> dict:
    """Observability indices of a Jacobian already in the fixed units (`parameter_units`), whose
    L columns are all the parameters that should be identified, rows 3 a pose (`n_poses`
    default rows // 3):

    - ``o1``: O1 = (sigma_1 ... sigma_L)^(1/L) / sqrt(m) (Borm & Menq 1991), m = `n_poses`;
      O1^(2 L) m^L = det(Js^T Js);
    - ``min_singular_value``: O3 = sigma_L (Nahvi, Hollerbach & Hayward 1994);
    - ``condition``: sigma_1 / sigma_L of `Js` (1 / O2 of Sun & Hollerbach).

    When `Js` does not have full column rank (`rank` < L if given, else numpy's numerical rank
    test: sigma_L <= sigma_1 max(rows, L) eps), the poses leave a parameter unidentified: O1 =
    O3 = 0 and the condition infinite."""
    Js = np.asarray(Js, float)
    rows, L = Js.shape
    m = max(rows // 3, 1) if n_poses is None else int(n_poses)
    s = np.linalg.svd(Js, compute_uv=False) if L and rows else np.zeros(0)
    full = len(s) == L and L > 0 and s[-1] > s[0] * max(rows, L) * np.finfo(float).eps
    if rank is not None:
        full = full and rank >= L
    if not full:
        return {"o1": 0.0, "min_singular_value": 0.0, "condition": float("inf")}
    return {
        "o1": float(np.exp(np.mean(np.log(s))) / np.sqrt(m)),
        "min_singular_value": float(s[-1]),
        "condition": float(s[0] / s[-1]),
    }


def _greedy(J: np.ndarray, order: list[str], col: dict[str, int], rtol: float):
    """Columns of J in `order` kept greedily (each independent of those kept before it, see
    `analyse`), and the dependent ones with the kept columns they combine."""
    norms = np.linalg.norm(J, axis=0)
    kept: list[str] = []
    dependent: dict[str, list[str]] = {}
    Q = np.zeros((J.shape[0], 0))
    for n in order:
        c = J[:, col[n]]
        nc = norms[col[n]]
        if nc < 1e-12 * max(norms.max(), 1e-300):
            dependent[n] = []  # no effect on the measured point at all
            continue
        u = c / nc
        r = u - Q @ (Q.T @ u)
        r = r - Q @ (Q.T @ r)  # re-orthogonalise
        if np.linalg.norm(r) < rtol:
            K = J[:, [col[k] for k in kept]] / norms[[col[k] for k in kept]]
            x, *_ = np.linalg.lstsq(K, u, rcond=None)
            big = np.abs(x) > 1e-3 * np.abs(x).max()
            dependent[n] = [k for k, b in zip(kept, big, strict=True) if b]
        else:
            kept.append(n)
            Q = np.column_stack([Q, r / np.linalg.norm(r)])
    return kept, dependent


def analyse(
    J: np.ndarray,
    names: list[str] | None = None,
    *,
    priority: list[str] | None = None,
    candidates: list[str] | None = None,
    rtol: float = 1e-6,
    structural: list[str] | None = None,
    units: np.ndarray | None = None,
) -> Identifiability:
    """Analyse a Jacobian J (3 rows a pose, P) whose columns are `names` (default: all 5 n + 9
    parameters of an n-joint chain, n from P; 39 for the 6-joint arms).

    `candidates` restricts the analysis to a subset of the columns (others are fixed anyway).
    A column is dependent when its distance from the span of the columns kept before it, relative
    to its norm, is below `rtol` (exact dependencies give ~1e-12; weak ones are reported through
    the condition number instead). `rank`, `singular_values` and `condition` are those of the
    kept columns, equilibrated (unit norm over these poses).

    The observability indices O1 and O3 (`observability`) are of J * `units` (default
    `parameter_units(names)`: fixed, so they compare pose sets) over the parameters `structural`
    (`structural_identifiable`: what the chain can identify at all); 0 when these poses leave
    one of them dependent (the same `rtol` test). Without `structural` they are over the kept
    columns, so a rank-deficient set is not scored 0: give it for the literature's indices.
    """
    if names is None:
        try:
            n_j = joints_of(np.empty(J.shape[1])) if J.ndim == 2 else N_JOINTS
        except ValueError:
            n_j = N_JOINTS  # the shape check below reports the mismatch
        names = param_names(n_j)
        if priority is None:
            priority = priority_for(n_j)
    names = list(names)
    if J.ndim != 2 or J.shape[1] != len(names):
        raise ValueError(f"Jacobian: expected shape (rows, {len(names)}), got {J.shape}")
    cand = [n for n in (candidates or names)]
    prio = priority or PRIORITY
    order = [n for n in prio if n in cand] + [n for n in cand if n not in prio]
    col = {n: i for i, n in enumerate(names)}
    kept, dependent = _greedy(J, order, col, rtol)
    norms = np.linalg.norm(J, axis=0)
    Js = J[:, [col[k] for k in kept]] / norms[[col[k] for k in kept]]
    s = np.linalg.svd(Js, compute_uv=False)
    # observability indices: fixed units, over the structurally identifiable parameters
    u = parameter_units(names) if units is None else np.asarray(units, float)
    if u.shape != (len(names),):
        raise ValueError(f"units: expected shape ({len(names)},), got {u.shape}")
    if structural is None:
        L_names, rank_L = list(kept), len(kept)
    else:
        unknown = [n for n in structural if n not in col]
        if unknown:
            raise ValueError(f"structural parameters not among the columns: {unknown}")
        L_names = [n for n in order if n in structural] + [n for n in structural if n not in order]
        rank_L = len(_greedy(J, L_names, col, rtol)[0])
    cols_L = [col[n] for n in L_names]
    obs = observability(J[:, cols_L] * u[cols_L], rank=rank_L)
    # groups: dependent parameters sharing the same support are merged with it
    by_support: dict[tuple, list[str]] = {}
    for n, sup in dependent.items():
        by_support.setdefault(tuple(sup), []).append(n)
    groups = [sorted(deps + list(sup), key=names.index) for sup, deps in by_support.items()]
    return Identifiability(
        names=names,
        rank=len(kept),
        singular_values=s,
        condition=float(s[0] / s[-1]) if len(s) and s[-1] > 0 else float("inf"),
        o1=obs["o1"],
        min_singular_value=obs["min_singular_value"],
        identifiable=sorted(kept, key=names.index),
        dependent=dependent,
        groups=groups,
        observability_parameters=None if structural is None else sorted(L_names, key=names.index),
    )


def fit_identifiability(
    J_weighted: np.ndarray,
    w: np.ndarray,
    dh: DH,
    tool_m: npt.ArrayLike,
    fixed: Iterable[str] | None = (),
) -> Identifiability:
    """A fit's identifiability: the rank analysis of its weighted Jacobian `J_weighted` (N, 3, P;
    pose i's rows times `w[i]`, 1 / sigma) over `candidates_for(dh, fixed)`, with the
    observability indices O1 and O3 as the dry run gives them: of the unweighted Jacobian (SI
    units) over the chain's structural set (`structural_identifiable`), 0 when these poses leave
    one of it dependent. `singular_values` and `condition` stay those of the weighted Jacobian
    (unit-norm columns; `jacobian_label` says so); `condition_unweighted` is the condition of the
    unweighted one, the dry run's definition. (Before 2026-11-26 a fit reported O1 of its weighted Jacobian, about
    1 / sigma times the dry run's: 19819 on series D against 0.4 for a planned pose set.)"""
    Jw = np.asarray(J_weighted, float)
    n_par = Jw.shape[-1]
    cand = candidates_for(dh, fixed)
    ident = analyse(Jw.reshape(-1, n_par), candidates=cand)
    J_si = (Jw / np.asarray(w, float)[:, None, None]).reshape(-1, n_par)
    obs = analyse(J_si, candidates=cand, structural=structural_identifiable(dh, tool_m, fixed))
    return replace(
        ident,
        o1=obs.o1,
        min_singular_value=obs.min_singular_value,
        observability_parameters=obs.observability_parameters,
        jacobian_label="rows weighted by 1 / sigma per pose",
        condition_unweighted=obs.condition,
    )


WEAK_BASIS = (
    "near-null directions of the estimated parameters' correlation matrix: a group is the "
    "parameters loading a direction (|component| >= 0.2) whose eigenvalue lambda gives "
    "1/sqrt(lambda) >= the threshold (100), kept when its std_inflation reaches the threshold "
    "too: the largest of the group's sqrt(variance inflation factors), a parameter's std over "
    "its std were every other estimated parameter known. The rank test keeps these parameters; "
    "the poses barely tell them apart, so their values are not separately meaningful, only "
    "their combination"
)


CORRELATED_ABS_R = 0.9  # a pair this correlated: its two +- are not independent


def correlated_pairs(
    cov: np.ndarray, names: list[str], threshold: float = CORRELATED_ABS_R
) -> list[dict]:
    """Pairs of estimated parameters whose correlation in the fit's covariance `cov` reaches
    |r| >= `threshold`: `{"parameters": [a, b], "correlation": r}`, strongest first; [] when the
    covariance is not usable. Their +- read as independent overstate what is known of a
    difference and understate what is known of a sum (metrology audit, 2026-11-29: series B's
    d4/alpha1 at r = -0.984 behind independent-looking +-)."""
    cov = np.asarray(cov, float)
    if cov.shape != (len(names), len(names)) or not np.all(np.isfinite(cov)):
        return []
    est = np.flatnonzero(np.diag(cov) > 0.0)
    s = np.sqrt(np.diag(cov)[est])
    C = cov[np.ix_(est, est)] / np.outer(s, s)
    i, j = np.triu_indices(len(est), 1)
    r = C[i, j]
    keep = np.flatnonzero(np.abs(r) >= threshold)
    keep = keep[np.argsort(-np.abs(r[keep]), kind="stable")]
    return [
        {"parameters": [names[est[i[k]]], names[est[j[k]]]], "correlation": float(r[k])}
        for k in keep
    ]


def weak_directions(cov: np.ndarray, names: list[str], inflation: float = 100.0) -> list[dict]:
    """Groups of estimated parameters the poses barely tell apart: the near-dependencies the rank
    test (exact ones) lets through, from the fit's covariance `cov` (P, P; fixed parameters have
    zero variance and are skipped). Each group: `{"parameters": [names], "std_inflation": x,
    "correlation": r}` (r for a pair, else None), most inflated first; [] when none reaches
    `inflation` or the covariance is not usable. See `WEAK_BASIS`."""
    cov = np.asarray(cov, float)
    if cov.ndim != 2 or cov.shape != (len(names), len(names)):
        raise ValueError(
            f"covariance: expected shape ({len(names)}, {len(names)}), got {cov.shape}"
        )
    if not np.all(np.isfinite(cov)):
        return []
    d = np.diag(cov)
    est = np.flatnonzero(d > 0.0)
    if len(est) < 2:
        return []
    s = np.sqrt(d[est])
    C = cov[np.ix_(est, est)] / np.outer(s, s)
    lam, V = np.linalg.eigh((C + C.T) / 2.0)
    lam = np.maximum(lam, np.finfo(float).tiny)
    vif = (V**2 / lam) @ np.ones(len(lam))  # diag(C^-1)
    out = []
    for k in np.flatnonzero(lam <= 1.0 / inflation**2):
        members = np.flatnonzero(np.abs(V[:, k]) >= 0.2)
        if len(members) < 2 or np.sqrt(vif[members].max()) < inflation:
            continue
        out.append(
            {
                "parameters": [names[est[i]] for i in members],
                "std_inflation": float(np.sqrt(vif[members].max())),
                "correlation": float(C[members[0], members[1]]) if len(members) == 2 else None,
            }
        )
    return sorted(out, key=lambda g: -g["std_inflation"])


def pose_set_report(
    dh: DH,
    q: np.ndarray,
    tool_m: npt.ArrayLike,
    reference_q: np.ndarray | None = None,
    *,
    sigma_m: np.ndarray | None = None,
    reference_sigma_m: np.ndarray | None = None,
    train_share: float = 1.0,
) -> dict:
    """What measuring the SMR (`tool_m` on the flange) at joint angles `q` (N, n) can identify,
    at the nominal chain, before anything moves: rank and condition of the identification
    Jacobian (Theorem 1), the observability indices O1 and O3 (`min_singular_value`) over the
    chain's `structural_identifiable` parameters (0 when `q` leaves one dependent; see
    `OBSERVABILITY_BASIS`), and the weakly identified groups (`weak_directions` of the unit-weight
    covariance). With `reference_q`, a rich pose set, also `rank_reference` and `missing`: what
    the reference identifies that `q` leaves dependent (too few or too alike poses).

    With `sigma_m` (N,), the per-axis 1-sigma each pose will be measured with, and
    `reference_sigma_m` (M,) at the reference poses, also what a fit of these poses should give
    at the reference poses if the geometric model holds (`expected_prediction`,
    `expected_prediction_sigma`); None when the poses leave a parameter dependent, which the fit
    then fixes at nominal, an error no noise figure bounds."""
    from workcell.kinematics.chain import jac_params, pack

    q = np.atleast_2d(np.asarray(q, float))
    n_j = len(dh.a)
    names = param_names(n_j)
    cand = candidates_for(dh)
    theta = pack(dh, tool=np.asarray(tool_m, float))
    structural = structural_identifiable(dh, tool_m)

    def analysed(qs):
        J = np.asarray(jac_params(theta, np.eye(4), qs)).reshape(-1, len(names))
        return J, analyse(
            J, names, priority=priority_for(n_j), candidates=cand, structural=structural
        )

    J, ident = analysed(q)
    keep = [names.index(n) for n in ident.identifiable]
    Js = J[:, keep] / np.linalg.norm(J[:, keep], axis=0)
    cov = np.zeros((len(names), len(names)))
    cov[np.ix_(keep, keep)] = np.linalg.pinv(Js.T @ Js)
    out = {
        "poses": int(len(q)),
        "rank": ident.rank,
        "condition": ident.condition,
        "o1": ident.o1,
        "min_singular_value": ident.min_singular_value,
        "observability_parameters": len(structural),
        "weakly_identified": weak_directions(cov, names),
    }
    if reference_q is not None:
        J_ref, ref = analysed(np.atleast_2d(np.asarray(reference_q, float)))
        out["rank_reference"] = ref.rank
        out["missing"] = [n for n in ref.identifiable if n not in ident.identifiable]
        if sigma_m is not None and reference_sigma_m is not None:
            out["expected_prediction"] = (
                None
                if out["missing"]
                else expected_prediction_sigma(
                    J[:, keep], sigma_m, J_ref[:, keep], reference_sigma_m, train_share
                )
            )
    return out


EXPECTED_PREDICTION_BASIS = (
    "first order at the nominal chain: the weighted least-squares covariance of the identifiable "
    "parameters from the poses the fit trains on (rows weighted by the tracker's per-axis "
    "1-sigma), propagated to the SMR position at the reference poses; it holds if the geometric "
    "model is the truth and the tracker meets its stated accuracy: what the model leaves out "
    "comes on top"
)


def expected_prediction_sigma(
    J: np.ndarray,
    sigma_m: np.ndarray,
    J_ref: np.ndarray,
    reference_sigma_m: np.ndarray,
    train_share: float = 1.0,
) -> dict:
    """The fitted geometry's expected 3-D prediction 1-sigma at reference poses, before anything
    is measured. J (3 N, P) is the identification Jacobian of the planned poses (identifiable
    columns only), `sigma_m` (N,) their per-axis 1-sigma, J_ref (3 M, P) and `reference_sigma_m`
    (M,) the same at the reference poses; the fit trains on `train_share` of the poses.

    Returns metres: `rms_m` (RMS over the reference poses of sqrt(trace of the 3 x 3 prediction
    covariance)), `max_m`, `floor_m` (the RMS 3-D noise of a measurement there) and
    `heldout_rms_m` = sqrt(rms^2 + floor^2), what the held-out RMS should come to."""
    sigma_m = np.asarray(sigma_m, float).reshape(-1)
    rs = np.asarray(reference_sigma_m, float).reshape(-1)
    if J.shape[0] != 3 * len(sigma_m) or J_ref.shape[0] != 3 * len(rs):
        raise ValueError(
            f"Jacobians {J.shape} and {J_ref.shape} need 3 rows a pose: sigmas {sigma_m.shape}, "
            f"{rs.shape}"
        )
    if not (0.0 < train_share <= 1.0):
        raise ValueError(f"train_share must be in (0, 1], got {train_share}")
    w = np.repeat(1.0 / sigma_m, 3)
    Jw = J * w[:, None]
    scale = np.linalg.norm(Jw, axis=0)
    scale = np.where(scale > 0.0, scale, 1.0)  # a column without effect: left unscaled
    cov_s = np.linalg.pinv((Jw / scale).T @ (Jw / scale)) / train_share
    G = J_ref / scale  # prediction Jacobian in the scaled parameters
    var = np.einsum("ij,jk,ik->i", G, cov_s, G).reshape(-1, 3).sum(axis=1)
    s3 = np.sqrt(np.maximum(var, 0.0))
    rms = float(np.sqrt(np.mean(s3**2)))
    floor = float(np.sqrt(np.mean(3.0 * rs**2)))
    return {
        "rms_m": rms,
        "max_m": float(s3.max()),
        "floor_m": floor,
        "heldout_rms_m": float(np.hypot(rms, floor)),
        "train_share": float(train_share),
        "basis": EXPECTED_PREDICTION_BASIS,
    }


def group_representatives(
    groups: Iterable[Sequence[str]], estimated: Iterable[str]
) -> dict[str, list[str]]:
    """{parameter: its group} for each dependent group (`Identifiability.unidentifiable`) of
    which exactly one member is estimated: that member carries the whole group's effect (its
    value and std are the group's; `workcell fit` and `replay` mark it with *, `GROUP_STAR_NOTE`)."""
    est = set(estimated)
    out = {}
    for g in groups:
        kept = [n for n in g if n in est]
        if len(g) > 1 and len(kept) == 1:
            out[kept[0]] = list(g)
    return out


GROUP_STAR_NOTE = (
    "*: value and std are those of the parameter's dependent group (listed above) taken "
    "together, not of the parameter alone: the poses cannot tell the group's members apart"
)
