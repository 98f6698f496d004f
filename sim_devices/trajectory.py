"""Continuous-trajectory data like seed 004's (Horvath & Neuner): one long, smooth joint path
sampled at a fixed rate, the SMR measured at every sample (about 7,300 samples).

How the trajectory is generated
-------------------------------
Every joint follows a sum of two sinusoids about a centre pose, q_j(t) = c_j + A_j1 sin(2 pi t /
T_j1 + phi_j1) + A_j2 sin(2 pi t / T_j2 + phi_j2), with periods between 23 s and 61 s (phases
from the seed), sampled at `rate_hz` (10 Hz: 7,300 samples = 730 s). The centre pose holds the
arm out in front of the base (shoulder about 20 deg from vertical, elbow bent about 57 deg) so
that gravity loads are large and change a lot, as the paper chose an "outstretched and very
exposed" trajectory. The path is quasi-periodic: the last 20 % (test part) revisits the region
the first 80 % covered, in new combinations. Every sample is checked against the default
safety envelope.

How the non-geometric part is generated
---------------------------------------
From the simulated physics in `sim_devices.truth`, not from a network: joint compliance
(link angle = encoder + c_i tau_i with the gravity + payload torque), link deflection (links 2
and 3 bend as cantilevers) and transmission error (harmonics of joints 1 and 2). These are the
effects that are a function of the joint angles alone (backlash depends on the direction of
motion, thermal drift on time; both are left out so the network's input, the joints, determines
the part it must learn). Their magnitudes are `DEFAULT_MAGNITUDES` multiplied by one common
factor chosen so that the *variation* of the non-geometric part over the trajectory - the
largest peak-to-peak of its three tracker-frame components - is `variation_m` (0.6 mm, as in the
paper). The true non-geometric displacement of each sample is
    smr_in_tracker(q, effects) - smr_in_tracker(q, no effects)     (same true geometry)
and is returned (for scoring only), never recorded.

Measurements: joints = encoder angles + white noise `sigma_q_rad`; SMR = true position + white
tracker noise with the instrument's per-axis sigma at that range (TrackerNoise.sigma_axis; a
continuous measurement has no per-pose systematic part). The recording uses the shared format
with one /campaign/sample per trajectory sample.

    python -m sim_devices.trajectory OUT.mcap [--samples 7300] [--seed 0]
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim_devices.truth import DEFAULT_MAGNITUDES, NOMINAL_SMR_M, TrackerNoise, TrueWorkcell
from sim_devices.truth import make_truth as _make_truth

Q_CENTRE = np.array([0.3, -1.2, 1.0, -1.4, -1.57, 0.0])
Q_AMPL = np.array([[0.45, 0.2], [0.25, 0.12], [0.3, 0.15], [0.4, 0.2], [0.35, 0.15], [0.6, 0.3]])
PERIODS_S = np.array(
    [[47.0, 23.0], [61.0, 29.0], [37.0, 53.0], [41.0, 31.0], [59.0, 27.0], [43.0, 33.0]]
)
NG_EFFECTS = ("joint_compliance", "link_deflection", "transmission_error")


@dataclass
class TrajectoryData:
    truth: TrueWorkcell
    t_s: np.ndarray  # (N,)
    q_true_rad: np.ndarray  # (N, 6) encoder angles (noise-free)
    q_meas_rad: np.ndarray  # (N, 6) recorded joints
    approach_sign: np.ndarray  # (N, 6) sign of joint velocity
    p_meas_m: np.ndarray  # (N, 3) recorded SMR positions, tracker frame
    sigma_m: np.ndarray  # (N, 3) stated per-axis sigma
    p_true_m: np.ndarray  # (N, 3) noise-free SMR positions (scoring only)
    ng_true_m: np.ndarray  # (N, 3) true non-geometric displacement, tracker frame (scoring only)
    effect_scale: float
    sigma_q_rad: float
    base_in_tracker_nominal: dict

    @property
    def variation_m(self) -> float:
        return float(np.max(np.ptp(self.ng_true_m, axis=0)))

    def __len__(self) -> int:
        return len(self.t_s)


def joint_path(n: int, rate_hz: float = 10.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(t (N,), q (N, 6)) of the smooth quasi-periodic joint path."""
    rng = np.random.default_rng(seed)
    phi = rng.uniform(0, 2 * np.pi, Q_AMPL.shape)
    t = np.arange(n) / rate_hz
    arg = 2 * np.pi * t[:, None, None] / PERIODS_S[None] + phi[None]
    q = Q_CENTRE[None] + np.sum(Q_AMPL[None] * np.sin(arg), axis=2)
    return t, q


def _scaled_effects(k: float) -> dict:
    eff = {e: copy.deepcopy(DEFAULT_MAGNITUDES[e]) for e in NG_EFFECTS}
    eff["joint_compliance"]["c_rad_per_nm"] = [
        k * c for c in eff["joint_compliance"]["c_rad_per_nm"]
    ]
    eff["link_deflection"]["flex_m_per_n"] = [k * c for c in eff["link_deflection"]["flex_m_per_n"]]
    eff["transmission_error"]["harmonics"] = {
        j: [(h, k * a, p) for h, a, p in hs]
        for j, hs in eff["transmission_error"]["harmonics"].items()
    }
    return eff


def _positions(truth: TrueWorkcell, q: np.ndarray, sign: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.array([truth.smr_in_tracker(q[i], sign[i], t[i]) for i in range(len(q))])


def make_trajectory(
    robot: str = "ur5e",
    n: int = 7300,
    seed: int = 0,
    *,
    rate_hz: float = 10.0,
    variation_m: float = 0.6e-3,
    sigma_q_rad: float = 1e-5,
    payload_kg: float = 0.5,
    dh_error_scale: float = 1.0,
) -> TrajectoryData:
    """Simulate a continuous trajectory measurement (see the module docstring)."""
    if n < 10:
        raise ValueError(f"trajectory needs at least 10 samples, got {n}")
    from workcell.campaign.envelope import default_envelope

    noise = TrackerNoise(beam_break_prob=0.0, outlier_prob=0.0)
    geo = _make_truth(
        robot, {}, seed, noise=noise, payload_kg=payload_kg, dh_error_scale=dh_error_scale
    )
    t, q = joint_path(n, rate_hz, seed)
    env = default_envelope(geo.nominal)
    bad = [v for v in env.violations(geo.nominal, q[:: max(1, n // 400)], NOMINAL_SMR_M) if v]
    if bad:
        raise ValueError(f"trajectory leaves the envelope: {bad[0]}")
    qd = np.gradient(q, axis=0)
    sign = np.sign(qd)
    p_geo = _positions(geo, q, sign, t)
    # one common factor for the effect magnitudes so that the variation is `variation_m`
    k = 1.0
    for _ in range(2):
        truth = dataclasses.replace(geo, effects=_scaled_effects(k))
        sub = slice(None, None, max(1, n // 500))
        ng = _positions(truth, q[sub], sign[sub], t[sub]) - p_geo[sub]
        var = float(np.max(np.ptp(ng, axis=0)))
        k *= variation_m / var
    truth = dataclasses.replace(geo, effects=_scaled_effects(k))
    p_true = _positions(truth, q, sign, t)
    rng = np.random.default_rng(seed + 4242)
    sig = np.array([noise.sigma_axis(float(np.linalg.norm(p))) for p in p_true])
    sigma = np.repeat(sig[:, None], 3, axis=1)
    p_meas = p_true + rng.normal(0.0, 1.0, p_true.shape) * sigma
    q_meas = q + rng.normal(0.0, sigma_q_rad, q.shape)
    return TrajectoryData(
        truth=truth,
        t_s=t,
        q_true_rad=q,
        q_meas_rad=q_meas,
        approach_sign=sign,
        p_meas_m=p_meas,
        sigma_m=sigma,
        p_true_m=p_true,
        ng_true_m=p_true - p_geo,
        effect_scale=k,
        sigma_q_rad=sigma_q_rad,
        base_in_tracker_nominal=truth.session_nominal(np.random.default_rng(seed + 99)),
    )


def record_trajectory(path: str | Path, traj: TrajectoryData) -> Path:
    """Write the trajectory as a recording (shared format, one /campaign/sample per sample)."""
    from sim_devices.cell import declared_cell
    from workcell.recording.writer import RecordingWriter

    tr = traj.truth
    cell = declared_cell(
        tr,
        0,
        tracker_model="simulated laser tracker (continuous)",
        base_in_tracker=traj.base_in_tracker_nominal,
    )
    session = cell.session(
        {
            "plan": "trajectory",
            "poses": len(traj),
            "rate_hz": float(1.0 / (traj.t_s[1] - traj.t_s[0])),
            "effects": ",".join(NG_EFFECTS),
            "effect_scale": traj.effect_scale,
            "sigma_q_rad": traj.sigma_q_rad,
            "generator": "sim_devices.trajectory",
        }
    )
    with RecordingWriter(path, session) as w:
        t0_ns = time.time_ns()  # the trajectory starts now, after its session
        for i in range(len(traj)):
            t_ns = t0_ns + int(round(traj.t_s[i] * 1e9))
            w.sample(
                t_ns,
                {
                    "index": i,
                    "pose_id": i,
                    "q_commanded_rad": traj.q_true_rad[i],
                    "q_measured_rad": traj.q_meas_rad[i],
                    "approach_sign": traj.approach_sign[i].astype(int),
                    "tracker_position_m": traj.p_meas_m[i],
                    "tracker_sigma_m": traj.sigma_m[i],
                    "n_readings": 1,
                    "joint_temperature_c": tr.joint_temperatures_c(traj.t_s[i]),
                    "ambient_temperature_c": tr.ambient_c,
                    "elapsed_s": float(traj.t_s[i]),
                    "payload_kg": float(tr.declared_payload_kg),
                },
                flush=False,
            )
    return Path(path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sim_devices.trajectory", description=__doc__)
    ap.add_argument("out")
    ap.add_argument("--samples", type=int, default=7300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--robot", default="ur5e")
    a = ap.parse_args(argv)
    traj = make_trajectory(a.robot, a.samples, a.seed)
    p = record_trajectory(a.out, traj)
    print(
        f"{p}: {len(traj)} samples, non-geometric variation {traj.variation_m * 1e3:.3f} mm "
        f"(effect scale {traj.effect_scale:.3f})"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
