"""`campaign --resume` of a file that is itself a resume follows its `chained_from` chain back:
the poses of every file of the chain count as measured; a link missing or changed is one line
(or, with --remeasure-missing, a warning and its poses measured again). A tracker re-plugged on
another serial port is the same cell when its serial number is the recorded one."""

import hashlib
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from simdata import aborted_sim_campaign

from workcell.recording.reader import read_recording

POSES = 10


def _campaign(out, stop_after: int, **kw):
    """A simulated 10-pose campaign (virtual time) aborted after `stop_after` samples."""
    return aborted_sim_campaign(out, stop_after, poses=POSES, **kw)


@pytest.fixture(scope="module")
def chain_dir(tmp_path_factory):
    """x.mcap (poses 0-2, died) and x.resumed1.mcap (its resume: poses 3-5, died again)."""
    from workcell.campaign.resume import continuation, resume_plan

    d = tmp_path_factory.mktemp("chain")
    _campaign(d / "x.mcap", 3)
    info = resume_plan(str(d / "x.mcap"))
    _campaign(d / "x.resumed1.mcap", 3, **continuation(info, d / "x.mcap"))
    return d


@pytest.fixture
def chain(chain_dir, tmp_path):
    """A copy of the chain in this test's own folder (byte for byte: the sha256 hold)."""
    d = tmp_path / "cell"
    shutil.copytree(chain_dir, d)
    return d


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _resume(path, *extra) -> int:
    from workcell.cli import main

    return main(["campaign", "--resume", str(path), "--on-protective-stop", "resume", *extra])


def _pose_ids(p: Path) -> list[int]:
    return [s["pose_id"] for s in read_recording(p).samples]


def _error_lines(err: str) -> list[str]:
    return [x for x in err.splitlines() if x.startswith("workcell campaign: error:")]


def test_a_resume_of_a_resume_counts_the_poses_of_the_whole_chain(chain, tmp_path, monkeypatch,
                                                                   capsys):  # fmt: skip
    """The resumed file names the file it continues relative to itself, so the chain holds when
    its folder is moved and the resume runs from another folder; nothing of x.mcap is measured
    again, the sample index continues from the chain's count, the old files are untouched."""
    moved = tmp_path / "archive" / "cell"
    shutil.move(chain, moved)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    first, second = moved / "x.mcap", moved / "x.resumed1.mcap"
    before = {p: _sha(p) for p in (first, second)}
    done = _pose_ids(first) + _pose_ids(second)
    assert sorted(done) == list(range(6))

    capsys.readouterr()
    assert _resume(second) == 0
    err = capsys.readouterr().err
    assert "6 poses measured (3 in x.mcap, 3 in x.resumed1.mcap), 4 to go" in err, err
    third = moved / "x.resumed2.mcap"  # not x.resumed1.resumed1.mcap
    rec = read_recording(third)
    more = [s["pose_id"] for s in rec.samples]
    skipped = [e for e in rec.events if e["kind"] in ("skip", "refused")]
    assert not set(done) & set(more), "a pose of the chain was measured again"
    assert set(done) | set(more) | {int(re.search(r"pose (\d+)", e["message"])[1])
                                    for e in skipped} == set(range(POSES))  # fmt: skip
    assert rec.samples[0]["index"] == len(done)
    assert read_recording(second).session["chained_from"]["path"] == "x.mcap"
    assert rec.session["chained_from"]["path"] == "x.resumed1.mcap"
    assert rec.session["chained_from"]["samples"] == 3
    assert rec.samples[0]["_log_time_ns"] > read_recording(second).last_ns
    assert {p: _sha(p) for p in (first, second)} == before, "an old file was modified"


def test_a_missing_link_is_refused_in_one_line_unless_remeasure_missing(chain, capsys):
    first, second = chain / "x.mcap", chain / "x.resumed1.mcap"
    shutil.move(first, chain.parent / "x.mcap.away")
    capsys.readouterr()
    assert _resume(second) == 2
    err = capsys.readouterr().err
    errors = _error_lines(err)
    assert len(errors) == 1 and "Traceback" not in err, err
    assert f"continues x.mcap (3 samples), which is not at {first}" in errors[0]
    assert "put the original back there and resume again" in errors[0]
    assert "--remeasure-missing" in errors[0]
    assert not (chain / "x.resumed2.mcap").exists()

    # the operator's choice: measure the lost file's poses again, said and recorded
    assert _resume(second, "--remeasure-missing") == 0
    err = capsys.readouterr().err
    assert "[warning] chain:" in err and "measured again" in err, err
    rec = read_recording(chain / "x.resumed2.mcap")
    assert any(e["kind"] == "chain" and e["level"] == "warning" for e in rec.events)
    assert {0, 1, 2} <= set(_pose_ids(chain / "x.resumed2.mcap")), "x.mcap's poses again"
    assert not set(_pose_ids(chain / "x.resumed2.mcap")) & set(_pose_ids(second))


def test_a_changed_link_is_refused_in_one_line(chain, capsys):
    first, second = chain / "x.mcap", chain / "x.resumed1.mcap"
    with open(first, "ab") as f:  # another tool appended to it: not the file that was continued
        f.write(b"\0")
    before = _sha(second)
    capsys.readouterr()
    assert _resume(second) == 2
    err = capsys.readouterr().err
    errors = _error_lines(err)
    assert len(errors) == 1 and "Traceback" not in err, err
    assert "but that file has changed since" in errors[0] and "--remeasure-missing" in errors[0]
    assert not (chain / "x.resumed2.mcap").exists()
    assert _sha(second) == before


def test_a_resume_that_named_its_file_as_typed_is_followed(chain, tmp_path, monkeypatch):
    """Resumes made before the chain was followed recorded the path as typed (relative to the
    folder the resume ran in): it is found from there, or beside the file that names it."""
    from workcell.campaign.resume import resume_plan
    from workcell.recording.schema import SAMPLE
    from workcell.recording.writer import RecordingWriter

    rec = read_recording(chain / "x.resumed1.mcap")
    session = {
        **rec.session,
        "chained_from": {**rec.session["chained_from"], "path": "cell/x.mcap"},
    }
    old_style = chain / "y.resumed1.mcap"
    with RecordingWriter(old_style, session) as w:
        for s in rec.samples:
            w._write(SAMPLE, {k: v for k, v in s.items() if not k.startswith("_")},
                     s["_log_time_ns"])  # fmt: skip
    monkeypatch.chdir(tmp_path)  # where that resume ran: cell/x.mcap
    assert resume_plan(str(old_style))["done"] == set(range(6))
    monkeypatch.chdir(chain)  # elsewhere: x.mcap beside it
    info = resume_plan("y.resumed1.mcap")
    assert info["done"] == set(range(6)) and info["index0"] == 6


def test_remeasure_missing_needs_resume(capsys):
    from workcell.cli import main

    assert main(["campaign", "--remeasure-missing", "--poses", "3", "--out", "x.mcap"]) == 2
    assert "--remeasure-missing goes with --resume" in capsys.readouterr().err


@pytest.fixture
def geocom_cell(tmp_path):
    """A campaign over the real GeoCOM driver (a simulated instrument on a pty, serial number
    900001) and the in-process simulated arm, recorded as a real cell, died after 2 poses.
    -> (recording, world, robot, cell, tracker url, started simulators)."""
    from sim_devices.cell import sim_cell
    from sim_devices.geocom_tracker import SimGeoComTracker
    from workcell.campaign.executor import CampaignConfig, CampaignControl
    from workcell.campaign.run import run_campaign
    from workcell.drivers.serial_tracker import SerialTracker

    world, robot, _, cell = sim_cell("ur5e", "none", 1, beam_break_prob=0.0)
    started = [SimGeoComTracker(world.read_tracker, seed=1).start()]
    url = f"serial://{started[0].port}"
    control = CampaignControl()
    rec = tmp_path / "real.mcap"
    try:
        run_campaign(
            robot, SerialTracker(started[0].port), cell, rec, poses=5, seed=1,
            config=CampaignConfig(readings_per_pose=1, settle_s=0.1), control=control,
            on_sample=lambda s: s["index"] >= 1 and control.abort.set(),
            extra_campaign={"robot_url": "ur://10.0.0.5", "tracker_url": url},
        )  # fmt: skip
        yield rec, world, robot, cell, url, started
    finally:
        for s in started:
            s.stop()


def _replug(geocom_cell, monkeypatch, serial_number: int) -> str:
    """The adapter re-plugged: the instrument (`serial_number`) answers on another port, which
    `campaign --resume --tracker serial://NEW` opens with the real driver."""
    from sim_devices.geocom_tracker import SimGeoComTracker
    from workcell.campaign import resume
    from workcell.drivers.serial_tracker import SerialTracker

    _, world, robot, cell, _, started = geocom_cell
    new = SimGeoComTracker(world.read_tracker, seed=1, serial_number=serial_number).start()
    started.append(new)
    started[0].stop()  # the old port is gone
    new_url = f"serial://{new.port}"

    def open_cell(ns):  # the arm is the in-process simulation; the tracker the real driver
        assert ns.robot == "ur://10.0.0.5" and ns.tracker == new_url
        return cell, robot, SerialTracker(ns.tracker[len("serial://") :]), None

    monkeypatch.setattr(resume, "open_cell", open_cell)
    return new_url


def test_a_tracker_on_a_new_serial_port_is_the_same_cell_if_its_serial_number_is(
    geocom_cell, monkeypatch, capsys
):
    rec, *_, old_url, _ = geocom_cell
    session = read_recording(rec).session
    assert session["tracker"]["serial_number"] == 900001
    assert session["tracker"]["instrument_name"] == "SIM GeoCOM tracker"
    new_url = _replug(geocom_cell, monkeypatch, 900001)
    assert new_url != old_url
    capsys.readouterr()
    assert _resume(rec, "--tracker", new_url) == 0
    err = capsys.readouterr().err
    said = [x for x in err.splitlines() if "tracker_port" in x]
    assert len(said) == 1, err
    assert (
        f"the tracker's port changed: {old_url} when {rec} was recorded, {new_url} now" in said[0]
    )
    assert "same instrument, serial number 900001 (SIM GeoCOM tracker)" in said[0]
    new = read_recording(rec.with_name("real.resumed1.mcap"))
    assert new.session["campaign"]["tracker_url"] == new_url  # where it is now
    assert any(e["kind"] == "tracker_port" for e in new.events)
    assert not set(_pose_ids(rec)) & {s["pose_id"] for s in new.samples}


def test_another_tracker_is_refused_on_a_new_port_too(geocom_cell, monkeypatch, capsys):
    rec = geocom_cell[0]
    new_url = _replug(geocom_cell, monkeypatch, 900002)
    capsys.readouterr()
    assert _resume(rec, "--tracker", new_url) == 2
    err = capsys.readouterr().err
    errors = _error_lines(err)
    assert len(errors) == 1 and "Traceback" not in err, err
    assert "recorded with the tracker serial number 900001" in errors[0]
    assert f"the one connected at {new_url} is serial number 900002" in errors[0]
    assert not rec.with_name("real.resumed1.mcap").exists()


@pytest.mark.parametrize(
    ("recorded", "connected", "url", "said"),
    [
        # same port, same instrument: nothing to say
        ({"serial_number": 7}, {"serial_number": 7}, "serial:///dev/ttyUSB0", None),
        # re-plugged
        ({"serial_number": 7}, {"serial_number": 7}, "serial:///dev/ttyUSB1", "port changed"),
        # another instrument, on the same port or another
        ({"serial_number": 7}, {"serial_number": 8}, "serial:///dev/ttyUSB0", "serial number 8"),
        ({"serial_number": 7, "instrument_name": "AT960"},
         {"serial_number": 7, "instrument_name": "AT403"}, "serial:///dev/ttyUSB1", "(AT403)"),
        # an older recording (no serial number): the same port only
        ({}, {"serial_number": 7}, "serial:///dev/ttyUSB0", None),
        ({}, {"serial_number": 7}, "serial:///dev/ttyUSB1", "does not record the tracker's"),
        # an instrument that does not say: the same port only
        ({"serial_number": 7}, {}, "serial:///dev/ttyUSB1", "does not give its serial number"),
        # its corrections changed since (a protocol audit: they were not recorded): refused;
        # another station (absorbed by the fitted base) or an unknown setup is not
        ({"serial_number": 7, "setup": {"prism_constant_m": 0.0}},
         {"serial_number": 7, "setup": {"prism_constant_m": -0.0344}}, "serial:///dev/ttyUSB0",
         "its prism constant is -34.4 mm now, 0 mm when recorded"),
        # the ppm follows the air: a warning at the campaign's start (setup_changed), not this
        ({"serial_number": 7, "setup": {"atm_ppm": 0.0}},
         {"serial_number": 7, "setup": {"atm_ppm": 12.5}}, "serial:///dev/ttyUSB0", None),
        ({"serial_number": 7, "setup": {"station_enh_m": [0, 0, 0], "atm_ppm": 1.0}},
         {"serial_number": 7, "setup": {"station_enh_m": [5, 0, 0], "atm_ppm": 1.0}},
         "serial:///dev/ttyUSB0", None),
        ({"serial_number": 7}, {"serial_number": 7, "setup": {"atm_ppm": 3.0}},
         "serial:///dev/ttyUSB0", None),
    ],
)  # fmt: skip
def test_check_same_tracker(recorded, connected, url, said):
    from workcell.campaign.run import check_same_tracker
    from workcell.errors import UserError

    same = {"source": "x.mcap", "url": "serial:///dev/ttyUSB0", **recorded}
    if said is None:
        assert check_same_tracker(same, connected, url) is None
    elif said == "port changed":
        line = check_same_tracker(same, connected, url)
        assert "port changed: serial:///dev/ttyUSB0 when x.mcap was recorded" in line
        assert "\n" not in line
    else:
        with pytest.raises(UserError, match=re.escape(said)):
            check_same_tracker(same, connected, url)


def test_check_same_cell_lets_a_new_tracker_port_through_but_not_another_robot():
    """The terminal UI's check before it connects: the serial number decides later."""
    from workcell.campaign.resume import check_same_cell
    from workcell.errors import UserError

    camp = {"robot_url": "ur://10.0.0.5", "tracker_url": "serial:///dev/ttyUSB0"}
    kw = dict(effects=None, sim_seed=None)
    check_same_cell(camp, "x.mcap", robot_url="ur://10.0.0.5",
                    tracker_url="serial:///dev/ttyUSB1", **kw)  # fmt: skip
    with pytest.raises(UserError, match="robot at ur://10.0.0.5"):
        check_same_cell(camp, "x.mcap", robot_url="ur://10.0.0.6",
                        tracker_url="serial:///dev/ttyUSB1", **kw)  # fmt: skip


def test_a_resumed_simulated_cell_draws_new_noise_on_the_same_truth(tmp_path, monkeypatch):
    """A resume of a simulated campaign re-created the simulated cell with the first run's noise
    stream (a replay of its readings' noise, not a new run: the same pose measured first in both
    gave bit-identical readings, which the fits set aside as an "exact copy"). Now the resume
    asks for noise stream k (k files in the chain) on the same simulated truth."""
    import sim_devices.cell as sc

    streams = []
    real = sc.sim_cell

    def spy(*a, **kw):
        streams.append(kw.get("noise_stream", 0))
        return real(*a, **kw)

    first = tmp_path / "ref.mcap"
    _campaign(first, 2)
    monkeypatch.setattr(sc, "sim_cell", spy)
    assert _resume(first, "--out", str(tmp_path / "ref.resumed.mcap")) == 0
    assert streams == [1]
    # same truth, other noise: the same pose read in both streams differs by the noise only
    readings = []
    for k in (0, 1):
        world, robot, tracker, _ = real("ur5e", "none", 1, beam_break_prob=0.0, noise_stream=k)
        robot.connect()
        tracker.connect()
        robot.move_joints(np.array([0.3, -1.2, 1.1, -1.4, -1.5, 0.2]), 1.0, 2.0)
        readings.append(tracker.measure().position_m)
    d = np.linalg.norm(readings[0] - readings[1])
    assert 0 < d < 1e-3, d


def test_a_resume_says_a_damaged_chunk_is_measured_again(tmp_path):
    """A byte flipped inside a chunk of the file a resume continues: the resume measured the
    lost poses again without a word. Now a `damaged` warning says so (and is recorded)."""
    first = tmp_path / "d.mcap"
    _campaign(first, 8)
    data = first.read_bytes()
    for at in range(len(data) // 3, len(data), 97):  # a byte inside a chunk
        bad = bytearray(data)
        bad[at] ^= 0xFF
        first.write_bytes(bytes(bad))
        try:
            r = read_recording(first)
        except Exception:  # noqa: BLE001 - the header or session hit: try another byte
            continue
        if any("damaged chunk" in p for p in r.problems):
            break
    else:
        pytest.skip("no byte inside a chunk found")
    out = tmp_path / "d.resumed.mcap"
    assert _resume(first, "--out", str(out)) == 0
    events = read_recording(out).events
    assert any(e["kind"] == "damaged" and "measured again" in e["message"] for e in events), [
        e["kind"] for e in events
    ]


def test_a_resume_of_a_simulated_campaign_refuses_a_time_scale(chain, capsys):
    """--time-scale on a resume of an in-process simulated campaign had no effect, silently."""
    assert _resume(chain / "x.resumed1.mcap", "--time-scale", "20") == 2
    err = [x for x in capsys.readouterr().err.splitlines() if ": error:" in x]
    assert len(err) == 1 and "--time-scale 20:" in err[0] and "virtual time" in err[0], err


def test_a_resume_prints_a_line_per_pose_as_a_first_run_does(chain, capsys):
    """A resumed campaign printed no per-pose progress (a first run prints one line a pose)."""
    capsys.readouterr()
    assert _resume(chain / "x.resumed1.mcap") == 0
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if re.match(r"pose +\d+ +\d+/\d+ more", x)]
    left = POSES - len(_pose_ids(chain / "x.mcap")) - len(_pose_ids(chain / "x.resumed1.mcap"))
    assert len(lines) == left and lines[-1].split()[2] == f"{left}/{left}", err[-1500:]


def test_resuming_a_file_already_continued_is_refused_in_one_line(chain, capsys):
    """After a resume that was itself interrupted, the operator's first command typed again
    (`--resume x.mcap`) forked the chain: x.resumed2.mcap continued x.mcap, measured
    x.resumed1.mcap's poses again and left that file out of every later chain (crash audit)."""
    first, second = chain / "x.mcap", chain / "x.resumed1.mcap"
    before = {p.name: _sha(p) for p in chain.iterdir()}
    capsys.readouterr()
    assert _resume(first) == 2
    err = capsys.readouterr().err
    errors = _error_lines(err)
    assert len(errors) == 1 and "Traceback" not in err, err
    assert f"{second} already continues {first} (3 poses measured there)" in errors[0]
    assert f"--resume {second}" in errors[0]
    assert {p.name: _sha(p) for p in chain.iterdir()} == before  # nothing written
    # a continuation with no pose (stopped at its start) loses nothing: not refused
    (chain / "x.resumed2.mcap").write_bytes(b"")
    shutil.move(second, chain.parent / "away.mcap")
    assert _resume(first, "--out", str(chain / "y.mcap")) == 0
    assert set(_pose_ids(chain / "y.mcap")) == set(range(3, POSES))


def test_an_empty_resume_file_points_at_the_file_it_was_to_continue(chain, capsys):
    """A resume killed right after creating its file left it empty; resuming that file said
    "delete it and start the campaign again", which throws away x.mcap's poses."""
    empty = chain / "x.resumed2.mcap"
    empty.write_bytes(b"")
    capsys.readouterr()
    assert _resume(empty) == 2
    line = _error_lines(capsys.readouterr().err)[0]
    assert "start the campaign again" not in line, line
    assert f"delete {empty}" in line and f"--resume {chain / 'x.resumed1.mcap'}" in line, line


def test_a_recording_still_being_written_is_not_resumed(chain, capsys):
    """A resume of a file another campaign still writes measured the same poses twice, in two
    files (crash audit: 7 of 7 accepted). The writer's lock tells it."""
    from workcell.recording.writer import RecordingWriter, being_written

    live = chain / "live.mcap"
    w = RecordingWriter(live, read_recording(chain / "x.mcap").session)
    try:
        assert being_written(live)
        capsys.readouterr()
        assert _resume(live) == 2
        line = _error_lines(capsys.readouterr().err)[0]
        assert "is still being written by a running campaign" in line, line
    finally:
        w.close()
    assert not being_written(live) and not being_written(chain / "x.mcap")


def test_a_resume_on_a_replugged_port_keeps_the_recorded_link_settings():
    """Typed as the refusal suggests (`--tracker serial:///dev/ttyUSB1`), a resume dropped the
    recorded `?baud=9600&timeout=15`, and the instrument stayed silent at 115200 baud (a
    review)."""
    from workcell.campaign.resume import with_recorded_link

    rec = "serial:///dev/ttyUSB0?baud=9600&timeout=15"
    assert with_recorded_link(rec, "serial:///dev/ttyUSB1") == (
        "serial:///dev/ttyUSB1?baud=9600&timeout=15"
    )
    assert with_recorded_link(rec, "serial:///dev/ttyUSB1?baud=19200") == (
        "serial:///dev/ttyUSB1?baud=19200"
    )
    assert with_recorded_link("serial:///dev/ttyUSB0", "serial:///dev/ttyUSB1") == (
        "serial:///dev/ttyUSB1"
    )


def test_setup_changed_says_which_correction_moved():
    from workcell.campaign.run import setup_changed

    rec, now = {"atm_ppm": 0.0, "prism_constant_m": 0.0}, {"atm_ppm": 12.5, "prism_constant_m": 0.0}
    assert setup_changed(rec, now, "atm_ppm") == (
        "atmospheric correction is 12.5 ppm now, 0 ppm when recorded"
    )
    assert setup_changed(rec, now, "prism_constant_m") is None
    assert setup_changed(None, now, "atm_ppm") is None
