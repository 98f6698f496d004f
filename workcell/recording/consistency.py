"""Do the tracker positions follow the arm at all? Screens run before any fit.

The unit and range checks (`checks`) look at each value alone. A recording can pass them and
still be no calibration data: the tracker locked on a fixed target while the arm moved, readings
paired with the wrong poses, a lost beam recorded as (0, 0, 0), another robot's DH in the
session, joints and limits both in degrees. A fit on such data converges to something and prints
a number. Here the session's nominal arm is registered to the measurements (rigidly, with the
SMR offset free and a robust loss, `workcell.kinematics.registration`) and the distances say:

- the median pose more than `GROSS_M` off: the data does not follow this arm; refuse;
- single poses more than `GROSS_M` off while the rest follow: gross readings; set aside, named.

`GROSS_M` is physical, not tuned: an arm a tracker can calibrate sits within a few millimetres of
its nominal kinematics once registered (the real UR10 recordings: median 1.0 and 0.7 mm, at most 2.1 mm), and
the calibration effects the tool models are sub-millimetre to a few millimetres.
Exact copies of a sample (same pose, joints and tracker position to the last bit: a stream
written twice, a bad merge) are not new measurements; they are dropped and counted.
"""

from __future__ import annotations

import numpy as np

from workcell.kinematics.robots import RobotSpec

GROSS_M = 0.02
MIN_SAMPLES = 6  # fewer cannot tell an arm that does not fit from one bad pose


def exact_copies(rows: list[dict]) -> list[int]:
    """Indices of samples equal to an earlier one in pose_id, q_measured_rad and
    tracker_position_m (all three, exactly)."""
    seen: set = set()
    out = []
    for i, r in enumerate(rows):
        key = (
            repr(r.get("pose_id")),
            repr(r.get("q_measured_rad")),
            repr(r.get("tracker_position_m")),
        )
        if key in seen:
            out.append(i)
        seen.add(key)
    return out


def nominal_distances(
    robot: RobotSpec, p_flange_smr_m: np.ndarray, q: np.ndarray, p_tracker: np.ndarray
) -> np.ndarray:
    """(N,) distance of each measured SMR position from the registered nominal arm's (m)."""
    from workcell.kinematics.dh_numpy import base_T_flange_nominal
    from workcell.kinematics.registration import register_nominal

    T = base_T_flange_nominal(robot.dh, np.asarray(q, float))
    return register_nominal(T, p_tracker, p_flange_smr_m).distance_m


def mismatch_message(robot: RobotSpec, median_m: float, n: int) -> str:
    return (
        f"the tracker positions do not follow the {robot.model}: after registering its nominal "
        f"kinematics the median of {n} samples is {median_m * 1e3:.1f} mm off (an arm a tracker "
        "can calibrate is within a few mm); check the session's robot model, that each tracker "
        "reading belongs to its pose, that the tracker followed the SMR, and that joints are in "
        "radians"
    )


def gross_note(pose_id: np.ndarray, dist_m: np.ndarray, n: int) -> str:
    shown = ", ".join(
        f"pose_id {int(p)} ({d * 1e3:.0f} mm)"
        for p, d in list(zip(pose_id, dist_m, strict=True))[:5]
    )
    more = f" and {len(dist_m) - 5} more" if len(dist_m) > 5 else ""
    return (
        f"{len(dist_m)} of {n} samples set aside as gross readings, more than "
        f"{GROSS_M * 1e3:.0f} mm from where the registered nominal arm puts the SMR (a lost beam "
        f"recorded as a position? another target?): {shown}{more}; the file is unchanged"
    )
