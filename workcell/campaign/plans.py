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

from collections.abc import Generator
from dataclasses import dataclass

import numpy as np

from workcell.campaign.envelope import Envelope, Guard
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


class Reach:
    """Which poses the arm may go to next, checked the way the executor moves (its
    `_pose_problems`): the approach path pre-pose -> pose inside the envelope, and a route from
    the last pose the arm was sent to (`last`) to the pre-pose (direct, else via the upright
    posture). Checked lazily and the approach checks cached, so a caller that takes the first
    reachable of an ordered list pays about one path check a step."""

    def __init__(
        self,
        spec: RobotSpec,
        env: Envelope,
        tool_m: np.ndarray,
        q: np.ndarray,
        signs: np.ndarray,
        approach_rad: float,
    ) -> None:
        self.guard = Guard(env, spec, np.asarray(tool_m, float))
        self.q = q
        self.pre = q - np.sign(signs) * approach_rad
        self._approach_ok: dict[int, bool] = {}
        self.last: np.ndarray | None = None  # where the arm is (None: not known, not checked)

    def approach_ok(self, i: int) -> bool:
        if i not in self._approach_ok:
            self._approach_ok[i] = self.guard.direct(self.pre[i], self.q[i]) is None
        return self._approach_ok[i]

    def ok(self, i: int) -> bool:
        if not self.approach_ok(i):
            return False
        if self.last is None:
            return True
        return self.guard.route(self.last, self.pre[i])[1] is None

    def first(self, order, scan: int | None = None) -> tuple[int | None, int]:
        """(the first pose of `order` the arm may go to, or None if none of the first `scan`
        (all: None) may; how many were passed over)."""
        order = list(order)[:scan]
        for k, i in enumerate(order):
            if self.ok(int(i)):
                return int(i), k
        return None, len(order)


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
    remaining = [i for i in range(len(q)) if reach.approach_ok(i)]
    order: list[int] = []
    while remaining:
        reach.last = q[order[-1]] if order else None
        nxt, _ = reach.first(remaining)
        if nxt is None:
            order.pop()  # a dead end: drop it and go on from the pose before it
            continue
        order.append(nxt)
        remaining.remove(nxt)
    idx = np.array(order, int)
    return q[idx], signs[idx]


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
    **kw,
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
            q, signs = order_for_paths(spec, env, q, signs, tool_m, approach_rad)
            if len(q) >= n:
                break
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
