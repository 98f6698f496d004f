"""The kinematic-margin watch: checks, pose by pose, the assumption the envelope rests on.

The envelope refuses a pose when the *nominal* SMR (nominal chain + the session's declared SMR
offset) comes within `kinematic_margin_m` of a face. That protects the cell only if the real SMR
is within the margin of the nominal one. Before a first fit nobody knows; this watch measures it
while the campaign runs, from the samples themselves:

- it fits, on the samples so far, the tracker registration (6) and the SMR offset on the flange
  (3) with the nominal chain (a 9-parameter least-squares problem, 5-25 ms), robustly: a Cauchy
  fit, and while there are few poses and one is off, the fits that leave one pose out;
- **SMR offset**: the real SMR sits |d| from the declared one, the same distance in every pose.
  The offset's covariance comes from the data alone (registration marginalised out; the fit's
  weak prior is not a measurement); a principal direction is resolved when k sigma < margin there
  (k: Student-t 99.73 % two-sided quantile for the fit's degrees of freedom). If the part of d
  in the resolved directions, d_r, has |d_r| - k sigma > margin (sigma: the standard error along
  d_r), the margin does not cover it: |d| >= |d_r|, so this holds before every direction is
  resolved;
- **the chain**: after that fit, a measured pose more than the margin from the nominal chain's
  prediction means the arm is not where its nominal model says (a wrong robot model, a large
  kinematic error). Two such poses are needed (one may be a bumped SMR).

- **before that fit** (3 to `MIN_POSES` - 1 poses): the distance between two measured points is
  the distance between the real SMR positions (the tracker's frame is rigid), so it differs from
  the nominal distance (nominal chain, declared offset) by at most the two poses' errors: more
  than twice the margin (plus `DISTANCE_SLACK_M`) means one of them is beyond it. Pairs that do
  not all share one pose (one may be bumped) stop the campaign: a declared SMR offset 0.2 m off
  took the real SMR 159 mm outside the box before the fit could start (a safety audit).

Either stops the campaign (robot stopped, recording closed, `margin` event). When neither does,
one `margin` info event says how well the margin was verified; the offset is unobservable in
the directions the flange orientation hardly changes (along the axis it only turns about, at an
ISO cube's one orientation in all three): the watch says in how many of 3 directions it was
resolved rather than passing it.

What it cannot see: kinematic errors that registration absorbs at the measured poses but that grow
elsewhere in the envelope (`workcell envelope --model` measures those after a fit).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_POSES = 6  # 18 coordinates for 9 parameters: 9 degrees of freedom
MIN_POSES_DISTANCES = 3  # the distance check: pairs that need not share one (maybe bumped) pose
DISTANCE_SLACK_M = 1e-3  # the tracker's and the encoders' share of a distance, generously
BAD_POSES_TO_STOP = 2
# a weak prior that keeps the fitted offset near the declared one when the data cannot place it
# (a flange at one orientation): 1 m of offset costs as much as a 10 mm residual on one coordinate
PRIOR_WEIGHT = 1e-2
ROBUST_M = 1e-3  # Cauchy loss scale of the robust fit
EVERY_POSE_UP_TO = 200  # poses; beyond, every (n // 200)-th pose, so a long campaign's cost
# stays linear in its poses
LEAVE_ONE_OUT_UP_TO = 20  # poses; beyond, the robust fit alone sets one bad pose aside


def _mm(value_m: float, sigma_m: float) -> str:
    """'15.9 +- 0.1' in mm, with the sigma's two significant digits below 0.1 mm."""
    v, e = 1e3 * value_m, 1e3 * sigma_m
    dec = 1 if not (np.isfinite(e) and 0 < e < 0.1) else min(3, int(-np.floor(np.log10(e))) + 1)
    return f"{v:.{dec}f} +- {e:.{dec}f}"


@dataclass
class MarginVerdict:
    n: int
    offset_m: np.ndarray  # fitted SMR offset minus the declared one, flange frame (3,)
    offset_sigma_m: float  # standard error of |offset| (along it)
    offset_sigma_max_m: float  # largest standard error of the offset in any direction
    resolved_directions: int  # principal directions of the offset known to k sigma < margin
    offset_resolved_m: float  # length of the offset's part in those directions
    offset_resolved_sigma_m: float  # and its standard error
    k: float  # coverage factor used
    residual_max_m: float  # largest distance from the nominal chain, poses within the margin
    bad_poses: list[int]  # pose ids more than the margin from the nominal chain, after the fit
    bad_dist_m: list[float]  # and their distances
    stop: str | None  # the reason to stop, one line, or None

    @property
    def offset_norm_m(self) -> float:
        return float(np.linalg.norm(self.offset_m))

    def resolves(self, margin_m: float) -> bool:
        """The offset is known well enough, in every direction, to tell it from the margin."""
        return bool(self.k * self.offset_sigma_max_m < margin_m)


class MarginWatch:
    """Feed it each recorded sample (`update`); it returns a `MarginVerdict` once it has
    `MIN_POSES` samples, with `stop` set when the margin demonstrably does not hold, and before
    that, from `MIN_POSES_DISTANCES` samples, one only when the distance check stops."""

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

    def _add(self, sample: dict) -> bool:
        from workcell.kinematics.chain import base_T_flange

        q = np.asarray(sample["q_measured_rad"], float)
        p = np.asarray(sample["tracker_position_m"], float)
        if q.shape != (self.spec.dh.n_joints,) or p.shape != (3,):
            return False
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(p))):
            return False
        T = np.asarray(base_T_flange(self.theta, q[None, :]))[0]
        self.R.append(T[:3, :3])
        self.t.append(T[:3, 3])
        self.p.append(p)
        self.ids.append(int(sample.get("pose_id", len(self.ids))))
        return True

    def extend(self, samples: list[dict]) -> MarginVerdict | None:
        """Samples recorded earlier (a resumed recording's), then one verdict on all of them."""
        for s in samples:
            self._add(s)
        if len(self.p) >= MIN_POSES:
            self.last = self._verdict() or self.last
        return self.last

    def update(self, sample: dict) -> MarginVerdict | None:
        if not self._add(sample):
            return None
        n = len(self.p)
        if MIN_POSES_DISTANCES <= n < MIN_POSES:
            verdict = self._distance_verdict()
            if verdict is not None:
                self.last = verdict
            return verdict
        if n < MIN_POSES or (n > EVERY_POSE_UP_TO and n % (n // EVERY_POSE_UP_TO) != 0):
            return None
        verdict = self._verdict()
        if verdict is not None:
            self.last = verdict
        return verdict

    def _distance_verdict(self) -> MarginVerdict | None:
        """Before the fit: a stop when measured distances between poses differ from the nominal
        ones by more than twice the margin, in pairs that do not all share one pose (module
        docstring); else None."""
        P = np.array(self.p)
        n = len(P)
        S = np.array(self.t) + np.einsum("nij,j->ni", np.array(self.R), self.tool_m)
        i, j = np.triu_indices(n, 1)
        gap = np.abs(np.linalg.norm(P[i] - P[j], axis=1) - np.linalg.norm(S[i] - S[j], axis=1))
        bad = np.flatnonzero(gap > 2 * self.margin_m + DISTANCE_SLACK_M)
        if not len(bad):
            return None
        for k in set(i[bad]) | set(j[bad]):
            if all(k in (i[b], j[b]) for b in bad):
                return None  # one pose in every pair that disagrees: a bumped SMR, maybe
        w = bad[int(np.argmax(gap[bad]))]
        a, b = self.ids[int(i[w])], self.ids[int(j[w])]
        stop = (
            f"poses {a} and {b} are {1e3 * np.linalg.norm(P[i[w]] - P[j[w]]):.1f} mm apart as the "
            f"tracker measured them, {1e3 * np.linalg.norm(S[i[w]] - S[j[w]]):.1f} mm as the "
            f"nominal {self.spec.model} chain with the declared smr_offset_m "
            f"[{', '.join(f'{1e3 * v:.1f}' for v in self.tool_m)}] mm puts them: more than twice the "
            f"envelope's {1e3 * self.margin_m:g} mm kinematic margin, so the SMR is more than "
            f"the margin from where the envelope check puts it ({len(bad)} of {len(gap)} pairs "
            f"of the first {n} poses disagree, not all through one pose): is the robot "
            "model right, and the declared SMR offset (--smr-offset: the SMR nest and "
            "extension)?"
        )
        return MarginVerdict(
            n=n,
            offset_m=np.full(3, np.nan),
            offset_sigma_m=float("inf"),
            offset_sigma_max_m=float("inf"),
            resolved_directions=0,
            offset_resolved_m=float("nan"),
            offset_resolved_sigma_m=float("inf"),
            k=float("nan"),
            residual_max_m=float("nan"),
            bad_poses=[],
            bad_dist_m=[],
            stop=stop,
        )

    def _verdict(self) -> MarginVerdict | None:
        from scipy.optimize import least_squares
        from scipy.special import stdtrit

        from workcell.kinematics.registration import smr_registration_problem

        R, t, P = np.array(self.R), np.array(self.t), np.array(self.p)
        n = len(P)
        tool0 = self.tool_m
        residual, jac, x0 = smr_registration_problem(R, t, P, tool0, PRIOR_WEIGHT)

        def distances(x: np.ndarray) -> np.ndarray:
            return np.linalg.norm(residual(x, np.arange(n))[:-3].reshape(-1, 3), axis=1)

        # one bumped pose must not drag the others off: among a robust (Cauchy) fit of all poses
        # and, while there are few and one is off, the fits that leave one pose out, take the one
        # with the most poses within the margin; then least squares on those. Fewer than
        # MIN_POSES within the margin of every fit: two or more poses are off (stop) or one is
        # (wait for the next pose)
        scale = np.full(9, 0.1)
        everything = np.arange(n)
        starts = [
            least_squares(
                residual,
                x0,
                jac=jac,
                args=(everything,),
                x_scale=scale,
                loss="cauchy",
                f_scale=ROBUST_M,
            ).x
        ]
        if n <= LEAVE_ONE_OUT_UP_TO and np.any(distances(starts[0]) > self.margin_m):
            for j in range(n):
                keep = np.delete(everything, j)
                starts.append(
                    least_squares(residual, x0, jac=jac, args=(keep,), x_scale=scale, max_nfev=30).x
                )
        best = None
        for x in starts:
            dd = distances(x)
            inside = dd <= self.margin_m
            key = (int(inside.sum()), -float(np.sum(dd[inside] ** 2)))
            if best is None or key > best[0]:
                best = (key, x, np.flatnonzero(inside))
        _, x, rows = best
        if len(rows) >= MIN_POSES:
            fit = least_squares(residual, x, jac=jac, args=(rows,), x_scale=scale)
            x, dof = fit.x, 3 * len(rows) - 9
            r = fit.fun[:-3]
            s2 = float(r @ r) / dof
            A = fit.jac[:-3].T @ fit.jac[:-3]  # the data's information (the prior is no datum)
        elif n - len(rows) >= BAD_POSES_TO_STOP:  # no MIN_POSES poses agree on any fit
            dof, s2, A = 3 * n - 9, float("inf"), None
        else:  # one pose off among MIN_POSES: wait for the next pose to tell which
            return None
        dist = distances(x)
        d = x[6:] - tool0
        k = float(stdtrit(dof, 1 - 0.0027 / 2))
        # the offset's variance along each principal direction, from the data alone (the
        # registration marginalised out: a Schur complement); infinite where the poses do not
        # see it (the flange orientation hardly changed in that sense), so no verdict is drawn
        # from the prior there
        var, V = np.full(3, np.inf), np.eye(3)
        if A is not None and np.isfinite(s2):
            try:
                S = A[6:, 6:] - A[6:, :6] @ np.linalg.solve(A[:6, :6], A[:6, 6:])
                lam, V = np.linalg.eigh(0.5 * (S + S.T))
                var = np.full(3, np.inf)
                var[lam > 0] = s2 / lam[lam > 0]
            except np.linalg.LinAlgError:
                pass

        def sigma_along(v: np.ndarray, among: np.ndarray) -> float:
            """Standard error along the unit vector v, which lies in the directions `among`."""
            w = (V[:, among].T @ v) ** 2
            return float(np.sqrt(np.sum(np.where(w > 0, w * var[among], 0.0))))

        # the largest standard error in any direction: what an unseen offset could be
        sigma_max = float(np.sqrt(var.max()))
        sigma = sigma_along(d / max(np.linalg.norm(d), 1e-12), np.arange(3))
        # the part of d in the directions the poses resolve (k sigma < margin there): the true
        # offset is at least that long, so it alone may stop the campaign before the offset is
        # resolved in every direction
        among = np.flatnonzero(k * np.sqrt(var) < self.margin_m)
        d_res = V[:, among] @ (V[:, among].T @ d)
        norm_res = float(np.linalg.norm(d_res))
        sigma_res = sigma_along(d_res / norm_res, among) if norm_res > 0 else float("inf")
        beyond = dist > self.margin_m
        bad = [self.ids[i] for i in np.flatnonzero(beyond)]
        margin_mm = 1e3 * self.margin_m
        stop = None
        # resolved in every direction, d_r is d: the test is then on |d| itself
        if norm_res - k * sigma_res > self.margin_m:
            fitted = ", ".join(f"{1e3 * v:.1f}" for v in x[6:])
            declared = ", ".join(f"{1e3 * v:.1f}" for v in tool0)
            where = f"{_mm(norm_res, sigma_res)} mm"
            if len(among) < 3:
                where = f"at least {where} (in the directions the poses so far resolve)"
            stop = (
                f"the SMR sits {where} from the declared "
                f"smr_offset_m (fitted on {len(rows)} poses: [{fitted}] mm on the flange, declared "
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
            resolved_directions=len(among),
            offset_resolved_m=norm_res,
            offset_resolved_sigma_m=sigma_res,
            k=k,
            residual_max_m=float(dist[~beyond].max()) if (~beyond).any() else float("nan"),
            bad_poses=bad,
            bad_dist_m=[float(x) for x in dist[beyond]],
            stop=stop,
        )

    def summary(self) -> str:
        """One line for the end of a campaign: how well the margin was verified (on all poses:
        a long campaign's last poses may not have been checked yet)."""
        n = len(self.p)
        if n >= MIN_POSES and (self.last is None or self.last.n != n):
            self.last = self._verdict() or self.last
        v = self.last
        margin_mm = 1e3 * self.margin_m
        if v is None and n < MIN_POSES:
            return (
                f"kinematic margin {margin_mm:g} mm not checked: fewer than {MIN_POSES} poses "
                "were measured"
            )
        if v is None:
            return (
                f"kinematic margin {margin_mm:g} mm not checked: one of the {n} poses is more "
                "than the margin from the fit of the others, too few to tell which is wrong"
            )
        if v.stop:
            return f"at the end of the campaign, {v.stop}"
        chain = f"measured poses within {1e3 * v.residual_max_m:.1f} mm of the nominal chain"
        if v.bad_poses:  # one (two would have stopped the campaign)
            chain += (
                f" except pose {v.bad_poses[0]}, {1e3 * v.bad_dist_m[0]:.1f} mm off (a bumped SMR "
                "or a bad reading? check that pose)"
            )
        if not v.resolves(self.margin_m):
            if v.resolved_directions == 0:
                what = "not resolved in any direction"
                unseen = "an error in smr_offset_m would go unseen"
            else:
                what = (
                    f"resolved in {v.resolved_directions} of 3 directions only "
                    f"({_mm(v.offset_resolved_m, v.offset_resolved_sigma_m)} mm from the declared "
                    "one there)"
                )
                unseen = "an error in smr_offset_m in the other directions would go unseen"
            return (
                f"kinematic margin {margin_mm:g} mm only partly checked on {v.n} poses: {chain}, "
                f"but the SMR offset is {what}: the flange orientation changed too little; "
                f"{unseen}"
            )
        return (
            f"kinematic margin {margin_mm:g} mm checked on {v.n} poses: SMR offset "
            f"{_mm(v.offset_norm_m, v.offset_sigma_m)} mm (1-sigma) from the declared one, {chain}"
        )
