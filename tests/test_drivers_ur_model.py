"""The UR driver's robot-model check against what a controller's dashboard answers.

The check against a real protocol (the simulated controller through ur_rtde) is in
tests/test_ur_sim.py; here, the answers a simulator does not give: an older controller that does
not know `get robot model`, an unreadable answer, an arm this build has no kinematics for.
"""

from __future__ import annotations

import pytest

from sim_devices.ur_controller import controller_version, dashboard_model_name
from workcell.drivers.ur_robot import (
    UrRobot,
    WrongRobotModel,
    generation_from_version,
    ur_family,
    ur_generation,
)


class _Dashboard:
    """Stands in for ur_rtde's DashboardClient: `getRobotModel` answers `answer` and
    `polyscopeVersion` answers `version`, or raise them."""

    def __init__(self, answer, version):
        self.answer = answer
        self.version = version

    @staticmethod
    def _give(x):
        if isinstance(x, Exception):
            raise x
        return x

    def getRobotModel(self):  # noqa: N802 - ur_rtde's name
        return self._give(self.answer)

    def polyscopeVersion(self):  # noqa: N802 - ur_rtde's name
        return self._give(self.version)


E_SERIES = "URSoftware 5.15.0.11820 (Mar 13 2024)"
CB3 = "URSoftware 3.15.8.106339 (Jun 08 2023)"


def _robot(model, answer, warned, version=None):
    if version is None:
        version = E_SERIES if model.endswith("e") else CB3
    r = UrRobot("192.0.2.7", model=model, on_warning=warned.append)
    r._db = _Dashboard(answer, version)
    return r


@pytest.mark.parametrize(
    "name, family",
    [("ur5e", "UR5"), ("UR5", "UR5"), ("UR10e", "UR10"), ("ur10", "UR10"), ("UR16", "UR16")],
)
def test_family_names(name, family):
    assert ur_family(name) == family
    assert dashboard_model_name(name) == family  # what the simulator's dashboard answers


def test_non_ur_names():
    assert ur_family("could not understand: 'get robot model'") is None
    assert ur_family("") is None
    with pytest.raises(ValueError, match="not a Universal Robots arm"):
        UrRobot("192.0.2.7", model="wam7")


@pytest.mark.parametrize(
    "model, answer, hint",
    [
        ("ur5e", "UR10", "give --model ur10"),
        ("ur10", "UR5", "give --model ur5e"),
        ("ur5e", "UR16", "this build has no kinematics for a UR16"),
    ],
)
def test_another_family_is_refused(model, answer, hint):
    warned = []
    with pytest.raises(WrongRobotModel) as ei:
        _robot(model, answer, warned)._check_model()
    msg = str(ei.value)
    assert f"the controller says it is a {answer} but --model is {model}" in msg
    assert hint in msg and "\n" not in msg and warned == []


def test_same_family_passes_silently():
    warned = []
    r = _robot("ur5e", "UR5", warned)
    r._check_model()
    assert warned == [] and r.controller_model == "UR5"


@pytest.mark.parametrize(
    "answer, said",
    [
        ("could not understand: 'get robot model'", "could not understand"),
        (RuntimeError("Failed to receive"), "Failed to receive"),
        ("", "''"),
    ],
)
def test_an_unknown_answer_warns_once_and_does_not_block(answer, said):
    warned = []
    r = _robot("ur5e", answer, warned)
    r._check_model()
    r._check_model()  # a reconnect: the same warning is not repeated
    assert len(warned) == 1 and r.warnings == warned
    assert "could not read the robot model" in warned[0] and said in warned[0]
    assert "make sure the arm is a UR5" in warned[0] and "\n" not in warned[0]


def test_no_model_no_question():
    r = UrRobot("192.0.2.7")
    r._db = _Dashboard(AssertionError("must not be asked"), AssertionError("nor this"))
    r._check_model()


@pytest.mark.parametrize(
    "name, generation",
    [("ur5e", "e-Series"), ("UR10e", "e-Series"), ("ur10", "CB3"), ("UR5", "CB3"),
     ("ur5cb3", "CB3"), ("wam7", None)],
)  # fmt: skip
def test_generation_names(name, generation):
    assert ur_generation(name) == generation
    if generation is not None:  # what the simulator's controller reports for that arm
        major = controller_version(name)[0]
        assert generation_from_version(f"URSoftware {major}.1.2.3")[0] == generation


@pytest.mark.parametrize(
    "answer, generation, version",
    [
        (E_SERIES, "e-Series", "5.15.0"),
        (CB3, "CB3", "3.15.8"),
        ("URSoftware 10.7.0.0", "e-Series", "10.7.0"),  # PolyScope X
        ("URSoftware 1.8.2.0", None, "1.8.2"),  # CB2: no kinematics here either way
        ("could not understand: 'PolyscopeVersion'", None, None),
    ],
)
def test_generation_from_version(answer, generation, version):
    assert generation_from_version(answer) == (generation, version)


@pytest.mark.parametrize(
    "model, version, said, hint",
    [
        ("ur10", E_SERIES, "so the arm is a UR10e, but --model ur10 is a CB3 UR10",
         "this build has no kinematics for a UR10e"),
        ("ur5e", CB3, "so the arm is a CB3 UR5, but --model ur5e is a UR5e",
         "this build has no kinematics for a CB3 UR5"),
    ],
)  # fmt: skip
def test_the_other_generation_of_the_same_family_is_refused(model, version, said, hint):
    """The dashboard says "UR10" for a CB3 UR10 and a UR10e alike; their shoulder heights differ
    by 53 mm (d1 0.1273 m against 0.1807 m). Until 2026-11-26 the driver compared families only
    and a UR10e passed as `--model ur10`."""
    warned = []
    with pytest.raises(WrongRobotModel) as ei:
        _robot(model, ur_family(model), warned, version)._check_model()
    msg = str(ei.value)
    assert said in msg and hint in msg and "nothing moves" in msg
    assert "\n" not in msg and warned == []


@pytest.mark.parametrize(
    "version, said",
    [(RuntimeError("Failed to receive"), "Failed to receive"), ("", "''"),
     ("URSoftware 1.8.2.0", "1.8.2")],
)  # fmt: skip
def test_an_unreadable_version_warns_once_and_does_not_block(version, said):
    warned = []
    r = _robot("ur10", "UR10", warned, version)
    r._check_model()
    r._check_model()
    assert len(warned) == 1 and "could not tell a CB3 from an e-Series" in warned[0]
    assert said in warned[0] and "make sure the arm is a CB3 UR10" in warned[0]
