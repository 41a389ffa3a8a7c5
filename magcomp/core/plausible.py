"""Plausibility gates on whole magnetometer columns, the same rules the live pipeline applies sample by
sample (service/align.py): a sample with any axis at or beyond the sensor's saturation is clipped, not a
field; a change of any axis larger than the jump limit between two samples is a corrupt value, dropped
with the sample after it. Pure: arrays in, masks out."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def mag_outliers(
    values: NDArray[np.float64], saturation_mgauss: float, jump_mgauss: float
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(saturated or non-finite, jump) masks of a compass's (n, 3) field in sample order."""
    v = np.asarray(values, dtype=np.float64)
    n = v.shape[0]
    finite = np.all(np.isfinite(v), axis=1) if n else np.zeros(0, dtype=bool)
    saturated = ~finite | np.any(np.abs(np.where(np.isfinite(v), v, 0.0)) >= saturation_mgauss, axis=1)
    jump = np.zeros(n, dtype=bool)
    if n >= 2:
        with np.errstate(invalid="ignore"):
            step = np.max(np.abs(np.diff(v, axis=0)), axis=1)
        big = ~(step <= jump_mgauss)  # (a non-finite step is a jump)
        jump[1:] |= big
        jump[2:] |= big[:-1]  # the sample after a jump goes too (the pipeline's rule)
    return saturated, jump & ~saturated
