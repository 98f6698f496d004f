"""What the online EKF-ANN says about its own estimate (audit 2026-11-26).

1. Its base offsets are relative to its own registration `base_ref` (not `fit`'s): the estimate
   carries `base_ref`, the combined `tracker_T_base` (with std) and `parameter_frames`, and a state
   that stands for a dependent group is marked as `workcell fit` marks it (`stands_for`, `*`).
2. `campaign --online ekf-ann` ends with the estimate, or a line saying the filter never started.
3. The model file stores the declared SMR offset as `info.nominal_tool_m`, the TCP an export
   commands with (it fell back to the filter's fitted SMR, theta[36:39]).
4. The geometric states are the filter's split between geometry and network: the estimate gives
   the RMS of the geometry alone beside the whole model's, and the text says the parameters are
   not comparable one by one with `fit`'s.
"""

from __future__ import annotations

import numpy as np
import pytest

from workcell.estimation.ekf_ann.filter import FilterConfig
from workcell.estimation.ekf_ann.live import LiveFilter
from workcell.kinematics.chain import IDX, PARAMETER_FRAMES, p_tracker, pack, tracker_T_base
from workcell.kinematics.frames import quat_wxyz_from_matrix
from workcell.kinematics.robots import robot_by_name

TOOL_M = np.array([0.004, -0.003, 0.06])  # declared SMR offset
TRUE_TOOL_M = TOOL_M + np.array([2e-4, -1e-4, 3e-4])  # the real one, which the filter fits
N_INIT = 30
N = 45
SIGMA_M = 10e-6


def _base() -> np.ndarray:
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.002, -0.001, 0.7]).as_matrix()
    T[:3, 3] = (2.0, 0.3, -0.2)
    return T


def _samples(seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    spec = robot_by_name("ur5e")
    theta = pack(spec.dh, tool=TRUE_TOOL_M)
    for n, v in (("a2", 3e-4), ("a3", -2e-4), ("alpha2", 2e-4), ("d4", 2e-4)):
        theta[IDX[n]] += v
    q = np.array([0.3, -1.2, 1.0, -1.4, -1.57, 0.0]) + rng.uniform(-0.8, 0.8, (N, 6))
    y = np.asarray(p_tracker(theta, _base(), q)) + SIGMA_M * rng.normal(size=(N, 3))
    return [
        {
            "index": i,
            "q_measured_rad": q[i].tolist(),
            "tracker_position_m": y[i].tolist(),
            "tracker_sigma_m": [SIGMA_M] * 3,
        }
        for i in range(N)
    ]


@pytest.fixture(scope="module")
def replayed():
    cfg = FilterConfig(ann_iter_every=0)  # adaptive: the states the first samples identify
    lf = LiveFilter(
        robot_by_name("ur5e"), TOOL_M, n_init=N_INIT, hidden=4, cfg=cfg, tracker_mpe=None
    )
    for s in _samples():
        lf.update(s)
    return lf


# ---------------------------------------------------------------- 1. frame of the base offsets
def test_estimate_says_the_frame_of_its_base_offsets(replayed):
    est = replayed.estimate()
    f = replayed.filter
    np.testing.assert_array_equal(est["base_ref"], f.base_ref)
    assert est["parameter_frames"] == PARAMETER_FRAMES
    T = np.asarray(tracker_T_base(f.theta, f.base_ref))
    tb = est["tracker_T_base"]
    np.testing.assert_allclose(tb["translation_m"], T[:3, 3], atol=1e-12)
    np.testing.assert_allclose(tb["quaternion_wxyz"], quat_wxyz_from_matrix(T[:3, :3]))
    # the combined base is what compares across models: here with the true one, within its std
    assert all(0 < s < 1e-3 for s in tb["translation_std_m"] + tb["rotation_std_rad"])
    d = np.asarray(tb["translation_m"]) - _base()[:3, 3]
    assert np.all(np.abs(d) < 5 * np.asarray(tb["translation_std_m"]) + 20e-6), d
    # ... the offsets are not: they are from the filter's own registration
    assert "base_ref" in est["base_ref_basis"] and "`workcell fit`" in est["base_ref_basis"]
    assert "first 30 samples" in est["base_ref_basis"]


def test_group_representatives_are_marked_as_fit_marks_them(replayed):
    est = replayed.estimate()
    geo = est["geometric"]
    groups = est["unidentifiable"]
    assert ["d2", "d3", "d4"] in groups and ["theta1_offset", "base_rz"] in groups
    assert geo["d4"]["stands_for"] == ["d2", "d3", "d4"]
    assert geo["base_rz"]["stands_for"] == ["theta1_offset", "base_rz"]
    assert geo["tool_z"]["stands_for"] == ["d6", "tool_z"]
    assert "stands_for" not in geo["a2"] and "stands_for" not in geo["base_tx"]
    # every marked state is the one estimated member of its group
    for n, g in geo.items():
        if "stands_for" in g:
            assert [m for m in g["stands_for"] if m in geo] == [n]


def test_replay_text_marks_groups_and_says_the_base_frame(replayed):
    from workcell.commands.replay import geometric_lines

    lines = geometric_lines(replayed.estimate())
    text = "\n".join(lines)
    rows = {ln.split()[0] for ln in lines if ln.startswith("  ") and "+-" in ln}
    assert {"d4*", "base_rz*", "tool_z*", "a2", "base_rx"} <= rows
    assert "   {d2, d3, d4*}" in lines
    assert "*: value and std are those of the parameter's dependent group" in text
    assert any(ln.startswith("base (combined, tracker_T_base") for ln in lines)
    assert "offsets from base_ref, this filter's own registration" in text
    assert "compare the combined\nbases" in text or "compare the combined bases" in text


# ---------------------------------------------------------------- 2. campaign --online's end
def test_campaign_online_ends_with_the_estimate(tmp_path, monkeypatch, capsys):
    from workcell.cli import main

    orig = LiveFilter.for_cell.__func__

    def small(cls, cell, **kw):  # a filter that starts within a short campaign
        return orig(cls, cell, n_init=8, hidden=4, **kw)

    monkeypatch.setattr(LiveFilter, "for_cell", classmethod(small))
    out = tmp_path / "c.mcap"
    argv = ["campaign", "--robot", "sim", "--tracker", "sim", "--poses", "12"]
    rc = main([*argv, "--online", "ekf-ann", "--out", str(out)])
    assert rc == 0
    stdout = capsys.readouterr().out
    assert "ekf-ann estimate at the end of the campaign:" in stdout
    assert "geometric estimate at the last sample" in stdout
    assert "base (combined, tracker_T_base" in stdout
    assert f"save it: workcell replay {out} --online ekf-ann --save MODEL\n" in stdout
    # the closing line stays last
    assert stdout.strip().splitlines()[-1].startswith("recorded 12 poses")


def test_a_filter_that_never_started_says_so():
    from workcell.commands.replay import final_lines

    lf = LiveFilter(robot_by_name("ur5e"), TOOL_M, hidden=4, tracker_mpe=None)
    for s in _samples()[:12]:
        lf.update(s)
    lines = final_lines(lf, "c.mcap")
    assert lines[0] == (
        "ekf-ann: no estimate: the filter never started (it initialises on its first 30 samples "
        "and was given 12)"
    )
    assert "  a batch estimate: workcell fit c.mcap" in lines
    assert "  the filter's: workcell replay c.mcap --online ekf-ann" in lines


# ---------------------------------------------------------------- 3. the TCP of the model file
def test_model_stores_the_declared_smr_offset(replayed, tmp_path):
    from workcell.estimation.models import load_model, save_model
    from workcell.export.correction import nominal_for

    m = load_model(save_model(replayed.model(), tmp_path / "m.json"))
    np.testing.assert_array_equal(m.info["nominal_tool_m"], TOOL_M)
    # the controller's TCP an export commands with is the declared one, not the fitted SMR
    assert np.linalg.norm(m.theta[36:39] - TOOL_M) > 1e-4
    np.testing.assert_allclose(nominal_for(m).theta[36:39], TOOL_M)
    assert m.info["geometric_stands_for"]["d4"] == ["d2", "d3", "d4"]


# ---------------------------------------------------------------- 4. geometry vs network
def test_estimate_gives_the_geometry_alone_beside_the_whole_model(replayed):
    from workcell.commands.replay import geometric_lines

    est = replayed.estimate()
    f = replayed.filter
    q = np.array([s["q_measured_rad"] for s in _samples()])
    y = np.array([s["tracker_position_m"] for s in _samples()])

    def rms(p):
        return float(np.sqrt(np.mean(np.sum((y - p) ** 2, axis=1))))

    assert est["fit_samples"] == N
    assert est["geometric_part_rms_m"] == pytest.approx(rms(p_tracker(f.theta, f.base_ref, q)))
    assert est["rms_m"] == pytest.approx(rms(f.predict(q)))
    assert "not comparable one by one" in est["geometry_split_basis"]
    text = " ".join(geometric_lines(est))
    assert f"geometry alone (network off) fits the {N} samples at" in text
    assert "conditional on the network" in text


def test_a_filter_that_never_started_reports_no_variance_test_in_strict_json():
    """A cut-short recording (12 samples) replayed with --json said `"variance_factor": NaN,
    "variance_test_ok": true`: invalid JSON and a test that never ran reported as passed."""
    import json

    from workcell import strict_json

    lf = LiveFilter(robot_by_name("ur5e"), TOOL_M, hidden=4, tracker_mpe=None)
    for s in _samples()[:12]:
        lf.update(s)
    assert lf.variance_test()[1] is None
    est = lf.estimate()
    assert est["initialised"] is False and est["variance_test_ok"] is None
    text = strict_json.dumps(est)
    d = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))
    assert d["variance_factor"] is None
    assert strict_json.dumps({"r": float("inf"), "v": np.array([1.0, np.nan])}) == (
        '{"r": null, "v": [1.0, null]}'
    )


def test_the_combined_base_says_when_its_std_is_a_prior():
    """Series D: base_ty and tool_z held by their priors, yet the combined base was printed
    +- (0.8, 0.2, 0.2) mm with nothing said (`fit`: 27 mm along that direction; audit)."""
    from workcell.commands.replay import base_lines

    est = {
        "tracker_T_base": {
            "translation_m": [2.9, -1.1, -1.2],
            "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0],
            "translation_std_m": [8e-4, 2e-4, 2e-4],
            "rotation_std_rad": [1e-4, 1e-4, 1e-4],
        },
        "held_by_prior": ["base_ty", "tool_z", "d4"],
    }
    text = " ".join(" ".join(base_lines(est)).split())
    assert "not measured: base_ty, tool_z held by their priors" in text
    est["held_by_prior"] = ["d4"]  # a chain state: not part of the combined base
    assert "not measured" not in " ".join(base_lines(est))
