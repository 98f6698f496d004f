"""Channel names and JSON schemas of recording format version 1 (../shared/recording-format.md).

Extensions made by workcell (optional, readers must not require them):
- `/campaign/sample` may carry `tracker_readings` (int, raw readings taken) and
  `rejected_readings` (int, outliers rejected) and `payload_com_m`.
- `/workcell/session` may carry `chained_from` (path, sha256 and sample count of the recording
  a resumed campaign continues; the path relative to this file's folder, or as typed in
  recordings made before 2026-11-26) and `truth` is never written (simulated truth stays in the
  simulator). Its `tracker` block may carry `instrument_name` (text) and `serial_number` (as the
  instrument gives it) of the connected tracker; a resume compares them.
"""

from __future__ import annotations

import json

FORMAT_VERSION = 1

SESSION = "/workcell/session"
JOINT_STATE = "/robot/joint_state"
TRACKER = "/tracker/measurement"
SAMPLE = "/campaign/sample"
EVENT = "/campaign/event"

_num = {"type": "number"}
_vec = lambda n: {"type": "array", "items": _num, "minItems": n, "maxItems": n}  # noqa: E731
_vec_or_null = lambda n: {"anyOf": [_vec(n), {"type": "null"}]}  # noqa: E731
_vec_nullable_items = lambda n: {  # noqa: E731
    "type": "array",
    "items": {"type": ["number", "null"]},
    "minItems": n,
    "maxItems": n,
}

SCHEMAS: dict[str, tuple[str, dict]] = {
    SESSION: (
        "workcell.Session",
        {
            "type": "object",
            "required": [
                "format_version",
                "created_utc",
                "robot",
                "tool",
                "tracker",
                "payload",
                "campaign",
                "software",
            ],
            "properties": {
                "format_version": {"type": "integer"},
                "created_utc": {"type": "string"},
                "robot": {"type": "object"},
                "tool": {"type": "object"},
                "tracker": {"type": "object"},
                "payload": {"type": "object"},
                "campaign": {"type": "object"},
                "software": {"type": "object"},
            },
        },
    ),
    JOINT_STATE: (
        "workcell.JointState",
        {
            "type": "object",
            "required": ["q_rad", "qd_rad_s"],
            "properties": {
                "q_rad": _vec(6),
                "qd_rad_s": _vec(6),
                "torque_nm": _vec_or_null(6),
                "temperature_c": _vec_or_null(6),
            },
        },
    ),
    TRACKER: (
        "workcell.TrackerMeasurement",
        {
            "type": "object",
            "required": ["position_m", "sigma_m", "status"],
            "properties": {
                # null components when the status is not ok (no position was read)
                "position_m": _vec_nullable_items(3),
                "sigma_m": _vec_nullable_items(3),
                "status": {"enum": ["ok", "beam_broken", "out_of_range", "error"]},
                # optional: the instrument's own time stamp (s on its clock; GeoCOM CoordTime)
                "instrument_time_s": {"type": "number"},
            },
        },
    ),
    SAMPLE: (
        "workcell.PoseSample",
        {
            "type": "object",
            "required": [
                "index",
                "pose_id",
                "q_commanded_rad",
                "q_measured_rad",
                "approach_sign",
                "tracker_position_m",
                "tracker_sigma_m",
                "n_readings",
                "joint_temperature_c",
                "elapsed_s",
                "payload_kg",
            ],
            "properties": {
                "index": {"type": "integer"},
                "pose_id": {"type": "integer"},
                "q_commanded_rad": _vec(6),
                "q_measured_rad": _vec(6),
                "approach_sign": {
                    "type": "array",
                    "items": {"type": "integer", "enum": [-1, 0, 1]},
                    "minItems": 6,
                    "maxItems": 6,
                },
                "tracker_position_m": _vec(3),
                "tracker_sigma_m": _vec(3),
                "n_readings": {"type": "integer"},
                "joint_temperature_c": _vec_or_null(6),
                "ambient_temperature_c": {"type": ["number", "null"]},
                "elapsed_s": _num,
                "payload_kg": _num,
            },
        },
    ),
    EVENT: (
        "workcell.Event",
        {
            "type": "object",
            "required": ["level", "kind", "message"],
            "properties": {
                "level": {"enum": ["info", "warning", "error"]},
                "kind": {"type": "string"},
                "message": {"type": "string"},
            },
        },
    ),
}


def schema_bytes(topic: str) -> tuple[str, bytes]:
    name, sch = SCHEMAS[topic]
    return name, json.dumps(sch).encode()
