"""`workcell fit --bounds`: the audit of the bounded fit's reporting and bounds-file reading.

1. a parameter pinned by a bound [v, v] was dropped from the estimated set and reported as if no
   bound held ("none holds a parameter") while the held-out RMS went 14.6 -> 54.4 um;
2. bounds files in millimetres or degrees that contained the nominal were accepted silently;
3. the stds beside a held parameter did not say they are conditional on it;
5. rank/condition and O1/O3 are of different Jacobians and nothing said which; fit printed no O1/O3;
7. bounds-file mistakes got misleading messages (unknown parameter 'mode', "is empty" for NaN,
   "not found" for a directory, duplicated keys kept silently).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from simdata import dh_error_dataset

from workcell.cli import main
from workcell.errors import UserError
from workcell.estimation.bounded import fit_dh_bounded, resolve_bounds
from workcell.estimation.dh import nominal_theta
from workcell.estimation.fitting import fit_dataset, keep_in_model
from workcell.kinematics.chain import IDX


@pytest.fixture(scope="module")
def sim_ds():
    return dh_error_dataset(40, seed=5)[1]


@pytest.fixture(scope="module")
def th(sim_ds):
    return nominal_theta(sim_ds)


# ------------------------------------------------------------------ 1. a bound [v, v] pins


def test_a_pinned_parameter_is_reported_as_fixed_by_its_bound(sim_ds, tmp_path, capsys):
    from workcell.commands.fit import print_report
    from workcell.export.ros_yaml import export_ros_yaml

    _, free_rep = fit_dataset(sim_ds, method="dh", bounds=None)
    model, rep = fit_dataset(sim_ds, method="dh", bounds={"a1": [0.0, 0.0]})
    assert model.theta[IDX["a1"]] == 0.0
    assert "a1" in model.info["active_bounds"] and model.info["pinned_by_bounds"] == ["a1"]
    b = rep["bounds"]
    at = {a["name"]: a for a in b["at_bound"]}
    assert at["a1"]["side"] == "fixed" and at["a1"]["value"] == 0.0
    # the unbounded fit's held-out RMS beside the bounded one
    assert b["heldout_rms_unbounded_m"] == pytest.approx(free_rep["heldout_rms_m"], rel=1e-9)
    assert "none holds a parameter" not in b["line"]
    assert "a1 (fixed at 0 m by its bound [0, 0])" in b["line"]
    p = rep["parameters"]["a1"]
    assert p["std"] is None and p["fixed_by_bound"] and p["value"] == 0.0
    rep["model"] = None
    print_report(rep)
    out = capsys.readouterr().out
    row = [x for x in out.splitlines() if x.split()[:1] == ["a1"]]
    assert len(row) == 1 and row[0].split()[3] == "fixed", row
    # the ROS YAML says the bound set it, as for an active bound
    _, info = export_ros_yaml(model, tmp_path / "cal.yaml")
    assert info["kinematics_fixed"]["upper_arm"]["x"] == ["a1 (at its bound)"]


# --------------------------------------------------------- 2. millimetres and degrees refused


@pytest.mark.parametrize(
    "spec, match",
    [
        ({"a1": [-5, 5]}, "looks like millimetres, give metres"),
        ({"mode": "delta", "bounds": {"a2": [-5, 5]}}, "looks like millimetres, give metres"),
        ({"mode": "delta", "bounds": {"tool_z": [-3, 3]}}, "looks like millimetres"),
        ({"base_tx": [-2, 2]}, "looks like millimetres"),
        ({"theta2_offset": [-1, 1]}, "looks like degrees, give radians"),
        ({"mode": "delta", "bounds": {"alpha1": [-1, 1]}}, "looks like degrees, give radians"),
        ({"alpha1": [88, 92]}, r"read as degrees, does; it looks like degrees, give radians"),
        ({"base_rz": [-0.6, 0.6]}, "looks like degrees"),
    ],
)
def test_bounds_in_millimetres_or_degrees_are_refused(th, spec, match):
    with pytest.raises(UserError, match=match) as e:
        resolve_bounds(spec, th)
    assert "\n" not in str(e.value)
    # while the documented forms and plausible bounds (within 0.1 m, 0.5 rad) still pass
    a2 = th[IDX["a2"]]
    for ok in (
        "default",
        "none",
        {"a2": [a2 - 1e-5, a2 + 1e-5]},
        {"mode": "delta", "bounds": {"tool_z": [-3e-3, 3e-3], "alpha3": [-1e-3, 1e-3]}},
        {"mode": "delta", "bounds": {"a2": [-0.09, 0.09], "theta2_offset": [-0.45, 0.45]}},
        {"a2": [-np.inf, np.inf]},
    ):
        lo, hi = resolve_bounds(ok, th)
        assert np.all(lo <= th) and np.all(th <= hi)


# ------------------------------------------------ 3. stds conditional on the held parameters


def test_std_basis_names_the_held_parameters(sim_ds):
    spec = {"mode": "delta", "bounds": {"a2": [-2e-5, 2e-5], "alpha3": [-2e-5, 2e-5]}}
    model, rep = fit_dataset(sim_ds, method="dh", bounds=spec)
    held = model.info["active_bounds"]
    assert held, "test setup: the tight bounds should hold"
    basis = rep["parameter_std_basis"]
    assert f"conditional on the parameters a bound holds ({', '.join(held)})" in basis
    keep_in_model(model, sim_ds, rep)  # the model file carries it too
    assert model.info["parameter_std_basis"] == basis
    # the std itself is unchanged: that of the others with the held ones known
    _, free_rep = fit_dataset(sim_ds, method="dh", bounds=None)
    assert "conditional on" not in free_rep["parameter_std_basis"]


# ------------------------------------------------ 5. each identifiability figure's basis


def test_identifiability_figures_name_their_basis_and_fit_prints_o1_o3(sim_ds, capsys):
    from workcell.commands.fit import print_report
    from workcell.estimation.bounded import jacobian_padded
    from workcell.estimation.dh import pose_sigma_model, register_base
    from workcell.estimation.identifiability import analyse, candidates_for

    _, rep = fit_dataset(sim_ds, method="dh", bounds=None, holdout=0.0)
    i = rep["identifiability"]
    assert "1 / sigma" in i["condition_basis"] and "unit norm" in i["condition_basis"]
    assert i["singular_values_basis"] == i["condition_basis"]
    assert "not the smallest of singular_values" in i["min_singular_value_basis"]
    # the unweighted condition is the dry run's definition, computed independently here
    th = nominal_theta(sim_ds)
    J = jacobian_padded(th, register_base(sim_ds, th), sim_ds.q).reshape(-1, len(th))
    ref = analyse(J, candidates=candidates_for(sim_ds.robot.dh))
    assert i["condition_unweighted"] == pytest.approx(ref.condition, rel=1e-6)
    w = 1.0 / pose_sigma_model(sim_ds)
    assert np.ptp(w) > 0  # the weights differ: so do the two conditions
    assert i["condition_unweighted"] != pytest.approx(i["condition"], rel=1e-6)
    rep["model"] = None
    print_report(rep)
    out = " ".join(capsys.readouterr().out.split())
    assert (
        f"condition {i['condition']:.3g} (rows weighted by 1 / sigma per pose, unit-norm "
        f"columns; {i['condition_unweighted']:.3g} unweighted, the dry run's definition); "
        f"O1 {i['o1']:.3g}, O3 {i['min_singular_value']:.3g}"
    ) in out


# ------------------------------------------------------------ 7. bounds-file messages


@pytest.mark.parametrize(
    "text, match",
    [
        ('{"mode": "delta", "bounds": []}', r'"bounds" must be an object \{name: \[lo, hi\]\}'),
        ('{"mode": "delta", "a1": [0, 0.001]}', r'"mode" goes with a "bounds" object'),
        ('{"mode": "delta", "bounds": {"a2": [0.001, 0.002]}}', "widen it to include 0"),
        ('{"a2": [NaN, 1]}', "is not a number"),
        ('{"a1": [-0.001, 0.001], "a1": [0, 0]}', "key 'a1' is given twice"),
        ('{"mode": "delta", "bounds": {"a1": [0, 0], "a1": [-1e-3, 1e-3]}}', "'a1' is given twice"),
    ],
)
def test_bounds_file_mistakes_are_named(th, tmp_path, text, match):
    path = tmp_path / "b.json"
    path.write_text(text)
    with pytest.raises(UserError, match=match) as e:
        resolve_bounds(str(path), th)
    assert "unknown parameter 'mode'" not in str(e.value)
    if "delta" in text and "widen" in match:
        assert 'give offsets from nominal with {"mode": "delta"}' not in str(e.value)


def test_a_directory_for_bounds_is_named_as_such(th, tmp_path):
    with pytest.raises(UserError, match="is a directory"):
        resolve_bounds(str(tmp_path), th)


def test_fit_help_mentions_none_for_bounds(capsys):
    with pytest.raises(SystemExit):
        main(["fit", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "'default' or 'none'" in out


def test_pinned_bound_fit_keeps_the_unbounded_qp_elsewhere(sim_ds):
    """The QP leaves the pinned parameter out, as before: the other values are its optimum."""
    m = fit_dh_bounded(sim_ds, bounds={"a1": [0.0, 0.0]})
    assert m.free[IDX["a1"]] and m.std[IDX["a1"]] == 0.0
    assert m.info["std_conditional_on"] == m.info["active_bounds"]
    json.dumps(m.info)
