"""Wrong units and malformed values in a recording: one line, non-zero exit, never a traceback.

The malformed files are written with the mcap library directly (as a third-party tool would),
not with workcell's writer, which refuses some of these values itself.
"""

from __future__ import annotations

import copy
import json
import math
import re
import shutil

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jsonfuzz import replace_any_field
from mcap.writer import CompressionType, Writer

from workcell.cli import main
from workcell.commands.info import summary
from workcell.recording import checks
from workcell.recording import schema as S
from workcell.recording.dataset import Dataset
from workcell.recording.reader import RecordingError, read_recording


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A clean 16-pose simulated campaign (no effects): session and samples as dicts."""
    d = tmp_path_factory.mktemp("checks")
    p = d / "base.mcap"
    rc = main(
        [
            "campaign",
            "--robot",
            "sim",
            "--tracker",
            "sim",
            "--poses",
            "16",
            "--effects",
            "none",
            "--out",
            str(p),
        ]
    )
    assert rc == 0
    rec = read_recording(p)
    strip = lambda m: {k: v for k, v in m.items() if not k.startswith("_")}  # noqa: E731
    times = [s["_log_time_ns"] for s in rec.samples]
    return strip(rec.session), [strip(s) for s in rec.samples], times, p


def write_raw(path, session, samples, times):
    """Write a recording with arbitrary JSON values (no validation)."""
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="", library="test")
        ids = {}
        for topic in (S.SESSION, S.SAMPLE):
            sid = w.register_schema(name=S.SCHEMAS[topic][0], encoding="jsonschema", data=b"{}")
            ids[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
        w.add_message(
            ids[S.SESSION],
            log_time=times[0],
            publish_time=times[0],
            data=json.dumps(session).encode(),
        )
        for s, t in zip(samples, times, strict=True):
            w.add_message(ids[S.SAMPLE], log_time=t, publish_time=t, data=json.dumps(s).encode())
        w.finish()
    return path


def run_cli(argv, capsys):
    rc = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    return rc, err


def test_clean_campaign_and_real_data_pass(base):
    session, samples, _, p = base
    assert (
        checks.recording_problems(
            read_recording(p).session, read_recording(p).samples, Dataset.from_recording(p).robot
        )
        == []
    )
    assert summary(str(p))["value_problems"] == []


def _scale_samples(samples, key, f):
    out = copy.deepcopy(samples)
    for s in out:
        s[key] = [f(x) for x in s[key]] if isinstance(s[key], list) else f(s[key])
    return out


UNIT_CASES = {
    "joints in degrees": (
        lambda se, sa: (se, _scale_samples(sa, "q_measured_rad", math.degrees)),
        "looks like degrees",
    ),
    "positions in millimetres": (
        lambda se, sa: (se, _scale_samples(sa, "tracker_position_m", lambda x: 1000 * x)),
        "looks like millimetres",
    ),
    "sigma in millimetres": (
        lambda se, sa: (se, _scale_samples(sa, "tracker_sigma_m", lambda x: 1000 * x)),
        "looks like millimetres",
    ),
    "temperatures in kelvin": (
        lambda se, sa: (se, _scale_samples(sa, "joint_temperature_c", lambda x: x + 273.15)),
        "looks like kelvin",
    ),
    "SMR offset in millimetres": (
        lambda se, sa: (
            {
                **se,
                "tool": {
                    **se["tool"],
                    "smr_offset_m": [1000 * x for x in se["tool"]["smr_offset_m"]],
                },
            },
            sa,
        ),
        "looks like millimetres",
    ),
    "payload in grams": (
        lambda se, sa: ({**se, "payload": {**(se.get("payload") or {}), "mass_kg": 2500.0}}, sa),
        "looks like grams",
    ),
    # fuzz audit, 2026-11-29: read, fitted (with the UR10's masses) and exported until then
    "robot model naming another arm": (
        lambda se, sa: ({**se, "robot": {**se["robot"], "model": "ur10"}}, sa),
        "robot.dh is not its chain: a2 is -0.425 m, a ur10's -0.612 m (it is a ur5e's)",
    ),
    "quaternion not unit": (
        lambda se, sa: (
            {
                **se,
                "tracker": {
                    **se["tracker"],
                    "base_in_tracker": {
                        **se["tracker"]["base_in_tracker"],
                        "quaternion_wxyz": [2.0, 0.0, 0.0, 0.0],
                    },
                },
            },
            sa,
        ),
        "unit quaternion",
    ),
}


@pytest.mark.parametrize("case", sorted(UNIT_CASES))
def test_wrong_units_refused_in_one_line(base, tmp_path, capsys, case):
    session, samples, times, _ = base
    make, hint = UNIT_CASES[case]
    se, sa = make(copy.deepcopy(session), copy.deepcopy(samples))
    p = write_raw(tmp_path / "bad.mcap", se, sa, times)
    before = p.read_bytes()
    for argv in (["fit", str(p), "--method", "dh"], ["replay", str(p), "--online", "ekf-ann"]):
        rc, err = run_cli(argv, capsys)
        assert rc == 2, (case, argv, err)
        assert len(err) == 1 and err[0].startswith(f"workcell {argv[0]}: error: "), err
        assert hint in err[0], err
    assert p.read_bytes() == before  # nothing written to the user's file
    # info does not refuse the file: it lists every bad value
    rc = main(["info", str(p)])
    out = capsys.readouterr().out
    assert rc == 0 and "bad value" in out and hint in out


def test_positions_in_millimetres_caught_by_scale_when_close_to_tracker(base, tmp_path):
    """A tracker 0.1 m from the base: millimetre positions stay within its range, but the
    points spread far more than the arm reaches."""
    session, samples, times, _ = base
    c = np.mean([s["tracker_position_m"] for s in samples], axis=0)
    sa = _scale_samples(samples, "tracker_position_m", lambda x: x)
    for s in sa:
        s["tracker_position_m"] = (1000 * (np.array(s["tracker_position_m"]) - c) / 20).tolist()
    p = write_raw(tmp_path / "mm.mcap", session, sa, times)
    with pytest.raises(RecordingError, match="reaches only"):
        Dataset.from_recording(p)


def test_elapsed_in_milliseconds(base, tmp_path):
    session, samples, times, _ = base
    assert (times[-1] - times[0]) * 1e-9 > 10  # the simulated campaign spans minutes
    sa = _scale_samples(samples, "elapsed_s", lambda x: 1000 * x)
    p = write_raw(tmp_path / "ms.mcap", session, sa, times)
    with pytest.raises(RecordingError, match="looks like milliseconds"):
        Dataset.from_recording(p)


def test_real_ur10_files_pass_the_checks():
    from pathlib import Path

    root = Path(__file__).resolve().parents[2] / "shared" / "data" / "ur10-leica"
    files = sorted(root.glob("*.mcap"))
    if not files:
        pytest.skip("../shared/data/ur10-leica not beside the repository")
    for f in files:
        assert len(Dataset.from_recording(f)) > 100


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_any_malformed_value_is_a_clean_refusal_or_a_valid_dataset(base, tmp_path_factory, data):
    """Put any JSON value in any field of the session or of one sample: the dataset either
    loads with finite, in-range arrays or is refused with a RecordingError; `workcell info`
    summarises the file unless the session itself is unusable (then a RecordingError too)."""
    session, samples, times, _ = base
    se, sa = copy.deepcopy(session), copy.deepcopy(samples)
    if data.draw(st.booleans(), label="in session"):
        target = se
    else:
        target = sa[data.draw(st.integers(0, len(sa) - 1), label="sample")]
    replace_any_field(data, target)
    d = tmp_path_factory.mktemp("fuzz")
    p = write_raw(d / "f.mcap", se, sa, times)
    try:
        ds = Dataset.from_recording(p)
    except RecordingError as e:
        assert "\n" not in str(e)
    else:
        assert np.all(np.isfinite(ds.q)) and np.all(np.isfinite(ds.p_tracker))
        lim = ds.robot.joint_limits_rad
        assert np.all(ds.q >= lim[:, 0] - 0.11) and np.all(ds.q <= lim[:, 1] + 0.11)
        assert np.all(ds.sigma_m > 0) and np.all(ds.sigma_m <= checks.SIGMA_CORRUPT_M)
    try:
        s = summary(str(p))
    except RecordingError as e:
        assert "\n" not in str(e) and "session" in str(e)
    else:
        assert s["poses"] == len(sa)
    shutil.rmtree(d, ignore_errors=True)


def test_one_disturbed_pose_is_not_a_unit_mistake(base, tmp_path):
    """Two readings, one disturbed: that pose's sigma of the mean is a millimetre or more. Found
    in a simulated campaign (seed 7, 2 readings a pose), which the fit refused as "millimetres".
    One such pose is kept (the fit down-weights it); most poses so are millimetres."""
    session, samples, times, _ = base
    sa = copy.deepcopy(samples)
    sa[3]["tracker_sigma_m"] = [2e-4, 1.1e-3, 3e-4]
    ds = Dataset.from_recording(write_raw(tmp_path / "one.mcap", session, sa, times))
    assert ds.sigma_m[3, 1] == pytest.approx(1.1e-3)
    big = copy.deepcopy(sa)  # a few large, the rest unknown (null): not "most are millimetres"
    for k, smp in enumerate(big):
        smp["tracker_sigma_m"] = [2e-3, 2e-3, 2e-3] if k < 3 else None
    Dataset.from_recording(write_raw(tmp_path / "nulls.mcap", session, big, times))
    sa[5]["tracker_sigma_m"] = [0.2, 0.0, 0.0]  # no tracker: corrupt, refused with the sample
    with pytest.raises(RecordingError, match=r"sample 5 .* \(no measurement has more than 0.1 m\)"):
        Dataset.from_recording(write_raw(tmp_path / "corrupt.mcap", session, sa, times))


def test_fractional_approach_sign_is_a_problem(base):
    """approach_sign is 6 ints, -1, 0 or +1 (recording format); 0.5 used to pass."""
    session, samples, _, _ = base
    robot = checks.session_robot(session)
    s = copy.deepcopy(samples[0])
    assert checks.sample_problems(s, 0, robot) == []
    s["approach_sign"] = [0.5, -0.5, 1, 1, -1, 0]
    assert any("approach_sign" in x for x in checks.sample_problems(s, 0, robot))


def test_required_fields_missing_are_read_with_a_warning_that_says_what_was_assumed(base, tmp_path):
    """A recording from another tool without tracker_sigma_m (and approach_sign, elapsed_s,
    payload_kg) was fitted with stand-in values without a word, and fit printed its noise floor
    as "the recorded sigmas". Now the data set carries what was assumed, and the commands print
    it as a warning."""
    from workcell.recording.dataset import read_warnings

    session, samples, times, _ = base
    drop = ("tracker_sigma_m", "approach_sign", "elapsed_s", "payload_kg")
    bare = [{k: v for k, v in s.items() if k not in drop} for s in samples]
    p = write_raw(tmp_path / "bare.mcap", session, bare, times)
    ds = Dataset.from_recording(p)
    lines = read_warnings(ds)
    assert len(lines) == 4 and all(line.startswith("warning: ") for line in lines)
    assert "no usable tracker_sigma_m" in lines[0] and "10 um" in lines[0]
    np.testing.assert_allclose(ds.sigma_m, 1e-5)
    # half of them lack sigma: the median of the recorded ones, said as such
    half = [s if i % 2 else bare[i] for i, s in enumerate(samples)]
    ds = Dataset.from_recording(write_raw(tmp_path / "half.mcap", session, half, times))
    med = np.median([s["tracker_sigma_m"] for s in samples[1::2]])
    assert f"{med * 1e6:.1f} um" in read_warnings(ds)[0]
    # a complete recording has none
    assert read_warnings(Dataset.from_recording(base[3])) == []


def _write_custom(path, session, samples, times, *, schema_name=None, encoding="jsonschema",
                  sample_first=False, sample_data=None):  # fmt: skip
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start(profile="", library="test")
        ids = {}
        for topic in (S.SESSION, S.SAMPLE):
            name = S.SCHEMAS[topic][0] if schema_name is None or topic != S.SAMPLE else schema_name
            sid = w.register_schema(name=name, encoding=encoding, data=b"{}")
            ids[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
        data = sample_data or [json.dumps(s).encode() for s in samples]
        msgs = [(ids[S.SAMPLE], t, d) for d, t in zip(data, times, strict=True)]
        head = (ids[S.SESSION], times[0], json.dumps(session).encode())
        msgs = msgs[:1] + [head] + msgs[1:] if sample_first else [head] + msgs
        for cid, t, d in msgs:
            w.add_message(cid, log_time=t, publish_time=t, data=d)
        w.finish()
    return path


def test_format_deviations_are_said_once_each(base, tmp_path):
    """The reader accepted silently (audit of the recording format, 2026-11-26 night): another
    schema name or encoding than the format's, a sample before the session, log times that are
    not Unix-epoch nanoseconds, samples whose index runs against their log times, required
    fields left out; a file of bad JSON gave one line per message, and a record cut short named
    Python's struct.error. Each is now one line, said once; the clean file says nothing."""
    session, samples, times, clean = base
    assert read_recording(clean).problems == []

    def problems(name, **kw):
        smp = kw.pop("samples", samples)
        tms = kw.pop("times", times)
        return read_recording(_write_custom(tmp_path / name, session, smp, tms, **kw)).problems

    p = problems("schema.mcap", schema_name="foo.Unknown")
    assert len(p) == 1 and "declares schema 'foo.Unknown'" in p[0] and "PoseSample" in p[0]
    p = problems("protobuf.mcap", encoding="protobuf")
    assert len(p) == 2 and all("protobuf encoding" in x for x in p)  # session and sample
    p = problems("first.mcap", sample_first=True)
    assert any("comes before the session" in x for x in p), p
    p = problems("ms.mcap", times=[t // 10**6 for t in times])
    assert len(p) == 1 and "before 2001" in p[0]
    p = problems("reversed.mcap", samples=samples[::-1])
    assert len(p) == 1 and "index does not rise" in p[0]
    bare = [{k: v for k, v in s.items() if k not in ("n_readings", "q_commanded_rad")}
            for s in samples]  # fmt: skip
    p = problems("bare.mcap", samples=bare)
    assert len(p) == 2 and all(f"{len(samples)} of {len(samples)} samples lack" in x for x in p)
    p = problems("garbage.mcap", sample_data=[b"\x00garbage"] * len(samples))
    assert p == [f"{S.SAMPLE}: {len(samples)} messages are not valid JSON objects; skipped"]
    # one message nested deeper than the parser recurses: that message skipped, not the rest
    # of the file (until 2026-11-28 a RecursionError ended the read there, and the file was
    # said to have no footer)
    deep = b'{"x": ' + b"[" * 5000 + b"]" * 5000 + b"}"
    ok = [json.dumps(s).encode() for s in samples]
    p = problems("deep.mcap", sample_data=[ok[0], deep, *ok[2:]])
    assert p == [f"{S.SAMPLE}: 1 message is not a valid JSON object; skipped"], p
    # a record cut short: one line naming it, the messages before it read
    data = clean.read_bytes()
    cut = tmp_path / "cut.mcap"
    for frac in (0.5, 0.8, 0.95):
        cut.write_bytes(data[: int(len(data) * frac)])
        try:
            rec = read_recording(cut)
        except RecordingError as e:
            assert "struct" not in str(e) and "\n" not in str(e)
            continue
        assert not any("struct" in x or "unpack" in x for x in rec.problems), rec.problems


@pytest.mark.parametrize(
    "version, said",
    [(True, "true"), (1.0, "1.0"), ("1", '"1"'), (None, "null"), ("missing", "missing")],
)
def test_format_version_is_the_integer(base, tmp_path, version, said):
    """`true` and 1.0 equal 1 in Python and were read as version 1 while "1" was refused, and a
    missing version was reported as "None" (fuzz audit, 2026-11-29)."""
    session, samples, times, _ = base
    se = copy.deepcopy(session)
    if version == "missing":
        del se["format_version"]
    else:
        se["format_version"] = version
    p = write_raw(tmp_path / "v.mcap", se, samples, times)
    with pytest.raises(RecordingError, match=f"session format_version is {re.escape(said)}; "):
        read_recording(p)


def test_a_footer_that_does_not_lead_to_the_summary_is_a_problem(base, tmp_path):
    """A flipped bit in the footer's summary_start: `info` said "closed cleanly" with no
    problem, while the mcap library's seeking reader (what Foxglove uses) could not open the
    file (fuzz audit, 2026-11-29)."""
    *_, p = base
    assert not any("footer" in x for x in read_recording(p).problems)
    data = bytearray(p.read_bytes())
    at = len(data) - 8 - 4 - 8 - 8  # the footer: ..., summary_start u64, offset u64, crc u32
    data[at + 2] ^= 0x10
    bad = tmp_path / "flip.mcap"
    bad.write_bytes(bytes(data))
    rec = read_recording(bad)
    assert len(rec.samples) == 16  # still read whole, from the start
    assert any(x.startswith("the footer does not lead to the summary") for x in rec.problems)
