"""Closed loop on the simulated robot: a model equal to the true geometry corrects to the table's
interpolation error; the nominal-only 'correction' does nothing."""

import numpy as np

from workcell.campaign.envelope import default_envelope
from workcell.campaign.run import sim_cell
from workcell.estimation.dh import DHModel
from workcell.export.build import make_table
from workcell.export.validate import run_validation, sim_measure
from workcell.kinematics.chain import pack
from workcell.kinematics.robots import DH


def _truth_model(truth):  # tests may read the truth; here it builds a perfect geometric model
    dh = DH(a=truth.a, d=truth.d, alpha=truth.alpha, theta_offset=truth.theta_offset)
    th = pack(dh, tool=truth.smr_flange_m, beta=truth.beta)
    return DHModel(
        robot_model="ur5e",
        nominal_dh=truth.nominal.dh,
        theta=th,
        base_ref=truth.tracker_T_base,
        cov=np.zeros((39, 39)),
        free=np.ones(39, bool),
        info={"nominal_tool_m": [0, 0, 0.06]},
    )


def test_closed_loop_geometry_only():
    world, robot, tracker, cell = sim_cell("ur5e", "none", 3)
    model = _truth_model(world.truth)
    table, corr = make_table(model, target_error_m=5e-6)
    env = default_envelope(cell.spec)

    def move(q):
        world.clock.advance(world.command_move(q, 0.5, 1.0))

    res = run_validation(
        corr.nominal,
        table,
        move,
        sim_measure(world),
        n=12,
        seed=1,
        check=lambda q: env.violations(cell.spec, q, cell.tool_m)[0],
    )
    assert res["targets"] >= 10
    assert res["before_rms_m"] > 2e-4  # the nominal controller misses by the DH errors
    assert res["after_rms_m"] < 1e-5  # interpolation error (5 um max) + nothing else
    assert res["after"]["max_m"] < 1.5e-5
