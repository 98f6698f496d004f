"""A model fitted with --holdout 0 has no held-out figure of what it leaves unexplained: `export`
says so where it states that figure for other models (audit 2026-11-26: the line was dropped
without a word, while the table's files said it)."""

from workcell.cli import main


def test_export_of_a_model_without_holdout_says_it_states_nothing_held_out(tmp_path, capsys):
    rec, model = tmp_path / "c.mcap", tmp_path / "m.json"
    argv = ["campaign", "--effects", "none", "--seed", "3", "--poses", "16", "--readings", "2"]
    assert main([*argv, "--out", str(rec)]) == 0
    assert main(["fit", str(rec), "--holdout", "0", "--out", str(model)]) == 0
    capsys.readouterr()
    assert main(["export", str(model), "--format", "table", "--out", str(tmp_path / "t")]) == 0
    out = capsys.readouterr().out
    assert "not in that 1-sigma: what the model leaves unexplained (its file states no " in out
    assert "held-out poses: none: fitted with --holdout 0" in out
