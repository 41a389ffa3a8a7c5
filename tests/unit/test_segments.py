"""Detection of the stationary throttle sweep used by the offline fit (sec. II-C-1, Fig. 7)."""

from __future__ import annotations

import numpy as np

from magcomp.core.segments import (
    SegmentParams,
    best_window,
    find_stationary_segments,
    find_sweep_in_log,
    stationary_mask,
)
from magcomp.core.types import LogData, Series


def _bench_log(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """150 s at 100 Hz: handling, a stationary 0-100-0 % sweep (20-60 s), a hand rotation at high throttle,
    a stationary hold at 50 % (80-118 s), handling, and a slow 0.03 rad/s yaw pan with a sweep (122-150 s)."""
    t = np.arange(0.0, 150.0, 0.01)
    rate = np.zeros((len(t), 3))
    handling = t < 20.0
    rate[handling] = 0.4 * np.sin(2 * np.pi * 0.3 * t[handling, None] + np.array([0.0, 1.0, 2.0]))
    rotating = ((t >= 60.0) & (t < 80.0)) | ((t >= 118.0) & (t < 122.0))
    rate[rotating] = 0.8 * np.sin(2 * np.pi * 0.2 * t[rotating, None] + np.array([0.5, 1.5, 2.5]))
    pan = t >= 122.0
    rate[pan, 2] = 0.03
    throttle = np.zeros(len(t))
    sweep = (t >= 20.0) & (t < 60.0)
    throttle[sweep] = 1.0 - np.abs((t[sweep] - 40.0) / 20.0)
    throttle[rotating] = 0.9
    throttle[(t >= 80.0) & (t < 118.0)] = 0.5
    throttle[pan] = (t[pan] - 122.0) / 28.0
    # motor vibration (aliased) and gyro noise: large per sample, zero mean
    gyro = rate + 0.05 * np.sin(2 * np.pi * 23.0 * t)[:, None] * (throttle[:, None] > 0.05)
    gyro = gyro + 0.02 * rng.standard_normal(gyro.shape)
    yaw = np.cumsum(rate[:, 2]) * 0.01
    att = np.column_stack([np.cumsum(rate[:, 0]) * 0.01, np.cumsum(rate[:, 1]) * 0.01, yaw])
    return {"t": t, "gyro": gyro, "throttle": throttle, "att": att}


def test_finds_the_stationary_sweep_and_rejects_motion_holds_and_pans() -> None:
    d = _bench_log(np.random.default_rng(12))
    p = SegmentParams()
    rates, att = Series(d["t"], d["gyro"]), Series(d["t"], d["att"])
    found = best_window(find_stationary_segments(rates, Series(d["t"][::5], d["throttle"][::5]), p, att))
    assert found is not None
    t0, t1 = found
    # inside the true sweep, trimmed by at most smoothing half-width + margin + 0.5 s
    assert 20.0 <= t0 < 21.5 and 58.5 < t1 <= 60.0, found
    segs = find_stationary_segments(rates, Series(d["t"], d["throttle"]), p, att)
    assert len(segs) == 1  # the 50 % hold has no span, the pan drifts 0.9 rad in yaw


def test_without_attitude_the_slow_pan_is_not_rejected() -> None:
    """Control: the pan at 0.03 rad/s passes the rate test; only the attitude test removes it."""
    d = _bench_log(np.random.default_rng(12))
    segs = find_stationary_segments(Series(d["t"], d["gyro"]), Series(d["t"], d["throttle"]), SegmentParams())
    starts = sorted(s.t_start_s for s in segs)
    assert len(segs) == 2 and starts[1] > 121.0


def test_no_sweep_returns_none() -> None:
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 60.0, 0.01)
    gyro = 0.01 * rng.standard_normal((len(t), 3))
    # stationary, no throttle change
    assert best_window(find_stationary_segments(Series(t, gyro), Series(t, np.full(len(t), 0.4)))) is None
    moving = gyro + 0.5
    ramp = t / 60.0
    # throttle changes, vehicle moving
    assert best_window(find_stationary_segments(Series(t, moving), Series(t, ramp))) is None


def test_stationary_mask_averages_vibration_but_not_rotation() -> None:
    t = np.arange(0.0, 10.0, 0.01)
    vib = np.column_stack([0.3 * np.sin(2 * np.pi * 31.0 * t)] * 3)
    assert stationary_mask(t, vib, SegmentParams())[100:-100].all()
    assert not stationary_mask(t, vib + np.array([0.0, 0.0, 0.1]), SegmentParams())[100:-100].any()


def test_find_sweep_in_log_uses_attitude_rates_when_gyro_is_missing() -> None:
    d = _bench_log(np.random.default_rng(3))
    log = LogData(
        source="fake",
        attitude_rad=Series(d["t"][::4], d["att"][::4]),
        throttle_01=Series(d["t"][::10], d["throttle"][::10]),
    )
    found = find_sweep_in_log(log)
    assert found is not None and 20.0 <= found[0] < 21.5 and 58.5 < found[1] <= 60.0
    assert find_sweep_in_log(LogData(source="empty")) is None
