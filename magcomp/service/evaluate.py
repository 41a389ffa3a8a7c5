"""Heading agreement between compasses of one log: how the real-log figures are measured.

On a real log there is no truth; a compass far from the power wires (external, the autopilot's primary) is
the reference the others are compared with. The rms of the heading difference is taken with its constant
part removed (a mounting offset between two compasses is not a heading error), over the samples before
``t_end_s`` (e.g. a crash).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from magcomp.core.selfcheck import offset_removed_rms_deg
from magcomp.core.types import HeadingEstimate

#: throttle above which the vehicle counts as flying (motors clearly above idle)
FLYING_THROTTLE_01 = 0.05


def heading_agreement(
    estimates: Sequence[HeadingEstimate], ref_index: int = 0, t_end_s: float = math.inf
) -> dict[int, dict[str, float]]:
    """Per compass other than ``ref_index``: rms difference (deg) of the published headings from the
    reference's, corrected (``heading``) and uncorrected (``heading_raw``), over all samples and over the
    flying ones (throttle above :data:`FLYING_THROTTLE_01`). ``t_end_s``: seconds after the reference's
    first sample (e.g. before a crash)."""
    by: dict[int, list[HeadingEstimate]] = {}
    for e in estimates:
        by.setdefault(e.mag_index, []).append(e)
    if ref_index not in by:
        return {}
    ref = by[ref_index]
    t_ref = np.array([e.t_s for e in ref])
    h_ref = np.unwrap(np.radians([e.heading_deg for e in ref]))
    r_ref = np.unwrap(np.radians([e.heading_raw_deg for e in ref]))
    out: dict[int, dict[str, float]] = {}
    for idx, es in sorted(by.items()):
        if idx == ref_index:
            continue
        t = np.array([e.t_s for e in es])
        keep = t - t_ref[0] < t_end_s
        fly = keep & (np.array([e.throttle_01 for e in es]) > FLYING_THROTTLE_01)
        dh = np.radians([e.heading_deg for e in es]) - np.interp(t, t_ref, h_ref)
        dr = np.radians([e.heading_raw_deg for e in es]) - np.interp(t, t_ref, r_ref)
        out[idx] = {
            "corrected_all_deg": offset_removed_rms_deg(dh[keep]),
            "uncorrected_all_deg": offset_removed_rms_deg(dr[keep]),
            "corrected_flying_deg": offset_removed_rms_deg(dh[fly]),
            "uncorrected_flying_deg": offset_removed_rms_deg(dr[fly]),
        }
    return out
