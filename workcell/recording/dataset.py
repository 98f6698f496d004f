"""In-memory dataset every estimator takes: arrays of pose samples plus the session's nominal model.

Built from a recording (`Dataset.from_recording`; a resumed one with every file it continues,
`workcell.recording.chain`) or directly from arrays (simulation, tests).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from workcell.kinematics.frames import matrix_from_quat_wxyz, transform_from
from workcell.kinematics.robots import RobotSpec
from workcell.recording import checks, consistency
from workcell.recording.chain import Chain, file_sha256, load_chain  # noqa: F401 - file_sha256: here since before
from workcell.recording.checks import is_finite_list
from workcell.recording.reader import Recording, RecordingError

HOLDOUT_SEED = 20240601


def holdout_indices(
    n: int, fraction: float = 0.25, groups: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The deterministic split of n poses in recording order (fixed-seed permutation):
    (train indices, held-out indices); what `Dataset.holdout_split` and the fits use.
    `groups` (n,): the samples of one group (one pose measured again, e.g. a reference) go to
    the same side, and to training unless the singly measured poses cannot fill the held-out
    share: so a held-out figure counts each pose once. Without repeats the split is the
    ungrouped one, sample for sample."""
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"holdout fraction must be in [0, 1), got {fraction}")
    n_test = int(round(fraction * n))
    perm = np.random.default_rng(HOLDOUT_SEED).permutation(n)
    if groups is None:
        return np.sort(perm[n_test:]), np.sort(perm[:n_test])
    _, g = np.unique(np.asarray(groups), return_inverse=True)
    g = np.asarray(g).ravel()
    size = np.bincount(g)
    test = np.zeros(n, bool)
    taken = 0
    for i in perm:  # singly measured poses first, in the permutation's order
        if size[g[i]] == 1 and taken < n_test:
            test[i] = True
            taken += 1
    if taken < n_test:  # too few: whole repeated groups, in the order they first appear
        for i in perm:
            if taken >= n_test:
                break
            if size[g[i]] > 1 and not test[i]:
                members = g == g[i]
                test |= members
                taken += int(members.sum())
    return np.flatnonzero(~test), np.flatnonzero(test)


@dataclass
class Dataset:
    robot: RobotSpec
    tool_offset_m: np.ndarray  # (3,) nominal SMR in flange
    tracker_T_base_nominal: np.ndarray  # (4, 4) (may be rough)
    q: np.ndarray  # (N, n) measured joints (n = robot.n_joints; 6 in recordings)
    p_tracker: np.ndarray  # (N, 3)
    sigma_m: np.ndarray  # (N, 3)
    q_commanded: np.ndarray | None = None
    approach_sign: np.ndarray | None = None  # (N, n)
    joint_temperature_c: np.ndarray | None = None  # (N, n), nan where unknown
    ambient_temperature_c: np.ndarray | None = None  # (N,)
    elapsed_s: np.ndarray | None = None
    payload_kg: np.ndarray | None = None
    payload_com_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    pose_id: np.ndarray | None = None
    # (N,) index of each sample among the recording's samples (log-time order; of a resumed
    # recording, among its chain's, oldest file first: `Chain.samples`): the screens of
    # `from_recording` leave some out (`consistency`); a replay streams the same ones
    row: np.ndarray | None = None
    session: dict = field(default_factory=dict)
    source: str = ""
    source_sha256: str = ""
    # what the reader could not read (a damaged chunk, a cut-off end): the data set is what
    # came before or around it; commands print these as warnings
    read_problems: tuple[str, ...] = ()
    # what the reader assumed for fields the format requires and the recording lacks (a file
    # written by another tool): commands print these as warnings too
    read_notes: tuple[str, ...] = ()
    # a resumed recording: {path, sha256, samples} of every file of its chain, oldest first
    # (this one last; `row` indexes their samples in that order), and the line that says so
    chain: tuple[dict, ...] = ()
    chain_line: str = ""

    def __post_init__(self) -> None:
        n = len(self.q)
        nj = self.robot.n_joints
        if self.q.shape != (n, nj) or self.p_tracker.shape != (n, 3):
            raise ValueError(
                f"dataset: q {self.q.shape} and p_tracker {self.p_tracker.shape} differ "
                f"(expected ({n}, {nj}) and ({n}, 3))"
            )
        if self.approach_sign is None:
            self.approach_sign = np.zeros((n, nj))
        if self.joint_temperature_c is None:
            self.joint_temperature_c = np.full((n, nj), np.nan)
        if self.ambient_temperature_c is None:
            self.ambient_temperature_c = np.full(n, np.nan)
        if self.elapsed_s is None:
            self.elapsed_s = np.arange(n, dtype=float)
        if self.payload_kg is None:
            self.payload_kg = np.zeros(n)
        if self.pose_id is None:
            self.pose_id = np.arange(n)
        if self.row is None:
            self.row = np.arange(n)
        if self.q_commanded is None:
            self.q_commanded = self.q.copy()

    def __len__(self) -> int:
        return len(self.q)

    def subset(self, idx: npt.ArrayLike) -> Dataset:
        idx = np.asarray(idx)
        arrays = {}
        for k in (
            "q",
            "p_tracker",
            "sigma_m",
            "q_commanded",
            "approach_sign",
            "joint_temperature_c",
            "ambient_temperature_c",
            "elapsed_s",
            "payload_kg",
            "pose_id",
            "row",
        ):
            arrays[k] = getattr(self, k)[idx]
        return replace(self, **arrays)

    def holdout_split(self, fraction: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
        """Deterministic split (fixed-seed permutation): (train indices, held-out indices)."""
        return holdout_indices(len(self), fraction, self.pose_groups())

    def pose_groups(self) -> np.ndarray:
        """(N,) group of each sample: samples of one pose measured again (same pose_id, same
        commanded configuration, e.g. `campaign --reference-every`) share a group, so a split
        never trains on one of them and tests on another."""
        q = self.q_commanded if self.q_commanded is not None else self.q
        key = np.round(np.nan_to_num(np.asarray(q, float)) / 1e-6).astype(np.int64)
        _, g = np.unique(
            np.c_[np.asarray(self.pose_id, np.int64), key], axis=0, return_inverse=True
        )
        return np.asarray(g).ravel()

    @classmethod
    def from_recording(
        cls, rec: Recording | Chain | str | os.PathLike, *, chain_missing: str = "refuse"
    ) -> Dataset:
        """The data set of a recording and of every file it continues (a resumed campaign's
        `chained_from` chain, `workcell.recording.chain.load_chain`): their samples in the order
        of measurement, the nominal model of the newest file's session. A link of the chain
        missing or changed is refused in one line unless `chain_missing` is "ignore"."""
        ch = rec if isinstance(rec, Chain) else load_chain(rec, missing=chain_missing)
        rec = ch.newest
        s = rec.session
        try:
            robot = checks.session_robot(s)
        except ValueError as e:
            raise RecordingError(f"{rec.path}: {e}") from None
        rows = ch.samples
        if not rows:
            why = f" ({rec.problems[0]})" if rec.problems else ""
            raise RecordingError(f"{rec.path}: no /campaign/sample messages{why}; nothing to fit")
        read_problems = list(rec.problems)
        for r in ch.recordings:
            if r is not rec:
                _check_same_cell(rec, r)
                read_problems += [f"in {r.path.name}, which it continues: {p}" for p in r.problems]
            problems = checks.recording_problems(r.session, r.samples, robot)
            if problems:
                raise RecordingError(f"{r.path}: {checks.first_problem(problems)}")
        notes = list(ch.notes)
        kept = list(range(len(rows)))
        copies = consistency.exact_copies(rows)
        if copies:
            notes.append(
                f"{len(copies)} of {len(rows)} samples are exact copies of earlier ones (same "
                "pose_id, joints and tracker position: a stream written twice?); each is used once"
            )
            drop = set(copies)
            kept = [i for i in kept if i not in drop]
            rows = [rows[i] for i in kept]
        tool = s["tool"]["smr_offset_m"]
        bit = s["tracker"]["base_in_tracker"]
        t, qw = bit["translation_m"], bit["quaternion_wxyz"]
        T = transform_from(matrix_from_quat_wxyz(np.array(qw, float)), np.array(t, float))
        n = len(rows)

        def arr(key, width, default):  # every field read here passed `checks.sample_problems`
            out = np.full((n, width) if width else n, default, dtype=float)
            for i, r in enumerate(rows):
                if r.get(key) is not None:
                    out[i] = np.asarray(r[key], dtype=float)
            return out

        q = arr("q_measured_rad", 6, np.nan)
        sig = arr("tracker_sigma_m", 3, np.nan)
        bad = ~np.isfinite(sig) | (sig <= 0)
        if bad.any():  # unknown sigma: use the median of the known ones, or 10 um
            good = sig[~bad]
            sig[bad] = np.median(good) if good.size else 1e-5
            notes.append(
                f"{int(bad.any(1).sum())} of {n} samples have no usable tracker_sigma_m; their "
                + (
                    f"weights use the median recorded sigma, {np.median(good) * 1e6:.1f} um"
                    if good.size
                    else "weights and the noise floor assume 10 um (none was recorded)"
                )
            )
        for key, means in (
            ("approach_sign", "backlash cannot be tested"),
            ("elapsed_s", "drift over time cannot be tested"),
            ("payload_kg", "the session's payload is assumed"),
        ):
            lacking = sum(1 for r in rows if r.get(key) is None)
            if lacking:
                notes.append(f"{lacking} of {n} samples have no {key}: {means} for those")
        payload = s.get("payload") or {}
        pkg = arr("payload_kg", 0, float(payload.get("mass_kg") or 0.0))
        com = payload.get("com_m")
        ds = cls(
            robot=robot,
            tool_offset_m=np.asarray(tool, float),
            tracker_T_base_nominal=T,
            q=q,
            p_tracker=arr("tracker_position_m", 3, np.nan),
            sigma_m=sig,
            q_commanded=arr("q_commanded_rad", 6, np.nan),
            approach_sign=arr("approach_sign", 6, 0.0),
            joint_temperature_c=arr("joint_temperature_c", 6, np.nan),
            ambient_temperature_c=arr("ambient_temperature_c", 0, np.nan),
            elapsed_s=arr("elapsed_s", 0, np.nan),
            payload_kg=pkg,
            payload_com_m=np.asarray(com if is_finite_list(com, 3) else [0.0, 0.0, 0.0], float),
            pose_id=arr("pose_id", 0, -1).astype(int),
            row=np.asarray(kept, int),
            session=s,
            source=os.path.abspath(rec.path),
            source_sha256=ch.sha256[-1],
            chain=tuple(ch.files()) if len(ch.recordings) > 1 else (),
            chain_line=ch.line(),
            read_problems=tuple(read_problems),
            read_notes=tuple(notes),
        )
        return replace(ds, read_notes=(*ds.read_notes, *ds.suspect_sample_notes())).screened()

    def suspect_sample_notes(self) -> list[str]:
        """Notes on samples the fit uses as they are but which say something went wrong:
        joints measured far from where they were commanded (the arm did not reach its target),
        and a pose measured again far beyond the tracker's noise from its first reading (the
        set-up or the arm moved between them, or the file holds a pose twice). Both were read
        without a word (fuzz audit, 2026-11-29: 1 rad off; every pose twice, 3 mm apart)."""
        out = []
        if self.q_commanded is not None and len(self):
            d = np.abs(np.asarray(self.q_commanded, float) - np.asarray(self.q, float))
            d = np.where(np.isfinite(d), d, 0.0)
            off = d.max(axis=1) > ARRIVAL_NOTE_RAD
            if off.any():
                i, j = np.unravel_index(int(np.argmax(d)), d.shape)
                out.append(
                    f"{int(off.sum())} of {len(self)} samples were measured with joints more "
                    f"than {ARRIVAL_NOTE_RAD * 1e3:g} mrad from their commanded ones (up to "
                    f"{d[i, j]:.3g} rad, joint {j + 1} of pose {int(self.pose_id[i])}): the arm "
                    "did not reach its target; the fit uses the measured joints"
                )
        if self.pose_id is not None and len(np.unique(self.pose_id)) < len(self):
            if (step := self._largest_repeat_step()) is not None:
                n, pid, jump, noise = step
                out.append(
                    f"{n} pose(s) measured again more than {REPEAT_NOTE_FACTOR:g}x the tracker's "
                    f"noise from their previous reading (pose {pid}: a step of {jump * 1e6:.0f} "
                    f"um, noise {noise * 1e6:.0f} um): the set-up or the arm moved between them, "
                    "or the file holds a pose twice; `workcell info` lists the repeats"
                )
        return out

    def _largest_repeat_step(self) -> tuple[int, int, float, float] | None:
        """Among poses measured more than once: how many moved between two consecutive
        readings by over REPEAT_NOTE_FACTOR x the noise of a difference, and the worst one's
        (pose id, step m, noise m); None when none did. Steps, not the distance from the first
        reading: a reference pose drifting smoothly with the arm's temperature (227 um over
        160 min in a simulated cell, 3 min apart) is what `--reference-every` records, a step
        is a set-up that moved (a review, 2026-11-29)."""
        from workcell.recording.repeats import reading_sigma

        groups = self.pose_groups()
        sig = reading_sigma(self.sigma_m, self.p_tracker)
        order = np.lexsort((np.asarray(self.elapsed_s, float), groups))  # by pose, then time
        a, b = order[:-1], order[1:]
        same = groups[a] == groups[b]  # consecutive readings of one pose
        a, b = a[same], b[same]
        jump = np.linalg.norm(self.p_tracker[b] - self.p_tracker[a], axis=1)
        noise = np.sqrt(np.sum(sig[a] ** 2 + sig[b] ** 2, axis=1))
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.where(np.isfinite(jump / noise), jump / noise, -np.inf)
        over = ratio > REPEAT_NOTE_FACTOR
        if not over.any():
            return None
        k = int(np.argmax(ratio))
        n = len(np.unique(groups[a[over]]))
        return n, int(self.pose_id[a[k]]), float(jump[k]), float(noise[k])

    def provenance(self) -> dict:
        """What a model file records of the data it was fitted on: the recording (path and
        sha256) and, for a resumed one, every file of its chain."""
        out = {"recording": self.source, "recording_sha256": self.source_sha256}
        if self.chain:
            out["recording_chain"] = [dict(f) for f in self.chain]
        return out

    def screened(self) -> Dataset:
        """Refuse data that does not follow the arm; set gross readings aside, with a note
        (`workcell.recording.consistency`)."""
        n = len(self)
        if n < consistency.MIN_SAMPLES:
            return self
        dist = consistency.nominal_distances(self.robot, self.tool_offset_m, self.q, self.p_tracker)
        med = float(np.median(dist))
        if not med <= consistency.GROSS_M:
            raise RecordingError(
                f"{self.source}: {consistency.mismatch_message(self.robot, med, n)}"
            )
        gross = dist > consistency.GROSS_M
        if not gross.any():
            return self
        note = consistency.gross_note(self.pose_id[gross], dist[gross], n)
        kept = self.subset(np.flatnonzero(~gross))
        return replace(kept, read_notes=(*self.read_notes, note))


def _check_same_cell(rec: Recording, older: Recording) -> None:
    """The files of a chain are fitted together: they must declare the same arm and SMR offset
    (a resume keeps them; a difference is a hand-edited or foreign file)."""
    a, b = rec.session, older.session
    for what, get in (
        ("robot model", lambda s: (s.get("robot") or {}).get("model")),
        ("nominal DH", lambda s: (s.get("robot") or {}).get("dh")),
        ("SMR offset", lambda s: (s.get("tool") or {}).get("smr_offset_m")),
    ):
        if get(a) != get(b):
            raise RecordingError(
                f"{rec.path} continues {older.path}, which declares another {what}; their poses "
                "cannot be fitted together (edited by hand?): restore the files as recorded"
            )


def read_warnings(ds: Dataset | Recording) -> list[str]:
    """One warning line per reader problem, up to READ_WARNINGS_SHOWN; more are one line with
    the first and their count (a file with seven damaged chunks gave seven lines): data may be
    missing and the fit would not show it. `workcell info` lists them all."""
    notes: tuple[str, ...] = ()
    if isinstance(ds, Recording):
        source, problems, n = ds.path, ds.problems, len(ds.samples)
    else:
        source, problems, n = ds.source, ds.read_problems, len(ds)
        notes = ds.read_notes
    using = f"using the {n} samples that could be read"
    if len(problems) > READ_WARNINGS_SHOWN:
        lines = [
            f"warning: {source}: {len(problems)} problems reading it, the first: {problems[0]}; "
            f"{using} (`workcell info {source}` lists them all)"
        ]
    else:
        lines = [f"warning: {source}: {p}; {using}" for p in problems]
    return lines + [f"warning: {source}: {x}" for x in notes]


READ_WARNINGS_SHOWN = 2
# a sample's measured joints this far from its commanded ones (the campaign's arrival check is
# 0.2 mrad; ~1 mm at the SMR): a note
ARRIVAL_NOTE_RAD = 1e-3
# a pose measured again this many times the tracker's noise from its previous reading: a note
REPEAT_NOTE_FACTOR = 10.0


DISTINCT_TOL_RAD = 1e-4  # 50x the encoders' noise (~2 urad): a pose measured again is one pose


def distinct_poses(q: np.ndarray, tol_rad: float = DISTINCT_TOL_RAD) -> int:
    """How many different joint configurations `q` (N, n) holds: configurations within
    `tol_rad` of each other on every joint, directly or through a chain of such neighbours, are
    one (the same pose measured again adds no geometry). Until 2026-11-26 this rounded at
    1 urad, below the encoders' noise, so a pose measured again counted as another one."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    q = np.nan_to_num(np.asarray(q, float))
    if len(q) == 0:
        return 0
    pairs = cKDTree(q).query_pairs(tol_rad, p=np.inf, output_type="ndarray")
    n = len(q)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return int(connected_components(g, directed=False)[0])
