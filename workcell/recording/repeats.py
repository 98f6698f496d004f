"""Poses measured more than once in a recording (`campaign --reference-every`, or another tool's
repeat measurements): how far the measured position of a fixed pose moved during the campaign,
against what the tracker alone gives. A drift of the whole measurement (temperature, the
tracker, the set-up) shows here directly, without any model."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from workcell.recording.dataset import Dataset
from workcell.recording.tracker_spec import tracker_spec_sigma

if TYPE_CHECKING:
    from workcell.recording.reader import Recording


def reading_sigma(sigma_m: npt.ArrayLike, p_tracker: np.ndarray) -> np.ndarray:
    """Per-axis sigma of recorded means (N, 3) or (3,) at `p_tracker`: at least the tracker's
    stated MPE / 4 (an unknown, NaN, sigma is that floor), as the fits weight them."""
    s = np.asarray(sigma_m, float)
    floor = tracker_spec_sigma(p_tracker)
    return np.fmax(s, floor[:, None] if s.ndim == 2 else floor[0])


def repeat_drift(ds: Dataset) -> list[dict]:
    """One entry per pose measured at least twice (same pose_id and commanded configuration),
    in order of its first measurement: `pose_id`, `measurements`, `span_s` (first to last),
    `displacement_m` of each measurement from the first (3-D, m; the first is 0), `elapsed_s`,
    `max_m`, `last_m`, `rms_m` (over the repeats), and `noise_m`: the RMS 3-D difference the
    measurement alone would give, each reading's sigma per axis being max(recorded sigma of the
    mean, the tracker's stated MPE / 4) as the fits weight them: the recorded sigma leaves out
    the tracker's per-pose systematic error, and a cell without drift then looked 3x off. (The
    arm's own repeatability comes on top.)"""
    groups = ds.pose_groups()
    _, first, counts = np.unique(groups, return_index=True, return_counts=True)
    t = np.asarray(ds.elapsed_s, float)
    s = reading_sigma(ds.sigma_m, ds.p_tracker)
    out = []
    for k in np.argsort(first):
        if counts[k] < 2:
            continue
        idx = np.flatnonzero(groups == groups[first[k]])
        idx = idx[np.argsort(t[idx], kind="stable")]
        d = np.linalg.norm(ds.p_tracker[idx] - ds.p_tracker[idx[0]], axis=1)
        noise = np.sqrt(np.sum(s[idx[1:]] ** 2 + s[idx[0]] ** 2, axis=1))
        out.append(
            {
                "pose_id": int(ds.pose_id[idx[0]]),
                "measurements": int(len(idx)),
                "span_s": float(t[idx[-1]] - t[idx[0]]),
                "elapsed_s": t[idx].tolist(),
                "displacement_m": d.tolist(),
                "max_m": float(d[1:].max()),
                "last_m": float(d[-1]),
                "rms_m": float(np.sqrt(np.mean(d[1:] ** 2))),
                "noise_m": float(np.sqrt(np.mean(noise**2))),
            }
        )
    return out


def repeat_beyond_noise(r: dict, level: float = 0.99) -> bool:
    """Whether a `repeat_drift` entry moved more than the tracker alone explains: its repeats'
    mean square displacement beyond the `level` quantile of noise_m^2 chi-square(3 m) / (3 m),
    m the number of repeats (taken as independent; they share the first reading, which makes
    this a little lenient)."""
    from scipy.stats import chi2

    m = max(int(r["measurements"]) - 1, 1)
    noise = float(r["noise_m"])
    if not np.isfinite(noise) or noise <= 0:
        return False
    return bool(r["rms_m"] ** 2 > noise**2 * chi2.ppf(level, 3 * m) / (3 * m))


def repeats_of(rec: Recording) -> list[dict]:
    """`repeat_drift` of a read recording, with the files it continues (a resumed campaign's
    reference pose is compared with its first reading, in the first file); none when its
    samples do not make a dataset (a damaged or foreign file: its problems are reported
    elsewhere). A link of the chain that is missing or changed is left out here (`workcell
    info` says so)."""
    if not rec.samples and not rec.session.get("chained_from"):
        return []
    try:
        from workcell.recording.chain import load_chain

        return repeat_drift(Dataset.from_recording(load_chain(rec, missing="ignore")))
    except Exception:  # noqa: BLE001 - an optional extra must not sink a report on a bad file
        return []


def repeat_line(r: dict) -> str:
    """One line for a `repeat_drift` entry."""
    um = 1e6
    return (
        f"pose {r['pose_id']} measured {r['measurements']} times over {r['span_s'] / 60:.1f} "
        f"min: up to {r['max_m'] * um:.1f} um from its first reading (last {r['last_m'] * um:.1f}"
        f" um, RMS {r['rms_m'] * um:.1f} um); the tracker alone (its readings' scatter, at least "
        f"its stated accuracy) would give about {r['noise_m'] * um:.1f} um"
    )


class RepeatWatch:
    """Live: each sample of a pose measured before (the reference of `campaign
    --reference-every`) is compared with that pose's first reading as it arrives. `first`:
    {pose_id: first sample} of a recording a resume continues."""

    def __init__(self, first: dict[int, dict] | None = None) -> None:
        self.first: dict[int, dict] = dict(first or {})

    def update(self, sample: dict) -> dict | None:
        """None for a pose's first sample; else `pose_id`, `elapsed_s`, `displacement_m` (3-D,
        from the first reading) and `noise_m` (what the two readings' recorded sigmas give)."""
        pid = int(sample["pose_id"])
        first = self.first.get(pid)
        if first is None:
            self.first[pid] = sample
            return None
        p0 = np.asarray(first["tracker_position_m"], float)
        p1 = np.asarray(sample["tracker_position_m"], float)
        s0 = reading_sigma(first.get("tracker_sigma_m", [np.nan] * 3), p0)
        s1 = reading_sigma(sample.get("tracker_sigma_m", [np.nan] * 3), p1)
        return {
            "pose_id": pid,
            "elapsed_s": float(sample.get("elapsed_s", np.nan)),
            "displacement_m": float(np.linalg.norm(p1 - p0)),
            "noise_m": float(np.sqrt(np.sum(s0**2 + s1**2))),
        }


def repeat_event_line(r: dict) -> str:
    """One line for a `RepeatWatch.update` result."""
    noise = r["noise_m"]
    scatter = f"; the tracker alone gives ~{noise * 1e6:.1f} um" if noise == noise else ""
    return (
        f"pose {r['pose_id']} measured again at {r['elapsed_s'] / 60:.1f} min: "
        f"{r['displacement_m'] * 1e6:.1f} um from its first reading{scatter}"
    )
