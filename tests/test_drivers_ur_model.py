"""The UR driver's robot-model check against what a controller's dashboard answers.

The check against a real protocol (the simulated controller through ur_rtde) is in
tests/test_ur_sim.py; here, the answers a simulator does not give: an older controller that does
not know `get robot model`, an unreadable answer, an arm this build has no kinematics for.
"""

from __future__ import annotations

import pytest

from sim_devices.ur_controller import dashboard_model_name
from workcell.drivers.ur_robot import UrRobot, WrongRobotModel, ur_family


class _Dashboard:
    """Stands in for ur_rtde's DashboardClient: `getRobotModel` answers `answer` or raises."""

    def __init__(self, answer):
        self.answer = answer

    def getRobotModel(self):  # noqa: N802 - ur_rtde's name
        if isinstance(self.answer, Exception):
            raise self.answer
        return self.answer


def _robot(model, answer, warned):
    r = UrRobot("192.0.2.7", model=model, on_warning=warned.append)
    r._db = _Dashboard(answer)
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
    r._db = _Dashboard(AssertionError("must not be asked"))
    r._check_model()
