"""Options shared by several commands."""

from __future__ import annotations

import argparse
import math

from workcell.errors import UserError
from workcell.estimation.dh import TRACKER_MPE_M


def say_replaced(lines: list[str]) -> None:
    """Print the "replacing X: why" lines `check_model_output` gathered as "replaced X: why",
    once the new file is written (a refusal found between the check and the write left X as it
    was, after "replacing X")."""
    import sys

    for line in lines:
        print(line.replace("replacing ", "replaced ", 1), file=sys.stderr)


def add_tracker_mpe(p: argparse.ArgumentParser) -> None:
    a, b = TRACKER_MPE_M
    p.add_argument(
        "--tracker-mpe",
        default=f"{a:g},{b:g}",
        metavar="A,B",
        help=(
            "tracker MPE A,B in m and m/m: sigma per axis >= (A + B*range)/4; "
            f"default {a * 1e6:g} um + {b * 1e6:g} um/m"
        ),
    )


def parse_tracker_mpe(text: str) -> tuple[float, float]:
    """'A,B' -> (A, B) in m and m/m; finite, non-negative, A below 1 mm (an MPE in um or mm
    typed without the e-6 would otherwise pass as metres)."""
    try:
        mpe = tuple(float(x) for x in str(text).split(","))
    except ValueError:
        mpe = ()
    if len(mpe) != 2 or not all(math.isfinite(x) and x >= 0.0 for x in mpe):
        raise UserError(
            f"--tracker-mpe must be two finite non-negative numbers A,B (m, m/m); got {text!r}"
        )
    if mpe[0] > 1e-3 or mpe[1] > 1e-3:
        raise UserError(
            f"--tracker-mpe {text!r}: A and B are in m and m/m (15 um + 6 um/m is 15e-6,6e-6); "
            "a value above 1e-3 looks like micrometres or millimetres"
        )
    return mpe[0], mpe[1]


def display_unit(unit: str) -> tuple[float, str]:
    """(scale, label) to print a parameter of SI `unit` in a table: m as mm, rad as mrad."""
    return {"m": (1e3, "mm"), "rad": (1e3, "mrad")}.get(unit, (1.0, unit))
