"""Find the stationary throttle sweep of a log: the data the offline fit of eqs. (12)-(15) needs.

The offline estimator (paper sec. II-C-1, Fig. 7) requires the vehicle at rest while the throttle is
moved ("the throttle is increased from 0 to 100 %"), so that any change of the field is the
current-induced bias. A log rarely says where that happened; this module finds it:

1. stationary = the gyro vector, averaged over ``smooth_s`` (vibration cancels in the mean, a real
   rotation does not), has a norm below ``max_rate_rad_s``;
2. the attitude (when given) stays within ``max_attitude_change_rad`` (roll, pitch) of the window's
   first sample, which rejects slow pans the rate test would let through. Yaw is special: an autopilot's
   yaw is fused from the very compass whose current-induced bias we measure, so on a bench sweep it swings
   with throttle (by up to Table III's 18.6 deg) while the vehicle does not turn. Yaw is therefore tested
   after removing its least-squares fit on throttle^2: a window whose residual yaw spans more than
   ``max_yaw_residual_rad`` is a pan and is dropped. The autopilot's filter lag leaves a hysteresis
   (7.6 deg span on the simulated bench log of replay_logs/); a pan at 0.03 rad/s with a simultaneous
   sweep leaves 11.9 deg;
3. the throttle spans at least ``min_throttle_span`` inside the window.

Among the candidates the best is the one with the most information about theta,
``sum (delta^2 - mean delta^2)^2`` (the denominator of the theta variance, eq. (14b)).

Departure: the paper selects the sweep by hand. A hover with a throttle change looks stationary to
these tests when attitude and rates stay small; pass explicit bounds for such logs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcomp.core.types import LogData, Series

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class SegmentParams:
    """Thresholds of :func:`find_stationary_segments` (rad/s, rad, s, throttle 0..1)."""

    max_rate_rad_s: float = 0.05
    smooth_s: float = 1.0
    max_attitude_change_rad: float = math.radians(3.0)
    max_yaw_residual_rad: float = math.radians(9.5)
    min_throttle_span: float = 0.3
    min_duration_s: float = 5.0
    edge_margin_s: float = 0.5
    max_gap_s: float = 1.0


@dataclass(frozen=True)
class Segment:
    """A stationary window: bounds (s, source clock), throttle span and theta information (see module doc)."""

    t_start_s: float
    t_end_s: float
    throttle_span: float
    information: float
    n_throttle: int


def _centered_mean(t: F64, x: F64, width_s: float) -> F64:
    """Mean of the rows of ``x`` (n, k) over ``[t - w/2, t + w/2]`` for irregular ``t`` (n,)."""
    csum = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0)])
    lo = np.searchsorted(t, t - width_s / 2.0, side="left")
    hi = np.searchsorted(t, t + width_s / 2.0, side="right")
    return (csum[hi] - csum[lo]) / np.maximum(hi - lo, 1)[:, None]


def stationary_mask(t_s: ArrayLike, rate_b_rad_s: ArrayLike, p: SegmentParams) -> NDArray[np.bool_]:
    """True where the smoothed body-rate vector (n, 3) has a norm below ``p.max_rate_rad_s``."""
    t = np.asarray(t_s, dtype=float)
    w = np.asarray(rate_b_rad_s, dtype=float)
    if t.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    good = np.all(np.isfinite(w), axis=1)
    w_s = _centered_mean(t, np.where(good[:, None], w, 0.0), p.smooth_s)
    return np.asarray(good & (np.linalg.norm(w_s, axis=1) < p.max_rate_rad_s))


def _runs(t: F64, mask: NDArray[np.bool_], max_gap_s: float) -> list[tuple[float, float]]:
    """Contiguous True stretches of ``mask`` as (t_first, t_last), split at time gaps > max_gap_s."""
    n = t.shape[0]
    if n == 0:
        return []
    gap = np.diff(t) > max_gap_s  # gap[i]: between sample i and i + 1
    prev_on = np.concatenate([[False], mask[:-1] & ~gap])
    next_on = np.concatenate([mask[1:] & ~gap, [False]])
    starts = np.flatnonzero(mask & ~prev_on)
    ends = np.flatnonzero(mask & ~next_on)
    return [(float(t[a]), float(t[b])) for a, b in zip(starts, ends, strict=True)]


def _split_by_attitude(
    a: float, b: float, att_t: F64, att: F64, tol_rad: float, yaw_tol_rad: float, thr_t: F64, thr: F64
) -> list[tuple[float, float]]:
    """Split [a, b] wherever roll or pitch leaves ``tol_rad`` of the current piece's first sample; then drop
    each piece whose yaw, less its least-squares fit on [1, throttle^2], spans more than ``yaw_tol_rad``
    (a slow pan: it turns steadily, so cutting it into shorter pieces would not make it stationary).
    """
    sel = (att_t >= a) & (att_t <= b)
    if not np.any(sel):
        return [(a, b)]
    ts, ang = att_t[sel], np.unwrap(att[sel], axis=0)
    bounds: list[tuple[int, int]] = []
    first = 0
    for i in range(1, len(ts)):
        if np.any(np.abs(ang[i, :2] - ang[first, :2]) > tol_rad):
            bounds.append((first, i - 1))
            first = i
    bounds.append((first, len(ts) - 1))
    pieces: list[tuple[float, float]] = []
    for k, (i0, i1) in enumerate(bounds):
        yaw = ang[i0 : i1 + 1, 2]
        if yaw.shape[0] > 2 and thr_t.shape[0] > 1:
            d2 = np.interp(ts[i0 : i1 + 1], thr_t, np.nan_to_num(thr)) ** 2
            x = np.column_stack([np.ones_like(d2), d2])
            coef, *_ = np.linalg.lstsq(x, yaw, rcond=None)
            yaw = yaw - x @ coef
        if yaw.shape[0] and float(np.ptp(yaw)) > yaw_tol_rad:
            continue
        pieces.append((a if k == 0 else float(ts[i0]), b if k == len(bounds) - 1 else float(ts[i1])))
    return pieces


def find_stationary_segments(
    rates_rad_s: Series,
    throttle_01: Series,
    p: SegmentParams | None = None,
    attitude_rad: Series | None = None,
) -> list[Segment]:
    """All stationary windows with enough throttle variation, best (most theta information) first.

    ``rates_rad_s``: (n, 3) gyro (or attitude-rate) samples, body FRD; ``throttle_01``: (m,) on the same
    clock; ``attitude_rad``: optional (k, 3) roll, pitch, yaw for the attitude-hold test.
    """
    p = p or SegmentParams()
    t = np.asarray(rates_rad_s.t_s, dtype=float)
    thr_t = np.asarray(throttle_01.t_s, dtype=float)
    thr = np.asarray(throttle_01.values, dtype=float)
    mask = stationary_mask(t, rates_rad_s.values, p)
    windows = _runs(t, mask, p.max_gap_s)
    if attitude_rad is not None:
        att_t = np.asarray(attitude_rad.t_s, dtype=float)
        att = np.asarray(attitude_rad.values, dtype=float)
        tol, yaw_tol = p.max_attitude_change_rad, p.max_yaw_residual_rad
        windows = [
            piece
            for a, b in windows
            for piece in _split_by_attitude(a, b, att_t, att, tol, yaw_tol, thr_t, thr)
        ]
    out: list[Segment] = []
    for a, b in windows:
        a2, b2 = a + p.edge_margin_s, b - p.edge_margin_s
        if b2 - a2 < p.min_duration_s:
            continue
        sel = (thr_t >= a2) & (thr_t <= b2) & np.isfinite(thr)
        d = thr[sel]
        if d.shape[0] < 10:
            continue
        span = float(np.percentile(d, 99) - np.percentile(d, 1)) if d.shape[0] >= 100 else float(np.ptp(d))
        if span < p.min_throttle_span:
            continue
        info = float(np.sum((d**2 - np.mean(d**2)) ** 2))
        out.append(Segment(a2, b2, span, info, int(d.shape[0])))
    out.sort(key=lambda s: s.information, reverse=True)
    return out


class TimeWindow(NamedTuple):
    """A time window of the log (s, on the log's clock)."""

    t_start_s: float
    t_end_s: float


def best_window(segments: Sequence[Segment]) -> TimeWindow | None:
    """The best of :func:`find_stationary_segments`' windows (its first) as a time window; None when it
    found none."""
    return TimeWindow(segments[0].t_start_s, segments[0].t_end_s) if segments else None


def attitude_rates(attitude_t_s: F64, attitude_rad: F64) -> F64:
    """Euler-angle rates (rad/s, (n, 3)) by finite differences: a stand-in for the gyro when a log lacks it.

    Not body rates, but zero exactly when the attitude is constant, which is all the stationarity test needs.
    """
    if attitude_t_s.shape[0] < 2:
        return np.zeros((attitude_t_s.shape[0], 3))
    ang = np.unwrap(attitude_rad, axis=0)
    return np.asarray(np.gradient(ang, attitude_t_s, axis=0))


def find_sweep_in_log(log: LogData, p: SegmentParams | None = None) -> TimeWindow | None:
    """:func:`find_stationary_segments` on a :class:`LogData`: gyro when present, else attitude rates.

    Returns None when no window qualifies or the log has neither gyro nor attitude.
    """
    att_t, att = log.attitude_rad.t_s, log.attitude_rad.values
    if log.imu_t_s.shape[0] > 0:
        rate_t, rate = log.imu_t_s, log.gyro_rad_s
    elif att_t.shape[0] > 1:
        rate_t, rate = att_t, attitude_rates(att_t, att)
    else:
        return None
    has_att = att_t.shape[0] > 0 and att.ndim == 2 and att.shape[1] == 3
    attitude = Series(att_t, att) if has_att else None
    return best_window(find_stationary_segments(Series(rate_t, rate), log.throttle_01, p, attitude))
