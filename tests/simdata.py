"""Simulated tracker data for tests that fit without running a campaign: random poses of a
simulated arm measured by the simulator's truth and tracker noise (the truth is used only to make
the measurements, as a campaign would)."""

from __future__ import annotations

import numpy as np

from workcell.recording.dataset import Dataset


def dh_error_dataset(n: int = 40, seed: int = 5, declared_smr_shift_m: float = 0.0):
    """(truth, Dataset): `n` random poses of a simulated UR5e with DH errors only (seed `seed`),
    each the mean of 5 tracker readings; the declared SMR offset is the nominal one moved by
    `declared_smr_shift_m` along the flange axis (the truth's stays)."""
    from sim_devices.truth import NOMINAL_SMR_M, TrackerNoise, make_truth
    from workcell.campaign.envelope import default_envelope
    from workcell.campaign.plans import random_configurations

    truth = make_truth("ur5e", "none", seed, noise=TrackerNoise())
    rng = np.random.default_rng(seed)
    env = default_envelope(truth.nominal)
    q = random_configurations(truth.nominal, env, n, rng, NOMINAL_SMR_M)
    p, s = [], []
    for qi in q:
        pt = truth.smr_in_tracker(qi, np.ones(6), 0.0)
        sig = truth.noise.sigma_of_mean(float(np.linalg.norm(pt)), 5)
        p.append(pt + rng.normal(0, sig, 3))
        s.append(np.full(3, sig))
    ds = Dataset(
        robot=truth.nominal,
        tool_offset_m=NOMINAL_SMR_M + np.array([0.0, 0.0, declared_smr_shift_m]),
        tracker_T_base_nominal=np.eye(4),
        q=q,
        p_tracker=np.array(p),
        sigma_m=np.array(s),
    )
    return truth, ds


def aborted_sim_campaign(out, stop_after: int, *, poses: int, noise_stream: int = 0, **kw):
    """A simulated campaign (in-process UR5e, no hidden effects, virtual time) of `poses` poses,
    aborted after `stop_after` samples, recorded as a simulated cell -> (path, CampaignResult).
    `noise_stream`: the simulated tracker's noise draw (a resumed run is another one); `kw` goes
    to `run_campaign` (a resume's `continuation`, `reference_every`)."""
    from sim_devices.cell import sim_cell
    from workcell.campaign.executor import CampaignConfig, CampaignControl
    from workcell.campaign.run import run_campaign

    _, robot, tracker, cell = sim_cell(
        "ur5e", "none", 1, beam_break_prob=0.0, noise_stream=noise_stream
    )
    control = CampaignControl()
    n = [0]

    def on_sample(s: dict) -> None:
        n[0] += 1
        if n[0] >= stop_after:
            control.abort.set()

    return run_campaign(
        robot, tracker, cell, out, poses=poses, seed=1,
        config=CampaignConfig(readings_per_pose=1, settle_s=0.1), control=control,
        on_sample=on_sample,
        extra_campaign={"robot_url": "sim", "tracker_url": "sim", "effects": "none"}, **kw,
    )  # fmt: skip
