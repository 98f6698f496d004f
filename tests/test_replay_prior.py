"""The online filter says which geometric states its prior holds, not the data (replay --json/text).

Audit 2026-11-26: replaying the real UR10 series D (iso cubes) reported tool_z = 109.3 +- 0.85 mm
and base_ty +- 0.85 mm, although `workcell fit` flags {base_ty, tool_z} as weakly identified and
series B puts the SMR at 93.2 mm: the filter's std of both had only come down from its prior
(sigma_g0_m = 0.1 mm) to 0.071 mm, and the value was the declared 109 mm. Here a synthetic cell
where that is exact: the SMR sits on the joint-6 axis, so theta6_offset does not move it (no
information at all), and d6 and tool_z translate it the same way (only their sum is measured);
the base translation is measured. The data carry more noise than the filter is told (s0^2 > 1),
so the scaled and the unscaled stds differ.
"""

from __future__ import annotations

import numpy as np
import pytest

from workcell.estimation.ekf_ann.filter import FilterConfig
from workcell.estimation.ekf_ann.live import LiveFilter
from workcell.kinematics.chain import IDX, p_tracker, pack
from workcell.kinematics.robots import robot_by_name

TOOL_M = np.array([0.0, 0.0, 0.06])  # on the joint-6 axis
STATES = ("base_tx", "base_ty", "base_tz", "base_rz", "theta6_offset", "d6", "tool_z")
N = 72
SIGMA_STATED_M = 10e-6
SIGMA_TRUE_M = 30e-6  # s0^2 about 9


def _samples(seed: int = 0) -> list[dict]:
    rng = np.random.default_rng(seed)
    spec = robot_by_name("ur5e")
    theta = pack(spec.dh, tool=TOOL_M)
    for n, v in (("base_tx", 3e-4), ("base_ty", -2e-4), ("d6", 2e-4), ("tool_z", 1e-4)):
        theta[IDX[n]] += v
    base = np.eye(4)
    base[:3, 3] = (2.0, 0.3, -0.2)
    q = np.array([0.3, -1.2, 1.0, -1.4, -1.57, 0.0]) + rng.uniform(-0.8, 0.8, (N, 6))
    y = np.asarray(p_tracker(theta, base, q)) + SIGMA_TRUE_M * rng.normal(size=(N, 3))
    return [
        {
            "index": i,
            "q_measured_rad": q[i].tolist(),
            "tracker_position_m": y[i].tolist(),
            "tracker_sigma_m": [SIGMA_STATED_M] * 3,
        }
        for i in range(N)
    ]


@pytest.fixture(scope="module")
def replayed():
    cfg = FilterConfig(geometric=STATES, ann_iter_every=0)
    lf = LiveFilter(robot_by_name("ur5e"), TOOL_M, n_init=8, hidden=4, cfg=cfg, tracker_mpe=None)
    for s in _samples():
        lf.update(s)
    return lf


def test_a_state_the_poses_cannot_see_is_flagged_as_held_by_its_prior(replayed):
    est = replayed.estimate()
    geo = est["geometric"]
    # each state carries its own prior: angles sigma_g0_rad, lengths sigma_g0_m
    cfg = replayed.filter.cfg
    assert geo["theta6_offset"]["std_prior"] == cfg.sigma_g0_rad
    assert geo["tool_z"]["std_prior"] == geo["base_tx"]["std_prior"] == cfg.sigma_g0_m
    for g in geo.values():
        assert g["std_filter_over_prior"] == pytest.approx(g["std_filter"] / g["std_prior"])
    # no information at all: the std stays at the prior
    assert geo["theta6_offset"]["std_filter_over_prior"] == pytest.approx(1.0, abs=1e-3)
    # only d6 + tool_z is measured: each keeps 1/sqrt(2) of its prior, perfectly correlated
    for n, other in (("d6", "tool_z"), ("tool_z", "d6")):
        assert geo[n]["std_filter_over_prior"] == pytest.approx(2**-0.5, abs=0.01)
        assert geo[n]["correlated_with"] == {other: pytest.approx(-1.0, abs=1e-3)}
    held = {"theta6_offset", "d6", "tool_z"}
    assert set(est["held_by_prior"]) == held
    assert est["held_by_prior_ratio"] == 0.5
    for n in held:
        assert geo[n]["determined_by"] == "prior"
    assert "held_by_prior" in est["geometric_std_basis"]
    assert replayed.model().info["geometric_held_by_prior"] == est["held_by_prior"]


def test_a_well_measured_state_is_not_flagged(replayed):
    geo = replayed.estimate()["geometric"]
    for n in ("base_tx", "base_ty", "base_tz", "base_rz"):
        assert geo[n]["determined_by"] == "data", (n, geo[n])
        assert geo[n]["std_filter_over_prior"] < 0.2
        assert "correlated_with" not in geo[n]


def test_top_level_geometric_std_is_the_scaled_one(replayed):
    """`geometric_std` used to be the unscaled filter std beside a scaled `geometric.*.std`; now
    both are the same scaled figure, with the factor stated."""
    est = replayed.estimate()
    assert est["variance_factor"] > 4
    for n, g in est["geometric"].items():
        assert est["geometric_std"][n] == g["std"] > 2 * g["std_filter"]
    k = est["std_scale"]
    assert k == pytest.approx(np.sqrt(est["variance_factor"]))
    for g in est["geometric"].values():
        assert g["std"] == pytest.approx(k * g["std_filter"])


def test_replay_text_says_held_by_prior_instead_of_a_plus_minus(replayed):
    from workcell.commands.replay import geometric_lines

    lines = geometric_lines(replayed.estimate())
    row = {ln.split()[0]: ln for ln in lines if ln.startswith("  ") and ln.split()[0] in STATES}
    assert "held by its prior (sigma_g0_m = 0.1 mm), not measured" in row["tool_z"]
    assert "held by its prior (sigma_g0_rad = 0.2 mrad), not measured" in row["theta6_offset"]
    assert "+-" not in row["tool_z"] and "+-" not in row["theta6_offset"]
    assert "+-" in row["base_tx"] and "held" not in row["base_tx"]
    text = "\n".join(lines)
    assert "combination with d6, correlation -1.00" in text
    assert "held by its prior: theta6_offset, d6, tool_z" in text
