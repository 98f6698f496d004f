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


def test_urscript_matches_python_table(table):
    ns = run_urscript(generate_urscript(table))
    rng = np.random.default_rng(0)
    P = rng.uniform(LO, HI, (150, 3))
    for i, x in enumerate(P):
        rv = DOWN if i % 2 else TILT
        got = np.array(ns["wc_correct"](ns["_pose"]([*x, *rv])))
        want = table.correct(x[None], rv)[0]
        assert np.abs(got[:3] - want).max() < 1e-12
        assert np.abs(got[3:] - rv).max() < 1e-9 or np.abs(got[3:]).max() > 3  # same rotation
    # the two orientations have different corrections (the selection matters)
    assert np.abs(table.interpolate(P[:5], 0) - table.interpolate(P[:5], 1)).max() > 1e-7


def test_urscript_halts_outside_volume_and_orientation(table):
    ns = run_urscript(generate_urscript(table))
    with pytest.raises(URScriptHalt, match="outside the correction volume"):
        ns["wc_correct"](ns["_pose"]([*(HI + 0.01), *DOWN]))
    with pytest.raises(URScriptHalt, match="orientation"):
        ns["wc_correct"](ns["_pose"]([*(LO + HI) / 2, 0.0, 0.0, 0.0]))


def test_interpreter_refuses_unknown_constructs():
    with pytest.raises(ValueError, match="subset"):
        translate_urscript("def f(x):\n  movel(x)\nend\n")
    with pytest.raises(ValueError, match="unknown name"):
        translate_urscript("def f(x):\n  return sin(x)\nend\n")
