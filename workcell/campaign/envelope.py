"""The safety envelope: joint limits, a workspace box, a floor, and speed/acceleration caps.

Every motion target is checked before any motion; a target outside is refused with the reason.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from workcell import strict_json
from workcell.errors import UserError
from workcell.kinematics.chain import base_T_frames, pack
from workcell.kinematics.robots import RobotSpec

if TYPE_CHECKING:
    import os

# Ceilings of an envelope's caps, whatever the arm: the UR controller's own joint limits (ur_rtde
# refuses a moveJ above 3.14 rad/s or 40 rad/s^2); the simulated 7-joint arm is slower.
SPEED_CEILING_RAD_S = float(np.pi)
ACCEL_CEILING_RAD_S2 = 40.0
# the slowest cap accepted (rad/s, rad/s^2): a move of a radian at it takes 17 min; a cap near
# zero (1e-300) made the move's duration overflow the recording's time stamps
CAP_FLOOR = 1e-3
# A reading of the arm this close to where it was last sent (each joint, rad) is that posture,
# whose paths were checked: encoder noise (~2 urad) and the UR driver's arrival tolerance (1e-4
# rad). Farther, the arm was moved since. 1e-3 until 2026-11-29: up to ~4 mm of an SMR's path
# unchecked, which only the kinematic margin covered (a safety audit).
AT_SENT_TOL_RAD = 2e-4

# How far the real arm may be from where the nominal kinematics put it, which is what every check
# here computes with. Measured on the real UR10 of ../shared/data/ur10-leica (series B, nominal
# DH after the best-fit base registration): SMR error RMS 2.9 mm, max 5.0 mm. Twice the max.
DEFAULT_KINEMATIC_MARGIN_M = 0.01


# What an envelope (a file, a recorded session's `campaign.envelope`) may hold: the keys
# `Envelope.to_dict` writes, and has written in every version (older ones without
# `kinematic_margin_m`; never metadata). Any other key is refused: a misspelt one ("floor_z") was
# ignored and its limit silently replaced by the default.
ENVELOPE_KEYS = (
    "joint_limits_rad",
    "box_min_m",
    "box_max_m",
    "floor_z_m",
    "max_speed_rad_s",
    "max_accel_rad_s2",
    "kinematic_margin_m",
)
# What a recorded session made by another tool may leave out (every file and session this tool
# writes has them; an envelope file must give them): their defaults.
_SESSION_DEFAULTS = {"floor_z_m": 0.02, "max_speed_rad_s": 1.0, "max_accel_rad_s2": 2.0}


class EnvelopeViolation(ValueError):
    """A target outside the configured envelope; nothing moved."""


def _unknown_keys_message(unknown: list) -> str:
    """'unknown key 'floor_z' (did you mean 'floor_z_m'?)...': the keys, the nearest known ones,
    and what an envelope may hold."""
    parts = []
    for k in unknown:
        near = difflib.get_close_matches(str(k), ENVELOPE_KEYS, n=1, cutoff=0.5)
        parts.append(f"{k!r}" + (f" (did you mean {near[0]!r}?)" if near else ""))
    return (
        f"envelope: unknown key{'s' if len(parts) > 1 else ''} {', '.join(parts)}: a limit under "
        f"another name would be ignored; an envelope holds only {', '.join(ENVELOPE_KEYS)} "
        "(`workcell envelope --out FILE` writes one to edit)"
    )


@dataclass
class Envelope:
    joint_limits_rad: np.ndarray  # (n, 2)
    box_min_m: np.ndarray = field(default_factory=lambda: np.array([-1.0, -1.0, 0.05]))
    box_max_m: np.ndarray = field(default_factory=lambda: np.array([1.0, 1.0, 1.2]))
    floor_z_m: float = 0.02  # DH frame origins 2..n and the SMR stay above this (base frame)
    max_speed_rad_s: float = 1.0
    max_accel_rad_s2: float = 2.0
    # the box and the floor are kept this far from every checked point (the nominal kinematics'
    # error; 0 trusts the model exactly, e.g. in a simulation with a known arm)
    kinematic_margin_m: float = DEFAULT_KINEMATIC_MARGIN_M
    # the keys `from_dict` filled in with defaults (absent from the file or session), for a
    # reader to say so; not part of the envelope (not in `to_dict`, not compared)
    defaulted: tuple[str, ...] = field(default=(), compare=False, repr=False)

    def __post_init__(self) -> None:
        """An envelope with NaN, an empty range or a non-positive cap would let motions through
        (every comparison with NaN is false): refuse it with the offending field."""
        try:
            lim = np.asarray(self.joint_limits_rad, dtype=float)
            lo_box = np.asarray(self.box_min_m, dtype=float)
            hi_box = np.asarray(self.box_max_m, dtype=float)
            caps = [
                float(self.floor_z_m),
                float(self.max_speed_rad_s),
                float(self.max_accel_rad_s2),
                float(self.kinematic_margin_m),
            ]
        except (TypeError, ValueError, OverflowError):
            raise ValueError("envelope: every limit must be a (finite) number") from None
        if lim.ndim != 2 or lim.shape[1] != 2 or lim.shape[0] < 1:
            raise ValueError(
                f"envelope joint_limits_rad: expected (n, 2) [lo, hi] pairs, got {lim.shape}"
            )
        if not np.all(np.isfinite(lim)) or np.any(lim[:, 0] >= lim[:, 1]):
            raise ValueError(
                f"envelope joint_limits_rad: need finite lo < hi per joint, got {lim.tolist()}"
            )
        if lo_box.shape != (3,) or hi_box.shape != (3,):
            raise ValueError(
                f"envelope box_min_m/box_max_m: expected 3 values each, got {lo_box.shape} "
                f"and {hi_box.shape}"
            )
        if not (np.all(np.isfinite(lo_box)) and np.all(np.isfinite(hi_box))) or np.any(
            lo_box >= hi_box
        ):
            raise ValueError(
                f"envelope box: need finite min < max per axis, got {lo_box.tolist()}.."
                f"{hi_box.tolist()}"
            )
        if not all(np.isfinite(caps)) or caps[1] <= 0 or caps[2] <= 0:
            raise ValueError(
                "envelope floor_z_m, max_speed_rad_s, max_accel_rad_s2 and kinematic_margin_m must "
                f"be finite and the caps > 0, got {caps}"
            )
        if caps[3] < 0 or caps[3] > 0.1:
            raise ValueError(
                f"envelope kinematic_margin_m {caps[3]:g} must be within [0, 0.1] m (metres; the "
                "nominal kinematics' error, a few mm on an uncalibrated arm)"
            )
        if np.any(hi_box - lo_box <= 2 * caps[3]):
            raise ValueError(
                f"envelope box {lo_box.tolist()}..{hi_box.tolist()} m leaves no room inside the "
                f"kinematic margin {caps[3]:g} m on each face"
            )
        for name, v, ceiling, what in (
            ("max_speed_rad_s", caps[1], SPEED_CEILING_RAD_S, "speed limit (rad/s)"),
            ("max_accel_rad_s2", caps[2], ACCEL_CEILING_RAD_S2, "acceleration limit (rad/s^2)"),
        ):
            if v > ceiling:
                raise ValueError(
                    f"envelope {name} {v:g} is above every supported arm's joint {what}, "
                    f"{ceiling:.4g}; give radians"
                )
            if v < CAP_FLOOR:
                raise ValueError(
                    f"envelope {name} {v:g} is below {CAP_FLOOR:g}, at which a move of one "
                    f"radian takes over a quarter of an hour; give the {what}"
                )
        self.joint_limits_rad, self.box_min_m, self.box_max_m = lim, lo_box, hi_box
        self.floor_z_m, self.max_speed_rad_s, self.max_accel_rad_s2 = caps[:3]
        self.kinematic_margin_m = caps[3]

    def with_arm_joint_ranges(self, spec: RobotSpec) -> Envelope:
        """This envelope with the arm's own joint ranges instead of its own: the box and the
        floor (what a motion may hit) stay. For the way back into the joint ranges."""
        return replace(self, joint_limits_rad=np.asarray(spec.joint_limits_rad, float).copy())

    def to_dict(self) -> dict:
        return {
            "joint_limits_rad": np.asarray(self.joint_limits_rad).tolist(),
            "box_min_m": np.asarray(self.box_min_m).tolist(),
            "box_max_m": np.asarray(self.box_max_m).tolist(),
            "floor_z_m": self.floor_z_m,
            "max_speed_rad_s": self.max_speed_rad_s,
            "max_accel_rad_s2": self.max_accel_rad_s2,
            "kinematic_margin_m": self.kinematic_margin_m,
        }

    @classmethod
    def from_dict(
        cls,
        d: dict,
        margin_if_absent_m: float = DEFAULT_KINEMATIC_MARGIN_M,
        *,
        limits_required: bool = False,
    ) -> Envelope:
        """The `to_dict` layout; any other key is refused (ValueError naming it and the nearest
        known one). A dict without `kinematic_margin_m` (written before it existed) gets
        `margin_if_absent_m`: the default for a file, 0 for a recorded session (what that
        campaign ran with, so that its resumption plans the same poses). Without `floor_z_m`,
        `max_speed_rad_s` or `max_accel_rad_s2` (never left out by this tool): refused when
        `limits_required` (an envelope file), else their defaults (a session of another tool).
        `defaulted` names every key filled in."""
        if not isinstance(d, dict):
            raise ValueError("envelope: expected a JSON object")
        unknown = [k for k in d if k not in ENVELOPE_KEYS]
        if unknown:
            raise ValueError(_unknown_keys_message(unknown))
        for key, v in d.items():
            flat = np.ravel(np.asarray(v, dtype=object)) if isinstance(v, list) else [v]
            bad = [x for x in flat if isinstance(x, (bool, str)) or x is None]
            if bad:
                raise ValueError(f"envelope {key}: every value must be a number, got {bad[0]!r}")
        missing = [k for k in ENVELOPE_KEYS[:3] if k not in d]
        if limits_required:
            missing += [k for k in _SESSION_DEFAULTS if k not in d]
        if missing:
            raise ValueError(
                f"envelope: missing {', '.join(map(repr, missing))}: give every limit "
                f"({', '.join(ENVELOPE_KEYS[:6])}; kinematic_margin_m may be left out, default "
                f"{DEFAULT_KINEMATIC_MARGIN_M:g} m); `workcell envelope --out FILE` writes a "
                "complete file to edit"
            )
        filled = {k: v for k, v in _SESSION_DEFAULTS.items() if k not in d}
        if "kinematic_margin_m" not in d:
            filled["kinematic_margin_m"] = margin_if_absent_m
        return cls(**{**filled, **d}, defaulted=tuple(filled))

    def violations(self, spec: RobotSpec, q: np.ndarray, tool_m: np.ndarray) -> list[str | None]:
        """For each row of q (N, n): None if inside, else the reason."""
        return self._evaluate(spec, q, tool_m)[0]

    def clearance(self, spec: RobotSpec, q: np.ndarray, tool_m: np.ndarray) -> np.ndarray:
        """For each row of q (N, n): how far (m) the SMR is from the workspace box's nearest face
        and the link frames 2..n and the SMR from the floor, the smaller, less the kinematic
        margin; negative outside.
        (Joint limits are left out: they are convex in joint space, a straight joint path
        between two postures inside them stays inside.)"""
        return self._evaluate(spec, q, tool_m)[1]

    def _evaluate(
        self, spec: RobotSpec, q: np.ndarray, tool_m: np.ndarray
    ) -> tuple[list[str | None], np.ndarray]:
        q = np.atleast_2d(np.asarray(q, float))
        if q.shape[1] != len(self.joint_limits_rad):
            raise ValueError(
                f"envelope has {len(self.joint_limits_rad)} joints, the targets {q.shape[1]}"
            )
        out: list[str | None] = [None] * len(q)
        finite = np.all(np.isfinite(q), axis=1)
        lim = self.joint_limits_rad
        T = np.asarray(base_T_frames(pack(spec.dh), np.where(finite[:, None], q, 0.0)))
        smr = np.einsum("nab,b->na", T[:, -1, :3, :3], np.asarray(tool_m, float)) + T[:, -1, :3, 3]
        # the floor holds for the link frames 2..n and for the SMR (a box reaching below the
        # floor does not let the tool under the table)
        zlinks = T[:, 2:, 2, 3].min(axis=1)
        low = np.minimum(zlinks, smr[:, 2])
        margin = self.kinematic_margin_m
        clear = (
            np.minimum(
                np.minimum(smr - self.box_min_m, self.box_max_m - smr).min(axis=1),
                (low - self.floor_z_m),
            )
            - margin
        )
        within = f" less the {1e3 * margin:g} mm kinematic margin" if margin > 0 else ""
        clear[~finite] = -np.inf
        # the message of each refused row; rows that pass (most of a sampled path) cost nothing
        q0 = np.where(finite[:, None], q, 0.0)
        joint_bad = (q0 < lim[:, 0]) | (q0 > lim[:, 1])
        box_bad = np.any(smr < self.box_min_m + margin, axis=1) | np.any(
            smr > self.box_max_m - margin, axis=1
        )
        floor_bad = low < self.floor_z_m + margin
        refused = ~finite | joint_bad.any(axis=1) | box_bad | floor_bad
        for i in np.flatnonzero(refused):
            if not finite[i]:
                out[i] = "target has non-finite joint values"
            elif joint_bad[i].any():
                j = int(np.flatnonzero(joint_bad[i])[0])
                out[i] = (
                    f"joint {j + 1} target {q[i, j]:.4f} rad outside the envelope "
                    f"[{lim[j, 0]:.4f}, {lim[j, 1]:.4f}] rad"
                )
            elif box_bad[i]:
                out[i] = (
                    f"SMR at {np.round(smr[i], 3).tolist()} m (base) outside the workspace box "
                    f"{np.round(self.box_min_m, 3).tolist()}..{np.round(self.box_max_m, 3).tolist()}"
                    + within
                )
            else:
                what = "the SMR" if smr[i, 2] < zlinks[i] else "a link frame"
                out[i] = (
                    f"{what} would go down to z = {low[i]:.3f} m, below the floor "
                    f"{self.floor_z_m} m{within}"
                )
        return out, clear

    def path_violation(
        self,
        spec: RobotSpec,
        q_from: np.ndarray,
        q_to: np.ndarray,
        tool_m: np.ndarray,
        max_step_rad: float = 0.02,
    ) -> str | None:
        """Where the joint-space straight line q_from -> q_to (the path of a UR moveJ: all
        joints start and stop together) leaves the envelope, or None. Joint limits are convex,
        but the workspace box and the floor are not in joint space: two valid end points can
        have a path that dips the SMR or a link below the table.

        The whole path is checked, not only samples of it. Samples at most `max_step_rad` apart
        on every joint are checked first; then, between neighbours s_k, s_k+1, no checked point
        (SMR, link frames) moves more than L (s_k+1 - s_k), L = sum_i |dq_i| R_i with R_i the
        chain's length beyond joint i (`_motion_bound`), and the box and floor distances change
        no faster. So the stretch is inside when the two clearances add up to at least that;
        where they do not, it is split in four and checked again, down to stretches along which
        nothing moves more than PATH_TOL_M (0.1 mm; then nothing can be outside by more than
        half of that)."""
        q0, q1 = np.asarray(q_from, float), np.asarray(q_to, float)
        if not (np.all(np.isfinite(q0)) and np.all(np.isfinite(q1))):
            return "path with non-finite joint values"
        dq = q1 - q0
        n = max(1, int(np.ceil(np.max(np.abs(dq)) / max_step_rad)))
        # a power of two >= 32 samples: few distinct shapes, so JAX compiles few times
        m = max(32, 1 << int(np.ceil(np.log2(n + 1))))
        s = np.linspace(0.0, 1.0, m)
        L = _motion_bound(spec, tool_m, dq)
        new = s
        c = np.empty(0)
        while True:
            msgs, c_new = self._evaluate(spec, _pad_pow2(q0 + new[:, None] * dq), tool_m)
            for si, v in zip(new, msgs, strict=False):
                if v is not None:
                    return f"the joint path leaves the envelope {100 * si:.0f} % of the way: {v}"
            if new is not s:
                order = np.argsort(np.r_[s, new], kind="stable")
                s, c = np.r_[s, new][order], np.r_[c, c_new[: len(new)]][order]
            else:
                c = c_new[: len(s)]
            h = np.diff(s)
            open_ = (c[:-1] + c[1:] < L * h) & (L * h > PATH_TOL_M)
            if not open_.any():
                return None
            k = np.where(open_)[0]
            new = (s[k, None] + h[k, None] * np.array([0.25, 0.5, 0.75])).ravel()

    def check(self, spec: RobotSpec, q: np.ndarray, tool_m: np.ndarray) -> None:
        v = self.violations(spec, np.atleast_2d(q), tool_m)[0]
        if v is not None:
            raise EnvelopeViolation(f"refused before any motion: {v}")

    def cap(self, speed: float, accel: float) -> tuple[float, float]:
        return min(speed, self.max_speed_rad_s), min(accel, self.max_accel_rad_s2)


PATH_TOL_M = 1e-4  # path_violation: stretches along which nothing moves more than this pass


def _motion_bound(spec: RobotSpec, tool_m: np.ndarray, dq: np.ndarray) -> float:
    """How far (m) any link frame or the SMR can travel along the joint path q + s dq, s in
    [0, 1]: joint i turns by |dq_i| about an axis through frame i-1's origin, and every point it
    carries is at most R_i = sum_(j >= i) (|a_j| + |d_j|) + |tool| from there."""
    seg = np.abs(np.asarray(spec.dh.a, float)) + np.abs(np.asarray(spec.dh.d, float))
    reach = np.cumsum(seg[::-1])[::-1] + float(np.linalg.norm(tool_m))
    return float(np.abs(np.asarray(dq, float)) @ reach)


def _pad_pow2(q: np.ndarray) -> np.ndarray:
    """q padded (repeating its last row) to a power of two >= 32 rows: few shapes to compile."""
    m = max(32, 1 << int(np.ceil(np.log2(len(q)))))
    return q if len(q) == m else np.r_[q, np.repeat(q[-1:], m - len(q), axis=0)]


def default_envelope(spec: RobotSpec) -> Envelope:
    """A conservative envelope for measurement poses: arm above the table, no wrapped joints."""
    reach = float(np.abs(spec.dh.a).sum() + np.abs(spec.dh.d[3:]).sum())
    d = np.deg2rad
    lim = np.array(
        [
            [-d(170), d(170)],
            [-d(175), -d(5)],
            [-d(160), d(160)],
            [-d(260), d(80)],
            [-d(170), d(170)],
            [-d(170), d(170)],
        ]
    )
    lim[:, 0] = np.maximum(lim[:, 0], spec.joint_limits_rad[:, 0])
    lim[:, 1] = np.minimum(lim[:, 1], spec.joint_limits_rad[:, 1])
    return Envelope(
        joint_limits_rad=lim,
        box_min_m=np.array([-reach, -reach, 0.05]),
        box_max_m=np.array([reach, reach, reach + spec.dh.d[0]]),
        floor_z_m=0.02,
        max_speed_rad_s=1.0,
        max_accel_rad_s2=2.0,
        kinematic_margin_m=DEFAULT_KINEMATIC_MARGIN_M,
    )


def check_envelope_for(env: Envelope, spec: RobotSpec, source: str = "envelope") -> Envelope:
    """Refuse an envelope that does not belong to this arm: a different joint count, or joint
    limits beyond the arm's own range (a file typed in degrees lands here). Returns `env`."""
    lim = np.asarray(env.joint_limits_rad)
    if len(lim) != spec.n_joints:
        raise UserError(f"{source}: {len(lim)} joint limits for a {spec.n_joints}-joint arm")
    arm = np.asarray(spec.joint_limits_rad)
    tol = 1e-9
    bad = np.where((lim[:, 0] < arm[:, 0] - tol) | (lim[:, 1] > arm[:, 1] + tol))[0]
    if len(bad):
        j = int(bad[0])
        hint = "; looks like degrees (give radians)" if np.max(np.abs(lim[j])) > 2.5 * np.pi else ""
        raise UserError(
            f"{source}: joint {j + 1} limits [{lim[j, 0]:.4g}, {lim[j, 1]:.4g}] rad go beyond the "
            f"arm's range [{arm[j, 0]:.4g}, {arm[j, 1]:.4g}] rad{hint}"
        )
    from workcell.recording.checks import millimetre_hint, reach_m

    r = reach_m(spec.dh, np.zeros(3)) + 0.5  # the arm plus a generous tool
    far = float(np.max(np.abs(np.r_[env.box_min_m, env.box_max_m])))
    if far > 3 * r:
        raise UserError(
            f"{source}: the workspace box reaches {far:.4g} m from the base, far beyond the arm "
            f"({r:.3g} m with a tool); "
            + millimetre_hint(far, r, "give the box in metres (base frame)")
        )
    links = reach_m(spec.dh, np.zeros(3))  # no link frame gets further from the base
    if env.floor_z_m < -links:
        raise UserError(
            f"{source}: floor_z_m {env.floor_z_m:g} m is further below the base than any link "
            f"frame of the {spec.model} reaches ({links:.3g} m, the sum of its link lengths): "
            "the floor check would never act; "
            + (
                f"it looks like millimetres, give metres ({env.floor_z_m / 1e3:g} m)"
                if abs(env.floor_z_m) > 3 * r
                else "give the table's height in metres, base frame (negative below the base)"
            )
        )
    if not env.floor_z_m < env.box_max_m[2]:
        raise UserError(
            f"{source}: floor_z_m {env.floor_z_m:g} m is above the box's top "
            f"{env.box_max_m[2]:g} m: no posture could pass"
            + ("; it looks like millimetres, give metres" if env.floor_z_m > 3 * r else "")
        )
    vmax = float(np.min(spec.max_joint_speed_rad_s))
    if env.max_speed_rad_s > vmax:
        raise UserError(
            f"{source}: max_speed_rad_s {env.max_speed_rad_s:g} is above the arm's joint speed "
            f"limit {vmax:.4g} rad/s"
        )
    return env


def load_envelope(path: str | os.PathLike, spec: RobotSpec) -> Envelope:
    """An envelope JSON file (the `Envelope.to_dict` layout, SI) checked for `spec`; every
    problem is one `UserError` naming the file."""
    p = Path(path)
    if not p.is_file():
        raise UserError(f"envelope file {p} does not exist (or is not a file)")
    try:
        text = p.read_text(encoding="utf-8-sig")  # a BOM from a Windows editor is fine
    except UnicodeDecodeError:
        raise UserError(
            f"envelope file {p}: not a text file; an envelope is JSON "
            "(`workcell envelope --out FILE` writes one to edit)"
        ) from None
    try:
        d = strict_json.loads(text)
    except strict_json.DuplicateKey as e:
        raise UserError(
            f"envelope file {p}: key {e.args[0]!r} is given twice (JSON readers keep only the "
            "last): give each once"
        ) from None
    except ValueError as e:
        raise UserError(f"envelope file {p}: {e}") from None
    try:
        env = Envelope.from_dict(d, limits_required=True)
    except ValueError as e:
        raise UserError(f"envelope file {p}: {e}") from None
    return check_envelope_for(env, spec, f"envelope file {p}")


def envelope_of_session(camp: dict, spec: RobotSpec, source: str) -> Envelope | None:
    """The envelope a recorded campaign ran in (its session's `campaign.envelope`), checked for
    `spec`; None when the recording has none (made by another tool)."""
    d = (camp or {}).get("envelope")
    if d is None:
        return None
    try:
        env = Envelope.from_dict(d, margin_if_absent_m=0.0)
    except ValueError as e:
        raise UserError(f"{source}: recorded envelope unusable ({e})") from None
    return check_envelope_for(env, spec, f"{source}: recorded envelope")


def upright(q: np.ndarray) -> np.ndarray:
    """The via posture for a UR arm: q with shoulder, elbow and wrist 1 set to (-pi/2, 0, -pi/2),
    upper arm and forearm pointing straight up, base and wrists 2-3 where they are."""
    u = np.array(q, float)
    u[1:4] = (-np.pi / 2, 0.0, -np.pi / 2)
    return u


def route(
    env: Envelope, spec: RobotSpec, tool_m: np.ndarray, q_from: np.ndarray, q_to: np.ndarray
) -> tuple[list[np.ndarray], str | None]:
    """Waypoints from q_from to q_to whose joint paths stay inside `env`: the direct move, else
    via the upright posture (`upright(q_from)`). Returns (waypoints, None), or ([], why) when
    neither stays inside (then nothing may move)."""
    return _route(env, env, spec, tool_m, q_from, q_to)


def route_back_in(
    env: Envelope, spec: RobotSpec, tool_m: np.ndarray, q_from: np.ndarray, q_to: np.ndarray
) -> tuple[list[np.ndarray], str | None]:
    """`route` for an arm beyond `env`'s joint ranges only (its SMR and links inside the box,
    above the floor) to q_to inside them: the direct move, checked against the box and the floor
    with the arm's own joint ranges (a straight joint path towards the ranges only comes nearer
    to them); else via the upright posture brought inside the joint ranges (the joints it keeps
    from q_from clipped into them), only when that posture, and the move on from it, are inside
    `env` itself."""
    return _route(env.with_arm_joint_ranges(spec), env, spec, tool_m, q_from, q_to)


def _route(first: Envelope, env: Envelope, spec, tool_m, q_from, q_to):
    """The direct move and the leg to the via posture checked against `first`; the via posture
    (upright, inside `env`'s joint ranges) and the leg on from it against `env`."""
    q_to = np.asarray(q_to, float)
    why = first.path_violation(spec, q_from, q_to, tool_m)
    if why is None:
        return [q_to], None
    if spec.n_joints == 6:
        lim = np.asarray(env.joint_limits_rad, float)
        u = upright(q_from)
        if first is not env:  # coming back in: the via posture inside the ranges
            u = np.clip(u, lim[:, 0], lim[:, 1])
        if (
            env.violations(spec, u[None], tool_m)[0] is None
            and first.path_violation(spec, q_from, u, tool_m) is None
            and env.path_violation(spec, u, q_to, tool_m) is None
        ):
            return [u, q_to], None
    return [], why


@dataclass
class Guard:
    """The envelope with its arm and tool, for code that moves the arm outside the campaign
    executor (closed-loop validation): may the arm stand at q, go straight from a to b, or get
    from a to b at all (direct or via upright)?"""

    env: Envelope
    spec: RobotSpec
    tool_m: np.ndarray

    def pose(self, q: np.ndarray) -> str | None:
        return self.env.violations(self.spec, np.asarray(q, float)[None], self.tool_m)[0]

    def direct(self, q_from: np.ndarray, q_to: np.ndarray) -> str | None:
        return self.env.path_violation(self.spec, q_from, q_to, self.tool_m)

    def route(self, q_from: np.ndarray, q_to: np.ndarray) -> tuple[list[np.ndarray], str | None]:
        return route(self.env, self.spec, self.tool_m, q_from, q_to)

    def with_arm_joint_ranges(self) -> Guard:
        """The same guard with the arm's own joint ranges (`Envelope.with_arm_joint_ranges`)."""
        return Guard(self.env.with_arm_joint_ranges(self.spec), self.spec, self.tool_m)

    def route_back_in(
        self, q_from: np.ndarray, q_to: np.ndarray
    ) -> tuple[list[np.ndarray], str | None]:
        """`route_back_in`: from beyond the joint ranges only, back inside them."""
        return route_back_in(self.env, self.spec, self.tool_m, q_from, q_to)
