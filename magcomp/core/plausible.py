"""Plausibility gates on whole magnetometer columns, the same rules the live pipeline applies sample by
sample (service/align.py): a sample with any axis at or beyond the sensor's saturation is clipped, not a
field; a sample that changes any axis by more than the jump limit from the previous one is dropped (so
a lone corrupt value goes with the sample after it). Pure: arrays in, masks out."""

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
    # jumps between the samples that pass the first gate, as the pipeline sees them (a saturated sample
    # never becomes "the previous sample")
    kept = np.flatnonzero(~saturated)
    jump_kept = np.zeros(kept.size, dtype=bool)
    if kept.size >= 2:
        step = np.max(np.abs(np.diff(v[kept], axis=0)), axis=1)
        big = step > jump_mgauss
        jump_kept[1:] = big  # (a lone corrupt value: it and the sample after it, as in the pipeline)
    jump = np.zeros(n, dtype=bool)
    jump[kept] = jump_kept
    return saturated, jump
