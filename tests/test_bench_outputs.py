"""A benchmark's output files: written whole (the atomic writer), and only over an earlier result
of the same bench unless --force. `bench discovery --out FILE` used to write over any file (a
fitted model was replaced by bench JSON); `bench lddmm-pendulum --out DIR` over any results.json
and heatmaps.png in DIR."""

from __future__ import annotations

import json

import pytest

from workcell.cli import main

PENDULUM = ["--scenario", "link_lengths", "--max-iter", "2", "--n-steps", "1"]


def test_discovery_refuses_a_file_that_is_not_its_result(tmp_path, capsys):
    model = tmp_path / "m.json"
    model.write_text('{"format": "workcell-model/1", "method": "dh"}')
    before = model.read_bytes()
    rc = main(["bench", "discovery", "--quick", "--out", str(model)])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert "is not a result of `workcell bench discovery`" in err[0] and "--force" in err[0]
    assert model.read_bytes() == before


def test_discovery_counts_poses_it_can_diagnose(capsys):
    """--poses 20 was accepted, then every case failed with "diagnosis needs at least 40"."""
    rc = main(["bench", "discovery", "--quick", "--poses", "20"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--poses must be 40..5000, got 20" in err[0], err


@pytest.mark.parametrize(
    "doc, bench",
    [
        ({"bench": "discovery", "x": 1}, "discovery"),
        ({"master_seed": 1, "cases": {}, "environment": {}}, "discovery"),  # before the key
        ({"bench": "lddmm-pendulum"}, "lddmm-pendulum"),
        ({"scenarios": {}, "heatmap_png": "h.png", "environment": {}}, "lddmm-pendulum"),
        ({"format": "workcell-model/1"}, None),
        ([1, 2], None),
    ],
)
def test_which_bench_wrote_a_result(tmp_path, doc, bench):
    from workcell.bench import result_of

    p = tmp_path / "r.json"
    p.write_text(json.dumps(doc))
    assert result_of(p) == bench
    assert result_of(tmp_path / "missing.json") is None


def test_an_earlier_result_is_replaced_and_said(tmp_path):
    from workcell.bench import check_bench_outputs
    from workcell.errors import UserError

    p = tmp_path / "d.json"
    p.write_text(json.dumps({"bench": "discovery"}))
    said: list[str] = []
    check_bench_outputs([p], "discovery", p, force=False, say=said.append)
    assert said == [f"replacing {p}: an earlier `workcell bench discovery` result"]
    with pytest.raises(UserError, match="not a result of `workcell bench lddmm-pendulum`"):
        check_bench_outputs([p], "lddmm-pendulum", p, force=False, say=said.append)


def test_pendulum_replaces_its_own_results_only(tmp_path, capsys):
    d = tmp_path / "out"
    d.mkdir()
    (d / "heatmaps.png").write_bytes(b"someone's picture")
    rc = main(["bench", "lddmm-pendulum", "--out", str(d), *PENDULUM])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "heatmaps.png exists and is not a result" in err[0], err
    assert (d / "heatmaps.png").read_bytes() == b"someone's picture"

    assert main(["bench", "lddmm-pendulum", "--out", str(d), "--force", *PENDULUM]) == 0
    assert "replacing" in capsys.readouterr().out
    assert (d / "heatmaps.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    doc = json.loads((d / "results.json").read_text())
    assert doc["bench"] == "lddmm-pendulum" and "link_lengths" in doc["scenarios"]

    assert main(["bench", "lddmm-pendulum", "--out", str(d), *PENDULUM]) == 0
    out = capsys.readouterr().out
    assert "an earlier `workcell bench lddmm-pendulum` result" in out
    assert sorted(p.name for p in d.iterdir()) == ["heatmaps.png", "results.json"]  # no temps


def test_a_long_name_is_written_and_a_too_long_one_refused_before_the_work(tmp_path, capsys):
    """The atomic writer's temporary name adds 14 characters: a 250-character output name was
    refused after the work, naming the temporary file. Now any name the file system takes is
    written, and one it cannot take is refused first, in one line."""
    from workcell.atomic import write_text
    from workcell.errors import UserError, check_output_path

    p = tmp_path / ("m" * 250 + ".json")
    write_text(p, "{}")
    assert p.read_text() == "{}" and [q.name for q in tmp_path.iterdir()] == [p.name]
    with pytest.raises(UserError, match=r"is 305 bytes long, and the file system takes at most"):
        check_output_path(tmp_path / ("m" * 300 + ".json"), "model file")


def test_bench_all_takes_no_options_and_skips_a_missing_default_recording(
    tmp_path, monkeypatch, capsys
):
    """`bench all --repeats 1` ran dh with it, then failed at the next benchmark (its help was
    dh's); `bench all` from an installed package failed at design-real, whose default recording
    is ../shared beside a source checkout (packaging audit)."""
    import workcell.bench.design_real as dr
    import workcell.commands.bench as cb
    from workcell.cli import main

    assert main(["bench", "all", "--repeats", "1"]) == 2
    err = capsys.readouterr().err
    assert "takes no options (got --repeats 1)" in err and "Traceback" not in err
    assert main(["bench", "all", "--help"]) == 0
    assert "each has its own options" in capsys.readouterr().out
    monkeypatch.setattr(cb, "BENCHES", {"design-real": "workcell.bench.design_real"})
    monkeypatch.setattr(dr, "DEFAULT_RECORDING", tmp_path / "not-here.mcap")
    assert main(["bench", "all"]) == 0
    out = capsys.readouterr().out
    assert "[bench design-real] skipped: its default recording" in out, out
