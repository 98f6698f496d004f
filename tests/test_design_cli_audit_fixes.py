"""Audit fixes: the `--plan bo` dry run, and `workcell bench design`'s option handling.

A `--plan bo` dry run stopped after its first lines (exit 0): no "nothing moved" line, no reason
why the poses are not listed, no pose-count warning, and `--reference-every` ignored. Now what
does not need the poses runs for bo too. `bench design` printed numpy's "zero-size array" for
`--plans ,`, ran duplicated plans twice into one entry, ignored `--half-width-deg` without
`--envelope compact` and `--small-errors` without `--robot wam7`, did not name `--seed0` in its
error, showed no defaults in `--help`, and called `--holdout 0.25` an "invalid int value"."""

from __future__ import annotations

import pytest

from workcell.cli import main

DRY = ["campaign", "--robot", "sim", "--tracker", "sim", "--effects", "none", "--dry-run"]


def test_a_bo_dry_run_says_why_no_poses_and_what_it_can_check(capsys):
    argv = [*DRY, "--poses", "5", "--seed", "3", "--out", "x.mcap"]
    assert main([*argv, "--plan", "bo", "--reference-every", "2"]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0].startswith("plan bo: adaptive;")
    assert "bo chooses each pose from the position errors measured so far" in out
    assert "cannot be listed before the campaign" in out
    assert "dry run: 5 poses, chosen during the campaign; nothing moved" in out
    assert "the first move is checked from the simulated arm's start posture" in out
    # the live campaign measures the plan's first pose (pose 0) again: 5 poses, every 2 -> 3
    assert (
        "reference: pose 0 (the first pose bo chooses) measured again after every 2 poses and "
        "at the end (3 more measurements;" in out
    )
    assert (
        "warning: too few poses to fit (5): a fit needs at least 12 training poses, 16 poses "
        "with the default 25 % held out" in out
    )
    assert "warning: 5 poses leave at least 10 of the 25 parameters" in out
    assert "a point tracker needs at least 9 poses" in out
    # still no pose list, and no preview word (tests/test_design_plans.py)
    assert not any(ln.startswith("pose ") for ln in lines) and "preview" not in out
    # the same warning as a listed plan's, whose dry run is as it was
    assert main([*argv, "--plan", "random"]) == 0
    out = capsys.readouterr().out
    assert "dry run: 5 poses, 0 problems; nothing moved" in out
    assert out.count("warning: too few poses to fit (5): a fit needs at least 12 training") == 1
    assert "chosen during the campaign" not in out


def test_the_tui_plan_check_of_bo_gives_the_pose_count_warnings():
    """The TUI's Plan screen check of a bo plan (no preview) gave nothing but "adaptive"."""
    from workcell.tui import backend

    dev = backend.open_devices(backend.DeviceConfig(effects="none", seed=3))
    try:
        res = backend.dry_run(backend.PlanConfig(kind="bo", poses=5, out="x.mcap"), dev)
    finally:
        dev.close()
    assert res["adaptive"] and res["ok"]
    warnings = res["identification"]
    assert any(w.startswith("warning: too few poses to fit (5)") for w in warnings), warnings
    assert any("5 poses leave at least 10 of the 25 parameters" in w for w in warnings), warnings


def test_a_bo_dry_run_with_enough_poses_warns_of_nothing(capsys):
    assert main([*DRY, "--plan", "bo", "--poses", "30"]) == 0
    out = capsys.readouterr().out
    assert "dry run: 30 poses, chosen during the campaign; nothing moved" in out
    assert "warning" not in out and "reference:" not in out


def bench_design(capsys, *argv):
    capsys.readouterr()
    try:
        rc = main(["bench", "design", *argv])
    except SystemExit as e:
        rc = e.code
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err + cap.out and "Warning" not in cap.err
    return rc, cap.err.strip().splitlines(), cap.out


@pytest.mark.parametrize(
    "argv, match",
    [
        (["--plans", ","], "give at least one of random,dopt,vopt,bo"),
        (["--plans", " , "], "names no plan"),
        (["--plans", "random,random"], "--plans names random more than once; give each plan once"),
        (["--seed0", "-1"], "--seed0 must be 0..4_294_967_295, got -1"),
        (["--half-width-deg", "30"], "--half-width-deg goes with --envelope compact"),
        (["--small-errors"], "--small-errors goes with --robot wam7"),
        (["--robot", "ur5e", "--small-errors"], "--small-errors goes with --robot wam7"),
        (["--holdout", "0.25"], "a fraction, as `workcell fit --holdout` takes"),
        (["--holdout", "0.25"], "the number of held-out poses per simulated cell"),
        (["--holdout", "5"], "--holdout must be 10..100_000, got 5"),
        (["--seeds", "0"], "--seeds must be 1..1_000, got 0"),
        # counts far beyond any run gave numpy's words or ran for days (audit 2026-11-26)
        (["--max-poses", str(10**30)], "--max-poses must be 12..5_000, got 1e+30"),
        (["--target-factor", "1e300"], "--target-factor must be 0.001..1000, got 1e+300"),
    ],
)
def test_bench_design_refuses_in_one_line(capsys, argv, match):
    rc, err, _ = bench_design(capsys, *argv)
    assert rc == 2 and len(err) == 1 and match in err[0], (rc, err)
    assert err[0].startswith("workcell bench design: error: ")


class Ran(Exception):
    pass


def test_bench_design_takes_its_options_where_they_apply(capsys, monkeypatch):
    """The options it refuses alone pass its checks with what they go with, and reach the run
    (the runs are not made here)."""
    from workcell.bench import design

    def one_run(*a, **k):
        raise Ran(a)

    monkeypatch.setattr(design, "one_run", one_run)
    rc, err, _ = bench_design(capsys, "--half-width-deg", "20")
    assert rc == 2 and len(err) == 1 and "--half-width-deg goes with" in err[0], err
    for argv, want in (
        (["--envelope", "compact", "--half-width-deg", "20"], ("random", 0, 80, 100)),
        (["--robot", "wam7", "--small-errors", "--seed0", "3"], ("random", 3, 80, 100)),
        (["--holdout", "10", "--plans", "bo,random"], ("bo", 0, 80, 10)),
    ):
        with pytest.raises(Ran) as e:
            design.main(["--seeds", "1", *argv])
        plan, seed, max_poses, holdout, _log, _factor, envelope, half, robot, small = e.value.args[
            0
        ]
        assert (plan, seed, max_poses, holdout) == want, argv
        if "--half-width-deg" in argv:
            assert (envelope, half) == ("compact", 20.0)
        if "--small-errors" in argv:
            assert (robot, small) == ("wam7", True)


def test_bench_design_help_shows_the_defaults(capsys):
    rc, _, out = bench_design(capsys, "--help")
    assert rc == 0
    text = " ".join(out.split())
    for s in (
        "number of simulated cells (>= 1; default: 10)",
        "(>= 12; default: 80)",
        "not a fraction as in `workcell fit --holdout` (default: 100)",
        "held-out poses per simulated cell",
        "this x floor (default: 2.0)",
        "half-width around the home pose in deg (default: 30)",
        "(default: random,dopt,vopt,bo)",
    ):
        assert s in text, s


def test_the_ratio_to_random_carries_a_paired_interval():
    """The design benches printed 'ratio best / random 0.85' with no interval (uncertainty audit,
    2026-11-27): a paired bootstrap over the seeds, which holds the point ratio and narrows with
    more seeds."""
    import numpy as np

    from workcell.bench.design import poses_summary, ratio_intervals

    rng = np.random.default_rng(0)

    def summary(n):
        rand = rng.integers(9, 13, n)
        return {
            "random": poses_summary([{"poses_to_target": int(x), "censored": False} for x in rand]),
            "dopt": poses_summary([{"poses_to_target": 9, "censored": False}] * n),
        }

    s10, s100 = summary(10), summary(100)
    lo, hi = ratio_intervals(s10)["dopt"]
    point = s10["dopt"]["mean"] / s10["random"]["mean"]
    assert lo < point < hi and hi - lo < 0.3
    lo2, hi2 = ratio_intervals(s100)["dopt"]
    assert hi2 - lo2 < hi - lo
    assert ratio_intervals({"dopt": s10["dopt"]}) == {}  # no random baseline: no ratio
