"""How fast an autopilot's yaw follows a compass: the straight-line fit of its gain (not in the paper).

An attitude filter propagates its yaw with the gyro and pulls it toward a compass's heading:
``d psi_ap / dt = psi_dot_gyro + b + k (psi_compass - psi_ap)`` (a complementary filter with gain ``k``, 1/s;
an EKF's magnetometer update acts the same way to first order, ``b`` the gyro bias it has not learned). So
the autopilot's yaw minus the gyro's integral, ``D = psi_ap - integral(psi_dot_gyro)``, changes at
``b + k (psi_compass - psi_ap)``: over short windows, one line through (mean offset, rate of D) gives ``k``.

Why it matters to the self-check (core/selfcheck.py): where ``k`` is fast against the check's window, the
autopilot's yaw carries the compass's own error on every time scale the windows do not already see, so it
is no second reference (:func:`follows_within`). Measured: log171's ArduCopter EKF ~0.02 /s, the
simulator's complementary filter 0.5 /s (docs/measured-data.md).

Pure numpy; angles in rad, times in s.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

#: windows whose rate lies beyond this many robust (median-absolute) sigmas of the line are left out: for
#: Gaussian scatter one window in 16,000 would be, a yaw reset or a gyro glitch always is
OUTLIER_Z = 4.0
#: the fewest windows a line is fitted on
MIN_WINDOWS = 5


class YawFollow(NamedTuple):
    """gain_per_s: k of the model above, 1/s, with its standard error; bias_rad_s: b; n_windows used;
    spread_rad: rms of the compass's heading minus the autopilot's yaw over the windows (what k is
    measured against: with a spread of a fraction of a degree, k is not determined); n_left_out: windows
    left out as jumps (OUTLIER_Z)."""

    gain_per_s: float
    gain_sigma_per_s: float
    bias_rad_s: float
    n_windows: int
    spread_rad: float
    n_left_out: int = 0


def fit_follow_gain(rates_rad_s: F64, offsets_rad: F64) -> YawFollow | None:
    """The line ``rate = b + k offset`` through the windows' rates of D and mean offsets (compass heading -
    autopilot yaw), with one pass of outlier removal (OUTLIER_Z). None with fewer than MIN_WINDOWS windows."""
    y = np.asarray(rates_rad_s, dtype=float)
    n_all = int(y.size)
    if n_all < MIN_WINDOWS:
        return None
    x = np.column_stack([np.ones(n_all), np.asarray(offsets_rad, dtype=float)])
    sol, *_ = np.linalg.lstsq(x, y, rcond=None)
    e = y - x @ sol
    # a yaw reset (an EKF realigning its yaw at take-off: 15.6 deg in one window on log171) or a gyro
    # glitch is a jump in one window, not a pull: windows beyond OUTLIER_Z robust sigmas are left out once
    scale = 1.4826 * float(np.median(np.abs(e)))
    keep = np.abs(e) <= OUTLIER_Z * scale if scale > 0.0 else np.ones(n_all, dtype=bool)
    if int(keep.sum()) >= MIN_WINDOWS and not bool(keep.all()):
        x, y = x[keep], y[keep]
        sol, *_ = np.linalg.lstsq(x, y, rcond=None)
        e = y - x @ sol
    dof = max(1, len(y) - 2)
    cov = float(e @ e) / dof * np.linalg.pinv(x.T @ x)
    return YawFollow(
        gain_per_s=float(sol[1]),
        gain_sigma_per_s=float(math.sqrt(max(0.0, cov[1, 1]))),
        bias_rad_s=float(sol[0]),
        n_windows=len(y),
        spread_rad=float(np.std(x[:, 1])),
        n_left_out=n_all - len(y),
    )


#: the fewest samples a window needs to give a rate of D
MIN_SAMPLES_PER_WINDOW = 3


def window_follow_terms(
    t_s: F64, compass_rad: F64, autopilot_yaw_rad: F64, gyro_yaw_rad: F64, ids: NDArray[np.int64]
) -> tuple[F64, F64]:
    """Per window (``ids``: consecutive samples of one window share an id; one gyro segment each): the rate
    of D = autopilot yaw - gyro yaw from its first to its last sample (rad/s) and the circular mean of
    (compass heading - autopilot yaw) (rad). Windows of fewer than MIN_SAMPLES_PER_WINDOW samples or no time
    span are left out."""
    t = np.asarray(t_s, dtype=float)
    if t.size == 0:
        return np.zeros(0), np.zeros(0)
    idv = np.asarray(ids, dtype=np.int64)
    d = np.asarray(autopilot_yaw_rad, dtype=float) - np.asarray(gyro_yaw_rad, dtype=float)
    off = np.asarray(compass_rad, dtype=float) - np.asarray(autopilot_yaw_rad, dtype=float)
    nw = int(idv.max()) + 1
    n = np.bincount(idv, minlength=nw)
    first = np.full(nw, t.size, dtype=np.int64)
    np.minimum.at(first, idv, np.arange(t.size))
    last = np.full(nw, -1, dtype=np.int64)
    np.maximum.at(last, idv, np.arange(t.size))
    keep = n >= MIN_SAMPLES_PER_WINDOW
    first, last = first[keep], last[keep]
    span = t[last] - t[first]
    ok = span > 0.0
    first, last, span = first[ok], last[ok], span[ok]
    step = np.angle(np.exp(1j * (d[last] - d[first])))  # D changes by a few degrees at most in a window
    s = np.bincount(idv, np.sin(off), minlength=nw)[keep][ok]
    c = np.bincount(idv, np.cos(off), minlength=nw)[keep][ok]
    return step / span, np.arctan2(s, c)


#: how many standard errors the gain must lie above a rate for :func:`follows_within` (one-sided ~97.7 %)
FOLLOW_Z = 2.0


def follows_within(follow: YawFollow | None, window_s: float) -> bool:
    """The autopilot's yaw follows the compass with a time constant shorter than ``window_s``, beyond the
    fit's noise (its gain FOLLOW_Z standard errors above 1 / window_s): then it holds that compass's error
    on every time scale longer than the window. A gain near the bound or poorly measured (a few windows, a
    yaw reset: 0.11 +- 0.06 /s on a development log) is not evidence enough."""
    return follow is not None and follow.gain_per_s - FOLLOW_Z * follow.gain_sigma_per_s >= 1.0 / window_s
