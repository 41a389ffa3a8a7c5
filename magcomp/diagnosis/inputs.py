"""Inputs of the diagnosis: a compass of a log aligned with its rotation and powertrain signals.

Finite, sorted series; the drive signals on a uniform grid (:class:`~magcomp.diagnosis.effects.DriveInputs`);
impacts and outliers left out; every signal the residual may follow (:func:`signals_at`). Pure, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from magcomp.core.rotations import euler_from_dcms
from magcomp.core.selfcheck import MOTORS_RUNNING_01
from magcomp.core.types import STANDARD_GRAVITY_M_S2, LogData, Series
from magcomp.diagnosis.attitude import MIN_GYRO_HZ, AttitudeSource, attitude_source
from magcomp.diagnosis.effects import DriveInputs
from magcomp.diagnosis.latency import MAX_HOLD_S, MIN_HELD_FRACTION, held_fraction, unheld_age_bounds_s
from magcomp.diagnosis.model import CompassData
from magcomp.errors import InputError

F64 = NDArray[np.float64]

GRID_DT_S = 0.01
MAX_SAMPLES = 5000


def finite_series(s: Series) -> Series:
    if len(s) == 0:
        return s
    v = s.values
    ok = np.isfinite(v) if v.ndim == 1 else np.all(np.isfinite(v), axis=1)
    ok &= np.isfinite(s.t_s)
    t, v = s.t_s[ok], v[ok]
    order = np.argsort(t, kind="stable")
    t, v = t[order], v[order]
    keep = np.concatenate([[True], np.diff(t) > 0]) if t.size else np.zeros(0, dtype=bool)
    return Series(t[keep], v[keep])


def drive_inputs(log: LogData, t_s: F64) -> DriveInputs:
    """The powertrain signals of ``log`` on a uniform grid around the compass times ``t_s``."""
    t0, t1 = float(t_s[0]) - 2.0, float(t_s[-1]) + 2.0
    grid = np.arange(t0, t1 + GRID_DT_S, GRID_DT_S)
    thr = finite_series(log.throttle_01)
    thr_g = np.interp(grid, thr.t_s, np.clip(thr.values, 0.0, 1.0)) if len(thr) else np.zeros_like(grid)
    mot = finite_series(log.motors_01)
    mot_g = None
    if len(mot) >= 2 and mot.values.ndim == 2 and mot.values.shape[1] >= 2:
        mv = np.clip(mot.values, 0.0, 1.0)
        active = [j for j in range(mv.shape[1]) if float(np.ptp(mv[:, j])) > 0.0]
        if len(active) >= 2:
            mot_g = np.column_stack([np.interp(grid, mot.t_s, mv[:, j]) for j in active])
    volt = finite_series(log.voltage_v)
    volt = Series(volt.t_s[volt.values > 0.5], volt.values[volt.values > 0.5]) if len(volt) else volt
    v_g = np.interp(grid, volt.t_s, volt.values) if len(volt) >= 2 else None
    # reference of the sag model: a full LiPo pack, 4.2 V per cell, cells counted from the highest voltage
    v_full = 4.2 * max(1.0, math.ceil(float(np.max(volt.values)) / 4.2 - 0.02)) if len(volt) >= 2 else 1.0
    temp = finite_series(log.temperature_degc)
    temp_m = np.interp(t_s, temp.t_s, temp.values) if len(temp) >= 2 else None
    thr_dt = float(np.median(np.diff(thr.t_s))) if len(thr) >= 2 else GRID_DT_S
    cur = finite_series(log.current_a)
    cur_t, cur_a = (cur.t_s, np.asarray(cur.values, dtype=float)) if len(cur) >= 2 else (None, None)
    return DriveInputs(
        t_s, grid, GRID_DT_S, thr_g, mot_g, v_g, v_full, temp_m, thr_dt, current_t_s=cur_t, current_a=cur_a
    )


IMPACT_M_S2 = 2.5 * STANDARD_GRAVITY_M_S2


def crash_mask(log: LogData, t_s: F64, before_s: float = 2.0, after_s: float = 3.0) -> NDArray[np.bool_]:
    """True for samples to leave out because of an impact (|specific force| above 2.5 g).

    The forward model holds for a vehicle handled or flown, not for one tumbling after a crash (the attitude
    estimate and the wiring may both be disturbed). When the vehicle ends the log tilted beyond 60 deg
    after an impact (a crash), everything from ``before_s`` before the first impact on is left out;
    otherwise only ``before_s``/``after_s`` around each impact.
    """
    out = np.zeros(t_s.shape[0], dtype=bool)
    if log.imu_t_s.shape[0] < 10:
        return out
    hits = log.imu_t_s[np.linalg.norm(log.accel_m_s2, axis=1) > IMPACT_M_S2]
    if hits.size == 0:
        return out
    att = finite_series(log.attitude_rad)
    ends_tilted = False
    if len(att) >= 2:
        tail = att.t_s > hits[0] + after_s
        if np.any(tail):
            cos_tilt = np.cos(att.values[tail, 0]) * np.cos(att.values[tail, 1])
            ends_tilted = bool(np.mean(cos_tilt < 0.5) > 0.5)
    if ends_tilted:
        return np.asarray(t_s >= hits[0] - before_s)
    for h in hits:
        out |= (t_s >= h - before_s) & (t_s <= h + after_s)
    return out


#: an impact is left out only when at least this many (decimated) compass samples remain; otherwise the whole
#: log is diagnosed as it is (too little data to model without the impact)
MIN_SAMPLES_AFTER_IMPACTS = 50


def decimation_step(n: int) -> int:
    """Every ``step``-th sample keeps at most MAX_SAMPLES of ``n``."""
    return max(1, math.ceil(n / MAX_SAMPLES))


def impact_left_out(log: LogData, t_s: F64, step: int = 1) -> NDArray[np.bool_]:
    """The samples at ``t_s`` that :func:`compass_data` leaves out (``crash_mask``), judged on every
    ``step``-th sample as it decimates; none when fewer than MIN_SAMPLES_AFTER_IMPACTS would remain."""
    crash = crash_mask(log, t_s)
    if np.count_nonzero(~crash[::step]) < MIN_SAMPLES_AFTER_IMPACTS:
        return np.zeros(t_s.shape[0], dtype=bool)
    return crash


def log_attitude(log: LogData, min_gyro_hz: float = MIN_GYRO_HZ) -> AttitudeSource:
    """The compass-free rotation of ``log`` (:func:`~magcomp.diagnosis.attitude.attitude_source`), once for
    all its compasses (``min_gyro_hz``: the slowest gyro integrated)."""
    att = finite_series(log.attitude_rad)
    imu_ok = log.imu_t_s.shape[0] >= 10
    return attitude_source(
        log.imu_t_s if imu_ok else np.zeros(0),
        log.gyro_rad_s if imu_ok else np.zeros((0, 3)),
        log.accel_m_s2 if imu_ok else np.zeros((0, 3)),
        att.t_s,
        att.values if len(att) else np.zeros((0, 3)),
        log.gps_velocity_ned_m_s.t_s,
        log.gps_velocity_ned_m_s.values,
        gps_flight_mask(log) if imu_ok else None,
        min_gyro_hz,
    )


def gps_flight_mask(log: LogData) -> NDArray[np.bool_]:
    """(n,) at the IMU times: where the GNSS tilt reference may be built and judged, i.e. the motors running
    (the lean it corrects comes with manoeuvres; on the ground a motors-off accelerometer bias differs from
    the flying one) and no impact (:func:`crash_mask`: there the GNSS reads ~0 while the accelerometer
    saturates). All samples when the log has no throttle."""
    t = log.imu_t_s
    keep = ~crash_mask(log, t)
    thr = finite_series(log.throttle_01)
    if len(thr):
        keep &= np.interp(t, thr.t_s, thr.values) > MOTORS_RUNNING_01
    return np.asarray(keep)


def compass_data(
    log: LogData,
    index: int,
    latency_s: float = 0.0,
    attitude: Callable[[], AttitudeSource] | None = None,
    age_s: float = 0.0,
) -> CompassData:
    """Align compass ``index`` of ``log`` with rotation and drive signals (decimated to MAX_SAMPLES).

    Each sample is taken at its own measurement time: the logged time, or for a held compass
    (:func:`magcomp.diagnosis.latency.held_fraction` at least ``MIN_HELD_FRACTION``) the time its value
    first appeared (:func:`measured_times_s`). The drive signals are taken there, and so is the rotation,
    ``latency_s`` earlier still: the compass's latency against the attitude source that the hold does not
    explain (:mod:`magcomp.diagnosis.latency`: the attitude source's own delay, the mean error of the
    measurement times). The drive is not moved by ``latency_s``: that latency carries the attitude source's
    delay too, which the powertrain does not have (a clean 5 Hz log gave a 42 ms current_lag that way).
    Measured (``benchmarks/diagnosis_heldout.py`` current_lag case, 20 Hz compass held in a 40 Hz RAW_IMU,
    seeds 5000-5007): the fitted 0.3 s lag 0.352 s on average with the drive at the logged time, 0.326 s at
    the measurement times (every seed about 26 ms lower; the mean age of the hold is 22 ms).

    Why the rotation per sample and not the logged time minus one fitted latency: a held sample's age is
    not one number but 0 to one message period apart from its neighbours' (20 Hz in a 40 Hz RAW_IMU from a
    50 Hz loop: 0 to 40 ms), and at 1 rad/s each 10 ms is 10 mrad of rotation, 5 mgauss on a 500 mgauss
    field. Measured on the held-out per-motor case (seed 5000, the simulator's rotation at each sample's
    true measurement time as the reference): tilt error 13.6 / 15.0 mrad rms (north / east axis), heading
    error 9-28 mrad rms within each 5 s of turning, with one latency for all samples; 9.0 / 10.4 and 8-19
    mrad with the rotation at the measurement times. The paper model's residual on seeds 5000-5011: 9.9 ->
    9.1 mgauss rms (8.6 with the simulator's rotation).

    attitude: gives the log's rotation (:func:`log_attitude`), for a caller that builds it once for every
    compass and latency of the log (``functools.cache``); by default it is built from ``log`` here.
    age_s: for an unheld compass, how long before its logged time each sample was measured (the fitted age,
    :func:`magcomp.diagnosis.latency.unheld_age_bounds_s`): the drive and the rotation are taken there."""
    if index not in log.mag:
        raise InputError(f"the log has no compass {index} (compasses: {sorted(log.mag)})")
    mag = finite_series(log.mag[index])
    if len(mag) < 50:
        raise InputError(f"compass {index} has only {len(mag)} usable samples (need 50)")
    step = decimation_step(len(mag))
    t = mag.t_s[::step]
    v = mag.values[::step].astype(float)
    keep = ~impact_left_out(log, t)
    t, v = t[keep], v[keep]
    # a held compass (updated slower than its messages) measured each sample when its value first appeared:
    # the powertrain that biased it is taken then, not at the logged time (measured_times_s)
    t_drive = t - age_s
    timing = unheld_age_bounds_s(mag.t_s)[1]  # an unheld sample is 0 to this old (its mean age fitted)
    if held_fraction(mag.values) >= MIN_HELD_FRACTION:
        t_drive = measured_times_s(mag.t_s, mag.values)[::step][keep]
        timing = min(float(np.median(np.diff(mag.t_s))), MAX_HOLD_S)  # the update fell between two messages
    track = (attitude() if attitude is not None else log_attitude(log)).at(t_drive - latency_s)
    drive = replace(drive_inputs(log, t_drive), compass_timing_s=timing)
    return CompassData(index, t, v, track.r_nb, drive, track.source, track.note)


def measured_times_s(t_s: F64, values: F64, max_age_s: float = MAX_HOLD_S) -> F64:
    """Each sample's measurement time for a held compass: the midpoint between the sample where its value
    first appeared and the sample before that one (the update fell somewhere between the two messages,
    uniformly when the compass and message clocks are not locked; the first sample: its own time). A sample
    that would be older than ``max_age_s`` is not held but read again unchanged (a compass updates at least
    that often, :data:`~magcomp.diagnosis.latency.MAX_HOLD_S`): its own time. Measured on a 4 Hz telemetry
    log of a rover standing still (thenewnexus mav1, 40 % of its compass samples repeat): without the bound
    the samples were placed 0.5 s (up to 7.6 s) before their logged times."""
    n = t_s.shape[0]
    changed = np.ones(n, dtype=bool)
    changed[1:] = np.any(np.diff(values, axis=0) != 0.0, axis=1)
    start = np.maximum.accumulate(np.where(changed, np.arange(n), 0))
    prev = np.maximum(start - 1, 0)
    mid = 0.5 * (t_s[start] + t_s[prev])
    return np.asarray(np.where(t_s - mid <= max_age_s, mid, t_s), dtype=float)


def inlier_mask(
    t_s: F64, residual_mgauss: F64, k_sigma: float = 10.0, pad_s: float = 0.5, max_fraction: float = 0.05
) -> NDArray[np.bool_] | None:
    """Samples to keep, or None when nothing is an outlier.

    A sample is an outlier when any axis of its residual lies more than ``k_sigma`` robust standard
    deviations (1.4826 MAD) from the median; outliers are padded by ``pad_s`` on both sides, because a crash
    or a sensor glitch corrupts its neighbourhood too. When more than ``max_fraction`` of the log would go,
    the model is wrong rather than the data, and nothing is excluded.
    """
    med = np.median(residual_mgauss, axis=0)
    sig = 1.4826 * np.median(np.abs(residual_mgauss - med), axis=0)
    bad = np.any(np.abs(residual_mgauss - med) > k_sigma * np.maximum(sig, 1e-9), axis=1)
    if not np.any(bad):
        return None
    tb = t_s[bad]
    idx = np.searchsorted(tb, t_s)
    near = np.zeros(t_s.shape[0], dtype=bool)
    for off in (-1, 0):
        j = np.clip(idx + off, 0, tb.size - 1)
        near |= np.abs(t_s - tb[j]) <= pad_s
    if np.mean(near) > max_fraction:
        return None
    return ~near


def spans(t_s: F64, mask: NDArray[np.bool_]) -> list[tuple[float, float]]:
    out: list[tuple[float, float]] = []
    start = None
    for i, m in enumerate(mask):
        if m and start is None:
            start = float(t_s[i])
        if not m and start is not None:
            out.append((start, float(t_s[i - 1])))
            start = None
    if start is not None:
        out.append((start, float(t_s[-1])))
    return out


def subset(data: CompassData, keep: NDArray[np.bool_]) -> CompassData:
    """``data`` restricted to the samples ``keep`` (the drive grid is kept whole: lags need the history)."""
    d = data.drive
    temp = d.temperature_degc[keep] if d.temperature_degc is not None else None
    drive = replace(
        d,
        t_s=d.t_s[keep],
        temperature_degc=temp,
        extra=d.extra[keep] if d.extra is not None else None,
    )
    return CompassData(
        data.mag_index,
        data.t_s[keep],
        data.field_mgauss[keep],
        data.r_nb[keep],
        drive,
        data.attitude_source,
        data.attitude_note,
        data.nuisance_flags,
    )


def signals_at(data: CompassData, log: LogData | None) -> dict[str, tuple[F64, F64]]:
    """Every signal the residual may follow, as (t_s, values)."""
    d = data.drive
    g = d.grid_t_s
    out: dict[str, tuple[F64, F64]] = {
        "throttle": (g, d.throttle_grid),
        "throttle^2": (g, d.throttle_grid**2),
        "throttle_rate": (g, np.gradient(_smooth(d.throttle_grid, 10), d.grid_dt_s)),
        "time": (data.t_s, data.t_s - data.t_s[0]),
    }
    roll, pitch, yaw = euler_from_dcms(data.r_nb).T
    out["roll"] = (data.t_s, roll)
    out["pitch"] = (data.t_s, pitch)
    out["yaw_deg"] = (data.t_s, np.degrees(np.unwrap(yaw)))
    out["cos_yaw"] = (data.t_s, np.cos(yaw))
    out["sin_yaw"] = (data.t_s, np.sin(yaw))
    if d.motors_grid is not None:
        for j in range(d.motors_grid.shape[1]):
            out[f"motor{j + 1}"] = (g, d.motors_grid[:, j])
    if d.voltage_grid is not None:
        out["voltage"] = (g, d.voltage_grid)
    if d.temperature_degc is not None:
        out["temperature"] = (data.t_s, d.temperature_degc)
    if log is not None:
        cur = finite_series(log.current_a)
        if len(cur) >= 2:
            out["current"] = (cur.t_s, cur.values)
        if log.imu_t_s.shape[0] >= 10:
            out["body_rate"] = (log.imu_t_s, np.linalg.norm(log.gyro_rad_s, axis=1))
        att = finite_series(log.attitude_rad)
        if len(att) >= 2:
            out["autopilot_yaw_rate"] = (att.t_s, np.gradient(np.unwrap(att.values[:, 2]), att.t_s))
        for k, s in log.mag.items():
            if k != data.mag_index and len(s) >= 2:
                fs = finite_series(s)
                out[f"compass{k}_norm"] = (fs.t_s, np.linalg.norm(fs.values, axis=1))
    return out


def _smooth(x: F64, w: int) -> F64:
    if w <= 1:
        return x
    k = np.ones(w) / w
    return np.convolve(x, k, mode="same")
