"""Reading `export --format targets --in FILE`: the targets to correct.

Accepted (one header row, then one target per line; blank lines and `#` comment lines anywhere
are skipped; a spreadsheet's byte-order mark, spaces and capitals in the header are fine; other
columns, such as a name, are ignored):

- desired positions x,y,z [orientation rx,ry,rz as a UR rotation vector] [IK seeds q1..q6];
- joint targets q1..q6 alone (nominal joints: the desired position is the nominal arm's there);
- the targets CSV `export --format targets` writes (also an edited copy, and the one written
  before 2026-11-26 without units): its desired targets x_m..rz_rad are read, never its
  commanded x_cmd_m.. (the earlier correction): a target is corrected once, from its desired
  position, by the model given now. Its corrected joints q1_cmd_rad.. only seed the IK (they keep
  each target on the arm configuration it was corrected on).

Units: a column without a unit is in m (positions) or rad (angles), as before; a unit stated in
the name (`x_mm`, `x [mm]`, `q1 (deg)`) is converted to m or rad (m, cm, mm, um; rad, deg); a
unit of the wrong kind (`x_deg`, `q1_mm`) or an unknown one in brackets is refused. The values
are checked for plausibility after that by `export` (reach, joint ranges: millimetres or degrees
under a column that says m or rad are refused with a hint).
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from workcell.errors import UserError

POSITION = ("x", "y", "z")
ROTATION = ("rx", "ry", "rz")
JOINTS = tuple(f"q{i}" for i in range(1, 7))
LENGTH_UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "µm": 1e-6}
ANGLE_UNITS = {"rad": 1.0, "deg": math.pi / 180, "degree": math.pi / 180}
ANGLE_UNITS.update({"degrees": math.pi / 180, "°": math.pi / 180})
# units recognised in a column name (so not another column) but not converted: ambiguous or
# unusual for a UR cell (`x_in`: inches or "input"?)
REFUSED_UNITS = ("in", "inch", "inches", "ft", "km", "nm", "mrad", "grad", "gon", "turn", "rev")
FORMAT_HINT = (
    "give a header row x,y,z (m; or x_m.., x_mm..) [rx,ry,rz (rad; or rx_deg..)] "
    "[q1..q6 seeds], or q1..q6 alone, and one target per line"
)
_NAME = re.compile(
    r"^(?P<name>x|y|z|rx|ry|rz|q(?P<j>\d{1,3}))(?P<cmd>_cmd)?"
    r"(?:_(?P<u1>[a-zµ°]+)|\s*[(\[]\s*(?P<u2>[^)\]]*?)\s*[)\]])?$"
)


@dataclass(frozen=True)
class Column:
    """A header cell naming a target column: quantity `name` (x..rz, q1..q6), whether it is a
    commanded (`_cmd`, already corrected) value, and the factor to m or rad."""

    index: int
    header: str
    name: str
    cmd: bool
    unit: str | None  # as stated; None: none stated (m or rad)
    factor: float


@dataclass
class TargetsIn:
    """The targets of an `--in` file, in m and rad, each row with its line in the file.

    `P` desired positions (N, 3) or None (joint targets); `rotvec` (N, 3) or None (tool down);
    `q` (N, 6) or None: joint targets when `P` is None, else IK seeds (`q_role`); `q_columns`
    the header names `q` came from (for messages); `notes` lines for the person (what was read
    and how it was converted)."""

    lines: list[int]
    P: np.ndarray | None
    rotvec: np.ndarray | None
    q: np.ndarray | None
    q_role: str | None  # "targets", "seeds" or None
    q_columns: tuple[str, ...] = ()
    corrected_csv: bool = False  # a corrected-targets CSV (its desired columns were read)
    columns: list[str] = field(default_factory=list)  # the header cells read
    notes: list[str] = field(default_factory=list)


def _column(i: int, cell: str, src: Path, hline: int) -> Column | None:
    h = cell.strip().lower()
    m = _NAME.match(h)
    if m is None:
        return None
    name, cmd = m["name"], m["cmd"] is not None
    unit = m["u1"] if m["u1"] is not None else m["u2"]
    where = f"{src}: line {hline}, column {cell.strip()!r}"
    if unit is not None and unit not in LENGTH_UNITS and unit not in ANGLE_UNITS:
        if m["u1"] is not None and unit not in REFUSED_UNITS:
            return None  # `x_pos`, `q1_note`: another column, ignored as any other name
        if unit:
            raise UserError(
                f"{where}: unit {unit!r} not accepted; name the unit m, cm, mm or um for "
                "positions, rad or deg for angles (or none: m, rad)"
            )
        unit = None  # `x ()`: no unit
    if m["j"] is not None:
        j = int(m["j"])
        if not 1 <= j <= 6:
            raise UserError(
                f"{where}: the arm has 6 joints, q1..q6 (base to wrist 3)"
                + ("; number them from 1" if j == 0 else f"; remove q{j}")
            )
        name = f"q{j}"
    length = name in POSITION
    table = LENGTH_UNITS if length else ANGLE_UNITS
    if unit is not None and unit not in table:
        raise UserError(
            f"{where}: {name} is {'a position' if length else 'an angle'}, not in {unit}; "
            + (
                "name its unit m, cm, mm or um (none: m)"
                if length
                else "name its unit rad or deg (none: rad)"
            )
        )
    return Column(i, cell.strip(), name, cmd, unit, 1.0 if unit is None else table[unit])


def _is_comment(row: list[str]) -> bool:
    """A `#` line (also as a spreadsheet saved it: split at its commas, or quoted); a header
    whose first column is named `#` (a row number) is not one."""
    first = row[0].strip() if row else ""
    if not first.startswith("#"):
        return False
    if first == "#" and any(_NAME.match(c.strip().lower()) for c in row[1:]):
        return False
    return True


def _rows(src: Path) -> tuple[list[str], tuple[list[str], int] | None, list]:
    """(comment lines before the header, (header, its line) or None, [(row, its line), ...]
    after it, blank lines left out)."""
    comments: list[str] = []
    header: tuple[list[str], int] | None = None
    body: list[tuple[list[str], int]] = []
    try:
        with open(src, newline="", encoding="utf-8-sig") as f:  # spreadsheets write a BOM
            reader = csv.reader(f)
            for r in reader:
                if not any(x.strip() for x in r):
                    continue
                if header is not None:  # `#` lines here: `_comment_after_header`
                    body.append((r, reader.line_num))
                elif _is_comment(r):
                    comments.append(",".join(r).strip())
                else:
                    header = (r, reader.line_num)
    except (UnicodeDecodeError, csv.Error) as e:
        raise UserError(f"{src}: not a text CSV file ({e}); {FORMAT_HINT}") from None
    except OSError as e:
        raise UserError(f"{src}: cannot be read ({e.strerror or e})") from None
    return comments, header, body


def _comment_after_header(r: list[str], ln: int, cols: dict, src: Path) -> bool:
    """Whether a row under the header is a `#` comment. When the first column is not a target
    column (a name), a `#` row holding a whole target is refused: a target commented out, or
    one whose name starts with `#`? Either reading would be silent."""
    if not r[0].strip().startswith("#"):
        return False
    if any(c.index == 0 for c in cols.values()):
        return True  # a number's place: a comment (or a target commented out)

    def number(c: Column) -> bool:
        try:
            return math.isfinite(float(r[c.index]))
        except (IndexError, ValueError):
            return False

    targets = [c for c in cols.values() if not c.cmd]
    if targets and all(number(c) for c in targets):
        raise UserError(
            f"{src}: line {ln}: starts with {r[0].strip()[:20]!r} but holds a whole target: "
            "commented out, or named with a leading '#'? Delete the line to leave it out, or "
            "rename it without the '#' to correct it"
        )
    return True


def _value(cell: str, src: Path, line: int, col: Column) -> float:
    v = cell.strip()
    unit = col.unit or ("m" if col.name in POSITION else "rad")
    if not v:
        raise UserError(
            f"{src}: line {line}, column {col.header}: missing value; fill in a number in "
            f"{unit} or delete the line"
        )
    try:
        if "_" in v:  # float() reads "0_1" as 1.0 (Python's digit grouping): not a CSV number
            raise ValueError(v)
        x = float(v)
    except ValueError:
        raise UserError(
            f"{src}: line {line}, column {col.header}: {v[:40]!r} is not a number; give a "
            f"plain number in {unit} (decimal point, no unit after it)"
        ) from None
    if not math.isfinite(x) or not math.isfinite(x * col.factor):
        raise UserError(
            f"{src}: line {line}, column {col.header}: not a finite number ({v[:40]!r}); give "
            f"a number in {unit} or delete the line"
        )
    return x * col.factor


def read_targets(path: str | Path) -> TargetsIn:
    """The targets of a `--in` file (see the module's doc); raises UserError, in one line
    naming the file's line and what to do, on anything else."""
    src = Path(path)
    from workcell.export.files import export_kind

    kind = export_kind(src) if src.is_file() else None
    if kind is not None and kind != "targets CSV":
        # a table's CSV has x,y,z columns too: its grid nodes were read as 2376 targets
        raise UserError(
            f"{src} is a workcell {kind}, not a list of targets; {FORMAT_HINT} (or give the "
            "targets CSV `export --format targets` wrote)"
        )
    comments, header, body = _rows(src)
    if header is None:
        raise UserError(
            f"{src}: "
            + ("only comment lines" if comments else "empty file")
            + f", no header row and no targets; {FORMAT_HINT}"
        )
    head, hline = header
    cols: dict[tuple[str, bool], Column] = {}
    for i, cell in enumerate(head):
        c = _column(i, cell, src, hline)
        if c is None:
            continue
        if (c.name, c.cmd) in cols:
            raise UserError(
                f"{src}: line {hline}: columns {cols[(c.name, c.cmd)].header!r} and "
                f"{c.header!r} both give {c.name}{'_cmd' if c.cmd else ''}; keep one"
            )
        cols[(c.name, c.cmd)] = c
    mark = any(t.startswith(_mark()) for t in comments)
    given = {n for (n, cmd) in cols if not cmd}
    for group in (ROTATION, JOINTS, POSITION):
        have = [n for n in group if n in given]
        if have and len(have) < len(group):
            raise UserError(
                f"{src}: line {hline}: columns {','.join(cols[(n, False)].header for n in have)} "
                f"without {','.join(n for n in group if n not in given)}; give all of "
                f"{','.join(group)} or none"
            )
    cmd_cols = [c for (n, cmd), c in cols.items() if cmd]
    corrected = mark or bool(cmd_cols)
    if not given:
        if cmd_cols:
            raise UserError(
                f"{src}: line {hline}: only commanded columns "
                f"({','.join(c.header for c in cmd_cols)[:60]}): those are an earlier "
                "correction, correcting them would correct twice; give the desired targets "
                "(x_m,y_m,z_m.. as `export --format targets` writes them beside)"
            )
        raise UserError(
            f"{src}: line {hline}: need columns x,y,z (and optional rx,ry,rz, q1..q6) or "
            f"q1..q6; the header has {','.join(h.strip().lower() for h in head)[:80]!r}; "
            "units in the name are read (x_m or x_mm, rx_rad or rx_deg), none means m and rad"
        )
    body = [(r, ln) for r, ln in body if not _comment_after_header(r, ln, cols, src)]
    if not body:
        raise UserError(
            f"{src}: line {hline} is a header but no target follows it; add one target per line"
        )
    n = len(body)
    lines = [ln for _, ln in body]
    for r, ln in body:
        extra = [x for x in r[len(head) :] if x.strip()]
        if extra:
            raise UserError(
                f"{src}: line {ln}: {len(head) + len(extra)} values under a header of "
                f"{len(head)} columns (line {hline}); a value too many or a column without a "
                "name: fix the line or name the column"
            )

    def block(names, cmd=False) -> np.ndarray:
        out = np.empty((n, len(names)))
        for k, name in enumerate(names):
            c = cols[(name, cmd)]
            for i, (r, ln) in enumerate(body):
                cell = r[c.index] if c.index < len(r) else ""
                out[i, k] = _value(cell, src, ln, c)
        return out

    P = block(POSITION) if set(POSITION) <= given else None
    rv = block(ROTATION) if set(ROTATION) <= given else None
    notes = []
    if rv is not None and P is None:
        if not set(JOINTS) <= given:
            raise UserError(
                f"{src}: line {hline}: an orientation rx,ry,rz without the positions x,y,z; "
                "give x,y,z with it, or joint targets q1..q6"
            )
        rv = None  # as before: joint targets carry their own orientation
        notes.append(f"{src}: rx,ry,rz not used: the joint targets q1..q6 set the orientation")
    q, q_role, q_cols, cmd_seeds = None, None, (), False
    if set(JOINTS) <= given:
        q, q_role = block(JOINTS), ("seeds" if P is not None else "targets")
        q_cols = tuple(cols[(j, False)].header for j in JOINTS)
    elif P is not None and all((j, True) in cols for j in JOINTS):
        q, q_role = _cmd_seeds(body, [cols[(j, True)] for j in JOINTS], src), "seeds"
        cmd_seeds = True
        q_cols = tuple(cols[(j, True)].header for j in JOINTS)
    if rv is not None:
        turn = np.linalg.norm(rv, axis=1)
        i = int(np.argmax(turn))
        if turn[i] > 2 * math.pi + 1e-9:
            deg = any(cols[(a, False)].unit in ("deg", "degree", "degrees", "°") for a in ROTATION)
            raise UserError(
                f"{src}: line {lines[i]}: rotation vector of {turn[i]:.4g} rad, more than a full "
                "turn; "
                + (
                    "a rotation vector's length is its angle, at most 360 deg"
                    if deg
                    else "it looks like degrees, give radians (UR rotation vectors) or name "
                    "the columns rx_deg,ry_deg,rz_deg"
                )
            )
    used = [c.header for c in sorted(cols.values(), key=lambda c: c.index) if not c.cmd]
    if corrected:
        model = next(
            (t[len("# model:") :].strip() for t in comments if t.startswith("# model:")), ""
        )
        was = f" (corrected before with {model})" if model else ""
        cmd = sorted(cmd_cols, key=lambda c: c.index)
        notes.append(
            f"{src}: a workcell corrected-targets CSV{was}: reading its desired targets "
            f"{_span(used)}"
            + (
                f", not its commanded {_span([c.header for c in cmd])} (the earlier correction)"
                if cmd
                else ""
            )
            + ", so no target is corrected twice"
            + (f"; {_span(q_cols)} only seed the IK (same arm configuration)" if cmd_seeds else "")
        )
    conv: dict[str, list[str]] = {}
    for c in sorted(cols.values(), key=lambda c: c.index):
        if c.unit is not None and c.factor != 1.0 and (not c.cmd or c.header in q_cols):
            conv.setdefault(f"{c.unit} to {'m' if c.name in POSITION else 'rad'}", []).append(
                c.header
            )
    if conv:
        notes.append(
            f"{src}: converted "
            + "; ".join(f"{','.join(h)} from {u}" for u, h in conv.items())
            + " (the unit their names state)"
        )
    return TargetsIn(
        lines=lines,
        P=P,
        rotvec=rv,
        q=q,
        q_role=q_role,
        q_columns=q_cols,
        corrected_csv=corrected,
        columns=used,
        notes=notes,
    )


def _span(names) -> str:
    return names[0] if len(names) == 1 else f"{names[0]}..{names[-1]}"


def _cmd_seeds(body, qcols: list[Column], src: Path) -> np.ndarray:
    """IK seeds from the corrected joints of a corrected-targets CSV: a row whose six are all
    blank (cleared after an edit) is seeded from the reference configuration."""
    from workcell.export.correction import Q_REF

    out = np.empty((len(body), 6))
    for i, (r, ln) in enumerate(body):
        cells = [r[c.index].strip() if c.index < len(r) else "" for c in qcols]
        if not any(cells):
            out[i] = Q_REF
            continue
        out[i] = [_value(cell, src, ln, c) for cell, c in zip(cells, qcols, strict=True)]
    return out


def _mark() -> str:
    from workcell.export.files import TARGETS_CSV_MARK

    return TARGETS_CSV_MARK
