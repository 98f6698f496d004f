"""The kinematic-margin watch: checks, pose by pose, the assumption the envelope rests on.

The envelope refuses a pose when the *nominal* SMR (nominal chain + the session's declared SMR
offset) comes within `kinematic_margin_m` of a face. That protects the cell only if the real SMR
is within the margin of the nominal one. Before a first fit nobody knows; this watch measures it
while the campaign runs, from the samples themselves:

- it fits, on the samples so far, the tracker registration (6) and the SMR offset on the flange
  (3) with the nominal chain (a 9-parameter least-squares problem, milliseconds);
- **SMR offset**: the real SMR sits |d| from the declared one, the same distance in every pose.
  If |d| - k sigma_d > margin (k: Student-t 99.73 % two-sided quantile for the fit's degrees of
  freedom; sigma_d: the fit's standard error along d), the margin does not cover it;
- **the chain**: after that fit, a measured pose more than the margin from the nominal chain's
  prediction means the arm is not where its nominal model says (a wrong robot model, a large
  kinematic error). Two such poses are needed (one may be a bumped SMR).

Either stops the campaign (robot stopped, recording closed, `margin` event). When neither does,
one `margin` info event says how well the margin was verified; the offset is unobservable while
the flange orientation hardly changes (an ISO cube at one orientation): the watch says so rather
than passing it.

What it cannot see: kinematic errors that registration absorbs at the measured poses but that grow
elsewhere in the envelope (`workcell envelope --model` measures those after a fit).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_POSES = 6  # 18 coordinates for 9 parameters: 9 degrees of freedom
BAD_POSES_TO_STOP = 2
# a weak prior that keeps the fitted offset near the declared one when the data cannot place it
# (a flange at one orientation): 1 m of offset costs as much as a 10 mm residual on one coordinate
PRIOR_WEIGHT = 1e-2


@dataclass
class MarginVerdict:
    n: int
    offset_m: np.ndarray  # fitted SMR offset minus the declared one, flange frame (3,)
    offset_sigma_m: float  # standard error of |offset| (along it)
    offset_sigma_max_m: float  # largest standard error of the offset in any direction
    k: float  # coverage factor used
    residual_max_m: float
    bad_poses: list[int]  # pose ids more than the margin from the nominal chain, after the fit
    stop: str | None  # the reason to stop, one line, or None

    @property
    def offset_norm_m(self) -> float:
        return float(np.linalg.norm(self.offset_m))

    def resolves(self, margin_m: float) -> bool:
        """The offset is known well enough, in every direction, to tell it from the margin."""
        return bool(self.k * self.offset_sigma_max_m < margin_m)


class MarginWatch:
    """Feed it each recorded sample (`update`); it returns a `MarginVerdict` once it has
    `MIN_POSES` samples, with `stop` set when the margin demonstrably does not hold."""

    def __init__(self, spec, tool_m, margin_m: float) -> None:
        from workcell.kinematics.chain import pack

        self.spec = spec
        self.tool_m = np.asarray(tool_m, float).reshape(3)
        self.margin_m = float(margin_m)
        self.theta = pack(spec.dh, tool=np.zeros(3))
        self.R: list[np.ndarray] = []  # base_R_flange
        self.t: list[np.ndarray] = []  # base_p_flange
        self.p: list[np.ndarray] = []  # p_tracker
        self.ids: list[int] = []
        self.last: MarginVerdict | None = None

    def update(self, sample: dict) -> MarginVerdict | None:
        from workcell.kinematics.chain import base_T_flange

        q = np.asarray(sample["q_measured_rad"], float)
        p = np.asarray(sample["tracker_position_m"], float)
        if q.shape != (self.spec.dh.n_joints,) or p.shape != (3,):
            return self.last
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(p))):
            return self.last
        T = np.asarray(base_T_flange(self.theta, q[None, :]))[0]
        self.R.append(T[:3, :3])
        self.t.append(T[:3, 3])
        self.p.append(p)
        self.ids.append(int(sample.get("pose_id", len(self.ids))))
        if len(self.p) < MIN_POSES:
            return None
        self.last = self._verdict()
        return self.last

    def _verdict(self) -> MarginVerdict:
        from scipy import stats
        from scipy.optimize import least_squares

        from workcell.kinematics.frames import kabsch, matrix_from_rotvec, rotvec_from_matrix

        R, t, P = np.array(self.R), np.array(self.t), np.array(self.p)
        n = len(P)
        tool0 = self.tool_m
        T0 = kabsch(np.einsum("nij,j->ni", R, tool0) + t, P)
        x0 = np.concatenate([rotvec_from_matrix(T0[:3, :3]), T0[:3, 3], tool0])

        def residual(x: np.ndarray) -> np.ndarray:
            p_base = np.einsum("nij,j->ni", R, x[6:]) + t
            r = (p_base @ matrix_from_rotvec(x[:3]).T + x[3:6] - P).ravel()
            return np.concatenate([r, PRIOR_WEIGHT * (x[6:] - tool0)])

        fit = least_squares(residual, x0, x_scale=np.full(9, 0.1))
        r = fit.fun[:-3].reshape(-1, 3)
        dist = np.linalg.norm(r, axis=1)
        dof = 3 * n - 9
        s2 = float(r.ravel() @ r.ravel()) / dof
        JtJ = fit.jac.T @ fit.jac
        d = fit.x[6:] - tool0
        # standard error of |d| along d; infinite when the offset is not observable (the flange
        # orientation hardly changed), so no verdict is drawn from it
        try:
            cov = np.linalg.inv(JtJ)[6:, 6:] * s2
        except np.linalg.LinAlgError:
            cov = np.full((3, 3), np.inf)
        if np.all(np.isfinite(cov)):
            u = d / max(np.linalg.norm(d), 1e-12)
            sigma = float(np.sqrt(max(u @ cov @ u, 0.0)))
            # the largest standard error in any direction: what an unseen offset could be
            sigma_max = float(np.sqrt(max(np.linalg.eigvalsh(cov).max(), 0.0)))
        else:
            sigma = sigma_max = float("inf")
        k = float(stats.t.ppf(1 - 0.0027 / 2, dof))
        bad = [self.ids[i] for i in np.flatnonzero(dist > self.margin_m)]
        margin_mm = 1e3 * self.margin_m
        stop = None
        norm = float(np.linalg.norm(d))
        resolved = k * sigma_max < self.margin_m  # in every direction, not only along d
        if resolved and norm - k * sigma > self.margin_m:
            fitted = ", ".join(f"{1e3 * v:.1f}" for v in fit.x[6:])
            declared = ", ".join(f"{1e3 * v:.1f}" for v in tool0)
            stop = (
                f"the SMR sits {1e3 * norm:.1f} +- {1e3 * sigma:.1f} mm from the declared "
                f"smr_offset_m (fitted on {n} poses: [{fitted}] mm on the flange, declared "
                f"[{declared}] mm), more than the envelope's {margin_mm:g} mm kinematic margin: "
                "poses may come closer to the envelope's faces than it allows. Check the SMR "
                "nest and extension and correct the tool offset, or widen kinematic_margin_m in "
                "the envelope file (workcell envelope --out)"
            )
        elif len(bad) >= BAD_POSES_TO_STOP:
            worst = int(np.argmax(dist))
            stop = (
                f"{len(bad)} of {n} measured poses are more than the envelope's {margin_mm:g} mm "
                f"kinematic margin from where the nominal {self.spec.model} chain puts them "
                f"(worst: pose {self.ids[worst]}, {1e3 * dist[worst]:.1f} mm, after fitting the "
                "tracker registration and SMR offset): is the robot model right? The envelope "
                "check cannot be trusted; widen kinematic_margin_m only if this error is known"
            )
        return MarginVerdict(
            n=n,
            offset_m=d,
            offset_sigma_m=sigma,
            offset_sigma_max_m=sigma_max,
            k=k,
            residual_max_m=float(dist.max()),
            bad_poses=bad,
            stop=stop,
        )

    def summary(self) -> str | None:
        """One line for the end of a campaign: how well the margin was verified."""
        v = self.last
        margin_mm = 1e3 * self.margin_m
        if v is None:
            return (
                f"kinematic margin {margin_mm:g} mm not checked: fewer than {MIN_POSES} poses "
                "were measured"
            )
        if v.stop:
            return None
        chain = f"measured poses within {1e3 * v.residual_max_m:.1f} mm of the nominal chain"
        if not v.resolves(self.margin_m):
            known = (
                f"known only to +- {1e3 * v.k * v.offset_sigma_max_m:.0f} mm"
                if np.isfinite(v.offset_sigma_max_m)
                else "not observable"
            )
            return (
                f"kinematic margin {margin_mm:g} mm only partly checked on {v.n} poses: {chain}, "
                f"but the SMR offset is {known} (the flange orientation changed too little); "
                "an error in smr_offset_m would go unseen"
            )
        return (
            f"kinematic margin {margin_mm:g} mm checked on {v.n} poses: SMR offset "
            f"{1e3 * v.offset_norm_m:.1f} +- {1e3 * v.offset_sigma_m:.1f} mm from the declared "
            f"one, {chain}"
        )
