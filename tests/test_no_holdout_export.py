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


def test_fit_json_without_holdout_puts_nothing_under_held_out_keys(tmp_path, capsys):
    """`fit --holdout 0 --json` gave the training figures under `heldout_rms_m`,
    `heldout_max_m`, ... (audit 2026-11-26): a script reading them took in-sample numbers for
    held-out ones. They are now null, the figures under `train_*`; the text says "train RMS"."""
    import json

    rec = tmp_path / "c.mcap"
    argv = ["campaign", "--effects", "none", "--seed", "3", "--poses", "16", "--readings", "2"]
    assert main([*argv, "--out", str(rec)]) == 0
    capsys.readouterr()
    assert main(["fit", str(rec), "--holdout", "0", "--json", "--out", str(tmp_path / "a")]) == 0
    r = json.loads(capsys.readouterr().out)
    for k in ("rms_m", "rms_ci95_m", "max_m", "median_m"):
        assert r[f"heldout_{k}"] is None and r[f"train_{k}"] is not None, k
    assert r["evaluated_on"] == "training poses (no hold-out)"
    assert main(["fit", str(rec), "--holdout", "0", "--out", str(tmp_path / "b")]) == 0
    text = capsys.readouterr().out
    line = next(x for x in text.splitlines() if x.startswith("calibrated"))
    assert "train RMS" in line and f"{r['train_rms_m'] * 1e6:.1f} um" in line
