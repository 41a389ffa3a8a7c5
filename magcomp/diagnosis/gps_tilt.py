"""A compass-free "down" reference from the accelerometer and the GNSS velocity.

Why: an autopilot with GPS-aided tilt (ArduPilot's AHRS, PX4's EKF) removes the kinematic acceleration
from the accelerometer with its own rotation, whose yaw is fused from the disturbed compass; a yaw error
``dpsi`` then leans its roll and pitch by about ``dpsi |a_n| / g`` whenever the vehicle accelerates, and
``dpsi`` follows the throttle-driven bias being diagnosed (docs/diagnosis.md, "Why diagnose's theta has a
bias that follows theta"). Here the same subtraction is made with diagnose's own gyro heading instead.

The specific force is ``f_b = R_nb^T (a_n - g_n)`` with ``g_n = (0, 0, g)`` (NED), so
``a_n - R_nb f_b = g_n``: the down direction in NED, whose body-axes image ``R_nb^T g_n / g`` is the tilt
reference. ``a_n`` is the derivative of the GNSS velocity (one derivative, not two of the position); to
give ``R_nb f_b`` exactly the same filtering, it is integrated to a velocity ``u_n`` at the IMU rate,
sampled at the GNSS times, and the difference ``v_n - u_n`` is differentiated there (central differences):
the result is ``g_n`` averaged over the GNSS sample spacing, whatever that spacing is. The rotation used is
the gyro integral's (a first pass of :func:`magcomp.diagnosis.attitude.propagate_attitude` with the log's
tilt) with its heading aligned to the log's yaw by a line in time (offset and gyro drift only: a line
cannot follow the throttle-driven part of the compass's yaw error).

On real logs the GNSS velocity arrives 0.1-0.3 s after the motion it describes, and a logged accelerometer
and a differentiated velocity are noisy by degrees of tilt at the GNSS rate: :func:`gps_tilt_reference`
measures the latency on the log, averages the correction, and uses it only where the log's own data show
the autopilot's tilt leaning with its yaw by more than the reference's own error (docs/diagnosis.md, "The
GNSS tilt reference on real logs").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from magcomp.core.rotations import dcms_from_quats, euler_from_dcms
from magcomp.core.types import STANDARD_GRAVITY_M_S2

F64 = NDArray[np.float64]

#: A GNSS velocity gap longer than this (or three of its sample spacings, if that is longer) leaves the
#: reference to the log's tilt there: across a longer gap the central difference is no acceleration.
GPS_STALE_S = 1.0

#: Window (s) over which the GNSS correction to the log's tilt is averaged (:func:`gps_tilt_reference`).
SMOOTH_S = 2.0

#: The GNSS latencies searched (s): a receiver's velocity solution reaches the log 0.1-0.3 s after the
#: motion it describes (ArduPilot's GPS_DELAY_MS and PX4's EKF2_GPS_DELAY default to 0.2 s and 0.11 s;
#: measured here on the development logs: 0.25 s on log171, 0.15-0.19 s on the peterbarker logs, 0.05-0.12 s
#: on the PX4 ones at 2 Hz); a simulated log has none. A best shift at either end is taken as not found; one
#: below 0 as 0 (:func:`gnss_delay`).
DELAY_GRID_S = np.round(np.arange(-0.2, 0.6001, 0.01), 3)

#: Fraction of the GNSS intervals (the best-agreeing) whose mean square mismatch the latency minimises: the
#: rest (an impact: log171's GNSS reads ~0 while its accelerometer saturates) is left out. On simulated logs
#: (no latency) the least median of squares scattered over -50..+10 ms, this over -10..+10 ms.
DELAY_TRIM = 0.9

#: Time constants (s) tried for the autopilot's lean behind its cause: a tilt filter follows its reference
#: with a lag (the best-explaining one is kept)
LEAN_LAGS_S = (0.0, 1.0, 2.0, 4.0, 8.0)

D2 = math.degrees(1.0) ** 2  # rad^2 -> deg^2

#: Fewer GNSS velocities than this and the reference is not built (a few seconds at the usual 5 Hz).
MIN_GPS_SAMPLES = 10

G = STANDARD_GRAVITY_M_S2


def aligned_gyro_rotation(
    imu_t_s: F64, q_nb: F64, att_t_s: F64, yaw_rad: F64, mask: NDArray[np.bool_] | None = None
) -> F64:
    """(n, 3, 3) rotation of the gyro integral ``q_nb`` at ``imu_t_s`` with its heading moved onto the log's
    yaw ``yaw_rad`` (at ``att_t_s``) by the least-squares line ``a + b t`` of their difference, fitted where
    ``mask`` (n,) is set (None: everywhere; an impact's gyro, saturated, would tilt the line)."""
    r = dcms_from_quats(q_nb)
    gyro_yaw = euler_from_dcms(r)[:, 2]
    log_yaw = np.interp(imu_t_s, att_t_s, np.unwrap(yaw_rad))
    diff = np.unwrap(np.angle(np.exp(1j * (log_yaw - gyro_yaw))))
    tc = imu_t_s - imu_t_s[0]
    m = mask if mask is not None and np.count_nonzero(mask) >= 2 else np.ones(tc.shape[0], dtype=bool)
    b, a = np.polyfit(tc[m], diff[m], 1) if np.ptp(tc[m]) > 0 else (0.0, float(np.mean(diff[m])))
    # R_nb = Rz(yaw) Ry(pitch) Rx(roll): turning the heading by d is Rz(d) R_nb
    d = a + b * tc
    c, s = np.cos(d), np.sin(d)
    rz = np.zeros_like(r)
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = c, -s, s, c, 1.0
    return np.matmul(rz, r)


def _gnss_rows(imu_t_s: F64, gps_t_s: F64, gps_vel_ned_m_s: F64, delay_s: float) -> tuple[F64, F64] | None:
    """The GNSS rows to use: finite, one per time stamp (the last), moved back by ``delay_s`` and inside
    the IMU's span; a NaN down velocity set to 0. None when fewer than MIN_GPS_SAMPLES remain."""
    t_g = np.asarray(gps_t_s, dtype=np.float64) - delay_s
    v = np.asarray(gps_vel_ned_m_s, dtype=np.float64).copy()
    ok = np.isfinite(t_g) & np.all(np.isfinite(v[:, :2]), axis=1)
    t_g, v = t_g[ok], v[ok]
    keep = np.concatenate([np.diff(t_g) > 0, [True]]) if t_g.size else np.zeros(0, dtype=bool)
    t_g, v = t_g[keep], v[keep]
    inside = (t_g >= imu_t_s[0]) & (t_g <= imu_t_s[-1])
    t_g, v = t_g[inside], v[inside]
    if t_g.size < MIN_GPS_SAMPLES:
        return None
    v[~np.isfinite(v[:, 2]), 2] = 0.0
    return t_g, v


def _integrated_specific_force(imu_t_s: F64, accel_b_m_s2: F64, r_nb: F64) -> F64:
    """``u_n`` (n, 3): the trapezoid integral of ``R_nb f_b`` from the first IMU sample (m/s)."""
    f_n = np.einsum("nij,nj->ni", r_nb, accel_b_m_s2)
    u_n = np.zeros_like(f_n)
    u_n[1:] = np.cumsum(0.5 * (f_n[1:] + f_n[:-1]) * np.diff(imu_t_s)[:, None], axis=0)
    return u_n


def gnss_delay(
    imu_t_s: F64, accel_b_m_s2: F64, r_nb: F64, gps_t_s: F64, gps_vel_ned_m_s: F64
) -> float | None:
    """The GNSS velocity's latency behind the IMU (s), measured on the log itself: the shift in
    DELAY_GRID_S that makes the GNSS velocity's horizontal change over each sample interval agree best with
    the kinematic acceleration ``R_nb f_b + g_n`` integrated over the same interval (mean square over the
    best-agreeing DELAY_TRIM of the intervals: an impact or a glitch does not move it). None when the best
    shift is at an end of the grid (no latency a receiver has) or the log has too little GNSS velocity."""
    got = _gnss_rows(imu_t_s, gps_t_s, gps_vel_ned_m_s, 0.0)
    if got is None:
        return None
    t_g, v = got
    u_n = _integrated_specific_force(imu_t_s, accel_b_m_s2, r_nb)[:, :2]
    dt = np.diff(t_g)
    ok = dt <= GPS_STALE_S
    if not ok.any():
        return None
    dv = np.diff(v[:, :2], axis=0)[ok]
    keep = max(1, int(DELAY_TRIM * dv.shape[0]))
    cost = np.empty(DELAY_GRID_S.shape[0])
    for k, d in enumerate(DELAY_GRID_S):
        u = np.column_stack([np.interp(t_g - d, imu_t_s, u_n[:, j]) for j in range(2)])
        du = np.diff(u, axis=0)[ok]
        e = np.sort(np.sum(np.square(dv - du), axis=1) / np.square(dt[ok]))
        cost[k] = float(np.mean(e[:keep]))
    best = int(np.argmin(cost))
    if not np.isfinite(cost[best]) or best in (0, DELAY_GRID_S.shape[0] - 1):
        return None
    # a receiver's velocity describes motion that has already happened: a latency is >= 0, and a best shift
    # below 0 (simulated logs, which have none: -20..+20 ms) is the estimate's scatter about none; the grid
    # reaches below 0 only so that a best shift at 0 is not taken for one at the grid's end
    return max(float(DELAY_GRID_S[best]), 0.0)


def gps_down_reference(
    imu_t_s: F64, accel_b_m_s2: F64, r_nb: F64, gps_t_s: F64, gps_vel_ned_m_s: F64, delay_s: float = 0.0
) -> tuple[F64, NDArray[np.bool_]] | None:
    """Down in body axes (n, 3, unit) at ``imu_t_s`` from the specific force and the GNSS velocity (module
    docstring), and where it is fresh (n,) bool; None when the log has too little GNSS velocity.

    accel_b_m_s2 : (n, 3) specific force, body FRD. r_nb : (n, 3, 3) rotation at ``imu_t_s``.
    gps_t_s, gps_vel_ned_m_s : (m,), (m, 3) m/s north, east, down (a NaN down is taken as no vertical
    acceleration). delay_s : the GNSS velocity's latency behind the IMU (:func:`gnss_delay`): a velocity
    stamped ``t`` is the vehicle's at ``t - delay_s``.
    """
    got = _gnss_rows(imu_t_s, gps_t_s, gps_vel_ned_m_s, delay_s)
    if got is None:
        return None
    t_g, v = got
    u_n = _integrated_specific_force(imu_t_s, accel_b_m_s2, r_nb)
    u_g = np.column_stack([np.interp(t_g, imu_t_s, u_n[:, j]) for j in range(3)])
    g_g = np.gradient(v - u_g, t_g, axis=0)  # a_n - R f_b = g_n, at the GNSS times
    g_n = np.column_stack([np.interp(imu_t_s, t_g, g_g[:, j]) for j in range(3)])
    ref = np.einsum("nji,nj->ni", r_nb, g_n)  # R^T g_n
    norm = np.linalg.norm(ref, axis=1, keepdims=True)
    ref /= np.maximum(norm, 1e-9)
    # fresh: bracketed by GNSS samples no further apart than the stale limit, and a plausible gravity
    stale_s = max(GPS_STALE_S, 3.0 * float(np.median(np.diff(t_g))))
    k = np.clip(np.searchsorted(t_g, imu_t_s), 1, t_g.size - 1)
    gap = t_g[k] - t_g[k - 1]
    fresh = (imu_t_s >= t_g[0]) & (imu_t_s <= t_g[-1]) & (gap <= stale_s)
    fresh &= (norm[:, 0] > 0.5 * G) & (norm[:, 0] < 1.5 * G)
    return ref, fresh


def _window_mean(t_s: F64, x: F64, use: NDArray[np.bool_], half_s: float) -> F64:
    """Mean of the rows of ``x`` (n, k) with ``use`` within ``half_s`` of each time of ``t_s`` (NaN rows where
    none is)."""
    w = use.astype(np.float64)
    cs = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(np.where(use[:, None], x, 0.0), axis=0)])
    cw = np.concatenate([[0.0], np.cumsum(w)])
    lo = np.searchsorted(t_s, t_s - half_s, side="left")
    hi = np.searchsorted(t_s, t_s + half_s, side="right")
    den = (cw[hi] - cw[lo])[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, (cs[hi] - cs[lo]) / np.maximum(den, 1.0), np.nan)


def _horizontal_acceleration(imu_t_s: F64, gps_t_s: F64, gps_vel_ned_m_s: F64, delay_s: float) -> F64:
    """(n, 2) north, east m/s^2 at ``imu_t_s``: the GNSS velocity's horizontal derivative (0 without rows)."""
    got = _gnss_rows(imu_t_s, gps_t_s, gps_vel_ned_m_s, delay_s)
    if got is None:
        return np.zeros((imu_t_s.shape[0], 2))
    t_g, v = got
    a = np.gradient(v[:, :2], t_g, axis=0)
    return np.column_stack([np.interp(imu_t_s, t_g, a[:, j]) for j in range(2)])


def _lagged(t_s: F64, x: F64, lag_s: float) -> F64:
    """``x`` (n, k) through a first-order lag of time constant ``lag_s`` (0: none), on the median step."""
    if lag_s <= 0.0:
        return x
    dt = float(np.median(np.diff(t_s)))
    a = dt / (lag_s + dt)
    return np.asarray(lfilter([a], [1.0, a - 1.0], x, axis=0, zi=np.zeros((1, x.shape[1])) + a * x[:1])[0])


def _lean_split(
    t_s: F64, c_n: F64, raw: F64, fresh: NDArray[np.bool_], half_s: float
) -> tuple[float, float, F64, NDArray[np.bool_]] | None:
    """``c_n`` (n, 2) as ``beta`` times the lean ``raw`` (n, 2) behind by the one of LEAN_LAGS_S that explains
    most, both averaged within ``half_s``: (beta, lag, the lean (n, 2), the samples used), None when fewer
    than two are usable."""
    best: tuple[float, float, float, F64, NDArray[np.bool_]] | None = None
    for lag in LEAN_LAGS_S:
        lean_n = _window_mean(t_s, _lagged(t_s, raw, lag), fresh, half_s)
        use = fresh & np.all(np.isfinite(c_n), axis=1) & np.all(np.isfinite(lean_n), axis=1)
        if np.count_nonzero(use) < 2:
            return None
        pp = float(np.sum(np.square(lean_n[use])))
        b = float(np.sum(c_n[use] * lean_n[use])) / pp if pp > 0 else 0.0
        if best is None or b * b * pp > best[0]:
            best = (b * b * pp, b, lag, lean_n, use)
    return None if best is None else best[1:]


@dataclass(frozen=True)
class GpsTilt:
    """The GNSS tilt reference of one log, or why it is not used.

    down_b: (n, 3) unit down reference at the IMU times (the log's tilt moved by the smoothed GNSS
    correction where it is fresh), None when not used; fresh: fraction of the log it covers; delay_s: the
    GNSS latency measured (None: not found); lean_deg: rms of the part of the GNSS-minus-log tilt that
    grows with the horizontal acceleration (the lean it corrects); noise_deg: the part that does not (its
    disagreement with the log's tilt where the vehicle does not accelerate); note: one clause for the report.
    """

    down_b: F64 | None
    fresh: float
    delay_s: float | None
    lean_deg: float
    noise_deg: float
    note: str


def gps_tilt_reference(
    imu_t_s: F64,
    accel_b_m_s2: F64,
    r_nb: F64,
    gps_t_s: F64,
    gps_vel_ned_m_s: F64,
    log_down_b: F64,
    log_yaw_rad: F64,
    mask: NDArray[np.bool_] | None = None,
    smooth_s: float | None = None,
) -> GpsTilt:
    """The down reference for the tilt filter from the GNSS velocity, gated on the log itself.

    1. The GNSS latency is measured (:func:`gnss_delay`); not found, the reference is not used.
    2. The correction ``c = d_gnss - d_log`` (body axes, per IMU sample where the GNSS is fresh and ``mask``
       (n,) allows: in flight, away from impacts) has its mean taken out (an accelerometer bias, which the
       autopilot estimates and the subtraction does not) and is averaged over ``smooth_s`` (SMOOTH_S): a
       differentiated velocity and a logged accelerometer are noisy at the GNSS rate (degrees on real logs),
       the lean they correct changes over seconds.
    3. The gate. An autopilot whose yaw is off by ``dpsi`` and which removes the GNSS acceleration with it
       leans its down vector by ``(dpsi / g) (a_E, -a_N)`` in NED, so ``c`` (in NED) should hold
       ``p = (dpsi / g) (-a_E, a_N)`` with ``dpsi`` = the log's yaw minus ``r_nb``'s, averaged alike and
       behind by one of LEAN_LAGS_S (a tilt filter's lag). ``c`` is split into ``beta p`` (least squares,
       the lag that explains most) and the rest. The reference is used only when ``beta > 0`` and the lean
       it removes, ``|beta p|^2``, exceeds on average what it adds, ``|c - beta p|^2`` (its own error,
       which is all of ``c`` where the vehicle does not accelerate). Otherwise the log's tilt is kept and
       the note says why. The split cannot tell the autopilot's yaw error from that of ``r_nb``'s heading
       line (both give ``p``'s shape); on the development logs every verdict is no (docs/diagnosis.md).
    """
    half = 0.5 * (SMOOTH_S if smooth_s is None else smooth_s)
    delay = gnss_delay(imu_t_s, accel_b_m_s2, r_nb, gps_t_s, gps_vel_ned_m_s)
    if delay is None:
        return GpsTilt(None, 0.0, None, math.nan, math.nan, "its latency is not found in the log")
    got = gps_down_reference(imu_t_s, accel_b_m_s2, r_nb, gps_t_s, gps_vel_ned_m_s, delay)
    if got is None or not got[1].any():
        return GpsTilt(None, 0.0, delay, math.nan, math.nan, "too little fresh GNSS velocity")
    ref, fresh = got
    if mask is not None:
        fresh = fresh & mask
        if not fresh.any():
            return GpsTilt(None, 0.0, delay, math.nan, math.nan, "no fresh GNSS velocity in flight")
    c = ref - log_down_b
    c -= np.mean(c[fresh], axis=0)
    c_s = _window_mean(imu_t_s, c, fresh, half)
    # the lean an autopilot steered by a yaw off by dpsi gives its down vector, seen from the GNSS reference:
    # (dpsi / g) (-a_E, a_N) in NED (it removes R(psi + dpsi) f, not R(psi) f, from the GNSS acceleration)
    gyro_yaw = np.arctan2(r_nb[:, 1, 0], r_nb[:, 0, 0])
    dpsi = np.angle(np.exp(1j * (log_yaw_rad - gyro_yaw)))
    a_h = _horizontal_acceleration(imu_t_s, gps_t_s, gps_vel_ned_m_s, delay)
    raw = dpsi[:, None] / G * np.column_stack([-a_h[:, 1], a_h[:, 0]])
    c_n = np.einsum("nij,nj->ni", r_nb, c_s)[:, :2]
    split = _lean_split(imu_t_s, c_n, raw, fresh, half)
    if split is None:
        return GpsTilt(None, 0.0, delay, math.nan, math.nan, "too little fresh GNSS velocity")
    beta, lag, lean_n, use = split
    lean_sq = np.sum(np.square(beta * lean_n[use]), axis=1)
    rest_sq = np.sum(np.square(c_n[use] - beta * lean_n[use]), axis=1)
    lean_deg = math.degrees(math.sqrt(float(np.mean(lean_sq))))
    noise_deg = math.degrees(math.sqrt(float(np.mean(rest_sq))))
    # the gain (lean^2 - rest^2) per block of the smoothing window: its mean and standard error
    block = np.floor((imu_t_s[use] - imu_t_s[0]) / max(2.0 * half, 1e-3)).astype(np.int64)
    counts = np.bincount(block)
    means = np.bincount(block, weights=lean_sq - rest_sq)[counts > 0] / counts[counts > 0]
    gain = float(np.mean(means))
    se = float(np.std(means, ddof=1) / math.sqrt(means.size)) if means.size > 1 else math.inf
    figures = (
        f"its latency {delay * 1e3:.0f} ms; the GNSS tilt differs from the log's by "
        f"{lean_deg:.2f} deg rms as the autopilot's yaw error leans it ({beta:.2f} of that lean, {lag:.0f} s "
        "behind) and by "
        f"{noise_deg:.2f} deg otherwise (lean^2 - rest^2 {gain * D2:.2f} +- {se * D2:.2f} deg^2)"
    )
    if beta <= 0.0 or gain <= 0.0:
        note = f"{figures}, so it would add more error than it removes"
        return GpsTilt(None, 0.0, delay, lean_deg, noise_deg, note)
    down = log_down_b.copy()
    down[use] += c_s[use]
    down /= np.linalg.norm(down, axis=1, keepdims=True)
    return GpsTilt(down, float(np.mean(use)), delay, lean_deg, noise_deg, figures)
