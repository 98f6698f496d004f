# ruff: noqa: F811 - the `base` fixture is imported from test_recording_checks
"""Data that passes every unit check but does not follow the arm: refused or set aside before any
fit (workcell/recording/consistency.py), and other malformed-recording cases an audit found."""

from __future__ import annotations

import copy
import json
import warnings

import numpy as np
import pytest
from mcap.writer import CompressionType, Writer
from test_recording_checks import base, run_cli, write_raw  # noqa: F401 - fixture

from workcell.recording import schema as S
from workcell.recording.dataset import Dataset
from workcell.recording.reader import RecordingError, read_recording


def _write(tmp_path, name, session, samples, times):
    p = tmp_path / name
    write_raw(p, session, samples, times)
    return p


def test_a_clean_campaign_is_not_touched(base):
    session, samples, times, p = base
    ds = Dataset.from_recording(p)
    assert len(ds) == len(samples) and not ds.read_notes


def test_a_tracker_locked_on_a_fixed_target_is_refused(base, tmp_path, capsys):
    """Every sample with the first one's position: before, `fit` printed a held-out RMS of
    0.0 um and wrote the model."""
    session, samples, times, _ = base
    s2 = copy.deepcopy(samples)
    for s in s2:
        s["tracker_position_m"] = list(samples[0]["tracker_position_m"])
    p = _write(tmp_path, "constant.mcap", session, s2, times)
    with pytest.raises(RecordingError, match="do not follow the ur5e"):
        Dataset.from_recording(p)
    rc, err = run_cli(["fit", str(p), "--out", str(tmp_path / "m.json")], capsys)
    assert rc != 0 and len(err) == 1 and "do not follow" in err[0]
    assert not (tmp_path / "m.json").exists()


def test_readings_paired_with_the_wrong_poses_are_refused(base, tmp_path):
    session, samples, times, _ = base
    s2 = copy.deepcopy(samples)
    pos = [s["tracker_position_m"] for s in samples]
    for i, s in enumerate(s2):
        s["tracker_position_m"] = pos[(i + 1) % len(pos)]
    p = _write(tmp_path, "shifted.mcap", session, s2, times)
    with pytest.raises(RecordingError, match=r"median of 16 samples is \d+\.\d mm off"):
        Dataset.from_recording(p)


def test_another_robots_dh_in_the_session_is_refused(base, tmp_path):
    session, samples, times, _ = base
    s = copy.deepcopy(session)
    s["robot"]["model"] = "ur10"
    s["robot"]["dh"] = {
        "a": [0, -0.612, -0.5723, 0, 0, 0],
        "d": [0.1273, 0, 0, 0.163941, 0.1157, 0.0922],
        "alpha": [np.pi / 2, 0, 0, np.pi / 2, -np.pi / 2, 0],
        "theta_offset": [0.0] * 6,
    }
    p = _write(tmp_path, "ur10dh.mcap", s, samples, times)
    with pytest.raises(RecordingError, match="do not follow the ur10"):
        Dataset.from_recording(p)


def test_a_lost_beam_recorded_as_zeros_is_set_aside_and_named(base, tmp_path):
    session, samples, times, _ = base
    s2 = copy.deepcopy(samples)
    s2[5]["tracker_position_m"] = [0.0, 0.0, 0.0]
    p = _write(tmp_path, "zero.mcap", session, s2, times)
    ds = Dataset.from_recording(p)
    assert len(ds) == len(samples) - 1
    assert s2[5]["pose_id"] not in ds.pose_id.tolist()
    (note,) = ds.read_notes
    assert f"pose_id {s2[5]['pose_id']} (" in note and "set aside as gross" in note
    # a 5 mm disturbance is no gross reading: kept (the fit's robust pass weighs it)
    s3 = copy.deepcopy(samples)
    s3[5]["tracker_position_m"] = (np.array(s3[5]["tracker_position_m"]) + 0.005).tolist()
    ds3 = Dataset.from_recording(_write(tmp_path, "bump.mcap", session, s3, times))
    assert len(ds3) == len(samples) and not ds3.read_notes


def test_exact_copies_of_samples_are_used_once(base, tmp_path):
    session, samples, times, _ = base
    s2 = copy.deepcopy(samples) + copy.deepcopy(samples)
    t2 = list(times) + [t + 1 for t in times]
    ds = Dataset.from_recording(_write(tmp_path, "dup.mcap", session, s2, t2))
    assert len(ds) == len(samples)
    assert any("16 of 32 samples are exact copies" in n for n in ds.read_notes)
    # the same pose measured again (another reading) is a repeat, not a copy
    s3 = copy.deepcopy(samples) + [copy.deepcopy(samples[0])]
    s3[-1]["tracker_position_m"][0] += 1e-6
    ds3 = Dataset.from_recording(_write(tmp_path, "rep.mcap", session, s3, list(times) + [t2[-1]]))
    assert len(ds3) == len(samples) + 1


@pytest.mark.parametrize(
    "limits, match",
    [
        ([[-360.0, 360.0]] * 6, "looks like degrees"),
        ([[float("nan"), 1.0]] + [[-3.0, 3.0]] * 5, "finite"),
        ([[3.0, -3.0]] * 6, "joint 1's pair is"),
    ],
)
def test_joint_limits_in_degrees_nan_or_swapped_are_refused(base, tmp_path, limits, match):
    session, samples, times, _ = base
    s = copy.deepcopy(session)
    s["robot"]["joint_limits_rad"] = limits
    p = _write(tmp_path, "lim.mcap", s, samples, times)
    with pytest.raises(RecordingError, match=match):
        Dataset.from_recording(p)


def test_a_pose_id_too_large_for_an_integer_is_a_problem_not_a_warning(base, tmp_path):
    session, samples, times, _ = base
    s2 = copy.deepcopy(samples)
    s2[3]["pose_id"] = 1e20
    p = _write(tmp_path, "pid.mcap", session, s2, times)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(RecordingError, match="pose_id must be an integer"):
            Dataset.from_recording(p)


def _rewrite_with_encoding(src, dst, topic, encoding):
    """Copy a recording, writing `topic`'s channel with another message encoding."""
    rec = read_recording(src)
    with open(dst, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="", library="test")
        ids = {}
        for t in (S.SESSION, S.SAMPLE, S.EVENT):
            sid = w.register_schema(name=t, encoding="jsonschema", data=b"{}")
            enc = encoding if t == topic else "json"
            ids[t] = w.register_channel(topic=t, message_encoding=enc, schema_id=sid)
        strip = lambda m: {k: v for k, v in m.items() if not k.startswith("_")}  # noqa: E731
        msgs = [(S.SESSION, rec.session)] + [(S.SAMPLE, s) for s in rec.samples]
        msgs += [(S.EVENT, e) for e in rec.events]
        for i, (t, m) in enumerate(msgs):
            lt = int(m.get("_log_time_ns", i))
            w.add_message(ids[t], log_time=lt, publish_time=lt, data=json.dumps(strip(m)).encode())
        w.finish()


def test_a_stream_in_another_encoding_is_skipped_unless_it_is_the_session_or_samples(
    base, tmp_path
):
    _, samples, _, p = base
    ev = tmp_path / "ev.mcap"
    _rewrite_with_encoding(p, ev, S.EVENT, "msgpack")
    rec = read_recording(ev)
    assert len(rec.samples) == len(samples) and rec.closed_cleanly
    assert any("/campaign/event uses encoding 'msgpack'" in x for x in rec.problems)
    assert len(Dataset.from_recording(ev)) == len(samples)
    se = tmp_path / "se.mcap"
    _rewrite_with_encoding(p, se, S.SESSION, "cbor")
    with pytest.raises(RecordingError, match="/workcell/session uses encoding 'cbor'"):
        read_recording(se)


def test_info_lists_what_fits_refuse_or_set_aside(base, tmp_path):
    from workcell.commands.info import summary

    session, samples, times, p = base
    assert summary(str(p))["set_aside"] == []
    s2 = copy.deepcopy(samples)
    for s in s2:
        s["tracker_position_m"] = list(samples[0]["tracker_position_m"])
    d = summary(str(_write(tmp_path, "constant.mcap", session, s2, times)))
    assert len(d["value_problems"]) == 1 and "do not follow" in d["value_problems"][0]
    s3 = copy.deepcopy(samples)
    s3[2]["tracker_position_m"] = [0.0, 0.0, 0.0]
    d = summary(str(_write(tmp_path, "zero.mcap", session, s3, times)))
    assert d["value_problems"] == [] and "gross readings" in d["set_aside"][0]


def test_replay_refuses_what_the_fits_refuse(base, tmp_path, capsys):
    session, samples, times, _ = base
    s2 = copy.deepcopy(samples)
    for s in s2:
        s["tracker_position_m"] = list(samples[0]["tracker_position_m"])
    p = _write(tmp_path, "constant.mcap", session, s2, times)
    rc, err = run_cli(["replay", str(p), "--online", "ekf-ann"], capsys)
    assert rc != 0 and len(err) == 1 and "do not follow" in err[0]


def test_the_tui_replay_feeds_the_filter_what_the_fits_keep(base, tmp_path):
    """The TUI's EKF-ANN replay fed the filter every sample of its training poses: a
    recording written twice over (exact copies, which `workcell replay` and the fits use once)
    went through the filter twice, as twice the evidence."""
    from workcell.recording.chain import load_chain
    from workcell.tui.backend import replay_samples

    session, samples, times, _ = base
    s2 = copy.deepcopy(samples) + copy.deepcopy(samples)
    t2 = list(times) + [t + 1 for t in times]
    chain = load_chain(_write(tmp_path, "dup.mcap", session, s2, t2))
    ds = Dataset.from_recording(chain)
    train, _ = ds.holdout_split(0.25)
    fed = replay_samples(chain, ds, train)
    assert len(fed) == len(train) < len(samples)
    assert len({s["pose_id"] for s in fed}) == len(fed)
    assert [s["index"] for s in fed] == sorted(s["index"] for s in fed)
