"""Volumetric correction table: commanded = desired + delta(desired), trilinear in a box grid.

One grid per declared tool orientation (UR rotation vector of the flange in base). The grid spacing
is chosen for a stated interpolation error: the spacing is refined until the worst trilinear error
on random points of the volume (against the exact correction) is below it. The same interpolation
is written into the URScript export (`urscript.py`); `interpolate` here is its reference.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from workcell import strict_json
from workcell.atomic import atomic_files
from workcell.errors import UserError
from workcell.export.correction import (
    CONFIGURATION_BASIS,
    Q_REF,
    Corrector,
    configuration,
    configuration_dh,
    matrix_to_rotvec,
    pad_batch,
    rotvec_to_matrix,
)
from workcell.export.frame import frame_lines, frame_meta
from workcell.recording.checks import DH_LENGTH_MAX_M, is_finite_number

if TYPE_CHECKING:
    from workcell.estimation.models import FittedModel
    from workcell.kinematics.robots import RobotSpec

TABLE_FORMAT = "workcell-correction-table/1"
DEFAULT_MAX_CORRECTION_M = 5e-3
MAX_FIXED_NODES = 100_000  # per orientation, for a fixed --spacing (each node is an IK solve)
DEFAULT_INTERP_ERROR_M = 5e-6
DEFAULT_ORIENTATION_TOL_RAD = 0.05
MAX_CORRECTION_BOUND_M = 0.1  # no calibration corrects by more: beyond, a unit mistake
DEGREES_HINT = "it looks like degrees, give radians (UR rotation vectors)"
OUTSIDE_TOL_M = 1e-6  # targets this far outside the box are still accepted (clamped cell)


def beyond_full_turn(rotvec: np.ndarray) -> tuple[int, float] | None:
    """(index, angle in rad) of the longest of the rotation vectors (N, 3) when it is longer
    than a full turn (one in degrees), else None."""
    with np.errstate(over="ignore"):  # 1e300: an inf angle, refused, without a warning
        turn = np.linalg.norm(np.asarray(rotvec, float).reshape(-1, 3), axis=1)
    if not np.any(turn > 2 * np.pi + 1e-9):
        return None
    i = int(np.argmax(turn))
    return i, float(turn[i])


class CorrectionRefused(UserError):
    """The model's correction is non-finite or too large somewhere in the declared volume."""


def default_volume(robot_spec: RobotSpec) -> tuple[np.ndarray, np.ndarray]:
    """A working box in front of the robot, scaled by its arm length (SMR positions, base)."""
    arm = float(abs(robot_spec.dh.a[1]) + abs(robot_spec.dh.a[2]))
    lo = np.array([-0.3, -0.67, 0.2]) * arm
    hi = np.array([0.3, -0.3, 0.55]) * arm
    return lo, hi


@dataclass
class CorrectionTable:
    lo_m: np.ndarray  # (3,)
    hi_m: np.ndarray  # (3,)
    shape: tuple[int, int, int]
    orientations_rotvec: np.ndarray  # (K, 3)
    delta_m: np.ndarray  # (K, nx, ny, nz, 3): commanded - desired
    q_nodes: np.ndarray | None = None  # (K, nx, ny, nz, 6) corrected joints (seeds), not saved
    # (K, nx, ny, nz, 3) 1-sigma of each correction component (base axes) from the model's
    # parameter covariance; None when the model carries none (`node_std`)
    std_m: np.ndarray | None = None
    meta: dict = field(default_factory=dict)
    orientation_tol_rad: float = DEFAULT_ORIENTATION_TOL_RAD
    # (K, 3) arm configuration signs (shoulder, elbow, wrist) each orientation's corrections were
    # solved on, and the nominal (a2, a3, d5) that defines them (`CONFIGURATION_BASIS`); None in
    # tables written before they were recorded
    configurations: np.ndarray | None = None
    configuration_dh_m: tuple[float, float, float] | None = None

    @property
    def spacing_m(self) -> np.ndarray:
        return (self.hi_m - self.lo_m) / (np.asarray(self.shape) - 1)

    def node_positions(self) -> np.ndarray:
        """(nx, ny, nz, 3) grid node positions in base."""
        axes = [np.linspace(self.lo_m[i], self.hi_m[i], self.shape[i]) for i in range(3)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)

    def orientation_index(self, rotvec: np.ndarray | None) -> int:
        if rotvec is None:
            return 0
        R = rotvec_to_matrix(rotvec)[0]
        Rk = rotvec_to_matrix(self.orientations_rotvec)
        ang = [np.linalg.norm(matrix_to_rotvec(Ri.T @ R)) for Ri in Rk]
        k = int(np.argmin(ang))
        if ang[k] > self.orientation_tol_rad:
            raise UserError(
                f"orientation {np.round(rotvec, 4).tolist()} is {ang[k]:.3g} rad from the nearest "
                f"orientation of the table (tolerance {self.orientation_tol_rad:.3g} rad: a "
                "tilt within it changes the correction by at most the interpolation error "
                "target); command the table's orientation, or export a table for this one "
                "(--orientation)"
            )
        return k

    def interpolate(self, p: np.ndarray, k: int = 0, D: np.ndarray | None = None) -> np.ndarray:
        """Trilinear delta (N, 3) at positions p (N, 3) (of the node values D (nx, ny, nz, 3)
        if given); raises outside the box."""
        p = np.atleast_2d(np.asarray(p, float))
        out = np.empty_like(p)
        for n, x in enumerate(p):
            out[n] = self._interp_one(x, k, D)
        return out

    def _interp_one(self, x: np.ndarray, k: int, D: np.ndarray | None = None) -> np.ndarray:
        # Written operation for operation as the URScript function (see urscript.py); D: the
        # node values (nx, ny, nz, 3), the corrections of orientation k unless given.
        if np.any(x < self.lo_m - OUTSIDE_TOL_M) or np.any(x > self.hi_m + OUTSIDE_TOL_M):
            raise UserError(
                f"target {np.round(x, 4).tolist()} m (base) is outside the correction volume "
                f"{np.round(self.lo_m, 4).tolist()}..{np.round(self.hi_m, 4).tolist()}"
            )
        h = self.spacing_m
        idx, t = [], []
        for a in range(3):
            f = (x[a] - self.lo_m[a]) / h[a]
            i = math.floor(f)
            i = min(max(i, 0), self.shape[a] - 2)
            idx.append(i)
            t.append(f - i)
        D = self.delta_m[k] if D is None else D
        i, j, l = idx
        tx, ty, tz = t
        c00 = D[i, j, l] * (1 - tx) + D[i + 1, j, l] * tx
        c10 = D[i, j + 1, l] * (1 - tx) + D[i + 1, j + 1, l] * tx
        c01 = D[i, j, l + 1] * (1 - tx) + D[i + 1, j, l + 1] * tx
        c11 = D[i, j + 1, l + 1] * (1 - tx) + D[i + 1, j + 1, l + 1] * tx
        c0 = c00 * (1 - ty) + c10 * ty
        c1 = c01 * (1 - ty) + c11 * ty
        return c0 * (1 - tz) + c1 * tz

    def interpolate_std(self, p: np.ndarray, k: int = 0) -> np.ndarray | None:
        """Trilinear 1-sigma (N, 3) of the correction at positions p (an upper bound of the
        interpolated correction's std: `STD_BASIS`); None when the table carries none."""
        if self.std_m is None:
            return None
        return self.interpolate(p, k, self.std_m[k])

    def correct(
        self,
        p: np.ndarray,
        rotvec: np.ndarray | None = None,
        q_actual: np.ndarray | None = None,
    ) -> np.ndarray:
        """Commanded positions for desired positions p (N, 3) at one tool orientation. With
        `q_actual` (the arm's joints, 6), refuses an arm on another configuration than the
        table's (`check_configuration`)."""
        k = self.orientation_index(rotvec)
        if q_actual is not None:
            self.check_configuration(q_actual, k)
        p = np.atleast_2d(np.asarray(p, float))
        return p + self.interpolate(p, k)

    def check_configuration(self, q_actual: np.ndarray, k: int = 0) -> None:
        """Raise UserError when joints q_actual are not on the arm configuration orientation k's
        corrections were solved on (nothing to check in a table without configurations)."""
        if self.configurations is None or self.configuration_dh_m is None:
            return
        got = configuration(np.asarray(q_actual, float).reshape(1, 6), self.configuration_dh_m)[0]
        want = self.configurations[k]
        if not np.array_equal(got, want):
            names = ("shoulder", "elbow", "wrist")
            diff = ", ".join(
                f"{n} {int(g):+d} (table {int(w):+d})"
                for n, g, w in zip(names, got, want, strict=True)
                if g != w
            )
            raise UserError(
                f"the arm is on another configuration than the table's: {diff}; the correction "
                "holds on the table's only: move the arm to that configuration, or export a "
                "table for this one"
            )

    def seed_for(self, p: np.ndarray, k: int = 0) -> np.ndarray:
        """Joint seeds (N, 6) for positions p: the corrected joints of the nearest node."""
        if self.q_nodes is None:
            return np.tile(Q_REF, (len(np.atleast_2d(p)), 1))
        p = np.atleast_2d(np.asarray(p, float))
        ijk = np.rint((p - self.lo_m) / self.spacing_m).astype(int)
        ijk = np.clip(ijk, 0, np.asarray(self.shape) - 1)
        return self.q_nodes[k][ijk[:, 0], ijk[:, 1], ijk[:, 2]]

    # ------------------------------------------------------------------ files
    def to_dict(self) -> dict:
        return {
            "format": TABLE_FORMAT,
            "meta": self.meta,
            "grid": {
                "frame": "base_ref (meta.base_ref: tracker_T_base; see meta.frame)",
                "units": "m",
                "lo_m": self.lo_m.tolist(),
                "hi_m": self.hi_m.tolist(),
                "shape": list(self.shape),
                "spacing_m": self.spacing_m.tolist(),
                "index_order": "orientation, x, y, z (z fastest)",
            },
            "orientations_rotvec": np.asarray(self.orientations_rotvec).tolist(),
            "orientation_tol_rad": self.orientation_tol_rad,
            "delta_m": self.delta_m.tolist(),
            "std_m": None if self.std_m is None else self.std_m.tolist(),
            "configuration": None
            if self.configurations is None
            else {
                "signs_shoulder_elbow_wrist": np.asarray(self.configurations, int).tolist(),
                "dh_m": list(self.configuration_dh_m),
                "basis": CONFIGURATION_BASIS,
            },
        }

    @classmethod
    def from_dict(cls, d: dict) -> CorrectionTable:
        if d.get("format") != TABLE_FORMAT:
            raise UserError(f"not a correction table (format is not {TABLE_FORMAT})")
        g = d["grid"]
        if not isinstance(d.get("meta", {}), dict):
            raise ValueError("meta must be an object")
        shape = g["shape"]
        if not (
            isinstance(shape, list)
            and len(shape) == 3
            and all(isinstance(x, int) and not isinstance(x, bool) and x >= 2 for x in shape)
        ):
            raise ValueError(f"grid shape must be 3 whole numbers >= 2, got {str(shape)[:60]}")
        tab = cls(
            lo_m=_numbers(g["lo_m"], "grid lo_m"),
            hi_m=_numbers(g["hi_m"], "grid hi_m"),
            shape=tuple(shape),
            orientations_rotvec=_numbers(d["orientations_rotvec"], "orientations_rotvec").reshape(
                -1, 3
            ),
            delta_m=_numbers(d["delta_m"], "delta_m"),
            std_m=None if d.get("std_m") is None else _numbers(d["std_m"], "std_m"),
            meta=d.get("meta", {}),
            orientation_tol_rad=float(
                _numbers(d.get("orientation_tol_rad", DEFAULT_ORIENTATION_TOL_RAD), "tolerance")
            ),
        )
        cfg = d.get("configuration")
        if cfg is not None:
            signs = _numbers(cfg["signs_shoulder_elbow_wrist"], "configuration signs")
            dh = _numbers(cfg["dh_m"], "configuration dh_m")
            K = len(tab.orientations_rotvec)
            if signs.shape != (K, 3) or not np.all(np.isin(signs, (-1.0, 1.0))):
                raise ValueError(f"configuration signs must be {K} triples of -1/+1")
            if dh.shape != (3,) or not np.all(np.isfinite(dh)):
                raise ValueError("configuration dh_m must be 3 finite lengths (a2, a3, d5)")
            tab.configurations = signs.astype(int)
            tab.configuration_dh_m = tuple(float(x) for x in dh)
        tab.check()
        return tab

    def check(self) -> None:
        """Raise ValueError naming the first inconsistency (a controller must not use it)."""
        lo, hi, K = self.lo_m, self.hi_m, len(self.orientations_rotvec)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite([lo, hi])):
            raise ValueError("grid lo_m/hi_m must be 3 finite numbers each")
        if np.any(hi <= lo):
            raise ValueError(f"grid needs lo < hi per axis, got {lo.tolist()}..{hi.tolist()}")
        if len(self.shape) != 3 or min(self.shape) < 2:
            raise ValueError(f"grid shape must be 3 sizes >= 2, got {list(self.shape)}")
        if K < 1 or not np.all(np.isfinite(self.orientations_rotvec)):
            raise ValueError("orientations_rotvec must be finite rotation vectors")
        if self.delta_m.shape != (K, *self.shape, 3):
            raise ValueError(
                f"delta_m has shape {self.delta_m.shape}, the grid needs {(K, *self.shape, 3)}"
            )
        if not np.all(np.isfinite(self.delta_m)):
            raise ValueError("delta_m has non-finite corrections")
        if self.std_m is not None:
            if self.std_m.shape != self.delta_m.shape:
                raise ValueError(
                    f"std_m has shape {self.std_m.shape}, the grid needs {self.delta_m.shape}"
                )
            if not (np.all(np.isfinite(self.std_m)) and np.all(self.std_m >= 0)):
                raise ValueError("std_m must be finite and non-negative")
        tol = self.orientation_tol_rad
        if not (np.isfinite(tol) and 0 < tol <= DEFAULT_ORIENTATION_TOL_RAD):
            raise ValueError(
                f"orientation_tol_rad must be a number of radians in (0, "
                f"{DEFAULT_ORIENTATION_TOL_RAD:g}], got {tol!r}"
            )
        measured_at = (self.meta if isinstance(self.meta, dict) else {}).get("orientation_tol_rad")
        if measured_at is not None and measured_at != tol:
            raise ValueError(
                f"orientation_tol_rad {tol!r} is not the tolerance the table's error was measured "
                f"at (meta orientation_tol_rad {measured_at!r}): edited by hand?"
            )
        # units: a controller moves the arm by these numbers, so a table in millimetres or
        # degrees (a hand edit, another tool's file) is refused, not used
        again = "export the table again with `workcell export`"
        far = float(np.max(np.abs(np.r_[lo, hi])))
        if far > DH_LENGTH_MAX_M:  # no arm reaches that far
            raise ValueError(
                f"grid bound {far:.4g} m from the base, beyond any arm's reach: "
                + ("it looks like millimetres; the table wants metres" if far <= 1e4 else "corrupt")
                + f"; {again}"
            )
        if (turn := beyond_full_turn(self.orientations_rotvec)) is not None:
            k, ang = turn
            raise ValueError(
                f"orientation {k} is a rotation vector of {ang:.4g} rad, more than a full "
                f"turn: {DEGREES_HINT}; {again}"
            )
        meta = self.meta if isinstance(self.meta, dict) else {}
        check_meta(meta, again)
        bound = meta.get("correction_bound_m")
        if bound is None:
            bound = MAX_CORRECTION_BOUND_M
            what = f"{bound:g} m, more than any calibration corrects"
        else:
            ok = isinstance(bound, (int, float)) and not isinstance(bound, bool)
            if not (ok and math.isfinite(bound) and 0.0 < bound <= MAX_CORRECTION_BOUND_M):
                raise ValueError(
                    f"meta correction_bound_m must be a number of metres in "
                    f"(0, {MAX_CORRECTION_BOUND_M:g}], got "
                    f"{bound!r}; {again}"
                )
            what = f"the bound {bound * 1e3:g} mm it was built with"
        mag = np.linalg.norm(self.delta_m.reshape(-1, 3), axis=1)
        i = int(np.argmax(mag))
        if mag[i] > bound * (1.0 + 1e-9):
            unit = (
                "it looks like millimetres; the table wants metres"
                if mag[i] / 1000.0 <= bound
                else "not a correction in metres or millimetres (corrupt?)"
            )
            raise ValueError(
                f"delta_m reaches {mag[i]:.4g} m (node {i} of {mag.size}), beyond {what}: "
                f"{unit}; {again}"
            )

    def csv_columns(self) -> list[str]:
        """The CSV's column names."""
        return (
            ["orientation", "rx", "ry", "rz", "i", "j", "k", "x_m", "y_m", "z_m"]
            + ["dx_m", "dy_m", "dz_m"]
            + ([] if self.std_m is None else ["sx_m", "sy_m", "sz_m"])
        )

    def csv_rows(self) -> np.ndarray:
        """The CSV's numbers, one row per node (orientation, then i, j, k), as floats."""
        K, shape = len(self.orientations_rotvec), tuple(self.shape)
        n = int(np.prod(shape))
        ijk = np.indices(shape).reshape(3, -1).T
        cols = [
            np.repeat(np.arange(K), n)[:, None],
            np.repeat(np.asarray(self.orientations_rotvec, float), n, axis=0),
            np.tile(ijk, (K, 1)),
            np.tile(self.node_positions().reshape(-1, 3), (K, 1)),
            np.asarray(self.delta_m, float).reshape(-1, 3),
        ]
        if self.std_m is not None:
            cols.append(np.asarray(self.std_m, float).reshape(-1, 3))
        return np.hstack([np.asarray(c, float) for c in cols])

    def csv_text(self) -> str:
        """The table's CSV: one row per node, header lines starting with '#'."""
        f = io.StringIO(newline="")
        f.write(f"# grid: lo {self.lo_m.tolist()} hi {self.hi_m.tolist()} shape {self.shape}\n")
        f.write(f"# max_interp_error_m: {self.meta.get('max_interp_error_m')}\n")
        for line in header_lines(self):
            f.write(f"# {' '.join(line.split())}\n")
        w = csv.writer(f)
        if self.std_m is not None and "std_basis" in self.meta:
            f.write(f"# sx_m, sy_m, sz_m: {self.meta['std_basis']}\n")
        f.write(
            "# columns: orientation index and its rotation vector rx, ry, rz (rad), grid "
            "index i, j, k, node position x_m, y_m, z_m (base_ref), correction dx_m, dy_m, "
            "dz_m (commanded = desired + delta)\n"
        )
        columns = self.csv_columns()
        w.writerow(columns)
        n_int = {c for c, name in enumerate(columns) if name in CSV_INDEX_COLUMNS}
        for row in self.csv_rows().tolist():
            w.writerow(int(v) if c in n_int else repr(v) for c, v in enumerate(row))
        return f.getvalue()

    def save(self, path: str | os.PathLike) -> tuple[Path, Path]:
        """Write PATH.json (everything) and PATH.csv (one row per node). Returns both paths.

        Each file is whole or not replaced (a full disk keeps an earlier pair); the two are
        renamed one after the other, the CSV first, and the JSON records the CSV's sha256, so a
        crash between the renames (a new CSV beside the earlier JSON) is refused by `load_table`
        instead of passing as one table."""
        pj, pc = table_files(path)
        csv_text = self.csv_text()
        d = self.to_dict()
        d["csv_sha256"] = hashlib.sha256(csv_text.encode("utf-8")).hexdigest()
        text = json.dumps(d, indent=1, allow_nan=False)
        with atomic_files(pc, pj, newline="") as (fc, fj):
            fc.write(csv_text)
            fj.write(text)
        return pj, pc


# the table meta's numbers a reader (header lines, `validate`) computes with: each a finite
# non-negative number or absent/null
META_NUMBERS = (
    "target_interp_error_m",
    "max_interp_error_m",
    "rms_interp_error_m",
    "max_correction_m",
    "median_std_m",
    "max_std_m",
    "orientation_error_at_tol_m",
    "orientation_change_at_tol_m",
    "orientation_change_budget_m",
)


def check_meta(meta: dict, again: str) -> None:
    """Raise ValueError naming the first meta field of a wrong type (a hand edit): the numbers
    `validate` and the headers compute with, and the conditions the correction was computed
    for (`conditions`: approach_sign, joint_temperature_c, elapsed_s, payload_kg)."""
    for key in META_NUMBERS:
        v = meta.get(key)
        if v is not None and not (is_finite_number(v) and v >= 0):
            raise ValueError(
                f"meta {key} must be a non-negative number of metres, got {v!r}; {again}"
            )
    notes = meta.get("conditions_note")
    if notes is not None and not (
        isinstance(notes, list) and all(isinstance(x, str) for x in notes)
    ):
        raise ValueError(f"meta conditions_note must be a list of lines, got {notes!r}; {again}")
    if "conditions" not in meta:
        return
    cond = meta["conditions"]
    if not isinstance(cond, dict):
        raise ValueError(
            f"meta conditions must be an object (approach_sign, joint_temperature_c, elapsed_s, "
            f"payload_kg), got {cond!r}; {again}"
        )
    sign = cond.get("approach_sign")
    if sign is not None and not (
        isinstance(sign, list)
        and len(sign) == 6
        and all(is_finite_number(x) and x in (-1, 0, 1) for x in sign)
    ):
        raise ValueError(
            f"meta conditions approach_sign must be 6 signs (-1, 0 or 1), got {sign!r}; {again}"
        )
    t = cond.get("joint_temperature_c")
    if t is not None and not (
        isinstance(t, list) and len(t) == 6 and all(map(is_finite_number, t))
    ):
        raise ValueError(
            f"meta conditions joint_temperature_c must be 6 numbers (degC), got {t!r}; {again}"
        )
    for key, unit in (("elapsed_s", "seconds"), ("payload_kg", "kilograms")):
        v = cond.get(key)
        if v is not None and not (is_finite_number(v) and v >= 0):
            raise ValueError(
                f"meta conditions {key} must be a non-negative number of {unit}, got {v!r}; {again}"
            )


def unexplained_lines(meta: dict) -> list[str]:
    """What the model leaves unexplained on its held-out poses (`model_unexplained` in a table's
    or summary's meta, and without the named outliers), which the correction's 1-sigma does not
    hold (or, when the model gives none, what it leaves out): the lines export files state it
    with."""
    from workcell.estimation.models import unexplained_text

    has_std = meta.get("median_std_m") is not None
    lead = "not in that 1-sigma:" if has_std else "the model gives no 1-sigma; what it leaves"
    if has_std and meta.get("std_posterior"):
        lead = f"beside that 1-sigma ({POSTERIOR_STD_NOTE}):"
    u = meta.get("model_unexplained")
    if not isinstance(u, dict):
        if has_std:
            return [
                "not in that 1-sigma: what the model leaves unexplained (its file states no "
                "held-out figure)"
            ]
        return [
            "the model gives no 1-sigma; what it leaves unexplained: not stated (its file "
            "states no held-out figure)"
        ]
    if has_std:
        first = f"{lead} the model leaves {unexplained_text(u)} on its held-out poses"
    else:
        first = f"{lead} unexplained: {unexplained_text(u)} on its held-out poses"
    out = [first]
    med = meta.get("median_std_m")
    if has_std and is_finite_number(med) and is_finite_number(u.get("rms_m")):
        # the advice the README gives, where the numbers are read (metrology audit, 2026-11-29):
        # the 1-sigma alone was 1.4-2.1x small on simulated cells for the augmented model
        both = float(np.hypot(med, u["rms_m"]))
        up = u.get("upper_m")
        upper = (
            f", {float(np.hypot(med, up)):.3g} m with the upper end of the unexplained"
            if is_finite_number(up)
            else ""
        )
        out.append(
            "for a target's uncertainty add the two in quadrature (3-D): median "
            f"sqrt(1-sigma^2 + unexplained^2) = {both:.3g} m{upper}"
        )
    w = meta.get("model_unexplained_without_outliers")
    if isinstance(w, dict):
        ids = ", ".join(str(i) for i in w.get("pose_ids", []))
        out.append(
            f"without the held-out outlier pose(s) {ids} ({w.get('rule', '')}): "
            f"{unexplained_text(w)}"
        )
    return out


def header_lines(table: CorrectionTable) -> list[str]:
    """What a controller needs to use the table, one line each (without `# `), shared by the
    table CSV's and the URScript's headers: model, recording, robot and units, the frame (with
    tracker_T_base and the base correction), the sign convention, the TCP, the volume, the
    interpolation error, the 1-sigma and what the model leaves out, the conditions and the arm
    configuration."""
    m = table.meta if isinstance(table.meta, dict) else {}
    K = len(table.orientations_rotvec)
    nx, ny, nz = table.shape
    ie = m.get("max_interp_error_m")
    ie = float("nan") if not isinstance(ie, int | float) else float(ie)
    return [
        f"model: {m.get('model', '?')}  method: {m.get('method', '?')}",
        f"recording sha256: {m.get('recording_sha256', '?')}",
        f"robot: {m.get('robot', '?')}",
        "units: m, rad (UR rotation vectors)",
        *frame_lines(m, "the table's nodes"),
        "semantics: commanded = desired + delta(desired), delta trilinear in the grid; the "
        "orientation is commanded as desired (the nominal one)",
        f"TCP (SMR) in flange: {m.get('tcp_m', '?')} m, the one the table assumes: set this TCP "
        "in the controller",
        f"volume {table.lo_m.tolist()}..{table.hi_m.tolist()} m (base_ref), grid {nx}x{ny}x{nz}, "
        f"{K} orientation(s)",
        f"interpolation error: largest on {m.get('interp_error_points', '?')} random points "
        f"{ie:.3g} m (a sample maximum, not a bound)",
        orientation_line(m, table.orientation_tol_rad),
        *uncertainty_lines(m),
        *conditions_lines(m),
        *configuration_lines(table),
    ]


def conditions_lines(meta: dict) -> list[str]:
    """The conditions the correction was computed for (`conditions:` lines)."""
    notes = meta.get("conditions_note") or []
    cond = meta.get("conditions") if isinstance(meta.get("conditions"), dict) else {}
    out = [f"conditions: {c}" for c in notes]
    sign = cond.get("approach_sign")
    sign = "" if sign is None else f"approach {[int(x) for x in sign]} per joint as computed; "
    if not notes:
        out.append(
            f"conditions: {sign}the model declares no payload-, approach- or thermal-dependent "
            "term: the correction is the same under any"
        )
    elif sign and not any("approach" in str(c) for c in notes):
        out.append(f"conditions: {sign}the model has no backlash term: it does not depend on it")
    return out


def uncertainty_lines(m: dict) -> list[str]:
    """The correction's 1-sigma, where it is undetermined, which nodes are extrapolations and
    what the model leaves unexplained (as `export` prints them), without `# `."""
    if m.get("median_std_m") is not None:
        out = [
            f"correction 1-sigma (3-D, model uncertainty): median {m['median_std_m']:.3g} m, "
            f"max {m.get('max_std_m', float('nan')):.3g} m; per node in the table's JSON/CSV"
        ]
    else:
        basis = m.get("std_basis")
        why = (
            basis[len("none: ") :] if isinstance(basis, str) and basis.startswith("none: ") else ""
        )
        out = [f"correction 1-sigma: not given ({why or NO_STD_WHY})"]
    if m.get("nodes_std_exceeds_correction"):
        out.append(
            f"WARNING: at {m['nodes_std_exceeds_correction']} nodes the correction's 1-sigma is "
            "larger than the correction itself: the measured poses do not determine it there"
        )
    if isinstance(m.get("joint_coverage"), dict):
        out.append(coverage_line(m["joint_coverage"]))
    return out + unexplained_lines(m)


def configuration_lines(table: CorrectionTable) -> list[str]:
    if table.configurations is None:
        return ["arm configuration: not recorded in this table (not checked)"]
    sg = "; ".join(
        f"orientation {k}: shoulder {s:+d}, elbow {e:+d}, wrist {w:+d}"
        for k, (s, e, w) in enumerate(np.asarray(table.configurations, int).tolist())
    )
    return [f"arm configuration (checked, halts otherwise): {sg}"]


def table_files(path: str | os.PathLike) -> tuple[Path, Path]:
    """The JSON and CSV of the table named `path`: a .json, .csv or .script extension is
    replaced (`export --out X.script` writes X.json and X.csv beside the script), any other
    dotted part is kept (`--out cell.v1` writes cell.v1.json and cell.v1.csv, not cell.json)."""
    p = Path(path)
    base = p.with_suffix("") if p.suffix.lower() in (".json", ".csv", ".script") else p
    return base.with_name(base.name + ".json"), base.with_name(base.name + ".csv")


def _numbers(v, name: str) -> np.ndarray:
    """A table's numeric field as a float array: every leaf a JSON number (not text, not true or
    false, which `np.asarray(..., float)` reads as 1.0: a hi_m of "1" stretched the grid)."""

    def leaves(x):
        if isinstance(x, list):
            for y in x:
                yield from leaves(y)
        else:
            yield x

    for x in leaves(v):
        if isinstance(x, bool) or not isinstance(x, int | float):
            raise ValueError(f"{name} holds {str(x)[:20]!r}, not a number")
    return np.asarray(v, float)


def load_table(path: str | os.PathLike) -> CorrectionTable:
    given = p = Path(path)
    if p.suffix.lower() != ".json":
        p = table_files(p)[0]  # `export --out X.script` writes the table as X.json
    if not p.exists():
        if given != p and given.exists():
            raise UserError(
                f"{given} is not a correction table (.json) and there is no {p.name} beside it; "
                "write one with `workcell export`"
            )
        raise UserError(f"{p}: no such correction table; write one with `workcell export`")
    if not p.is_file():
        raise UserError(f"{p}: not a regular file; give a correction table (.json)")
    try:
        d = strict_json.loads(p.read_text(encoding="utf-8-sig"))
        if not isinstance(d, dict):
            raise ValueError("not a JSON object")
        tab = CorrectionTable.from_dict(d)
    except UserError as e:
        raise UserError(f"{p}: {e}") from None
    except strict_json.DuplicateKey as e:
        raise UserError(
            f"{p}: the key {e.args[0]!r} is given twice in one object (edited by hand?); "
            "export the table again"
        ) from None
    except (ValueError, KeyError, TypeError, AttributeError, IndexError, OverflowError) as e:
        raise UserError(f"{p}: unreadable correction table ({type(e).__name__}: {e})") from None
    _check_csv_beside(p, d.get("csv_sha256"), tab)
    return tab


CSV_INDEX_COLUMNS = ("orientation", "i", "j", "k")
# a CSV number may differ from the JSON's by this much (m, rad) and still be the same table: a
# spreadsheet that re-wrote the CSV with fewer digits; an edit is far larger
CSV_MATCH_ATOL = 1e-9


def _check_csv_beside(pj: Path, want: object, tab: CorrectionTable | None = None) -> None:
    """The CSV beside a table's JSON is the one written with it: a controller reads the CSV,
    workcell the JSON, and the two must be one table. `CorrectionTable.save` records the CSV's
    sha256 (a JSON written before 2026-11-29 has none), and the CSV's rows are compared with the
    JSON's nodes (`tab`) to `CSV_MATCH_ATOL`, whichever file was edited. A JSON without a CSV
    beside passes."""
    pc = table_files(pj)[1]
    if not pc.is_file():
        return
    if isinstance(want, str):
        h = hashlib.sha256()
        with open(pc, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        if h.hexdigest() != want.lower():
            raise UserError(
                f"{pc} is not the CSV written with {pj.name} (its sha256 differs: an export "
                "interrupted between the two files, or a CSV edited since); export the table again"
            )
    if tab is not None and (why := _csv_rows_differ(tab, pc)) is not None:
        raise UserError(
            f"{pc} and {pj.name} are not one table: {why}; one of them was edited since the "
            "export: export the table again"
        )


def _csv_numbers(text: str) -> tuple[list[str], np.ndarray]:
    """A table CSV's column names and numbers (rows x columns); UserError when they are not
    numbers in rows of one length."""
    lines = text.splitlines()
    head = next(
        (i for i, x in enumerate(lines) if x.strip() and not x.lstrip().startswith("#")), None
    )
    if head is None:
        return [], np.zeros((0, 0))
    names = next(csv.reader([lines[head]]))
    body = [x for x in lines[head + 1 :] if x.strip() and not x.lstrip().startswith("#")]
    try:
        got = np.loadtxt(body, delimiter=",", ndmin=2) if body else np.zeros((0, len(names)))
    except ValueError as e:  # a cell that is not a number, or rows of unequal length
        raise UserError(f"a row that is not {len(names)} numbers ({e})") from None
    return names, got


def _csv_rows_differ(tab: CorrectionTable, pc: Path) -> str | None:
    """Why the CSV's rows are not the table's nodes (its columns, row count or a number beyond
    `CSV_MATCH_ATOL`), or None when they are."""
    try:
        text = pc.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as e:
        return f"the CSV cannot be read: {e}"
    try:
        head, got = _csv_numbers(text)
    except UserError as e:
        return f"the CSV has {e}"
    want_head, want = tab.csv_columns(), tab.csv_rows()
    if [h.strip() for h in head] != want_head:
        return f"the CSV's columns are {head}, the JSON's {want_head}"
    if got.shape != want.shape:
        return f"the CSV has {len(got)} node rows, the JSON {len(want)}"
    bad = ~(np.abs(got - want) <= CSV_MATCH_ATOL)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        return (
            f"{int(bad.any(axis=1).sum())} row(s) differ, the first node row {r + 1}'s "
            f"{want_head[c]}: {float(got[r, c])!r} in the CSV, {float(want[r, c])!r} in the JSON"
        )
    return None


# ---------------------------------------------------------------------- building
def _grid_shape(lo, hi, h) -> tuple[int, int, int]:
    return tuple(int(max(2, math.ceil((hi[a] - lo[a]) / h - 1e-9) + 1)) for a in range(3))


def _solve_grid(corr: Corrector, X: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact corrections at grid nodes X (nx, ny, nz, 3), solved outward from the node nearest the
    reference configuration, each layer seeded from its already-solved neighbours."""
    shape = X.shape[:3]
    p_ref, _ = corr.nominal.fk(Q_REF)
    # the start node: IK of the reference configuration to the box centre, then nearest node
    centre = X.reshape(-1, 3).mean(0)
    q_c, r_c = corr.nominal.ik(centre[None], R[None], Q_REF, iters=100)
    flat = X.reshape(-1, 3)
    start = np.unravel_index(int(np.argmin(np.linalg.norm(flat - centre, axis=1))), shape)
    idx = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), -1).reshape(-1, 3)
    off = idx - np.asarray(start)
    layer = np.abs(off).sum(1)
    D = np.full((*shape, 3), np.nan)
    Q = np.full((*shape, 6), np.nan)
    for L in range(int(layer.max()) + 1):
        sel = np.where(layer == L)[0]
        nodes = idx[sel]
        if L == 0:
            seeds = q_c
        else:
            parent = nodes.copy()
            o = off[sel]
            ax = np.argmax(np.abs(o), axis=1)
            parent[np.arange(len(sel)), ax] -= np.sign(o[np.arange(len(sel)), ax])
            seeds = Q[parent[:, 0], parent[:, 1], parent[:, 2]]
            seeds = np.where(np.isfinite(seeds), seeds, Q_REF)
        y = X[nodes[:, 0], nodes[:, 1], nodes[:, 2]]
        c, q, _ = corr.correct_positions(y, R, seeds)
        D[nodes[:, 0], nodes[:, 1], nodes[:, 2]] = c - y
        Q[nodes[:, 0], nodes[:, 1], nodes[:, 2]] = q
    return D, Q


def weak_groups(model: FittedModel) -> list[list[str]]:
    """The parameter groups the model's fit found weakly identified (`fit` prints them), from
    its own info or its geometric base's; [] when it names none."""
    for m in (model, getattr(model, "base", None)):
        info = getattr(m, "info", None)
        ident = info.get("identifiability") if isinstance(info, dict) else None
        groups = ident.get("weakly_identified") if isinstance(ident, dict) else None
        if isinstance(groups, list) and groups:
            return [
                [str(n) for n in g.get("parameters", [])]
                for g in groups
                if isinstance(g, dict) and isinstance(g.get("parameters"), list)
            ]
    return []


def weak_hint(model: FittedModel) -> str:
    """'; the fit left {a, b} weakly identified ...' for a refusal's line, or ''."""
    groups = weak_groups(model)
    if not groups:
        return ""
    names = ", ".join("{" + ", ".join(g) + "}" for g in groups[:3])
    return (
        f"; the fit left {names} weakly identified (only their combination is known), which "
        "can put a large and uncertain correction anywhere: measure poses that tell them apart "
        "(other tool orientations), then fit again"
    )


def smr_hint(model: FittedModel) -> str:
    """For an oversized correction's refusal: the fitted SMR far from the declared one (the
    fit's own note, `fitting.smr_change`), which is the TCP to declare, not a correction; ''
    when it is not. Without it the refusal said to raise --max-correction, and a table of
    24 mm corrections for a TCP 15.8 mm off was one option away (series B, real-data audit
    of 2026-11-29)."""
    from workcell.estimation.fitting import smr_change
    from workcell.estimation.models import geometric_part

    g = geometric_part(model)
    try:
        smr = smr_change(g.parameters()) if g is not None else None
    except Exception:  # noqa: BLE001 - a hint only: a model without those figures gets none
        smr = None
    if smr is None:
        return ""
    to = ",".join(f"{x:.4f}" for x in smr["suggested_m"])
    rec = (getattr(model, "info", {}) or {}).get("recording") or "REC"
    return (
        f"the fitted SMR is {smr['change_m'] * 1e3:.1f} mm (std {smr['std_m'] * 1e3:.2f} mm) "
        "from the offset the recording declares: that is the TCP, not a correction; fit again "
        f"with it declared (`workcell fit {rec} --smr-offset={to}`) and set the controller's "
        "TCP to it"
    )


def _std_limit(bound_m: float) -> tuple[float, str]:
    """The largest correction 1-sigma an export accepts: the correction bound, never more than
    the default (a bound raised to let large corrections through does not make them known),
    and how a refusal names it."""
    lim = min(float(bound_m), DEFAULT_MAX_CORRECTION_M)
    said = (
        "the correction bound"
        if lim == bound_m
        else "the default correction bound, whatever --max-correction allows"
    )
    return lim, f"more than {lim * 1e3:g} mm ({said})"


def check_std_bound(
    s3: np.ndarray, bound_m: float, model: FittedModel, where: str = "node"
) -> None:
    """Refuse corrections whose median 1-sigma (3-D, `s3`) exceeds the correction bound, or the
    default bound when a larger one is given (a bound raised to let large corrections through
    does not make them known): the measured poses do not determine them, and a controller would
    apply noise (series D's DH model with --max-correction 0.05: a table with a 38 mm median
    1-sigma was written)."""
    med = float(np.median(s3))
    lim, more_than = _std_limit(bound_m)
    if med > lim:
        raise CorrectionRefused(
            f"refused: the corrections' median 1-sigma is {med * 1e3:.3g} mm over the {where}s, "
            f"{more_than}: the measured poses do not determine them"
            + (weak_hint(model) or "; measure poses in this volume and orientation")
        )


def check_target_std(
    s3: np.ndarray, bound_m: float, model: FittedModel, src: object, lines: list[int]
) -> None:
    """Refuse targets whose correction 1-sigma (3-D, `s3`) exceeds the correction bound (at most
    the default): each target is commanded on its own, so one undetermined target is refused by
    its CSV line as an oversized correction is, where a table's grid is judged by its median."""
    lim, more_than = _std_limit(bound_m)
    over = ~(s3 <= lim)  # a non-finite 1-sigma too
    if over.any():
        i = int(np.argmax(over))
        more = int(over.sum()) - 1
        said = f"{s3[i] * 1e3:.3g} mm" if np.isfinite(s3[i]) else "not finite"
        raise CorrectionRefused(
            f"refused: {src}: line {lines[i]}: the correction's 1-sigma there is {said}, "
            f"{more_than}{f'; and {more} more target(s)' if more else ''}: the measured poses "
            "do not determine it" + (weak_hint(model) or "; measure poses near these targets")
        )


def check_corrections(
    delta: np.ndarray,
    X: np.ndarray,
    bound_m: float,
    orientation: int = 0,
    where: str = "node",
    hint: str = "",
    cause: str = "",
) -> None:
    """Refuse non-finite or oversized corrections, naming where (one clear line); `hint` (from
    `weak_hint`) follows the advice on an oversized one; `cause` (from `smr_hint`), when given,
    replaces that advice (raising --max-correction is then the wrong remedy)."""
    delta = delta.reshape(-1, 3)
    X = X.reshape(-1, 3)
    bad = ~np.all(np.isfinite(delta), axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise CorrectionRefused(
            f"refused: no finite correction at {bad.sum()} {where}(s), first at "
            f"{np.round(X[i], 4).tolist()} m (base), orientation {orientation} "
            "(IK or the model did not converge there); shrink the volume (--volume)"
        )
    mag = np.linalg.norm(delta, axis=1)
    i = int(np.argmax(mag))
    if mag[i] > bound_m:
        raise CorrectionRefused(
            f"refused: correction {mag[i] * 1e3:.3f} mm at {np.round(X[i], 4).tolist()} m (base), "
            f"orientation {orientation}, exceeds the bound {bound_m * 1e3:g} mm "
            f"({(mag > bound_m).sum()} {where}(s) over); "
            + (cause + hint if cause else "check the model or raise --max-correction" + hint)
        )


ORIENTATION_PROBE_RAD = 0.01  # tilt of the finite differences that estimate the slope
ORIENTATION_POINTS = 100  # random points of the volume the tolerance is measured on
ORIENTATION_TOL_MIN_RAD = 1e-4  # below: the orientation is commanded as the table's anyway
ORIENTATION_TOL_NARROW_RAD = 1e-3  # below: a taught pose may miss it (said when exporting)
ORIENTATION_TOL_BASIS = (
    "largest angle between the commanded tool orientation and the nearest of the table's at "
    "which the table (and wc_correct) still applies that orientation's corrections: a tilt by "
    "that angle about any axis changes the exact correction by at most the interpolation error "
    "target (the tilt costs no more than the interpolation may), on random points of the "
    "volume: each point's most sensitive axis is found from the correction's finite-difference "
    "response to the tilt and checked with exact corrections about it. Also measured there: "
    "how far the table is off the exact correction for the tilted orientation, the "
    "interpolation error included (each point's worst of 256 axes). Sample maxima, not bounds. "
    "A tool orientation further off is refused (the URScript halts)"
)


def _tilted(R: np.ndarray, axes: np.ndarray, angle: float) -> np.ndarray:
    """Rotations (N, 3, 3): R (3, 3) tilted by `angle` about each unit axis (N, 3) of the tool."""
    return R @ rotvec_to_matrix(np.asarray(axes, float) * angle)


def _exact_at(corr: Corrector, tab: CorrectionTable, P: np.ndarray, k: int, Rs: np.ndarray):
    """Exact corrections (N, 3) of positions P (N, 3) at rotations Rs (N, 3, 3), seeded from the
    table's orientation k (NaN rows where IK or the model did not converge)."""
    c, _, _ = corr.correct_positions(P, Rs, tab.seed_for(P, k))
    return c - P


def _sphere(n: int = 256) -> np.ndarray:
    """n unit vectors spread evenly over the sphere (a Fibonacci lattice), (n, 3)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z**2)
    phi = np.pi * (1.0 + 5**0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def orientation_tolerance(
    corr: Corrector,
    tab: CorrectionTable,
    P: np.ndarray,
    exact: list,
    budget_m: float,
    tol_max: float = DEFAULT_ORIENTATION_TOL_RAD,
) -> dict:
    """The orientation tolerance of the table (`ORIENTATION_TOL_BASIS`) and what was measured at
    it -> the meta entries. Per point, the exact correction's response to a tilt of the tool is
    estimated by finite differences (a 3x3 Jacobian J); a tilt by angle a about unit axis u
    changes the correction by ~ a J u, at most a times J's largest singular value, so the
    tolerance is the largest angle (at most `tol_max`) keeping that within `budget_m` on every
    point. It is then checked with exact corrections at +-tolerance about each point's most
    sensitive axis and narrowed until the check holds. `exact[k]`: the exact corrections (N, 3)
    at P for orientation k."""
    n = min(len(P), ORIENTATION_POINTS)
    P = np.asarray(P, float)[:n]
    K = len(tab.orientations_rotvec)
    Rk = rotvec_to_matrix(tab.orientations_rotvec)
    probe = min(ORIENTATION_PROBE_RAD, tol_max)
    U = _sphere()
    per = []  # per orientation: exact (N, 3), table (N, 3), J (N, 3, 3), most sensitive axes
    est = [tol_max]
    for k in range(K):
        ex, D = exact[k][:n], tab.interpolate(P, k)
        eye = np.repeat(np.eye(3), n, axis=0)  # tool axes x, y, z, each for every point
        d = _exact_at(corr, tab, np.tile(P, (3, 1)), k, _tilted(Rk[k], eye, probe))
        J = (d - np.tile(ex, (3, 1))).reshape(3, n, 3).transpose(1, 2, 0) / probe
        ok = np.all(np.isfinite(J.reshape(n, -1)), axis=1) & np.all(np.isfinite(ex), axis=1)
        J = np.where(ok[:, None, None], J, 0.0)
        _, sv, Vt = np.linalg.svd(J)
        per.append((ex, D, J, Vt[:, 0, :]))
        top = sv[:, 0][ok]
        if top.size and top.max() > 0:
            est.append(0.98 * budget_m / float(top.max()))  # a little under: checked below
    tol = float(np.clip(min(est), ORIENTATION_TOL_MIN_RAD, tol_max))
    while True:
        change, error = [], []
        for k, (ex, D, J, u1) in enumerate(per):
            # each point's worst axis for the table's error (interpolation and tilt together)
            lin = np.linalg.norm(
                (D - ex)[:, None, :] - tol * np.einsum("nij,mj->nmi", J, U), axis=2
            )
            axes = np.concatenate([u1, -u1, U[lin.argmax(axis=1)]])
            d = _exact_at(corr, tab, np.tile(P, (3, 1)), k, _tilted(Rk[k], axes, tol))
            c = np.linalg.norm(d[: 2 * n] - np.tile(ex, (2, 1)), axis=1)
            e = np.linalg.norm(np.tile(D, (3, 1)) - d, axis=1)
            change.append(c[np.isfinite(c)])
            error.append(e[np.isfinite(e)])
        c, e = np.concatenate(change), np.concatenate(error)
        if not c.size:  # no tilted correction converged: the orientation as the table's only
            tol, c_max, e_max = ORIENTATION_TOL_MIN_RAD, None, None
            break
        c_max, e_max = float(c.max()), float(e.max())
        if c_max <= budget_m or tol <= ORIENTATION_TOL_MIN_RAD:
            break
        tol = max(ORIENTATION_TOL_MIN_RAD, 0.9 * tol * min(1.0, budget_m / c_max))
    return {
        "orientation_tol_rad": tol,
        "orientation_change_at_tol_m": c_max,
        "orientation_change_budget_m": float(budget_m),
        "orientation_error_at_tol_m": e_max,
        "orientation_error_points": int(n * K),
        "orientation_tol_basis": ORIENTATION_TOL_BASIS,
    }


def orientation_line(m: dict, tol: float | None = None) -> str:
    """The orientation tolerance and what was measured at it, one line (the export log, the
    table CSV's and the URScript's headers); `m`: the table's meta (`orientation_tolerance`)."""
    tol = float(m.get("orientation_tol_rad") if tol is None else tol)
    c, e = m.get("orientation_change_at_tol_m"), m.get("orientation_error_at_tol_m")
    if not (is_finite_number(c) and is_finite_number(e)):
        why = (
            "no tilted correction converged"
            if "orientation_tol_basis" in m
            else "a table written before it was; export it again"
        )
        return (
            f"orientation tolerance: {tol:.3g} rad (what a tilt that far costs was not measured: "
            f"{why}); command the table's orientation(s)"
        )
    return (
        f"orientation tolerance: {tol:.3g} rad ({math.degrees(tol):.2g} deg) from the table's "
        f"orientation(s), further off is refused; a tilt that far changes the exact correction by "
        f"up to {c:.3g} m (within the interpolation error target), and the table is off the exact "
        f"correction there by up to {e:.3g} m, interpolation included, on "
        f"{m.get('orientation_error_points', '?')} random points (sample maxima, not bounds)"
    )


STD_BASIS = (
    "1 sigma of each correction component (base axes) from the model's parameter covariance "
    "(geometry, and for an augmented model its accepted effects), propagated to first order: "
    "the covariance of the model's predicted SMR position at the corrected joints, which is the "
    "correction's to first order (the commanded position moves opposite to the prediction); the "
    "model's own basis for that covariance holds (see `workcell fit`). A model with a "
    "Gaussian-process residual (gp, or augmented with a residual) adds the GP's posterior "
    "variance of that residual, as if independent of the parametric part (an upper estimate of "
    "their sum, not a bound on the true error: in simulated cells with physics the model leaves "
    "out, the true error was 1.4x (gp) to 1.6x (augmented) this 1-sigma); "
    "it grows away from the measured poses. An lddmm model adds its deformation's posterior "
    "variance, linearised at its base chain as its cross-validation is (the kernel ridge fit read "
    "as a Gaussian process, scale by maximum likelihood), to its base's, likewise as if "
    "independent. Between nodes, trilinear interpolation of these "
    "stds bounds the interpolated correction's std from above"
)


def node_std(corr: Corrector, q_nodes: np.ndarray) -> np.ndarray | None:
    """1-sigma (..., 3) of the corrections at corrected joints q_nodes (..., 6), base axes
    (`STD_BASIS`); None when the model carries no covariance of its prediction."""
    C = corr.real_base_cov(np.asarray(q_nodes, float).reshape(-1, 6))
    if C is None:
        return None
    sd = np.sqrt(np.clip(np.einsum("nii->ni", C), 0.0, None))
    return sd.reshape(*np.shape(q_nodes)[:-1], 3)


def approach_sensitivity(corr: Corrector, q_nodes: np.ndarray) -> dict | None:
    """How far the model's SMR moves at the nodes' joints when every joint approaches from the
    other side than the table's conditions declare (a joint declared 0 stays 0); None when the
    model does not depend on the approach (no backlash terms)."""
    from dataclasses import replace

    q = np.asarray(q_nodes, float).reshape(-1, 6)
    flipped = replace(
        corr.conditions, approach_sign=-np.asarray(corr.conditions.approach_sign, float)
    )
    delta = Corrector(corr.model, corr.nominal, flipped).real_base(q) - corr.real_base(q)
    d = np.linalg.norm(delta, axis=1)
    if not np.all(np.isfinite(d)) or d.max() < 1e-9:
        return None
    out = {
        "rms_m": float(np.sqrt(np.mean(d**2))),
        "max_m": float(d.max()),
        "basis": "SMR displacement the model predicts at the table's node joints if every joint "
        "arrived from the other side than declared (conditions.approach_sign): the correction "
        "holds for the declared approach only",
    }
    out.update(_approach_std(corr, flipped, q, delta))
    return out


def approach_line(a: dict) -> str:
    """The export log's line for `approach_sensitivity`'s result, with the 1-sigma when given."""

    def um(key: str) -> str:
        sd = a.get(key.replace("_m", "_std_m"))
        return f"{a[key] * 1e6:.1f}" + ("" if sd is None else f" +- {sd * 1e6:.1f}")

    sig = " (+- 1-sigma from the fit's covariance)" if "rms_std_m" in a else ""
    return (
        "approach: if every joint arrived from the other side than declared, the model moves "
        f"the SMR by {um('rms_m')} um RMS, {um('max_m')} um at most over the nodes{sig} (its "
        "backlash terms): approach as declared"
    )


def _approach_std(corr: Corrector, flipped, q: np.ndarray, delta: np.ndarray) -> dict:
    """1-sigma of `approach_sensitivity`'s RMS and max from the model's parameter covariance
    (first order; the nodes share the parameters, so the RMS's std is not a per-node average),
    `delta` (n, 3) its displacements in base axes; {} when the model gives no Jacobian and
    covariance of its prediction."""
    jac = getattr(corr.model, "prediction_jacobian", None)
    cov = getattr(corr.model, "cov", None)
    if jac is None or cov is None:
        return {}
    qp = pad_batch(q)
    n = len(q)
    a, b = corr.conditions.aux(len(qp)), flipped.aux(len(qp))
    Jd = np.asarray(jac(qp, **b) - jac(qp, **a), float)[:n]  # (n, 3, P), tracker axes
    d = np.linalg.norm(delta, axis=1)
    # the displacement's direction in tracker axes (the Jacobian's): base -> tracker rotation
    u = (delta / np.maximum(d, 1e-300)[:, None]) @ corr.nominal.base_ref[:3, :3].T
    g = np.einsum("ni,nip->np", u, Jd)  # d(d_i)/d(params)
    C = np.asarray(cov, float)
    rms = float(np.sqrt(np.mean(d**2)))
    g_rms = (d[:, None] * g).sum(0) / (n * max(rms, 1e-300))
    k = int(np.argmax(d))
    return {
        "rms_std_m": float(np.sqrt(max(g_rms @ C @ g_rms, 0.0))),
        "max_std_m": float(np.sqrt(max(g[k] @ C @ g[k], 0.0))),
        "std_basis": "1-sigma from the fit's parameter covariance (first order; the max's at "
        "the node where it occurs)",
    }


def joint_coverage(corr: Corrector, q_nodes: np.ndarray, what: str = "nodes") -> dict:
    """Which of the nodes' joints (..., 6) lie outside the joint range the model was fitted on
    (`info["joint_range_rad"]`, written by fit/diagnose/replay since 2026-11-26): there the
    correction is the model's extrapolation. Joint values are compared as they are (a joint
    2 pi away from the measured range counts as outside: a non-geometric model sees it so).
    `what` names the points in the basis (a table's "nodes", or "targets")."""
    info = getattr(corr.model, "info", None)
    rng = info.get("joint_range_rad") if isinstance(info, dict) else None
    try:
        lohi = np.asarray(rng, float).reshape(6, 2)
    except (TypeError, ValueError):
        lohi = None
    if lohi is None or not np.all(np.isfinite(lohi)) or np.any(lohi[:, 1] < lohi[:, 0]):
        return {"basis": "unknown: the model file does not say which joints it was fitted on"}
    q = np.asarray(q_nodes, float).reshape(-1, 6)
    beyond = np.maximum(lohi[:, 0] - q, q - lohi[:, 1]).clip(0.0, None)  # (N, 6) rad
    out = beyond > 0
    return {
        "basis": f"{what} whose corrected joints lie outside the joint range of the poses the "
        "model was fitted on (the correction there is an extrapolation)",
        "measured_range_rad": lohi.tolist(),
        "nodes": int(len(q)),
        "nodes_outside": int(np.any(out, axis=1).sum()),
        "per_joint": {
            str(j + 1): {"nodes_outside": int(out[:, j].sum()), "max_beyond_rad": float(b)}
            for j, b in enumerate(beyond.max(axis=0))
            if b > 0
        },
    }


def coverage_line(cov: dict, what: str = "nodes") -> str:
    """One line for the export log / CSV header from `joint_coverage`'s result; `what` names
    the corrected points ("nodes" of a table, "targets" of `export --format targets`)."""
    if "nodes_outside" not in cov:
        return f"joint coverage {cov['basis']}"
    if cov["nodes_outside"] == 0:
        return f"all {cov['nodes']} {what}' joints lie inside the range the model was fitted on"
    worst = ", ".join(
        f"joint {j} by up to {v['max_beyond_rad']:.3f} rad ({v['nodes_outside']} {what})"
        for j, v in cov["per_joint"].items()
    )
    remedy = "measure poses there" + (" or shrink the volume (--volume)" if what == "nodes" else "")
    return (
        f"WARNING: {cov['nodes_outside']} of {cov['nodes']} {what} need joints outside the range "
        f"the model was fitted on ({worst}): their corrections are extrapolations; {remedy}"
    )


def undetermined_line(s3: np.ndarray, mags: np.ndarray, what: str = "nodes") -> str | None:
    """The warning when corrections (3-D sizes `mags`) are smaller than their own 1-sigma `s3`
    somewhere: the measured poses do not determine them there; None when nowhere."""
    n = int(np.sum(s3 > mags))
    if not n:
        return None
    return (
        f"WARNING: at {n} of {s3.size} {what} the correction's 1-sigma is larger than the "
        f"correction itself (median 1-sigma {np.median(s3) * 1e3:.3g} mm, median correction "
        f"{np.median(mags) * 1e3:.3g} mm): the measured poses do not determine it there (see "
        "`fit`'s weakly identified groups); measure poses in this volume and orientation"
    )


NO_STD_WHY = "the model carries no covariance of its prediction"
# an ekf-ann model keeps its geometric states' covariance (the ROS YAML's +-) but not its
# network weights' covariance with them: its prediction's covariance cannot be propagated
EKF_NO_STD_WHY = (
    "the ekf-ann model keeps the filter's covariance of its geometric states only (the ROS "
    "YAML's +-), not its network weights' joint covariance with them, so the covariance of its "
    "prediction (geometry plus network) cannot be propagated from it"
)


POSTERIOR_STD_NOTE = (
    "a Gaussian-process posterior in part: it holds some of the error the model expects "
    "between its poses, not what it cannot represent"
)


def std_is_posterior(model: FittedModel) -> bool:
    """Whether a model's prediction covariance holds a Gaussian-process posterior (gp, lddmm,
    an augmented model with a residual GP): part of what it leaves unexplained on held-out
    poses is then in its 1-sigma, not all outside it as for a parametric model's."""
    method = getattr(model, "method", None)
    return method in ("gp", "lddmm") or getattr(model, "residual", None) is not None


LDDMM_OLD_NO_STD_WHY = (
    "the lddmm model file predates its prediction covariance (no posterior_scale_m2, before "
    "2026-11-27); fit it again for a 1-sigma"
)


def no_std_why(model: FittedModel) -> str:
    """Why a model's correction has no 1-sigma (`node_std` gave None)."""
    if getattr(model, "method", None) == "ekf-ann" and _has_theta_cov(model):
        return EKF_NO_STD_WHY
    if (
        getattr(model, "method", None) == "lddmm"
        and getattr(model, "posterior_scale_m2", None) is None
    ):
        return LDDMM_OLD_NO_STD_WHY
    return NO_STD_WHY


def no_std_line(model: FittedModel) -> str:
    return f"correction 1-sigma: not given ({no_std_why(model)})"


def _has_theta_cov(model) -> bool:
    f = getattr(model, "theta_cov", None)
    try:
        return f is not None and f() is not None
    except Exception:  # noqa: BLE001 - a statement only
        return False


def is_warning(line: str) -> bool:
    """Whether an export log line is a warning (`export --json` lists those in `warnings`)."""
    return line.strip().startswith(("WARNING", "warning:", "correction 1-sigma: not given"))


def _configurations(corr: Corrector, tab: CorrectionTable) -> tuple[np.ndarray, tuple]:
    """The one arm configuration each orientation's nodes were solved on (continuation from the
    reference configuration keeps them on one); refuses a grid whose nodes span several (it
    crosses a singularity: no table entry there is continuous with its neighbours)."""
    dh_m = configuration_dh(corr.nominal.theta)
    out = []
    for k in range(len(tab.orientations_rotvec)):
        c = configuration(tab.q_nodes[k].reshape(-1, 6), dh_m)
        uniq = np.unique(c, axis=0)
        if len(uniq) != 1 or np.any(uniq == 0):
            raise CorrectionRefused(
                f"refused: orientation {k}'s grid spans {len(uniq)} arm configurations (shoulder/"
                "elbow/wrist) or touches a singularity; shrink the volume (--volume) so the arm "
                "stays on one"
            )
        out.append(uniq[0])
    return np.asarray(out, int), dh_m


def build_table(
    corr: Corrector,
    lo_m: np.ndarray,
    hi_m: np.ndarray,
    orientations_rotvec: np.ndarray,
    *,
    target_error_m: float = DEFAULT_INTERP_ERROR_M,
    max_correction_m: float = DEFAULT_MAX_CORRECTION_M,
    spacing_m: float | None = None,
    n_check: int = 300,
    max_nodes: int = 4000,
    seed: int = 0,
    meta: dict | None = None,
    log: Callable[[str], None] | None = None,
) -> CorrectionTable:
    """Build the table, refining the spacing until the measured interpolation error is below
    `target_error_m` (or `max_nodes` per orientation is reached, which is reported)."""
    lo_m, hi_m = np.asarray(lo_m, float), np.asarray(hi_m, float)
    if lo_m.shape != (3,) or hi_m.shape != (3,) or np.any(hi_m <= lo_m):
        raise UserError(f"volume: need lo < hi per axis, got {lo_m.tolist()}..{hi_m.tolist()}")
    for name, v in (
        ("interpolation error target", target_error_m),
        ("max correction", max_correction_m),
    ):
        if not (np.isfinite(v) and v > 0):
            raise UserError(f"{name} must be a positive number of metres, got {v}")
    if target_error_m < 1e-12:
        raise UserError(
            f"interpolation error target {target_error_m:g} m is below a picometre; give metres "
            "(5e-6 for 5 um)"
        )
    if target_error_m > 1e-3:
        raise UserError(
            f"interpolation error target {target_error_m:g} m is beyond any calibration (they "
            "are micrometres); give metres (5e-6 for 5 um)"
        )
    if max_correction_m > MAX_CORRECTION_BOUND_M:
        raise UserError(
            f"max correction {max_correction_m:g} m is beyond any calibration (they are mm); "
            "give metres"
        )
    if (turn := beyond_full_turn(orientations_rotvec)) is not None:
        raise UserError(
            f"orientation rotation vector of {turn[1]:.4g} rad: more than a full turn; "
            f"{DEGREES_HINT}"
        )
    if spacing_m is not None:
        if not (np.isfinite(spacing_m) and spacing_m > 0):
            raise UserError(f"spacing must be a positive number of metres, got {spacing_m}")
        if spacing_m > (hi_m - lo_m).max():
            raise UserError(
                f"spacing {spacing_m:g} m is wider than the volume ({(hi_m - lo_m).max():.3g} m "
                "at its widest): one cell, no table; give metres"
            )
        with np.errstate(over="ignore", divide="ignore"):  # a tiny spacing: inf, refused below
            n = float(np.prod(np.floor((hi_m - lo_m) / spacing_m) + 2))
        if n > MAX_FIXED_NODES:
            h_min = float((np.prod(hi_m - lo_m) / MAX_FIXED_NODES) ** (1 / 3))
            raise UserError(
                f"spacing {spacing_m:g} m gives ~{n:.2g} nodes per orientation (limit "
                f"{MAX_FIXED_NODES}); use a spacing of at least {h_min * 1.05:.3g} m"
            )
    rv = np.asarray(orientations_rotvec, float).reshape(-1, 3)
    Rs = rotvec_to_matrix(rv)
    rng = np.random.default_rng(seed)
    P = rng.uniform(lo_m, hi_m, (n_check, 3))
    K = len(rv)
    h = float(spacing_m) if spacing_m is not None else float(min(0.1, (hi_m - lo_m).max() / 2))
    log = log or (lambda m: None)
    exact = [None] * K
    hint, cause = weak_hint(corr.model), smr_hint(corr.model)  # for a refusal's line
    while True:
        shape = _grid_shape(lo_m, hi_m, h)
        tab = CorrectionTable(
            lo_m, hi_m, shape, rv, np.zeros((K, *shape, 3)), np.zeros((K, *shape, 6))
        )
        X = tab.node_positions()
        for k in range(K):
            D, Q = _solve_grid(corr, X, Rs[k])
            check_corrections(D, X, max_correction_m, k, hint=hint, cause=cause)
            tab.delta_m[k], tab.q_nodes[k] = D, Q
        errs = []
        for k in range(K):
            if exact[k] is None:
                c, _, _ = corr.correct_positions(P, Rs[k], tab.seed_for(P, k))
                check_corrections(c - P, P, max_correction_m, k, "check point", hint, cause)
                exact[k] = c - P
            errs.append(np.linalg.norm(tab.interpolate(P, k) - exact[k], axis=1))
        err = np.concatenate(errs)
        log(
            f"  table spacing {tab.spacing_m.max() * 1e3:.1f} mm, {np.prod(shape)} nodes/orientation: "
            f"max interpolation error {err.max() * 1e6:.3f} um on {len(err)} random points"
        )
        finer = _grid_shape(lo_m, hi_m, h / 1.5)
        if spacing_m is not None or err.max() <= target_error_m or np.prod(finer) > max_nodes:
            break
        h /= 1.5
    mags = np.linalg.norm(tab.delta_m.reshape(-1, 3), axis=1)
    tab.configurations, tab.configuration_dh_m = _configurations(corr, tab)
    # the orientation tolerance: as wide as a tilt changes the correction by no more than the
    # interpolation error target (the table's error there is measured and stated too)
    ori = orientation_tolerance(corr, tab, P, exact, float(target_error_m))
    tab.orientation_tol_rad = ori["orientation_tol_rad"]
    log("  " + orientation_line(ori))
    if ori["orientation_tol_rad"] < ORIENTATION_TOL_NARROW_RAD:
        log(
            "  note: the correction changes fast with the tool's orientation here: command the "
            "table's orientation as numbers (not a taught pose)"
        )
    approach = approach_sensitivity(corr, tab.q_nodes)
    if approach is not None:
        log("  " + approach_line(approach))
    coverage = joint_coverage(corr, tab.q_nodes)
    log("  " + coverage_line(coverage))
    tab.std_m = node_std(corr, tab.q_nodes)
    std_meta: dict = {"std_basis": f"none: {no_std_why(corr.model)}"}
    if tab.std_m is not None:
        s3 = np.linalg.norm(tab.std_m.reshape(-1, 3), axis=1)
        std_meta = {
            "std_basis": STD_BASIS,
            "median_std_m": float(np.median(s3)),
            "max_std_m": float(s3.max()),
            "std_posterior": std_is_posterior(corr.model),
        }
        i = int(np.argmax(s3))
        log(
            f"  correction 1-sigma (model uncertainty, 3-D): median {np.median(s3) * 1e6:.1f} um, "
            f"max {s3.max() * 1e6:.1f} um at {np.round(X.reshape(-1, 3)[i % X[..., 0].size], 3).tolist()} m"
        )
        check_std_bound(s3, max_correction_m, corr.model)
        # a correction smaller than its own 1-sigma is not determined by the measurements
        std_meta["nodes_std_exceeds_correction"] = int(np.sum(s3 > mags))
        if (line := undetermined_line(s3, mags)) is not None:
            log(f"  {line}")
    else:
        log(f"  {no_std_line(corr.model)}")
    tab.meta = {
        **(meta or {}),
        **frame_meta(corr.model, corr.nominal.base_ref, X),
        "units": "m, rad (UR rotation vectors)",
        "semantics": "commanded = desired + delta(desired), delta trilinear in the grid",
        "conditions": corr.conditions.to_dict(),
        "tcp_m": np.asarray(corr.nominal.tool_m).tolist(),
        "target_interp_error_m": float(target_error_m),
        "max_interp_error_m": float(err.max()),
        "rms_interp_error_m": float(np.sqrt(np.mean(err**2))),
        "interp_error_points": int(len(err)),
        "interp_error_target_met": bool(err.max() <= target_error_m),
        **ori,
        "max_correction_m": float(mags.max()),
        **std_meta,
        "correction_bound_m": float(max_correction_m),
        **({"approach_sensitivity": approach} if approach is not None else {}),
        "joint_coverage": coverage,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    return tab
