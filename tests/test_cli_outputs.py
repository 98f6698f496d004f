"""Output paths that cannot be written are refused in one line before any work starts."""

from __future__ import annotations

import pytest

from workcell.cli import main


@pytest.mark.parametrize(
    "argv, match",
    [
        (["fit", "{rec}", "--method", "dh", "--out", "{file}/m.json"], "is a file, not a folder"),
        (["fit", "{rec}", "--method", "dh", "--out", "{dir}"], "is a folder; give a file name"),
        (["export", "{rec}", "--format", "table", "--out", "{file}/t"], "is a file, not a folder"),
        (["replay", "{rec}", "--online", "ekf-ann", "--save", "{file}/e.json"], "not a folder"),
        (["demo", "--out", "{file}"], "exists and is a file; give a folder"),
        (
            [
                "campaign",
                "--robot",
                "sim",
                "--tracker",
                "sim",
                "--poses",
                "3",
                "--out",
                "{file}/c.mcap",
            ],
            "is a file, not a folder",
        ),
    ],
)
def test_unwritable_output_refused_first(tmp_path, capsys, argv, match):
    f = tmp_path / "afile"
    f.write_text("keep me")
    d = tmp_path / "adir"
    d.mkdir()
    fill = {"rec": str(tmp_path / "missing.mcap"), "file": str(f), "dir": str(d)}
    rc = main([a.format(**fill) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and match in err[0], err
    assert f.read_text() == "keep me" and list(d.iterdir()) == []
