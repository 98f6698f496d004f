"""Campaign plans: generators over a closed set of steps, run by `workcell.campaign.executor`.

A plan yields `PoseTarget`s; the executor turns each into Move (via an approach pre-pose) ->
Settle -> Measure -> Record, and sends the recorded sample (or None if the pose was skipped) back
into the generator, so adaptive plans (bo, dopt, vopt) can choose the next pose from what was
measured.

`grid` and `random` choose joint configurations inside the envelope. The approach direction of
every joint is varied on purpose: each pose is approached from a pre-pose offset by
`approach_rad` with a random sign per joint, so backlash is observable.
"""

from __future__ import annotations

from collections.abc import Generator, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from workcell.campaign.envelope import Envelope, Guard, upright
from workcell.errors import stop_if_interrupted
from workcell.kinematics.robots import RobotSpec


@dataclass(frozen=True)
class PoseTarget:
    pose_id: int
    q_rad: np.ndarray  # (n,)
    approach_sign: np.ndarray  # (n,) desired direction of the final motion of each joint


Plan = Generator[PoseTarget, "dict | None", None]

STATIC_KINDS = ("grid", "random")  # planned ahead, resumed by pose id
ADAPTIVE_KINDS = ("bo", "dopt", "vopt")  # each pose chosen from the measurements so far
PLAN_KINDS = STATIC_KINDS + ADAPTIVE_KINDS
PLAN_CHOICES = ", ".join(PLAN_KINDS[:-1]) + " or " + PLAN_KINDS[-1]


def random_configurations(
    spec: RobotSpec,
    env: Envelope,
    n: int,
    rng: np.random.Generator,
    tool_m: np.ndarray,
    max_tries: int = 200_000,
) -> np.ndarray:
    """n joint configurations uniformly inside the envelope's joint ranges and workspace."""
    lim = env.joint_limits_rad
    out = []
    tries = 0
    while len(out) < n:
        m = max(4 * (n - len(out)), 64)
        q = rng.uniform(lim[:, 0], lim[:, 1], size=(m, len(lim)))
        ok = [v is None for v in env.violations(spec, q, tool_m)]
        out.extend(q[np.array(ok)][: n - len(out)])
        tries += m
        if tries > max_tries and len(out) < n:
            raise ValueError(
                f"could only find {len(out)} of {n} poses inside the envelope; widen it"
            )
    return np.array(out)


def grid_configurations(
    spec: RobotSpec, env: Envelope, n: int, tool_m: np.ndarray, seed: int = 0
) -> np.ndarray:
    """About n configurations on a regular grid over joints 1-3 (arm) with wrist angles varied
    deterministically; poses outside the workspace are dropped, extra ones thinned evenly."""
    lim = env.joint_limits_rad
    k = 2
    while True:
        g = np.stack(
            np.meshgrid(
                *[np.linspace(lim[j, 0], lim[j, 1], k + 2)[1:-1] for j in range(3)], indexing="ij"
            ),
            -1,
        ).reshape(-1, 3)
        rng = np.random.default_rng(seed)
        wrist = rng.uniform(lim[3:, 0], lim[3:, 1], size=(len(g), 3))
        q = np.hstack([g, wrist])
        ok = np.array([v is None for v in env.violations(spec, q, tool_m)])
        if ok.sum() >= n or k > 30:
            q = q[ok]
            break
        k += 1
    if len(q) > n:
        q = q[np.round(np.linspace(0, len(q) - 1, n)).astype(int)]
    return q


def approach_signs(
    spec: RobotSpec,
    env: Envelope,
    q: np.ndarray,
    tool_m: np.ndarray,
    approach_rad: float,
    seed: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Random approach signs whose pre-pose (q - sign * approach_rad) is inside the envelope.

    Returns (kept configurations, their signs); a pose whose pre-pose cannot be placed inside
    the envelope with either random or flipped signs is dropped."""
    rng = np.random.default_rng(seed + 1)
    signs = rng.choice([-1.0, 1.0], size=q.shape)
    ok = np.ones(len(q), bool)
    for attempt in range(3):
        bad = [i for i, v in enumerate(env.violations(spec, q - signs * approach_rad, tool_m)) if v]
        if not bad:
            break
        if attempt < 2:
            signs[bad] = (
                -signs[bad] if attempt == 0 else rng.choice([-1.0, 1.0], (len(bad), q.shape[1]))
            )
        else:
            ok[bad] = False
    return q[ok], signs[ok]


@dataclass
class ArmPosture:
    """Where the arm is, as the campaign executor last read it (`q`, None: not known yet). The
    executor sets it before it asks the plan for its next pose; an adaptive plan given one
    (`Reach.arm`) chooses among the poses the arm may move to from there, so the arm's start
    posture, a pose skipped after the arm moved to it, or a jog during a pause are all known."""

    q: np.ndarray | None = None


class PlanStuck(Exception):
    """An adaptive plan has no pose left that the arm may move to from where it is (every path
    leaves the envelope, also via the upright posture): the campaign stops (`str(e)` says which
    limit the paths cross; `suggest`: a posture of the plan well inside the envelope, or None)."""

    def __init__(self, message: str, suggest: np.ndarray | None = None) -> None:
        super().__init__(message)
        self.suggest = suggest


class Reach:
    """Which poses the arm may go to next, checked the way the executor moves (its
    `_pose_problems` and `_move_along`): the approach path pre-pose -> pose inside the envelope,
    and a route from where the arm is to the pre-pose (direct, else via the upright posture; from
    beyond the envelope's joint ranges only, the executor's way back in). Where the arm is: `arm`
    (an `ArmPosture` the executor keeps up to date) when it knows, else `last` (the last pose the
    arm was sent to; None: not known, not checked). Checked lazily, the approach checks and the
    leg to the upright posture cached, so a caller that takes the first reachable of an ordered
    list pays about one path check a step."""

    def __init__(
        self,
        spec: RobotSpec,
        env: Envelope,
        tool_m: np.ndarray,
        q: np.ndarray,
        signs: np.ndarray,
        approach_rad: float,
        arm: ArmPosture | None = None,
    ) -> None:
        self.guard = Guard(env, spec, np.asarray(tool_m, float))
        self.q = q
        self.pre = q - np.sign(signs) * approach_rad
        self._approach_ok: dict[int, bool] = {}
        self.last: np.ndarray | None = None  # the last pose the arm was sent to
        self.arm = arm
        self._loose: Envelope | None = None
        self._from_key: bytes | None = None
        self._from: tuple = (None, None)
        self._leg: bool | None = None  # the leg from `_from_key` to its via posture passes

    def where(self) -> np.ndarray | None:
        """Where the arm is: the executor's reading when given, else the last pose sent to."""
        if self.arm is not None and self.arm.q is not None:
            return np.asarray(self.arm.q, float)
        return self.last

    def approach_ok(self, i: int) -> bool:
        if i not in self._approach_ok:
            self._approach_ok[i] = self.guard.direct(self.pre[i], self.q[i]) is None
        return self._approach_ok[i]

    def _legs_from(self, q_from: np.ndarray) -> tuple[Envelope | None, np.ndarray | None]:
        """(the envelope a path from q_from is checked against, None when the arm is beyond the
        box or the floor; the via posture), cached for q_from: the same as `envelope.route` /
        `route_back_in`, the executor's routes."""
        key = q_from.tobytes()
        if key == self._from_key:
            return self._from
        env, spec, tool = self.guard.env, self.guard.spec, self.guard.tool_m
        first: Envelope | None = env
        if env.violations(spec, q_from[None], tool)[0] is not None:
            if self._loose is None:
                self._loose = env.with_arm_joint_ranges(spec)
            # beyond the joint ranges only: the executor's way back in; beyond the box or the
            # floor: it moves nothing and stops the campaign itself (not this plan's call)
            ok = self._loose.violations(spec, q_from[None], tool)[0] is None
            first = self._loose if ok else None
        u = None
        if first is not None and spec.n_joints == 6:
            u = upright(q_from)
            if first is not env:
                lim = np.asarray(env.joint_limits_rad, float)
                u = np.clip(u, lim[:, 0], lim[:, 1])
        self._from_key, self._from, self._leg = key, (first, u), None
        return self._from

    def route_ok(self, q_from: np.ndarray, q_to: np.ndarray) -> bool:
        """May the arm get from q_from to q_to (direct, else via upright) as the executor moves?"""
        q_from = np.asarray(q_from, float)
        first, u = self._legs_from(q_from)
        if first is None:
            return True
        env, spec, tool = self.guard.env, self.guard.spec, self.guard.tool_m
        if first.path_violation(spec, q_from, q_to, tool) is None:
            return True
        if u is None:
            return False
        if self._leg is None:  # the leg to the via posture, once for q_from
            self._leg = (
                env.violations(spec, u[None], tool)[0] is None
                and first.path_violation(spec, q_from, u, tool) is None
            )
        return self._leg and env.path_violation(spec, u, q_to, tool) is None

    def ok(self, i: int) -> bool:
        if not self.approach_ok(i):
            return False
        q_from = self.where()
        if q_from is None:
            return True
        return self.route_ok(q_from, self.pre[i])

    def first(self, order: Iterable[int], scan: int | None = None) -> tuple[int | None, int]:
        """(the first pose of `order` the arm may go to, or None if none of the first `scan`
        (all: None) may; how many were passed over)."""
        order = list(order)[:scan]
        for k, i in enumerate(order):
            if self.ok(int(i)):
                return int(i), k
        return None, len(order)

    def stuck(self, order: Iterable[int], kind: str, shown: int = 12) -> PlanStuck:
        """The `PlanStuck` for a plan none of whose poses `order` (best first) the arm may reach
        from where it is: which limit the paths to the best `shown` of them cross first."""
        env, spec, tool = self.guard.env, self.guard.spec, self.guard.tool_m
        q_from = self.where()
        order = [int(i) for i in order]
        best = order[:shown]
        suggest = None
        if order:
            clear = env.clearance(spec, self.q[order], tool)
            suggest = self.q[order[int(np.argmax(clear))]].copy()
        if q_from is None:  # no position yet (a plan's first pose): only approaches were checked
            names = [path_limit(env, spec, tool, self.pre[i], self.q[i]) for i in best]
            msg = (
                f"the {kind} plan has no pose whose own approach stays inside the envelope: the "
                f"approaches of the best {len(best)} of its {len(order)} poses first cross "
                f"{limits_summary(names)}"
            )
            return PlanStuck(msg, suggest)
        names = [path_limit(env, spec, tool, q_from, self.pre[i]) for i in best]
        msg = (
            f"the {kind} plan has no pose left that the arm may move to from where it is "
            f"(q = {fmt_q(q_from)} rad): the paths to all {len(order)} of its remaining poses "
            f"leave the envelope, also via the upright posture; those to the best "
            f"{len(best)} first cross {limits_summary(names)}"
        )
        return PlanStuck(msg, suggest)


def fmt_q(q: npt.ArrayLike) -> str:
    return "[" + ", ".join(f"{x:+.3f}" for x in np.asarray(q, float)) + "]"


def limit_name(env: Envelope, spec: RobotSpec, tool_m: np.ndarray, q: np.ndarray) -> str:
    """The envelope's limit the posture q is beyond, or nearest to (the one with the least
    clearance): a joint's range, a face of the workspace box (for the SMR), or the floor (for
    the link frames), with where it is."""
    from workcell.kinematics.chain import base_T_frames, pack

    q = np.asarray(q, float)
    if not np.all(np.isfinite(q)):
        return "non-finite joint values"
    lim = np.asarray(env.joint_limits_rad, float)
    beyond = np.maximum(lim[:, 0] - q, q - lim[:, 1])
    if np.any(beyond > 0):
        j = int(np.argmax(beyond))
        return f"joint {j + 1}'s range [{lim[j, 0]:.3f}, {lim[j, 1]:.3f}] rad"
    T = np.asarray(base_T_frames(pack(spec.dh), q[None]))[0]
    smr = T[-1, :3, :3] @ np.asarray(tool_m, float) + T[-1, :3, 3]
    lo, hi = np.asarray(env.box_min_m, float), np.asarray(env.box_max_m, float)
    m = env.kinematic_margin_m
    less = f", less the {1e3 * m:g} mm kinematic margin" if m > 0 else ""
    faces = [
        (smr[0] - lo[0], f"the workspace box's -x side (x = {lo[0]:g} m{less})"),
        (hi[0] - smr[0], f"the workspace box's +x side (x = {hi[0]:g} m{less})"),
        (smr[1] - lo[1], f"the workspace box's -y side (y = {lo[1]:g} m{less})"),
        (hi[1] - smr[1], f"the workspace box's +y side (y = {hi[1]:g} m{less})"),
        (smr[2] - lo[2], f"the workspace box's bottom (z = {lo[2]:g} m{less})"),
        (hi[2] - smr[2], f"the workspace box's top (z = {hi[2]:g} m{less})"),
        (float(T[2:, 2, 3].min()) - env.floor_z_m, f"the floor (z = {env.floor_z_m:g} m{less})"),
    ]
    return min(faces, key=lambda f: f[0])[1]


def path_limit(
    env: Envelope, spec: RobotSpec, tool_m: np.ndarray, q_from: np.ndarray, q_to: np.ndarray
) -> str:
    """Which limit the straight joint path q_from -> q_to crosses first (`limit_name` of the
    first of dense samples outside the box or above the floor, else of the one with the least
    clearance). For the one line a stopped campaign prints, not a safety check."""
    q0, q1 = np.asarray(q_from, float), np.asarray(q_to, float)
    if not (np.all(np.isfinite(q0)) and np.all(np.isfinite(q1))):
        return "non-finite joint values"
    n = max(32, int(np.ceil(np.max(np.abs(q1 - q0)) / 0.005)) + 1)
    qs = q0 + np.linspace(0.0, 1.0, n)[:, None] * (q1 - q0)
    c = env.clearance(spec, qs, tool_m)
    out = np.flatnonzero(c < 0)
    return limit_name(env, spec, tool_m, qs[out[0] if len(out) else int(np.argmin(c))])


def limits_summary(names: list[str]) -> str:
    """'the workspace box's top (z = 0.65 m) (11 of 12), the floor (z = 0.02 m) (1 of 12)'."""
    from collections import Counter

    counts = Counter(names).most_common()
    if len(counts) == 1:
        return counts[0][0]
    return ", ".join(f"{name} ({k} of {len(names)})" for name, k in counts)


def order_for_paths(
    spec: RobotSpec,
    env: Envelope,
    q: np.ndarray,
    signs: np.ndarray,
    tool_m: np.ndarray,
    approach_rad: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Keep the given (random or raster) order, but defer a pose whose move from the previous
    pose leaves the envelope part-way (the joint-space path of a moveJ can dip the SMR or a link
    below the table between two valid end points) until a pose it can be reached from has been
    measured, the way the executor moves (`Reach`). A pose whose own approach (pre-pose -> pose)
    leaves the envelope is dropped, and so is a pose from which no remaining pose can be reached
    (the order then goes on from the pose before it).
    Deterministic, so a resumed campaign re-plans the same pose ids."""
    reach = Reach(spec, env, tool_m, q, signs, approach_rad)
    remaining = _approachable(reach, len(q))
    order: list[int] = []
    while remaining:
        stop_if_interrupted()
        reach.last = q[order[-1]] if order else None
        nxt, _ = reach.first(remaining)
        if nxt is None:
            order.pop()  # a dead end: drop it and go on from the pose before it
            continue
        order.append(nxt)
        remaining.remove(nxt)
    idx = np.array(order, int)
    return q[idx], signs[idx]


def _approachable(reach: Reach, n: int) -> list[int]:
    """The poses (of `reach`'s n) whose own approach, pre-pose -> pose, stays inside."""
    ok = []
    for i in range(n):  # a path check each: minutes for thousands, so Ctrl-C is heeded
        stop_if_interrupted()
        if reach.approach_ok(i):
            ok.append(i)
    return ok


# the pairwise check of `largest_family`: ~1.4 s for 22 candidates, minutes past this
FAMILY_MAX_CANDIDATES = 400


def largest_family(
    spec: RobotSpec,
    env: Envelope,
    q: np.ndarray,
    signs: np.ndarray,
    tool_m: np.ndarray,
    approach_rad: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The largest set of candidate poses the arm can move between inside the envelope (a
    strongly connected component of "reachable from", checked as the executor moves), in
    `order_for_paths`' order. In a tight envelope the poses fall into families (elbow or wrist
    postures) with no path between them that stays inside: the greedy order keeps whichever
    family its first pose is in, and may keep 2 of 8 where another family holds 10. A pairwise
    check, so only for up to FAMILY_MAX_CANDIDATES (returns `order_for_paths`' own order past
    that)."""
    from scipy.sparse.csgraph import connected_components

    if len(q) > FAMILY_MAX_CANDIDATES:
        return order_for_paths(spec, env, q, signs, tool_m, approach_rad)
    reach = Reach(spec, env, tool_m, q, signs, approach_rad)
    ok = _approachable(reach, len(q))
    if not ok:
        return q[:0], signs[:0]
    A = np.zeros((len(ok), len(ok)), bool)
    for a, i in enumerate(ok):
        stop_if_interrupted()
        reach.last = q[i]
        for b, j in enumerate(ok):
            A[a, b] = i != j and reach.ok(j)
    _, label = connected_components(A, directed=True, connection="strong")
    big = int(np.argmax(np.bincount(label)))
    members = np.array([ok[k] for k in np.flatnonzero(label == big)], int)
    return order_for_paths(spec, env, q[members], signs[members], tool_m, approach_rad)


def static_plan(
    q: np.ndarray, signs: np.ndarray, *, start_id: int = 0, skip_ids: set[int] | None = None
) -> Plan:
    for i, (qi, si) in enumerate(zip(q, signs, strict=True)):
        pid = start_id + i
        if skip_ids and pid in skip_ids:
            continue
        yield PoseTarget(pose_id=pid, q_rad=qi, approach_sign=si)


def with_reference(plan: Plan, every: int, reference: PoseTarget | None = None) -> Plan:
    """The plan, with a reference pose (default: the plan's first) measured again after every
    `every` measured poses and once at the end: a record of how the measured position of one
    fixed pose drifts during the campaign (temperature, the tracker, the set-up). The
    reference is approached with its own approach signs each time, so backlash is the same.
    Its repeats are recorded like any sample, with the reference's pose_id, and are not sent to
    the plan: an adaptive plan sees each of its poses once."""
    if every <= 0:
        raise ValueError(f"reference interval must be a positive number of poses, got {every}")
    try:
        t = next(plan)
    except StopIteration:
        return
    ref = t if reference is None else reference
    measured = 0
    while True:
        sample = yield t
        just_checked = False
        if sample is not None:
            measured += 1
            if measured % every == 0:
                yield ref
                just_checked = True
        try:
            t = plan.send(sample)
        except StopIteration:
            if measured and not just_checked:
                yield ref
            return


MAX_POSES = 100_000  # ~10 s a pose: eleven days at the tracker


def reference_repeats(poses: int, every: int) -> int:
    """How many times `with_reference` measures the reference again in a plan of `poses` poses
    (0 when `every` is 0): after every `every` poses, and at the end unless it just was."""
    if every <= 0 or poses <= 0:
        return 0
    return poses // every + (poses % every > 0)


def reference_line(pose_id: int, poses: int, every: int) -> str:
    """The dry run's line for a reference interval."""
    return (
        f"reference: pose {pose_id} measured again after every {every} poses and at the end "
        f"({reference_repeats(poses, every)} more measurements; each move to it is checked "
        "against the envelope when it is made)"
    )


CANDIDATE_SPARE = (1.1, 1.5, 2.5)  # candidates drawn per pose asked for, tried in turn


def make_plan(
    kind: str,
    spec: RobotSpec,
    env: Envelope,
    n: int,
    *,
    seed: int,
    tool_m: np.ndarray,
    skip_ids: set[int] | None = None,
    approach_rad: float = 0.02,
    **kw: Any,
) -> tuple[Plan, np.ndarray | None]:
    """Build a plan by name. Returns (generator, the planned configurations if known ahead)."""
    if n <= 0:
        raise ValueError(f"number of poses must be positive, got {n}")
    if kind in ("random", "grid"):
        # 10 % spare candidates; in a tight envelope, where more are lost to their approach and
        # the paths between them, more spare ones (the first try unchanged, so a recording
        # planned by it resumes with the same plan)
        for spare in CANDIDATE_SPARE:
            m = int(n * spare) + 2
            if kind == "random":
                q = random_configurations(spec, env, m, np.random.default_rng(seed), tool_m)
            else:
                q = grid_configurations(spec, env, m, tool_m, seed)
            q, signs = approach_signs(spec, env, q, tool_m, approach_rad, seed)
            if kind == "grid" and len(q) > n:
                idx = np.round(np.linspace(0, len(q) - 1, n)).astype(int)
                q, signs = q[idx], signs[idx]
            cand = (q, signs)
            q, signs = order_for_paths(spec, env, q, signs, tool_m, approach_rad)
            if len(q) >= n:
                break
        if len(q) < n:
            # only when every try above fell short (so a plan made before this step, and the
            # resume of its recording, is unchanged): the largest family the arm can move
            # between, of the last try's candidates
            fq, fs = largest_family(spec, env, *cand, tool_m, approach_rad)
            if len(fq) > len(q):
                q, signs = fq, fs
        if len(q) < n:
            raise ValueError(
                f"only {len(q)} of {n} poses fit the envelope with their approach and the paths "
                "between them; widen the envelope or ask for fewer poses"
            )
        q, signs = q[:n], signs[:n]
        return static_plan(q, signs, skip_ids=skip_ids), q
    if kind in ADAPTIVE_KINDS:
        from workcell.campaign import adaptive  # optional module (experiment design)

        return adaptive.make_adaptive_plan(
            kind,
            spec,
            env,
            n,
            seed=seed,
            tool_m=tool_m,
            skip_ids=skip_ids,
            approach_rad=approach_rad,
            **kw,
        ), None
    raise ValueError(f"unknown plan {kind!r}; choose {PLAN_CHOICES}")
