"""Parity: the interpolation as written in the generated URScript equals the Python table."""

import numpy as np
import pytest
from test_export_table import DOWN, HI, LO, make_model  # noqa: E402

from workcell.export.correction import Corrector, nominal_for
from workcell.export.table import build_table
from workcell.export.urscript import (
    URScriptHalt,
    generate_urscript,
    run_urscript,
    translate_urscript,
)

TILT = [0.0, np.pi * 0.9, 0.0]


@pytest.fixture(scope="module")
def table():
    m = make_model(7)
    return build_table(Corrector(m, nominal_for(m)), LO, HI, [DOWN, TILT], spacing_m=0.07)


def _on_table(table, k: int) -> np.ndarray:
    """Joints on the arm configuration orientation k's corrections were solved on."""
    return table.q_nodes[k][0, 0, 0]


def test_urscript_matches_python_table(table):
    text = generate_urscript(table)
    rng = np.random.default_rng(0)
    P = rng.uniform(LO, HI, (150, 3))
    for i, x in enumerate(P):
        rv = DOWN if i % 2 else TILT
        ns = run_urscript(text, actual_joints=_on_table(table, 0 if i % 2 else 1))
        got = np.array(ns["wc_correct"](ns["_pose"]([*x, *rv])))
        want = table.correct(x[None], rv)[0]
        assert np.abs(got[:3] - want).max() < 1e-12
        assert np.abs(got[3:] - rv).max() < 1e-9 or np.abs(got[3:]).max() > 3  # same rotation
    # the two orientations have different corrections (the selection matters)
    assert np.abs(table.interpolate(P[:5], 0) - table.interpolate(P[:5], 1)).max() > 1e-7


def test_urscript_halts_outside_volume_and_orientation(table):
    ns = run_urscript(generate_urscript(table), actual_joints=_on_table(table, 0))
    with pytest.raises(URScriptHalt, match="outside the correction volume"):
        ns["wc_correct"](ns["_pose"]([*(HI + 0.01), *DOWN]))
    with pytest.raises(URScriptHalt, match="orientation"):
        ns["wc_correct"](ns["_pose"]([*(LO + HI) / 2, 0.0, 0.0, 0.0]))


def test_interpreter_refuses_unknown_constructs():
    with pytest.raises(ValueError, match="subset"):
        translate_urscript("def f(x):\n  movel(x)\nend\n")
    with pytest.raises(ValueError, match="unknown name"):
        translate_urscript("def f(x):\n  return tan(x)\nend\n")


def test_urscript_and_table_halt_on_another_arm_configuration(table):
    """The corrections hold on the IK branch they were solved on: an arm on another (elbow
    flipped, wrist flipped, or shoulder over) is refused by the script and by the table, on the
    table's own joints and on the same joints with one branch changed."""
    from workcell.errors import UserError
    from workcell.export.correction import configuration
    from workcell.export.table import CorrectionTable

    text = generate_urscript(table)
    x = (LO + HI) / 2
    q0 = _on_table(table, 0)
    dh_m = table.configuration_dh_m
    assert np.array_equal(configuration(q0, dh_m)[0], table.configurations[0])
    flips = {
        "elbow": q0 * [1, 1, -1, 1, 1, 1] + [0, 0, 0, 0, 0, 0],
        "wrist": q0 * [1, 1, 1, 1, -1, 1],
        "shoulder": q0 + [0, np.pi, 0, 0, 0, 0],
    }
    for name, q in flips.items():
        got = configuration(q, dh_m)[0]
        assert not np.array_equal(got, table.configurations[0]), name
        ns = run_urscript(text, actual_joints=q)
        with pytest.raises(URScriptHalt, match="configuration"):
            ns["wc_correct"](ns["_pose"]([*x, *DOWN]))
        with pytest.raises(UserError, match=name):
            table.correct(x[None], DOWN, q_actual=q)
    # the file keeps the configurations
    back = CorrectionTable.from_dict(table.to_dict())
    assert np.array_equal(back.configurations, table.configurations)
    back.correct(x[None], DOWN, q_actual=q0)  # on the table's: no refusal


def test_the_shoulder_sign_is_the_ur_ik_shoulder_branch():
    """The shoulder sign is (minus) the branch of the UR analytic IK's q1 = atan2(p5y, p5x) +
    pi/2 +- acos(d4 / r), p5 the wrist point (DH frame 5), on 20,000 random joint vectors of
    the UR5e and the UR10 (the README quotes this)."""
    from workcell.export.correction import _frames_np, configuration, configuration_dh
    from workcell.kinematics.chain import pack
    from workcell.kinematics.robots import UR5E, UR10

    for spec in (UR5E, UR10):
        th = np.asarray(pack(spec.dh), float)
        q = np.random.default_rng(1).uniform(-2 * np.pi, 2 * np.pi, (20000, 6))
        p5 = _frames_np(th, q)[:, 5, :3, 3]
        d = q[:, 0] - np.arctan2(p5[:, 1], p5[:, 0]) - np.pi / 2
        branch = np.sign(np.sin(d))
        assert np.array_equal(configuration(q, configuration_dh(th))[:, 0], -branch), spec.model
