"""A resumed recording is estimated with every file it continues: `Dataset.from_recording` (and
so fit, diagnose, replay, info and the model files) follows the `chained_from` chain back, each
link's sha256 checked, and uses the poses of every file, saying so; a link missing or changed is
refused in one line naming it, never silently dropped (`--chain-missing ignore` leaves it out,
with a warning)."""

import ast
import hashlib
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from simdata import aborted_sim_campaign

from workcell.recording.reader import read_recording

POSES = 24
REF = 4  # the reference pose (plan pose 0) measured again after every 4 poses


def _campaign(out, stop_after: int, noise_stream: int = 0, **kw):
    """A simulated campaign (virtual time) aborted after `stop_after` samples; each run of a
    chain draws its own tracker noise (`noise_stream`), as a resume does."""
    kw.setdefault("reference_every", REF)
    return aborted_sim_campaign(out, stop_after, poses=POSES, noise_stream=noise_stream, **kw)


def _resume(old: Path, new: Path, stop_after: int, noise_stream: int, **kw) -> None:
    from workcell.campaign.resume import continuation, resume_plan

    info = resume_plan(str(old), **kw)
    _campaign(new, stop_after, noise_stream, **continuation(info, old))


@pytest.fixture(scope="module")
def chain_dir(tmp_path_factory):
    """x.mcap (died after 7 samples), x.resumed1.mcap (its resume, died after 6 more) and
    x.resumed2.mcap (the resume of that, run to the end)."""
    d = tmp_path_factory.mktemp("chain")
    _campaign(d / "x.mcap", 7)
    _resume(d / "x.mcap", d / "x.resumed1.mcap", 6, 1)
    _resume(d / "x.resumed1.mcap", d / "x.resumed2.mcap", 10_000, 2)
    return d


@pytest.fixture
def chain(chain_dir, tmp_path):
    d = tmp_path / "cell"
    shutil.copytree(chain_dir, d)
    return d


FILES = ("x.mcap", "x.resumed1.mcap", "x.resumed2.mcap")


def _samples(d: Path) -> list[list[dict]]:
    return [read_recording(d / f).samples for f in FILES]


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _main(*argv) -> int:
    from workcell.cli import main

    return main([str(a) for a in argv])


def _split(out: str) -> int:
    """Train + held-out poses of a fit's report."""
    m = re.search(r"^poses +(\d+) train, (\d+) held out", out, re.M)
    return int(m[1]) + int(m[2])


def _error_lines(err: str) -> list[str]:
    return [x for x in err.splitlines() if ": error:" in x]


def test_a_resumed_recording_is_loaded_with_every_file_of_its_chain(chain):
    from workcell.recording.dataset import Dataset, distinct_poses

    per = _samples(chain)
    every = [s for f in per for s in f]
    assert all(len(f) for f in per) and len(every) > POSES  # the reference measured again too
    ds = Dataset.from_recording(chain / FILES[-1])
    assert len(ds) == len(every)
    assert ds.pose_id.tolist() == [s["pose_id"] for s in every]
    assert set(ds.pose_id.tolist()) == set(range(POSES))
    assert distinct_poses(ds.q_commanded) == POSES
    assert [s["index"] for s in every] == list(range(len(every)))  # resume's own contract
    assert ds.row.tolist() == list(range(len(every)))
    assert np.all(np.diff(ds.elapsed_s) > 0), "the chain's samples out of measurement order"
    counts = " + ".join(str(len(f)) for f in per)
    assert ds.chain_line == f"x.resumed2.mcap continues x.mcap, x.resumed1.mcap: {counts} poses"
    assert [f["path"] for f in ds.chain] == [str((chain / f).resolve()) for f in FILES]
    assert [f["sha256"] for f in ds.chain] == [_sha(chain / f) for f in FILES]
    assert [f["samples"] for f in ds.chain] == [len(f) for f in per]
    prov = ds.subset(np.arange(5)).provenance()  # a fit's training subset keeps it
    assert prov["recording_sha256"] == _sha(chain / FILES[-1])
    assert [f["sha256"] for f in prov["recording_chain"]] == [_sha(chain / f) for f in FILES]
    # the reference pose, measured in every file, stays on one side of the split
    _, test = ds.holdout_split(0.25)
    ref = np.flatnonzero(ds.pose_id == 0)
    assert len({int(i in test) for i in ref}) == 1 and len(ref) >= 4


def test_a_single_recording_is_loaded_as_before(chain):
    from workcell.recording.dataset import Dataset

    ds = Dataset.from_recording(chain / "x.mcap")
    assert len(ds) == len(read_recording(chain / "x.mcap").samples)
    assert ds.chain == () and ds.chain_line == ""
    assert set(ds.provenance()) == {"recording", "recording_sha256"}


def test_the_reference_pose_drift_spans_the_chain(chain):
    from workcell.recording.repeats import repeats_of

    every = [s for f in _samples(chain) for s in f]
    (r,) = repeats_of(read_recording(chain / FILES[-1]))
    assert r["pose_id"] == 0
    assert r["measurements"] == sum(s["pose_id"] == 0 for s in every)
    assert r["elapsed_s"][0] == pytest.approx(every[0]["elapsed_s"])


def test_fit_uses_and_names_every_file_and_its_model_records_them(chain, monkeypatch, capsys):
    monkeypatch.chdir(chain)
    n = sum(len(f) for f in _samples(chain))
    capsys.readouterr()
    assert _main("fit", FILES[-1], "--out", "m.json") == 0
    out = capsys.readouterr().out
    assert "chain           x.resumed2.mcap continues x.mcap, x.resumed1.mcap: " in out, out
    assert _split(out) == n, out
    info = json.loads((chain / "m.json").read_text())["info"]
    assert info["recording_sha256"] == _sha(chain / FILES[-1])
    assert [f["sha256"] for f in info["recording_chain"]] == [_sha(chain / f) for f in FILES]
    assert [Path(f["path"]).name for f in info["recording_chain"]] == list(FILES)
    assert _main("fit", FILES[-1], "--out", "m.json", "--json") == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["train_poses"] + rep["heldout_poses"] == n
    assert [Path(f["path"]).name for f in rep["recording_chain"]] == list(FILES)


def test_replay_streams_every_file_of_the_chain(chain):
    from workcell.commands.replay import screened_samples

    every = [s for f in _samples(chain) for s in f]
    got, ds = screened_samples(read_recording(chain / FILES[-1], streams=False), "x")
    assert [s["index"] for s in got] == [s["index"] for s in every]
    assert len(ds.chain) == 3


def test_info_reports_the_chain_total(chain, capsys):
    per = [len(f) for f in _samples(chain)]
    capsys.readouterr()
    assert _main("info", chain / FILES[-1]) == 0
    out = capsys.readouterr().out
    assert f"chain       {sum(per)} samples in 3 files" in out, out
    assert _main("info", chain / FILES[-1], "--json") == 0
    d = json.loads(capsys.readouterr().out)
    assert d["chain"]["samples"] == sum(per) and d["chain"]["problem"] is None


@pytest.mark.parametrize("damage", ["missing", "changed"])
def test_a_missing_or_changed_link_is_refused_in_one_line(chain, monkeypatch, capsys, damage):
    monkeypatch.chdir(chain)
    first = chain / "x.mcap"
    if damage == "missing":
        shutil.move(first, chain.parent / "x.mcap.away")
        said = "continues x.mcap ("
    else:
        with open(first, "ab") as f:
            f.write(b"\0")
        said = "but that file has changed since"
    capsys.readouterr()
    for argv in (
        ("fit", FILES[-1], "--out", "m.json"),
        ("diagnose", FILES[-1]),
        ("replay", FILES[-1], "--online", "ekf-ann"),
    ):
        assert _main(*argv) == 2, argv
        err = capsys.readouterr().err
        errors = _error_lines(err)
        assert len(errors) == 1 and "Traceback" not in err, err
        assert said in errors[0] and "--chain-missing ignore" in errors[0], errors[0]
    assert not (chain / "m.json").exists()
    assert _main("info", FILES[-1]) == 0
    assert "chain       fits refuse this file: " in capsys.readouterr().out

    # the operator's choice: the files after the broken link, said so
    kept = sum(len(read_recording(chain / f).samples) for f in FILES[1:])
    assert _main("fit", FILES[-1], "--out", "m.json", "--chain-missing", "ignore") == 0
    cap = capsys.readouterr()
    assert "left out (--chain-missing ignore)" in cap.err, cap.err
    assert _split(cap.out) == kept, cap.out


def test_a_chain_cut_by_remeasure_missing_is_used_from_there_on(chain):
    """`campaign --resume --remeasure-missing` measured a lost file's poses again: the chain
    ends there by the operator's choice; fits use the files from there on, with a note."""
    from workcell.recording.dataset import Dataset

    (chain / "x.resumed2.mcap").unlink()
    shutil.move(chain / "x.mcap", chain.parent / "x.mcap.away")
    _resume(chain / "x.resumed1.mcap", chain / "x.resumed2.mcap", 10_000, 3, remeasure_missing=True)
    ds = Dataset.from_recording(chain / "x.resumed2.mcap")
    assert set(ds.pose_id.tolist()) == set(range(POSES))
    assert len(ds.chain) == 2
    assert any("measured again in x.resumed2.mcap" in n for n in ds.read_notes), ds.read_notes


def test_recording_and_estimation_do_not_import_the_campaign():
    """drivers -> campaign -> recording -> estimation: the chain is read in workcell.recording."""
    root = Path(__file__).resolve().parents[1] / "workcell"
    for pkg in ("recording", "estimation"):
        for p in (root / pkg).rglob("*.py"):
            for node in ast.walk(ast.parse(p.read_text())):
                names = (
                    [a.name for a in node.names]
                    if isinstance(node, ast.Import)
                    else [node.module or ""]
                    if isinstance(node, ast.ImportFrom)
                    else []
                )
                assert not any(n.startswith("workcell.campaign") for n in names), p


def test_the_tuis_online_fit_is_fed_every_file_of_the_chain(chain, monkeypatch):
    """The TUI's EKF-ANN fit of a resumed recording fed the filter the newest file's samples
    only, while its data set held the chain's."""
    import importlib
    import types

    from workcell.tui import backend

    fed = []

    class Stop(Exception):
        pass

    class FakeFilter:
        n_init = 1

        @classmethod
        def from_session(cls, session):
            return cls()

        def update(self, smp):
            fed.append(int(smp["index"]))
            return ""

        def model(self):
            raise Stop

    real = importlib.import_module
    fake = types.SimpleNamespace(LiveFilter=FakeFilter)
    monkeypatch.setattr(
        backend.importlib,
        "import_module",
        lambda name, *a: fake if name == "workcell.estimation.ekf_ann.live" else real(name, *a),
    )
    with pytest.raises(Stop):
        backend._replay(chain / FILES[-1], None, 0.25, chain / "m.json")
    per_file = [{int(s["index"]) for s in f} for f in _samples(chain)]
    assert all(any(i in f for i in fed) for f in per_file), (fed, per_file)
