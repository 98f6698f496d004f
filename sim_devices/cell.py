"""A simulated cell as the operator would set it up: the truth stays in the simulator; the cell
setup (`CellSetup`) carries only what an operator declares (the catalogue robot, the nominal SMR
offset, a rough base pose, the payload as declared, not as it really is)."""

from __future__ import annotations

import numpy as np

from sim_devices.truth import NOMINAL_SMR_M, TrackerNoise, TrueWorkcell, make_truth
from workcell.campaign.run import CellSetup


def declared_cell(
    truth: TrueWorkcell,
    seed: int,
    *,
    tracker_model: str = "simulated laser tracker",
    base_in_tracker: dict | None = None,
) -> CellSetup:
    """What the operator declares about `truth`'s cell. `base_in_tracker` defaults to a rough
    nominal base pose drawn from `seed` (`TrueWorkcell.session_nominal`)."""
    if base_in_tracker is None:
        base_in_tracker = truth.session_nominal(np.random.default_rng(seed + 99))
    return CellSetup(
        spec=truth.nominal,
        tool_m=NOMINAL_SMR_M.copy(),
        base_in_tracker=base_in_tracker,
        tracker_model=tracker_model,
        payload_kg=truth.declared_payload_kg,
        payload_com_m=tuple(np.asarray(truth.declared_payload_com_m, float).tolist()),
    )


def sim_cell(
    robot: str = "ur5e",
    effects: str | dict | None = "realistic",
    seed: int = 0,
    *,
    beam_break_prob: float = 0.01,
    outlier_prob: float = 0.005,
    dh_error_scale: float = 1.0,
    noise: TrackerNoise | None = None,
    noise_stream: int = 0,
):
    """An in-process simulated cell: (SimWorld, SimRobot, SimTracker, CellSetup).
    `noise_stream` > 0: the same simulated truth, another draw of the noise (a resumed campaign
    is a new run on the same cell, not a replay of the first run's readings)."""
    from sim_devices.inprocess import SimRobot, SimTracker
    from sim_devices.world import SimWorld

    nz = noise or TrackerNoise(beam_break_prob=beam_break_prob, outlier_prob=outlier_prob)
    truth = make_truth(robot, effects, seed, noise=nz, dh_error_scale=dh_error_scale)
    world = SimWorld(truth, seed=seed, noise_stream=noise_stream)
    return world, SimRobot(world), SimTracker(world), declared_cell(truth, seed)
