"""The measuring instrument's stated accuracy, shared by the fits (their weights floor) and the
recording's own checks (how far a pose measured again may move by the tracker alone)."""

from __future__ import annotations

import numpy as np

# A laser tracker's maximum permissible error, A [m] + B [m/m] * range (a Leica AT960's stated
# MPE); 1 sigma per axis is taken as MPE / 4. The recorded sigma of a mean comes from the scatter
# of the readings at one pose, which leaves out the tracker's per-pose systematic error.
TRACKER_MPE_M: tuple[float, float] = (15e-6, 6e-6)


def tracker_spec_sigma(
    p_tracker: np.ndarray, mpe: tuple[float, float] = TRACKER_MPE_M
) -> np.ndarray:
    """Per-axis 1-sigma (N,) of a tracker meeting its MPE (A + B x range) at the points
    p_tracker (N, 3) in its frame: MPE / 4, the floor the fits weight by."""
    return (mpe[0] + mpe[1] * np.linalg.norm(np.atleast_2d(p_tracker), axis=1)) / 4.0
