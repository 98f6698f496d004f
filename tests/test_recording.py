"""Recording format v1: round trip, crash tolerance (truncation at any byte), bad input."""

import json
import subprocess
import sys

import numpy as np
import pytest
from mcap.reader import make_reader

from workcell.recording.dataset import Dataset
from workcell.recording.reader import RecordingError, read_recording
from workcell.recording.writer import RecordingWriter

SESSION = {
    "robot": {"model": "ur5e"},
    "tool": {"smr_offset_m": [0.0, 0.0, 0.06]},
    "tracker": {
        "model": "t",
        "base_in_tracker": {"translation_m": [2, 0, 0], "quaternion_wxyz": [1, 0, 0, 0]},
    },
    "payload": {"mass_kg": 0.5, "com_m": [0, 0, 0.03]},
    "campaign": {"plan": "test"},
}


def p_nominal(q):
    """Where the session's nominal UR5e puts the SMR in the tracker frame: the readings of a
    recording must follow the arm (`Dataset.from_recording` refuses random positions)."""
    from workcell.kinematics.chain import p_tracker, pack
    from workcell.kinematics.robots import UR5E

    T = np.eye(4)
    T[:3, 3] = SESSION["tracker"]["base_in_tracker"]["translation_m"]
    th = pack(UR5E.dh, tool=SESSION["tool"]["smr_offset_m"])
    return np.asarray(p_tracker(th, T, np.atleast_2d(q)))[0]


def sample(i, rng):
    q = rng.normal(size=6)
    return {
        "index": i,
        "pose_id": i,
        "q_commanded_rad": rng.normal(size=6).tolist(),
        "q_measured_rad": q.tolist(),
        "approach_sign": [1, -1, 1, 1, -1, 1],
        "tracker_position_m": (p_nominal(q) + rng.normal(size=3) * 1e-4).tolist(),
        "tracker_sigma_m": [1e-5] * 3,
        "n_readings": 5,
        "joint_temperature_c": [25.0] * 6,
        "ambient_temperature_c": None,
        "elapsed_s": float(i),
        "payload_kg": 0.5,
    }


def write(path, n=30, close=True, seed=0):
    rng = np.random.default_rng(seed)
    w = RecordingWriter(path, SESSION)
    samples = []
    for i in range(n):
        for k in range(5):
            w.joint_state(10**18 + i * 10**9 + k, rng.normal(size=6), np.zeros(6))
            w.tracker_measurement(10**18 + i * 10**9 + k, rng.normal(size=3), [1e-5] * 3, "ok")
        s = sample(i, rng)
        w.sample(10**18 + i * 10**9 + 9, s)
        samples.append(s)
        if i % 7 == 3:
            w.event(10**18 + i * 10**9 + 9, "warning", "beam_broken", "test")
    if close:
        w.close()
    return samples


def test_a_reading_that_is_not_ok_is_recorded_without_position_or_sigma(tmp_path):
    """The simulated tracker returned its stated sigma beside a broken beam, and it was recorded
    as if a position had been read with that sigma; the format's raw reading has none."""
    p = tmp_path / "r.mcap"
    with RecordingWriter(p, SESSION) as w:
        w.tracker_measurement(10**18, [1.0, 2.0, 3.0], [1e-5] * 3, "ok")
        w.tracker_measurement(10**18 + 1, [float("nan")] * 3, [6.75e-6] * 3, "beam_broken")
        w.tracker_measurement(10**18 + 2, [1.0, 2.0, 3.0], [1e-5] * 3, "out_of_range")
    m = read_recording(p).tracker_measurements
    assert m[0]["position_m"] == [1.0, 2.0, 3.0] and m[0]["sigma_m"] == [1e-5] * 3
    for r in m[1:]:
        assert r["position_m"] == [None] * 3 and r["sigma_m"] == [None] * 3


def test_round_trip(tmp_path):
    p = tmp_path / "r.mcap"
    samples = write(p)
    rec = read_recording(p)
    assert rec.closed_cleanly and not rec.problems
    assert [s["q_measured_rad"] for s in rec.samples] == [s["q_measured_rad"] for s in samples]
    assert rec.channel_counts["/robot/joint_state"] == 150
    assert len(rec.events) == 4
    ds = Dataset.from_recording(p)
    assert len(ds) == 30 and ds.robot.model == "ur5e"
    np.testing.assert_allclose(ds.payload_kg, 0.5)
    # Foxglove convention: json messages with jsonschema schemas; summary present
    with open(p, "rb") as f:
        r = make_reader(f)
        summ = r.get_summary()
        assert summ is not None and len(summ.chunk_indexes) >= 30
        assert {s.encoding for s in summ.schemas.values()} == {"jsonschema"}
        assert {c.message_encoding for c in summ.channels.values()} == {"json"}


def test_samples_are_read_in_log_time_order_whatever_the_file_order(tmp_path):
    """MCAP does not require file order to be time order (a merged or rewritten file): the
    hold-out split, replay and drift tests must see the same order of measurement either way."""
    rng = np.random.default_rng(3)
    samples = [sample(i, rng) for i in range(12)]
    t = [10**18 + i * 10**9 for i in range(12)]
    for name, order in (("fwd.mcap", range(12)), ("rev.mcap", reversed(range(12)))):
        with RecordingWriter(tmp_path / name, SESSION) as w:
            for i in order:
                w.event(t[i], "info", "note", f"pose {i}")
                w.sample(t[i] + 1, samples[i])
    fwd, rev = (read_recording(tmp_path / n) for n in ("fwd.mcap", "rev.mcap"))
    assert [s["index"] for s in rev.samples] == list(range(12))
    assert [e["message"] for e in rev.events] == [f"pose {i}" for i in range(12)]
    a, b = (Dataset.from_recording(tmp_path / n) for n in ("fwd.mcap", "rev.mcap"))
    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_array_equal(a.elapsed_s, b.elapsed_s)
    assert [x.tolist() for x in a.holdout_split()] == [x.tolist() for x in b.holdout_split()]


def test_refuses_to_overwrite(tmp_path):
    p = tmp_path / "r.mcap"
    write(p, n=2)
    with pytest.raises(FileExistsError):
        RecordingWriter(p, SESSION)


def test_truncated_at_random_bytes_keeps_every_complete_pose(tmp_path):
    p = tmp_path / "full.mcap"
    samples = write(p, n=25)
    data = p.read_bytes()
    with open(p, "rb") as f:
        summ = make_reader(f).get_summary()
    sample_ch = next(c.id for c in summ.channels.values() if c.topic == "/campaign/sample")
    session_ch = next(c.id for c in summ.channels.values() if c.topic == "/workcell/session")
    # end offset of the chunk that holds each sample (the writer flushes a chunk per pose)
    ends = sorted(
        c.chunk_start_offset + c.chunk_length
        for c in summ.chunk_indexes
        if sample_ch in c.message_index_offsets
    )
    session_end = min(
        c.chunk_start_offset + c.chunk_length
        for c in summ.chunk_indexes
        if session_ch in c.message_index_offsets
    )
    assert len(ends) == 25
    rng = np.random.default_rng(42)
    cuts = list(rng.integers(8, len(data), 40)) + [len(data) - 1, 9, ends[3], ends[3] - 1]
    cuts += [session_end, session_end - 1]
    for cut in cuts:
        q = tmp_path / f"cut{cut}.mcap"
        q.write_bytes(data[:cut])
        try:
            rec = read_recording(q)
        except RecordingError as e:
            assert "session" in str(e) and cut < session_end
            continue
        got = [s["pose_id"] for s in rec.samples]
        complete = sum(1 for e in ends if e <= cut)
        assert got == list(range(len(got))), "samples must be a prefix, in order"
        assert len(got) == complete, (cut, len(got), complete)
        for a, b in zip(rec.samples, samples, strict=False):
            assert a["tracker_position_m"] == b["tracker_position_m"]
        if cut < len(data):
            assert not rec.closed_cleanly and rec.problems


def test_unclosed_writer_is_readable(tmp_path):
    p = tmp_path / "open.mcap"
    write(p, n=10, close=False)
    rec = read_recording(p)
    assert len(rec.samples) == 10 and not rec.closed_cleanly
    assert any("footer" in x or "ends" in x for x in rec.problems)


def run_cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "workcell.cli", *args], capture_output=True, text=True, timeout=120
    )


def assert_one_line_error(r, *words):
    assert r.returncode != 0
    assert "Traceback" not in r.stderr
    lines = [x for x in r.stderr.strip().splitlines() if x.strip()]
    assert len(lines) == 1, r.stderr
    for w in words:
        assert w in lines[0], lines[0]


def test_bad_inputs_give_one_clear_line(tmp_path):
    assert_one_line_error(run_cli("fit", str(tmp_path / "missing.mcap")), "no such file")
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file at all")
    assert_one_line_error(run_cli("fit", str(junk)), "not an MCAP file")
    assert_one_line_error(run_cli("info", str(junk)), "not an MCAP file")
    # wrong schema: a session without the tracker object
    bad = tmp_path / "schema.mcap"
    with RecordingWriter(bad, {"robot": {"model": "ur5e"}, "tool": {}}) as w:
        w.sample(1, sample(0, np.random.default_rng(0)))
    assert_one_line_error(run_cli("fit", str(bad)), "tracker")
    # NaN in a sample (bypassing the writer's own check, as another tool might)
    nan = tmp_path / "nan.mcap"
    with RecordingWriter(nan, SESSION) as w:
        s = sample(0, np.random.default_rng(0))
        w._write("/campaign/sample", {**s, "tracker_position_m": [float("nan"), 0, 0]}, 1)
    assert_one_line_error(run_cli("fit", str(nan)), "sample 0", "tracker_position_m")
    # unknown robot without a DH chain
    unk = tmp_path / "unknown.mcap"
    with RecordingWriter(unk, {**SESSION, "robot": {"model": "abb-irb-9999"}}) as w:
        w.sample(1, sample(0, np.random.default_rng(0)))
    assert_one_line_error(run_cli("fit", str(unk)), "unknown robot")
    assert_one_line_error(run_cli("fit", str(tmp_path)), "directory")


def test_info_reports_closed_state(tmp_path):
    p = tmp_path / "r.mcap"
    write(p, n=5)
    r = run_cli("info", str(p), "--json")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["poses"] == 5 and d["closed_cleanly"] and d["robot"] == "ur5e"
    assert d["events"] == {"beam_broken": 1}
    assert d["trailing_bytes"] == 0 and not d["problems"]


def test_bytes_appended_after_a_clean_close_are_reported(tmp_path):
    p = tmp_path / "r.mcap"
    samples = write(p, n=5)
    size = p.stat().st_size
    with open(p, "ab") as f:
        f.write(b"appended by another tool")
    rec = read_recording(p)
    assert [s["pose_id"] for s in rec.samples] == [s["pose_id"] for s in samples]
    assert rec.closed_cleanly and rec.trailing_bytes == 24
    assert any(f"byte {size}" in x and "appended" in x for x in rec.problems)
    r = run_cli("info", str(p))
    assert r.returncode == 0, r.stderr
    assert "cleanly, then 24 bytes appended" in r.stdout


def test_unreachable_devices_give_one_clear_line(tmp_path):
    out = tmp_path / "u.mcap"
    r = run_cli(
        "campaign",
        "--robot",
        "ur://127.0.0.250",
        "--tracker",
        "serial:///dev/nonexistent",
        "--poses",
        "3",
        "--out",
        str(out),
    )
    assert_one_line_error(r, "unreachable")
    assert not out.exists(), "no recording is started before the devices answer"


def test_a_recording_that_cannot_start_leaves_no_file(tmp_path, monkeypatch):
    """A campaign that failed while writing its session (a full disk) left a header-only .mcap
    that blocked the same --out and that --resume refused as "bad magic"; now nothing is left,
    and the writer never opens over a file that appeared meanwhile."""
    import errno

    import pytest

    import workcell.recording.writer as writer_mod
    from workcell.recording.writer import RecordingWriter

    def full(self):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(writer_mod.RecordingWriter, "flush", full)
    with pytest.raises(OSError, match="No space left"):
        RecordingWriter(tmp_path / "r.mcap", {"campaign": {}})
    assert list(tmp_path.iterdir()) == []


def test_every_message_of_a_campaign_meets_the_schema_written_with_it(tmp_path):
    """The schemas written into the file (Foxglove validates against them) follow the format:
    the session's required fields, approach_sign -1/0/+1 integers (was any number), typed tracker
    readings (were untyped arrays; null components when the beam was broken), and each sample's
    joint temperatures and payload."""
    import jsonschema

    from sim_devices.cell import sim_cell
    from workcell.campaign.executor import CampaignConfig
    from workcell.campaign.run import run_campaign

    _, robot, tracker, cell = sim_cell("ur5e", "realistic", 5, beam_break_prob=0.3)
    p = tmp_path / "c.mcap"
    run_campaign(robot, tracker, cell, p, poses=8, seed=5,
                 config=CampaignConfig(readings_per_pose=3, settle_s=0.2))  # fmt: skip
    seen, statuses = set(), set()
    with open(p, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            msg = json.loads(message.data)
            jsonschema.validate(msg, json.loads(schema.data))
            seen.add(channel.topic)
            if channel.topic == "/tracker/measurement":
                statuses.add(msg["status"])
    assert {"/workcell/session", "/campaign/sample", "/tracker/measurement"} <= seen
    assert "beam_broken" in statuses  # the nullable reading was exercised
    # and the schemas are strict enough to refuse what the format does not allow
    from workcell.recording import schema as S

    bad = sample(0, np.random.default_rng(0)) | {"approach_sign": [0.5, 1, 1, 1, 1, 1]}
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, S.SCHEMAS[S.SAMPLE][1])
