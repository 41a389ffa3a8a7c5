"""Whose slow error is it: the compass's or the autopilot's yaw's?

The att metric (:func:`magcomp.core.selfcheck.offset_removed_rms_deg` of heading - autopilot yaw) charges
to the compass every slow difference from the autopilot's yaw. Where that yaw is itself wrong for a while
(an EKF yaw reset, a yaw fused from another compass that a current step bent) the compass is charged with
the autopilot's error, and no correction of the compass can lower it. The gyro decides: over windows long
enough for a slow error to show (30 s) and short enough for a rate bias to stay constant, each window's
offset and linear drift (the gyro's rate bias) are removed from (compass - gyro yaw) and from (autopilot
yaw - gyro yaw); whichever stays larger carries the slow error.

Pure numpy; angles in rad, times in s, results in deg.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magcomp.core.selfcheck import window_ids

F64 = NDArray[np.float64]

#: long enough for a slow error to show, short enough for a MEMS gyro's rate bias to stay constant
SLOW_WINDOW_S = 30.0
#: fewer samples than this in a window: the window is left out (an offset and a drift need a few more)
MIN_PER_SLOW_WINDOW = 8


def drift_removed_rms_deg(
    t_s: F64, err_rad: F64, ids: NDArray[np.int64], min_per_window: int = MIN_PER_SLOW_WINDOW
) -> float:
    """rms (deg) of ``err_rad`` (continuous, not wrapped: a difference of unwrapped angles) after removing,
    in each window, its mean and its linear trend in time (a constant gyro rate bias makes one); NaN where no
    window has ``min_per_window`` samples."""
    t = np.asarray(t_s, dtype=float)
    e = np.asarray(err_rad, dtype=float)
    ok = np.isfinite(t) & np.isfinite(e)
    t, e, ids = t[ok], e[ok], ids[ok]
    if ids.size == 0:
        return math.nan
    nw = int(ids.max()) + 1
    n = np.bincount(ids, minlength=nw).astype(float)
    keep = n[ids] >= min_per_window
    if not keep.any():
        return math.nan
    t, e, ids, n = t[keep], e[keep], ids[keep], np.maximum(n, 1.0)
    # per-window least squares of e on (1, t - mean t): slope = cov(t, e) / var(t)
    tm = np.bincount(ids, t, minlength=nw)[ids] / n[ids]
    em = np.bincount(ids, e, minlength=nw)[ids] / n[ids]
    dt, de = t - tm, e - em
    var_t = np.bincount(ids, dt * dt, minlength=nw)
    cov = np.bincount(ids, dt * de, minlength=nw)
    slope = np.divide(cov, var_t, out=np.zeros(nw), where=var_t > 0)
    res = de - slope[ids] * dt
    return math.degrees(math.sqrt(float(np.mean(res * res))))


@dataclass(frozen=True)
class SlowErrorOwner:
    """Slow (window-length) errors against the gyro, deg, each window's offset and drift removed."""

    compass_vs_gyro_deg: float
    autopilot_vs_gyro_deg: float
    compass_vs_autopilot_deg: float
    n_windows: int

    @property
    def autopilot_yaw_limited(self) -> bool:
        """The autopilot's yaw departs from the gyro more than the compass does: its slow difference from
        the compass is (mostly) the autopilot's."""
        return self.autopilot_vs_gyro_deg > self.compass_vs_gyro_deg


def slow_error_owner(
    t_s: F64,
    heading_rad: F64,
    autopilot_yaw_rad: F64,
    gyro_yaw_rad: F64,
    segment: F64 | None = None,
    window_s: float = SLOW_WINDOW_S,
) -> SlowErrorOwner:
    """Compare the compass's heading and the autopilot's yaw with the gyro's integrated yaw (all at the
    compass's sample times ``t_s``) on ``window_s`` windows (a restart of the gyro's integral, ``segment``,
    starts a new one)."""
    t = np.asarray(t_s, dtype=float)
    ids = window_ids(t, segment, window_s)
    h = np.unwrap(np.asarray(heading_rad, dtype=float))
    y = np.unwrap(np.asarray(autopilot_yaw_rad, dtype=float))
    g = np.asarray(gyro_yaw_rad, dtype=float)
    # the differences unwrapped once each (the angles' own unwrapping may differ by whole turns)
    hg = np.unwrap(h - g)
    yg = np.unwrap(y - g)
    hy = np.unwrap(h - y)
    n = np.bincount(ids).astype(int) if ids.size else np.zeros(0, dtype=int)
    return SlowErrorOwner(
        drift_removed_rms_deg(t, hg, ids),
        drift_removed_rms_deg(t, yg, ids),
        drift_removed_rms_deg(t, hy, ids),
        int(np.sum(n >= MIN_PER_SLOW_WINDOW)),
    )
