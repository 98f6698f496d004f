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


def _tcp(table) -> list[float]:
    """The TCP the table assumes, as `get_tcp_offset()` returns it after `set_tcp(wc_tcp)`."""
    return [*table.meta["tcp_m"], 0.0, 0.0, 0.0]


def _on_table(table, k: int) -> np.ndarray:
    """Joints on the arm configuration orientation k's corrections were solved on."""
    return table.q_nodes[k][0, 0, 0]


def test_urscript_matches_python_table(table):
    text = generate_urscript(table)
    rng = np.random.default_rng(0)
    P = rng.uniform(LO, HI, (150, 3))
    for i, x in enumerate(P):
        rv = DOWN if i % 2 else TILT
        ns = run_urscript(text, actual_joints=_on_table(table, 0 if i % 2 else 1), tcp=_tcp(table))
        got = np.array(ns["wc_correct"](ns["_pose"]([*x, *rv])))
        want = table.correct(x[None], rv)[0]
        assert np.abs(got[:3] - want).max() < 1e-12
        assert np.abs(got[3:] - rv).max() < 1e-9 or np.abs(got[3:]).max() > 3  # same rotation
    # the two orientations have different corrections (the selection matters)
    assert np.abs(table.interpolate(P[:5], 0) - table.interpolate(P[:5], 1)).max() > 1e-7


def test_urscript_halts_outside_volume_and_orientation(table):
    ns = run_urscript(generate_urscript(table), actual_joints=_on_table(table, 0), tcp=_tcp(table))
    with pytest.raises(URScriptHalt, match="outside the correction volume"):
        ns["wc_correct"](ns["_pose"]([*(HI + 0.01), *DOWN]))
    with pytest.raises(URScriptHalt, match="orientation"):
        ns["wc_correct"](ns["_pose"]([*(LO + HI) / 2, 0.0, 0.0, 0.0]))


def test_interpreter_refuses_unknown_constructs():
    with pytest.raises(ValueError, match="subset"):
        translate_urscript("def f(x):\n  movel(x)\nend\n")
    with pytest.raises(ValueError, match="unknown name"):
        translate_urscript("def f(x):\n  return tan(x)\nend\n")


def test_the_script_halts_on_another_tcp(table):
    """The table holds for the TCP (SMR) it was computed for: a TCP 1 mm or 10 mrad off moves
    every corrected target by about that much. The header said "set the TCP above first" and
    nothing checked it (URScript export audit, 2026-11-29)."""
    text = generate_urscript(table)
    assert "set_tcp(wc_tcp)" in text.split("global wc_lo")[0]  # the usage line says how
    x, q0 = (LO + HI) / 2, _on_table(table, 0)
    want = table.correct(x[None], DOWN)[0]
    tcp = np.array(_tcp(table))
    for off in ([1e-3, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0.01], -tcp):  # the last: no TCP set
        ns = run_urscript(text, actual_joints=q0, tcp=tcp + off)
        with pytest.raises(URScriptHalt, match="active TCP is not the correction table's"):
            ns["wc_correct"](ns["_pose"]([*x, *DOWN]))
    ns = run_urscript(text, actual_joints=q0, tcp=tcp + [5e-6, 0, 0, 0, 0, 5e-5])  # within
    assert np.abs(np.array(ns["wc_correct"](ns["_pose"]([*x, *DOWN])))[:3] - want).max() < 1e-12


def test_every_temporary_is_declared_local():
    """URScript's scoping rules: a name assigned in a function without `local` is the program's
    global of that name if one exists, so `i`, `a`, `k`, `x`, `t` of the correction overwrote a
    program's variables (a loop counter `i` driving `movel(wc_correct(targets[i]))`). The
    interpreter now refuses such a script, and the generated one passes it (the tests above
    translate it)."""
    with pytest.raises(ValueError, match="'i' assigned in f without `local`"):
        translate_urscript("def f(x):\n  i = floor(x)\n  return i\nend\n")
    with pytest.raises(ValueError, match="without `global`"):
        translate_urscript("n = 3\n")
    with pytest.raises(ValueError, match="'c' assigned in f without `local`"):
        translate_urscript("def f(x):\n  c[0] = x\n  return c\nend\n")
    src = translate_urscript("def f(x):\n  local i = floor(x)\n  i = i + 1\n  return i\nend\n")
    assert "i = floor(x)" in src


def test_a_script_larger_than_any_known_to_run_is_written_with_a_warning(table, tmp_path):
    """No URScript size limit is documented; the largest script known to run on every UR
    generation is UR's external_control (52 KB): beyond it, export says so."""
    from workcell.export.urscript import KNOWN_RUNNING_BYTES, size_warning, write_urscript

    small = write_urscript(table, tmp_path / "s.script")
    assert small.stat().st_size < KNOWN_RUNNING_BYTES and size_warning(small) is None
    big = tmp_path / "big.script"
    big.write_text(small.read_text() + "# " + "x" * KNOWN_RUNNING_BYTES + "\n")
    w = size_warning(big)
    assert w is not None and w.startswith("warning: big.script is ") and "URSim" in w


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
        ns = run_urscript(text, actual_joints=q, tcp=_tcp(table))
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
