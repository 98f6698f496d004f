"""Plausibility checks of a recording's values: types, ranges and units.

The recording format is SI (metres, radians, seconds, kilograms; degrees Celsius). A file written
in millimetres or degrees is still valid JSON of the right shape, and a fit would run on it and
print absurd numbers. These checks find such values and say, in one line each, what is wrong and
what to do. Each returns a list of problems (empty when the values are plausible); the caller
decides whether a problem refuses the file (`Dataset.from_recording`, `workcell replay`) or is
only listed (`workcell info`).

The ranges are physical, not tuned: a joint cannot pass its limit, a laser tracker does not
measure beyond ~160 m, an SMR is not a metre from the flange, a tracker's standard deviation of
a mean is micrometres, a joint motor is not at 300 degC.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence

import numpy as np

from workcell.drivers.protocols import TRACKER_RANGE_M
from workcell.kinematics.robots import DH, RobotSpec, catalogue_mismatch, robot_from_session

JOINT_LIMIT_MARGIN_RAD = 0.1  # measured joints may pass a limit by noise and overshoot only
SMR_OFFSET_MAX_M = 1.0  # an SMR mounted a metre from the flange is not a calibration tool
# standard deviation of a mean of tracker readings: micrometres. One pose may have a large one (two
# readings, one disturbed), so the unit check is on the file's median; a single sigma above
# SIGMA_CORRUPT_M is no measurement at all
SIGMA_MAX_M = 1e-3
SIGMA_CORRUPT_M = 0.1
JOINT_TEMP_RANGE_C = (-40.0, 150.0)  # motor/gear temperature in service
AMBIENT_TEMP_RANGE_C = (-40.0, 80.0)
PAYLOAD_FACTOR = 3.0  # payloads beyond 3x the rated payload are not carried
QUAT_NORM_TOL = 1e-3
DH_LENGTH_MAX_M = 10.0  # the longest serial arms reach ~4 m; a 10 m link is millimetres


def is_finite_number(x: object) -> bool:
    """A finite JSON number (an integer too large for a float is not: OverflowError)."""
    if not isinstance(x, (int, float)) or isinstance(x, bool):
        return False
    try:
        return math.isfinite(x)
    except OverflowError:
        return False


def is_finite_list(v: object, n: int) -> bool:
    return isinstance(v, list) and len(v) == n and all(is_finite_number(x) for x in v)


def _fmt(x: float) -> str:
    return f"{x:.4g}"


def _norm(v, axis=None):
    """Euclidean norm that neither overflows to inf nor warns for huge finite values (1e300 in
    a mistyped file): where it would, the largest component stands in (within sqrt(3) of the
    norm, enough to say "far too big")."""
    v = np.asarray(v, dtype=float)
    with np.errstate(over="ignore", invalid="ignore"):
        n = np.linalg.norm(v, axis=axis)
        return np.where(np.isinf(n), np.max(np.abs(v), axis=axis), n)


def _length_hint(length_m: float, limit_m: float) -> str:
    """Why a length is too long: millimetres when a thousandth of it is plausible, else a
    corrupt value (1e300 is no unit mistake)."""
    if length_m <= 1000 * limit_m:
        return "it looks like millimetres; the format wants metres"
    return "not a length in metres or millimetres (a corrupt value?); repair or drop it"


def _dh_problems(robot: RobotSpec) -> list[str]:
    """The declared DH chain in the format's units (link lengths in metres, angles in radians),
    and the arm `robot.model` names: a catalogue arm's model name with another arm's chain
    (a UR10 with a UR5e's links) was read, fitted and exported with the named arm's masses, to
    be refused only by `export` as a model "edited by hand" (fuzz audit, 2026-11-29)."""
    out = []
    for name, lim, unit, other in (
        ("a", DH_LENGTH_MAX_M, "m", "millimetres; the format wants metres"),
        ("d", DH_LENGTH_MAX_M, "m", "millimetres; the format wants metres"),
        ("alpha", 2 * np.pi, "rad", "degrees; the format wants radians"),
        ("theta_offset", 2 * np.pi, "rad", "degrees; the format wants radians"),
    ):
        v = np.abs(np.asarray(getattr(robot.dh, name), float))
        if np.any(v > lim):
            j = int(np.argmax(v))
            out.append(
                f"session robot.dh.{name}[{j}] is {_fmt(float(v[j]))} {unit} (more than "
                f"{_fmt(lim)} {unit}): it looks like {other}"
            )
    if not out and (why := catalogue_mismatch(robot.model, robot.dh.a, robot.dh.d)) is not None:
        out.append(f"session robot.model is {robot.model!r} but robot.dh is not its chain: {why}")
    return out


def session_problems(s: dict, robot: RobotSpec | None = None) -> list[str]:
    """Problems of the session's nominal values (tool, tracker placement, payload)."""
    out: list[str] = []
    if robot is not None:
        out.extend(_dh_problems(robot))
    tool = s.get("tool")
    smr = tool.get("smr_offset_m") if isinstance(tool, dict) else None
    if not is_finite_list(smr, 3):
        out.append("session tool.smr_offset_m must be 3 finite numbers (metres)")
    elif _norm(smr) > SMR_OFFSET_MAX_M:
        out.append(
            f"session tool.smr_offset_m is {_fmt(float(_norm(smr)))} m from the flange "
            f"(more than {SMR_OFFSET_MAX_M:g} m): {_length_hint(_norm(smr), SMR_OFFSET_MAX_M)}"
        )
    tracker = s.get("tracker")
    bit = tracker.get("base_in_tracker") if isinstance(tracker, dict) else None
    t = bit.get("translation_m") if isinstance(bit, dict) else None
    qw = bit.get("quaternion_wxyz") if isinstance(bit, dict) else None
    if not (is_finite_list(t, 3) and is_finite_list(qw, 4)):
        out.append(
            "session tracker.base_in_tracker needs translation_m (3 numbers, metres) and "
            "quaternion_wxyz (4 numbers)"
        )
    else:
        dist = float(_norm(t))
        if dist > TRACKER_RANGE_M:
            out.append(
                f"session tracker.base_in_tracker.translation_m puts the robot {_fmt(dist)} m "
                f"from the tracker (no tracker measures beyond {TRACKER_RANGE_M:g} m): "
                + _length_hint(dist, TRACKER_RANGE_M)
            )
        nq = float(_norm(qw))
        if abs(nq - 1.0) > QUAT_NORM_TOL:
            out.append(
                f"session tracker.base_in_tracker.quaternion_wxyz has norm {_fmt(nq)}; write a "
                "unit quaternion (w, x, y, z)"
            )
    payload = s.get("payload")
    if payload is not None and not isinstance(payload, dict):
        out.append("session payload must be an object with mass_kg and com_m")
    elif isinstance(payload, dict):
        m = payload.get("mass_kg")
        if m is not None and not is_finite_number(m):
            out.append("session payload.mass_kg must be a finite number (kilograms)")
        elif m is not None:
            out.extend(_payload_problem("session payload.mass_kg", float(m), robot))
        com = payload.get("com_m")
        if com is not None and not is_finite_list(com, 3):
            out.append("session payload.com_m must be 3 finite numbers (metres)")
        elif com is not None and _norm(com) > SMR_OFFSET_MAX_M:
            out.append(
                f"session payload.com_m is {_fmt(float(_norm(com)))} m from the flange: "
                + _length_hint(_norm(com), SMR_OFFSET_MAX_M)
            )
    return out


def _payload_problem(what: str, m: float, robot: RobotSpec | None) -> list[str]:
    if m < 0:
        return [f"{what} is negative ({_fmt(m)} kg)"]
    if robot is not None and m > PAYLOAD_FACTOR * robot.max_payload_kg:
        return [
            f"{what} is {_fmt(m)} kg, {m / robot.max_payload_kg:.0f}x the {robot.model}'s rated "
            f"{robot.max_payload_kg:g} kg: it looks like grams; the format wants kilograms"
        ]
    return []


def joint_range_problem(
    where: str,
    key: str,
    v: Sequence[float],
    robot: RobotSpec,
    label: Callable[[int], str] | None = None,
) -> list[str]:
    """A joint vector outside the arm's ranges (plus a small margin), with a unit hint.
    `label(j)` names element j (default `key[j]`, 0-based as in the JSON array)."""
    q = np.asarray(v, dtype=float)
    lim = robot.joint_limits_rad
    lo, hi = lim[:, 0] - JOINT_LIMIT_MARGIN_RAD, lim[:, 1] + JOINT_LIMIT_MARGIN_RAD
    bad = np.where((q < lo) | (q > hi))[0]
    if bad.size == 0:
        return []
    j = int(bad[np.argmax(np.abs(q[bad]))])
    hint = (
        "it looks like degrees; the format wants radians"
        if np.max(np.abs(q)) <= 370.0 and np.max(np.abs(q)) > 2 * math.pi + JOINT_LIMIT_MARGIN_RAD
        else "wrong robot model in the session, or not radians"
    )
    name = label(j) if label else f"{key}[{j}]"
    return [
        f"{where}: {name} is {_fmt(float(q[j]))}, outside joint {j + 1}'s range "
        f"[{lim[j, 0]:.3g}, {lim[j, 1]:.3g}] rad of the {robot.model}: {hint}"
    ]


def sample_problems(smp: dict, k: int, robot: RobotSpec) -> list[str]:
    """Problems of one /campaign/sample message (k: its position in the file)."""
    n = robot.n_joints
    idx = smp.get("index", k)
    where = f"sample {idx if is_finite_number(idx) else k} (pose_id {smp.get('pose_id')!r})"
    out: list[str] = []
    pid = smp.get("pose_id")
    if not (is_finite_number(pid) and float(pid) == int(pid) and abs(pid) < 2**53):
        out.append(f"{where}: pose_id must be an integer (below 2^53)")
    for key, least in (("index", 0), ("n_readings", 1)):
        v = smp.get(key)
        if v is not None and not (
            is_finite_number(v) and float(v) == int(v) and least <= v < 2**53
        ):
            out.append(f"{where}: {key} must be an integer >= {least}, got {v!r}")
    for key, width, required in (
        ("q_measured_rad", n, True),
        ("tracker_position_m", 3, True),
        ("q_commanded_rad", n, False),
        ("tracker_sigma_m", 3, False),
        ("approach_sign", n, False),
    ):
        v = smp.get(key)
        if v is None and not required:
            continue
        if not is_finite_list(v, width):
            out.append(
                f"{where}: {key} must be {width} finite numbers"
                + ("; repair or drop that sample" if required else " or null")
            )
            continue
        if key in ("q_measured_rad", "q_commanded_rad"):
            out.extend(joint_range_problem(where, key, v, robot))
        elif key == "tracker_position_m" and _norm(v) > TRACKER_RANGE_M:
            out.append(
                f"{where}: tracker_position_m puts the SMR {_fmt(float(_norm(v)))} m "
                f"from the tracker (no tracker measures beyond {TRACKER_RANGE_M:g} m): "
                + _length_hint(_norm(v), TRACKER_RANGE_M)
            )
        elif key == "tracker_sigma_m":
            s = np.asarray(v, dtype=float)
            if np.any(s < 0):
                out.append(f"{where}: tracker_sigma_m has a negative standard deviation")
            elif np.max(s) > SIGMA_CORRUPT_M:
                out.append(
                    f"{where}: tracker_sigma_m is {_fmt(float(np.max(s)))} m; a tracker's standard "
                    f"deviation of a mean is micrometres (no measurement has more than "
                    f"{SIGMA_CORRUPT_M:g} m): repair or drop that sample"
                )
        elif key == "approach_sign" and any(x not in (-1, 0, 1) for x in v):
            out.append(f"{where}: approach_sign values must be -1, 0 or +1")
    temps = smp.get("joint_temperature_c")
    if temps is not None:
        if not (isinstance(temps, list) and len(temps) == n):
            out.append(f"{where}: joint_temperature_c must be {n} numbers or null")
        else:
            t = [x for x in temps if x is not None]
            if not all(is_finite_number(x) for x in t):
                out.append(f"{where}: joint_temperature_c has a non-number")
            else:
                out.extend(
                    _temperature_problem(where, "joint_temperature_c", t, JOINT_TEMP_RANGE_C)
                )
    amb = smp.get("ambient_temperature_c")
    if amb is not None:
        if not is_finite_number(amb):
            out.append(f"{where}: ambient_temperature_c must be a finite number or null")
        else:
            out.extend(
                _temperature_problem(where, "ambient_temperature_c", [amb], AMBIENT_TEMP_RANGE_C)
            )
    el = smp.get("elapsed_s")
    if el is not None and not (is_finite_number(el) and el >= 0):
        out.append(f"{where}: elapsed_s must be a finite number of seconds >= 0")
    pk = smp.get("payload_kg")
    if pk is not None:
        if not is_finite_number(pk):
            out.append(f"{where}: payload_kg must be a finite number (kilograms)")
        else:
            out.extend(_payload_problem(f"{where}: payload_kg", float(pk), robot))
    return out


def _temperature_problem(
    where: str, key: str, t: Iterable[float], rng: tuple[float, float]
) -> list[str]:
    t = list(t)
    if not t:
        return []
    lo, hi = min(t), max(t)
    if lo >= rng[0] and hi <= rng[1]:
        return []
    hint = (
        "it looks like kelvin; the format wants degrees Celsius"
        if lo >= rng[0] + 273.15 and hi <= rng[1] + 273.15
        else "the format wants degrees Celsius"
    )
    worst = hi if hi > rng[1] else lo
    return [f"{where}: {key} {_fmt(worst)} is outside {rng[0]:g}..{rng[1]:g} degC: {hint}"]


def reach_m(dh: DH, smr_offset_m: Sequence[float]) -> float:
    """Upper bound of the distance from the base origin to the SMR over all joint angles."""
    return float(np.sum(np.hypot(dh.a, dh.d)) + _norm(smr_offset_m))


def scale_problems(
    p_tracker: np.ndarray, robot: RobotSpec, smr_offset_m: Sequence[float]
) -> list[str]:
    """Measured positions must fit in the ball the arm can reach (diameter 2 x reach)."""
    p = np.asarray(p_tracker, dtype=float)
    if len(p) < 2:
        return []
    with np.errstate(over="ignore", invalid="ignore"):
        spread = float(np.max(_norm(p - p.mean(axis=0), axis=1)))
    r = reach_m(robot.dh, smr_offset_m)
    if spread <= 1.5 * (2 * r):
        return []
    return [
        f"tracker positions lie up to {_fmt(spread)} from their centroid, but the "
        f"{robot.model} with this SMR reaches only {r:.3g} m from its base: "
        + millimetre_hint(spread, r, "wrong robot model in the session, or not metres")
    ]


def millimetre_hint(length: float, expected_m: float, otherwise: str) -> str:
    """'looks like millimetres' when `length` is ~1000x what metres would give."""
    if 300 * expected_m < length < 3000 * expected_m:
        return "it looks like millimetres; the format wants metres"
    return otherwise


def sigma_problems(sigmas: Sequence) -> list[str]:
    """The file's typical tracker sigma must be micrometres: a median above SIGMA_MAX_M is a unit
    mistake (millimetres). A few large ones are disturbed poses, which the fit down-weights."""
    # a sample without sigmas counts as small: 5 large of 40 is not "most are millimetres"
    worst = [
        max(v) if isinstance(v, list) and v and all(is_finite_number(x) for x in v) else 0.0
        for v in sigmas
    ]
    if not worst:
        return []
    med = float(np.median(worst))
    if med <= SIGMA_MAX_M:
        return []
    return [
        f"tracker_sigma_m: the median sample's is {_fmt(med)}; a tracker's standard deviation "
        f"of a mean is micrometres (limit {SIGMA_MAX_M:g} m): it looks like millimetres; the "
        "format wants metres"
    ]


def timing_problems(elapsed_s: Sequence[float], log_time_ns: Sequence[int]) -> list[str]:
    """elapsed_s must run at the pace of the recording's log times (seconds, not ms)."""
    e = np.asarray(elapsed_s, dtype=float)
    t = np.asarray(log_time_ns, dtype=float) * 1e-9
    ok = np.isfinite(e) & np.isfinite(t)
    if ok.sum() < 2:
        return []
    span_t = float(np.ptp(t[ok]))
    span_e = float(np.ptp(e[ok]))
    if span_t < 10.0 or span_e <= 0:
        return []  # log times not informative (too short, or all equal)
    ratio = span_e / span_t
    if 0.01 <= ratio <= 100.0:  # time-scaled simulation runs fast, never 100x off seconds
        return []
    hint = (
        "it looks like milliseconds; the format wants seconds"
        if 300 < ratio < 3000
        else "the format wants seconds"
    )
    return [
        f"elapsed_s spans {_fmt(span_e)} while the samples' log times span {span_t:.1f} s: {hint}"
    ]


def recording_problems(session: dict, samples: Sequence[dict], robot: RobotSpec) -> list[str]:
    """Every problem of a recording's values; the file-wide checks (scale, timing) run only when
    each sample is well-formed."""
    out = session_problems(session, robot)
    for k, smp in enumerate(samples):
        out += sample_problems(smp, k, robot)
    if not out and samples:
        out += sigma_problems([x.get("tracker_sigma_m") for x in samples])
        out += scale_problems(
            [x["tracker_position_m"] for x in samples], robot, session["tool"]["smr_offset_m"]
        )
        out += timing_problems(
            [x.get("elapsed_s", float("nan")) for x in samples],
            [x.get("_log_time_ns", float("nan")) for x in samples],
        )
    return out


def session_robot(session: dict) -> RobotSpec:
    """The nominal arm a session declares; ValueError (one line) if it cannot be built."""
    try:
        return robot_from_session(session["robot"])
    except (KeyError, TypeError, AttributeError) as e:
        raise ValueError(f"session robot unusable ({type(e).__name__}: {e})") from None


def problems_of(session: dict, samples: Sequence[dict]) -> list[str]:
    """`recording_problems` with the session's own arm (an unusable arm is the problem)."""
    try:
        robot = session_robot(session)
    except ValueError as e:
        return [str(e)]
    return recording_problems(session, samples, robot)


def first_problem(problems: list[str]) -> str:
    """One line for a refused file: the first problem, and how many more there are."""
    if len(problems) == 1:
        return problems[0]
    return f"{problems[0]} (and {len(problems) - 1} more; `workcell info` lists them)"
