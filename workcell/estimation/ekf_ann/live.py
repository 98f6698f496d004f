"""Live use of the EKF-ANN: feed it every sample as it is measured (campaign) or replayed.

`LiveFilter.update(sample)` takes a /campaign/sample dict and returns one progress line.

Initialisation (documented scheme for a random network, issue item 2b):
1. The first `n_init` samples are buffered. The nominal chain (session DH, nominal SMR offset)
   is registered rigidly to them (Kabsch) - this replaces the session's rough base pose.
2. The geometric states are the parameters the identification Jacobian of these samples can
   separate (`workcell.estimation.identifiability.analyse`, the project's priority order: base
   and lever arm first, dependent DH parameters stay fixed at nominal).
3. The network input standardisation comes from the buffered joints; the weights are drawn at
   random (Glorot, seeded). With geometric states (the default) the filter starts from this
   random network, as in the paper. Without them the network is pre-fitted by LM on the
   position corrections R^T (y - f(q)) of half the buffered samples and the pre-fit is kept
   only if it predicts the other half better than the random network and than no correction.
4. The filter then processes the buffered samples and every later one, one at a time. The
   buffered samples' innovations are not predictions (the initialisation saw them): the
   innovation shown and the variance test start with the first sample after them.

Model adequacy (2c): the innovation-based variance factor s0^2 = mean(e^T S^-1 e) / 3 over the
last `window` samples is reported on every line with the chi^2 test (95 %): "ok" if
sum(e^T S^-1 e) <= chi2_0.95(3 n), else "REJECT" (the model or the stated noise is inadequate).

What the estimate says about itself (`LiveFilter.estimate`, printed by `workcell replay` and at the
end of `workcell campaign --online ekf-ann`): the frame of its base offsets (`base_ref`, its own
registration, and the combined `tracker_T_base` to compare with other models), the dependent
groups a state stands for (as `workcell fit` marks them), and how the final state splits the
samples between geometry and network (`GEOMETRY_SPLIT_BASIS`). `LiveFilter.model` stores the
declared SMR offset as `info.nominal_tool_m`, the TCP an export commands with.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
from scipy.stats import chi2

from workcell.estimation.dh import TRACKER_MPE_M
from workcell.estimation.ekf_ann import ann as A
from workcell.estimation.ekf_ann.filter import EkfAnnFilter, FilterConfig, prefit_weights
from workcell.estimation.ekf_ann.model import EkfAnnModel
from workcell.estimation.identifiability import (
    Identifiability,
    analyse,
    candidates_for,
    group_representatives,
)
from workcell.estimation.models import note_joint_range, rms_interval
from workcell.kinematics.chain import (
    N_PARAMS,
    PARAM_NAMES,
    PARAM_UNITS,
    PARAMETER_FRAMES,
    base_pose_with_std,
    jac_params,
    p_tracker,
    pack,
    tracker_T_base,
)
from workcell.kinematics.frames import kabsch
from workcell.kinematics.robots import DH, RobotSpec, robot_from_session

# A geometric state is "held by its prior" when the data left its (unscaled) filter std above
# PRIOR_HELD_RATIO of its starting std. Why 0.5: with the diagonal starting covariance P0 of the
# filter, the linear-Gaussian estimate is P P0^-1 x0 + P H^T R^-1 y, so the coefficient of a
# state's own starting value in its estimate is P_ii / P0_ii = (std_filter / std_prior)^2; above
# 0.5 the prior carries more than 25 % of the value. A state of which only a combination with one
# other state of the same prior is measured - however well - ends at 1/sqrt(2) = 0.71 (series D,
# iso cubes: base_ty and tool_z, 0.708 each, which `workcell fit` flags as weakly identified), so
# the threshold sits below that; the states the data determine end far below it (series D: the
# largest of the other 23 is alpha5 at 0.16).
PRIOR_HELD_RATIO = 0.5
# a held state's partners: the estimated geometric states it is correlated with at least this much
# in the final covariance (what the data measured is then their combination)
PARTNER_CORRELATION = 0.9

GEOMETRIC_STD_BASIS = (
    "std_filter: sqrt(diag P) of the filter, right only if the stated measurement noise is; std "
    "(and geometric_std): that times std_scale = sqrt(max(1, s0^2)), s0^2 the innovation variance "
    "factor over the window (variance_factor; above 1 the innovations are larger than the stated "
    "noise); std_prior: the filter's starting std of the state (sigma_g0_m, sigma_g0_rad); "
    f"determined_by 'prior' (the states in held_by_prior): std_filter / std_prior > "
    f"{PRIOR_HELD_RATIO} (the prior carries more than {PRIOR_HELD_RATIO**2 * 100:.0f} % of the "
    "value): the data did not determine the state; its value is its start (nominal DH, declared "
    "SMR offset, registered base) moved only by its prior's share of a combination the data "
    "measured (correlated_with), and its std reflects the prior's spread, not a measurement "
    "uncertainty"
)

BASE_REF_BASIS = (
    "base_t*, base_r* (geometric) are offsets from base_ref, this filter's own registration: the "
    "nominal chain with the declared SMR offset fitted rigidly (Kabsch) to its first n_init "
    "samples. `workcell fit` registers its own base_ref (on all its poses), so the offsets of the "
    "two are in different frames and not comparable; compare the combined base tracker_T_base = "
    "base_ref @ Trans(t) @ Rot(r) (a model file's tracker_T_base) instead. tracker_T_base: "
    "translation_m, quaternion_wxyz (rotation tracker <- base), std of the translation (m) and of "
    "the rotation (rad, small rotation about the tracker's x, y, z), propagated from the "
    "geometric states' covariance times std_scale^2"
)

UNIDENTIFIABLE_BASIS = (
    "groups of geometric parameters the first n_init samples cannot tell apart (the rank test "
    "`workcell fit` uses, `workcell.estimation.identifiability.analyse` of their weighted "
    "Jacobian); the group's other members stay at nominal, and where the filter estimates one "
    "member alone (geometric.*.stands_for, marked * in the text) its value and std are those of "
    "the whole group taken together, not of the parameter alone"
)

GEOMETRY_SPLIT_BASIS = (
    "the geometric states are the filter's split of the position error between the geometry "
    "and the network, which learns alongside them and absorbs part of what a geometry-only "
    "model puts into the DH parameters, base and SMR: they are not comparable one by one with "
    "`workcell fit --method dh` (compare predictions, or the combined base tracker_T_base). "
    "Their stds are those of this split: conditional on the network (its form, its prior "
    "sigma_w0 and its linearisation at the current weights), not the uncertainty of a "
    "geometry-only fit. geometric_part_rms_m: RMS of y - f(q; theta) (the geometry alone, network "
    "off) over the samples the filter saw, at its final state; rms_m: the whole model's (geometry "
    "plus network) on the same samples, in-sample (not predictions). Their difference is what the "
    "network carries; `workcell fit --method dh` reports the RMS of a geometry-only fit"
)


def _std_scale(s0: float) -> float:
    """sqrt(max(1, s0^2)) (1 when s0^2 is not known yet): the factor on the filter's stds."""
    return float(np.sqrt(max(s0, 1.0))) if np.isfinite(s0) else 1.0


def geometry_identification(
    dh: DH, theta: np.ndarray, base_ref: np.ndarray, q: np.ndarray, sigma: np.ndarray
) -> Identifiability:
    """The identifiability analysis of these samples (weighted Jacobian, the candidates and
    priority order `workcell fit` uses): what is identifiable and the dependent groups."""
    w = 1.0 / np.sqrt(np.mean(np.asarray(sigma) ** 2, axis=1))
    J = np.asarray(jac_params(theta, base_ref, np.asarray(q))) * w[:, None, None]
    return analyse(J.reshape(-1, N_PARAMS), candidates=candidates_for(dh))


def identifiable_geometry(
    dh: DH, theta: np.ndarray, base_ref: np.ndarray, q: np.ndarray, sigma: np.ndarray
) -> list[str]:
    """Geometric parameters separately identifiable from these samples (weighted Jacobian)."""
    return geometry_identification(dh, theta, base_ref, q, sigma).identifiable


class LiveFilter:
    """Online EKF-ANN for a cell. Not thread-safe; call `update` from one thread."""

    def __init__(
        self,
        spec: RobotSpec,
        tool_m: np.ndarray,
        *,
        n_init: int = 30,
        cfg: FilterConfig | None = None,
        hidden: int = 29,
        seed: int = 0,
        adaptive_geometry: bool = True,
        window: int = 100,
        tracker_mpe: tuple[float, float] | None = TRACKER_MPE_M,
    ) -> None:
        if n_init < 6:
            raise ValueError(
                f"n_init must be >= 6 (registration needs several poses), got {n_init}"
            )
        self.robot = spec
        self.tool_m = np.asarray(tool_m, float)
        self.n_init = int(n_init)
        self.cfg = cfg or FilterConfig()
        self.hidden = hidden
        self.seed = seed
        self.adaptive_geometry = adaptive_geometry
        # measurement noise per axis: max(recorded sigma of the mean, tracker MPE / 4) -- the
        # recorded sigma comes from the scatter of the readings at one pose and leaves out the
        # tracker's per-pose systematic error (None: the recorded sigma alone)
        self.tracker_mpe = tracker_mpe
        self.filter: EkfAnnFilter | None = None
        self._buf: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._nis: deque = deque(maxlen=window)
        self.n = 0
        self.last_innovation_m = float("nan")
        self.prefit_accepted: bool | None = None  # None until initialised
        # the identifiability analysis of the initialisation samples (None until initialised)
        self.identification: Identifiability | None = None

    @classmethod
    def for_cell(cls, cell: Any, **kw: Any) -> LiveFilter:
        """From a campaign's cell setup (anything with `spec` and `tool_m`)."""
        return cls(cell.spec, np.asarray(cell.tool_m, float), **kw)

    @classmethod
    def from_session(cls, session: dict, **kw: Any) -> LiveFilter:
        """From a recording's session message (replay)."""
        spec = robot_from_session(session["robot"])
        return cls(spec, np.asarray(session["tool"]["smr_offset_m"], float), **kw)

    # ------------------------------------------------------------------ feeding
    @staticmethod
    def _parse(sample: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        try:
            q = np.asarray(sample["q_measured_rad"], float)
            y = np.asarray(sample["tracker_position_m"], float)
            s = sample.get("tracker_sigma_m")
            s = np.full(3, 1e-5) if s is None else np.asarray(s, float)
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"sample {sample.get('index')}: malformed ({e})") from None
        if q.shape != (6,) or y.shape != (3,) or s.shape != (3,):
            raise ValueError(f"sample {sample.get('index')}: q {q.shape}, position {y.shape}")
        s = np.where(np.isfinite(s) & (s > 0), s, 1e-5)
        return q, y, s

    def _sigma(self, y: np.ndarray, s: np.ndarray) -> np.ndarray:
        if self.tracker_mpe is None or not np.all(np.isfinite(y)):
            return s
        a, b = self.tracker_mpe
        return np.maximum(s, (a + b * float(np.linalg.norm(y))) / 4.0)

    def update(self, sample: dict) -> str:
        """Process one /campaign/sample dict; return a one-line progress string."""
        q, y, s = self._parse(sample)
        s = self._sigma(y, s)
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(y))):
            return f"ekf-ann {self.n:5d}  sample {sample.get('index')} skipped (non-finite)"
        self.n += 1
        if self.filter is None:
            self._buf.append((q, y, s))
            if len(self._buf) < self.n_init:
                return f"ekf-ann {self.n:5d}  collecting {len(self._buf)}/{self.n_init} samples"
            Q, Y, S = (np.array(v) for v in zip(*self._buf, strict=True))
            self._initialise(Q, Y, S)
            self.filter.process(Q, Y, S)
            self._buf = []
            # The initialisation used these samples (base registration, choice of the geometric
            # states, the pre-fit if any): their innovations are not predictions, so they enter
            # neither the variance test nor the innovation shown.
            pre = "pre-fitted network" if self.prefit_accepted else "random network"
            return (
                f"ekf-ann {self.n:5d}  initialised on {self.n_init} samples, {pre} "
                f"(innovations and the variance test start with the next sample)"
            )
        log = self.filter.process(q[None], y[None], s[None])
        self._nis.extend(log.nis.tolist())
        self.last_innovation_m = float(np.linalg.norm(log.innovation_m[-1]))
        return self.status_line(q)

    def _initialise(self, Q: np.ndarray, Y: np.ndarray, S: np.ndarray) -> None:
        th = pack(self.robot.dh, tool=self.tool_m)
        base_ref = kabsch(np.asarray(p_tracker(th, np.eye(4), Q)), Y)
        cfg = self.cfg
        if cfg.mode == "adaptive":
            # what these samples identify, and the dependent groups (`estimate` reports which
            # state stands for a group, as `workcell fit` marks it)
            ident = geometry_identification(self.robot.dh, th, base_ref, Q, S)
            self.identification = ident
            if self.adaptive_geometry and not cfg.geometric:
                from dataclasses import replace

                cfg = replace(cfg, geometric=tuple(ident.identifiable))
        spec = A.AnnSpec.from_joints(Q, hidden=self.hidden)
        w0 = A.random_weights(self.hidden, self.seed)
        if cfg.geometric:
            # The geometric states take the geometric error; a network pre-fitted on the raw
            # corrections would hold it instead and extrapolate it badly. Measured on two
            # simulated realistic campaigns replayed live (`workcell campaign --robot sim
            # --tracker sim`, 120 poses seed 0 and 150 poses seed 11): innovations of the 20 poses
            # after a 30-sample initialisation 1191 / 975 um RMS after a pre-fit, 171 / 124 um
            # from the random network; with 100 initial samples 335 um after a pre-fit that
            # passed the guard of `_guarded_prefit`, 114 um from the random network.
            self.prefit_accepted = False
        else:
            w0 = self._guarded_prefit(w0, Q, Y, th, base_ref, spec)
        self.filter = EkfAnnFilter.create(cfg, spec, th, base_ref, w0, seed=self.seed)

    def _guarded_prefit(self, w_rand, Q, Y, th, base_ref, spec) -> np.ndarray:
        """Pre-fit the random network on half the buffer; keep it only if it predicts the other
        half's corrections better than the random network and than no correction (else start
        from the random network). Used when the filter has no geometric states."""
        rng = np.random.default_rng(self.seed)
        idx = rng.permutation(len(Q))
        tr, va = idx[: len(Q) // 2], idx[len(Q) // 2 :]
        w_fit = prefit_weights(w_rand, Q[tr], Y[tr], th, base_ref, spec, seed=self.seed)
        R = np.asarray(tracker_T_base(th, base_ref))[:3, :3]
        d = (Y[va] - np.asarray(p_tracker(th, base_ref, Q[va]))) @ R

        def cost(w):
            return float(np.sum((A.predict_base_m(w, Q[va], spec) - d) ** 2))

        # better than both the random network and no correction at all (the registered chain)
        self.prefit_accepted = cost(w_fit) < min(cost(w_rand), float(np.sum(d**2)))
        return w_fit if self.prefit_accepted else np.asarray(w_rand, float)

    # ------------------------------------------------------------------ reporting
    def variance_test(self) -> tuple[float, bool | None]:
        """(s0^2 over the window, passes the 95 % chi^2 test); (nan, None) before any
        innovation (the filter has not started: nothing was tested)."""
        if not self._nis:
            return float("nan"), None
        v = np.asarray(self._nis)
        dof = 3 * len(v)
        return float(v.sum() / dof), bool(v.sum() <= chi2.ppf(0.95, dof))

    def status_line(self, q: np.ndarray | None = None) -> str:
        s0, ok = self.variance_test()
        f = self.filter
        ng = ""
        if f is not None and q is not None:
            ng = f"  |ng| {np.linalg.norm(f.ann_tracker_m(q[None])[0]) * 1e3:6.3f} mm"
        return (
            f"ekf-ann {self.n:5d}  innov {self.last_innovation_m * 1e6:7.1f} um  "
            f"s0^2 {s0:6.2f} {'--' if ok is None else 'ok' if ok else 'REJECT'}{ng}"
            f"  ann-iter {0 if f is None else f'{f.ann_accepted}/{f.ann_iterations}'}"
        )

    def estimate(self) -> dict:
        """The current estimate as plain data (what `replay --json` prints)."""
        s0, ok = self.variance_test()
        f = self.filter
        out = {
            "samples": self.n,
            "variance_factor": s0,
            "variance_test_ok": ok,
            "initialised": f is not None,
            "n_init": self.n_init,
        }
        if f is not None:
            k = _std_scale(s0)
            geo = self._geometric(f, s0)
            out.update(
                {
                    "mode": f.cfg.mode,
                    "prefit_accepted": self.prefit_accepted,
                    "geometric_states": list(f.cfg.geometric),
                    "theta": f.theta.tolist(),
                    "theta_names": list(PARAM_NAMES),
                    # the same scaled std as geometric.*.std (until 2026-11-26 this was the
                    # unscaled std_filter, with nothing saying so)
                    "geometric_std": {n: g["std"] for n, g in geo.items()},
                    "std_scale": k,
                    "held_by_prior": [
                        n for n, g in geo.items() if g.get("determined_by") == "prior"
                    ],
                    "held_by_prior_ratio": PRIOR_HELD_RATIO,
                    "geometric": geo,
                    "geometric_std_basis": GEOMETRIC_STD_BASIS,
                    "unidentifiable": self._groups(),
                    "unidentifiable_basis": UNIDENTIFIABLE_BASIS.replace(
                        "n_init", str(self.n_init)
                    ),
                    "parameter_frames": PARAMETER_FRAMES,
                    "base_ref": np.asarray(f.base_ref, float).tolist(),
                    "tracker_T_base": self._base_pose(f, k),
                    "base_ref_basis": BASE_REF_BASIS.replace("n_init", str(self.n_init)),
                    **self._split(f),
                    "geometry_split_basis": GEOMETRY_SPLIT_BASIS,
                    "ann_iterations": f.ann_iterations,
                    "ann_iterations_accepted": f.ann_accepted,
                    "state_norm": float(np.linalg.norm(f.x)),
                }
            )
        return out

    def _groups(self) -> list[list[str]]:
        """The dependent groups of the initialisation samples (`geometry_identification`)."""
        return [] if self.identification is None else [list(g) for g in self.identification.groups]

    @staticmethod
    def _theta_cov(f: EkfAnnFilter) -> np.ndarray:
        """Covariance (39, 39) of theta from the filter's geometric states (unscaled)."""
        K, E = f.n_weights, f.E  # E: (39, 0) in paper mode (no geometric states)
        n = E.shape[1]
        return E @ np.asarray(f.P[K : K + n, K : K + n], float) @ E.T

    @classmethod
    def _base_pose(cls, f: EkfAnnFilter, k: float) -> dict:
        """The combined base tracker_T_base = base_ref @ Trans(t) @ Rot(r) with the std of its
        translation and rotation (first order, from the geometric states' covariance, scaled by
        `k`); the rotation std is of a small rotation about the tracker's axes."""
        return base_pose_with_std(f.theta, f.base_ref, cls._theta_cov(f) * k**2)

    @staticmethod
    def _split(f: EkfAnnFilter) -> dict:
        """How the final state splits the samples seen between geometry and network: the RMS of
        the whole model and of the geometry alone (network off), in-sample."""
        q = f.q_seen()
        if not len(q):
            return {}
        y = np.concatenate(f._y)
        geo = np.asarray(p_tracker(f.theta, f.base_ref, q)) + f.offset_m()
        full = geo + f.ann_tracker_m(q)
        return {
            "fit_samples": len(q),
            "rms_m": float(np.sqrt(np.mean(np.sum((y - full) ** 2, axis=1)))),
            "rms_ci95_m": list(rms_interval(np.linalg.norm(y - full, axis=1))),
            "geometric_part_rms_m": float(np.sqrt(np.mean(np.sum((y - geo) ** 2, axis=1)))),
            "geometric_part_rms_ci95_m": list(rms_interval(np.linalg.norm(y - geo, axis=1))),
        }

    def _geometric(self, f: EkfAnnFilter, s0: float) -> dict[str, dict]:
        """Each estimated geometric state: value, the filter's std, that std scaled by the
        innovation variance factor, and (adaptive mode) the starting std and whether the data
        or the prior determined the state (`GEOMETRIC_STD_BASIS`, `PRIOR_HELD_RATIO`)."""
        k = _std_scale(s0)
        x_geo = f.x[f.n_weights :]
        prior = f.geometric_prior_std()
        sd_all = f.geometric_std()
        names = list(sd_all)
        C = np.asarray(f.P[f.n_weights :, f.n_weights :], float)
        d = np.sqrt(np.clip(np.diag(C), 0, None))
        with np.errstate(divide="ignore", invalid="ignore"):
            corr = C / np.outer(d, d)
        out = {}
        for i, (n, sd) in enumerate(sd_all.items()):
            if n in PARAM_NAMES:
                value, unit = float(f.theta[PARAM_NAMES.index(n)]), PARAM_UNITS[n]
            else:  # paper mode: the position state, tracker frame
                value, unit = float(x_geo[i]), "m"
            g = {"value": value, "std": sd * k, "std_filter": sd, "unit": unit}
            if n in prior:
                r = sd / prior[n]
                held = bool(r > PRIOR_HELD_RATIO)
                g.update(
                    std_prior=prior[n],
                    std_filter_over_prior=r,
                    determined_by="prior" if held else "data",
                )
                if held:
                    g["correlated_with"] = {
                        m: float(corr[i, j])
                        for j, m in enumerate(names)
                        if j != i
                        and np.isfinite(corr[i, j])
                        and abs(corr[i, j]) >= PARTNER_CORRELATION
                    }
            out[n] = g
        for n, group in group_representatives(self._groups(), out).items():
            out[n]["stands_for"] = group
        return out

    def model(self) -> EkfAnnModel:
        if self.filter is None:
            raise ValueError(f"not initialised yet: {self.n} of {self.n_init} samples seen")
        s0, _ = self.variance_test()
        info = {"variance_factor": s0} if np.isfinite(s0) else {}
        # the recording's declared SMR offset, as the batch fits store it: the controller's TCP
        # an export commands with (`export.correction.nominal_for`), not the filter's fitted SMR
        info["nominal_tool_m"] = self.tool_m.tolist()
        model = EkfAnnModel.from_filter(self.filter, self.robot.model, self.robot.dh, info=info)
        # which states only the prior holds (`PRIOR_HELD_RATIO`): their covariance in the model is
        # the prior's spread, not a measurement uncertainty
        geo = self._geometric(self.filter, s0)
        model.info["geometric_held_by_prior"] = [
            n for n, g in geo.items() if g.get("determined_by") == "prior"
        ]
        stands = {n: g["stands_for"] for n, g in geo.items() if "stands_for" in g}
        if stands:  # the states that carry a dependent group (`group_representatives`)
            model.info["geometric_stands_for"] = stands
        note_joint_range(model, self.filter.q_seen())
        return model
