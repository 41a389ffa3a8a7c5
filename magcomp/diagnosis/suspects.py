"""Residual analysis that can point beyond the model library: what does the residual follow?

For every signal the log has (throttle, throttle^2, throttle rate, current, voltage, temperature, time,
attitude, body rate, each motor output, ...) and every lag in a window, the residual (n, 3) is regressed on
the lagged signal plus a constant, per axis; the share of the residual variance this explains (R^2 over all
three axes) ranks the signals. The best one is the "named suspect" even for an effect no extension models.
A positive lag means the residual follows the signal late (the residual at t matches the signal at t - lag).

A step detector looks for the largest sudden shift of the residual's mean (difference of means in windows
before and after each sample) and reports which signals, and which logged events, change at the same time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class SignalRelation:
    """How much of the residual one signal explains: r2 (0..1) at its best lag_s, and the residual per
    unit of signal (slope_mgauss_per_unit, compass frame)."""

    signal: str
    lag_s: float
    r2: float
    slope_mgauss_per_unit: tuple[float, float, float]


@dataclass(frozen=True)
class StepEvent:
    """The largest step in the residual: time, size vector (after - before, mgauss), size in noise units,
    the signals that step at the same time (name -> their step in their own standard deviations) and the
    logged events within ``window_s``."""

    t_s: float
    size_mgauss: tuple[float, float, float]
    size_sigma: float
    co_stepping: dict[str, float]
    events: list[tuple[float, str]]


def _r2_with(rc: F64, tss: float, s: F64) -> tuple[float, F64]:
    """R^2 over the three axes of the centred residual ``rc`` (total sum of squares ``tss``) regressed on
    ``s`` plus a constant, and the slope per axis."""
    sc = s - s.mean()
    ss = float(sc @ sc)
    if ss <= 1e-12 or tss <= 0.0:
        return 0.0, np.zeros(3)
    slope = (sc @ rc) / ss
    explained = float(np.sum(slope**2)) * ss
    return explained / tss, slope


def relate(
    t_s: F64,
    residual_mgauss: F64,
    signals: dict[str, tuple[F64, F64]],
    max_lag_s: float = 2.0,
    lag_step_s: float = 0.1,
) -> list[SignalRelation]:
    """Rank ``signals`` (name -> (t_s, values)) by the residual variance they explain at their best lag.

    Signals are interpolated onto the residual's times; a lag L uses the signal at t - L. Returns the
    relations sorted by r2, best first.
    """
    out = []
    lags = np.arange(-max_lag_s, max_lag_s + 1e-9, lag_step_s)
    # the residual's side of every regression, once: centred, and its total sum of squares
    rc = residual_mgauss - residual_mgauss.mean(axis=0)
    tss = float(np.sum(rc**2))
    # every lag's sample times in one array (row j: t - lags[j]), interpolated per signal in one call
    t_lagged = t_s[None, :] - lags[:, None]
    for name, (ts, vs) in signals.items():
        if ts.shape[0] < 2 or not np.all(np.isfinite(vs)) or float(np.ptp(vs)) <= 0.0:
            continue
        best = SignalRelation(name, 0.0, -1.0, (0.0, 0.0, 0.0))
        lagged = np.interp(t_lagged, ts, vs)
        for lag, s in zip(lags, lagged, strict=True):
            r2, slope = _r2_with(rc, tss, s)
            # prefer the smallest |lag| among near-ties
            if r2 > best.r2 + 1e-6:
                best = SignalRelation(
                    name, round(float(lag), 3), r2, (float(slope[0]), float(slope[1]), float(slope[2]))
                )
        if best.r2 >= 0.0:
            out.append(best)
    return sorted(out, key=lambda r: -r.r2)


def find_step(
    t_s: F64,
    residual_mgauss: F64,
    signals: dict[str, tuple[F64, F64]],
    events: list[tuple[float, str]] | None = None,
    window_s: float = 2.0,
) -> StepEvent | None:
    """Largest mean shift of the residual between the ``window_s`` before and after a sample.

    Returns None when the log is too short. ``size_sigma`` compares the step with the residual's
    sample-to-sample noise (median absolute first difference / (0.6745 sqrt 2)).
    """
    n = t_s.shape[0]
    if n < 20:
        return None
    dt = float(np.median(np.diff(t_s)))
    w = max(3, round(window_s / max(dt, 1e-6)))
    if n <= 2 * w + 1:
        return None
    c = np.vstack([np.zeros((1, 3)), np.cumsum(residual_mgauss, axis=0)])
    idx = np.arange(w, n - w)
    before = (c[idx] - c[idx - w]) / w
    after = (c[idx + w] - c[idx]) / w
    jump = after - before
    k = int(np.argmax(np.linalg.norm(jump, axis=1)))
    i = int(idx[k])
    size = jump[k]
    d = np.diff(residual_mgauss, axis=0)
    noise = float(np.median(np.abs(d - np.median(d, axis=0)))) / (0.6745 * math.sqrt(2.0))
    noise = max(noise, float(np.std(d)) / math.sqrt(2.0) * 0.1, 0.3)  # quantised logs: MAD can be 0
    sigma = float(np.linalg.norm(size)) / max(noise * math.sqrt(2.0 / w) * math.sqrt(3.0), 1e-9)
    t_step = float(0.5 * (t_s[i - 1] + t_s[i]))
    co: dict[str, float] = {}
    for name, (ts, vs) in signals.items():
        if ts.shape[0] < 2:
            continue
        bt = (ts >= t_step - window_s) & (ts < t_step)
        at = (ts >= t_step) & (ts < t_step + window_s)
        if np.count_nonzero(bt) < 2 or np.count_nonzero(at) < 2:
            continue
        sd = float(np.std(vs))
        if sd <= 0.0:
            continue
        co[name] = round(float(np.mean(vs[at]) - np.mean(vs[bt])) / sd, 3)
    co = dict(sorted(co.items(), key=lambda kv: -abs(kv[1])))
    near = [(float(te), txt) for te, txt in (events or []) if abs(te - t_step) <= window_s]
    return StepEvent(t_step, (float(size[0]), float(size[1]), float(size[2])), sigma, co, near)


def step_at(t_s: F64, x: F64, t_step: float, window_s: float = 2.0) -> F64 | None:
    """Mean of ``x`` (n, k) in the ``window_s`` after ``t_step`` minus the mean in the window before; None
    when either window is empty."""
    before = (t_s >= t_step - window_s) & (t_s < t_step)
    after = (t_s >= t_step) & (t_s < t_step + window_s)
    if not np.any(before) or not np.any(after):
        return None
    return np.asarray(np.mean(x[after], axis=0) - np.mean(x[before], axis=0))
