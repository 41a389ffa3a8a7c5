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
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from magcomp.core.rotations import dcms_from_quats, euler_from_dcms

F64 = NDArray[np.float64]

#: A GNSS velocity gap longer than this (or three of its sample spacings, if that is longer) leaves the
#: reference to the log's tilt there: across a longer gap the central difference is no acceleration.
GPS_STALE_S = 1.0

#: Fewer GNSS velocities than this and the reference is not built (a few seconds at the usual 5 Hz).
MIN_GPS_SAMPLES = 10


def aligned_gyro_rotation(imu_t_s: F64, q_nb: F64, att_t_s: F64, yaw_rad: F64) -> F64:
    """(n, 3, 3) rotation of the gyro integral ``q_nb`` at ``imu_t_s`` with its heading moved onto the log's
    yaw ``yaw_rad`` (at ``att_t_s``) by the least-squares line ``a + b t`` of their difference."""
    r = dcms_from_quats(q_nb)
    gyro_yaw = euler_from_dcms(r)[:, 2]
    log_yaw = np.interp(imu_t_s, att_t_s, np.unwrap(yaw_rad))
    diff = np.unwrap(np.angle(np.exp(1j * (log_yaw - gyro_yaw))))
    tc = imu_t_s - imu_t_s[0]
    b, a = np.polyfit(tc, diff, 1) if tc[-1] > 0 else (0.0, float(np.mean(diff)))
    # R_nb = Rz(yaw) Ry(pitch) Rx(roll): turning the heading by d is Rz(d) R_nb
    d = a + b * tc
    c, s = np.cos(d), np.sin(d)
    rz = np.zeros_like(r)
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1], rz[:, 2, 2] = c, -s, s, c, 1.0
    return np.matmul(rz, r)


def gps_down_reference(
    imu_t_s: F64, accel_b_m_s2: F64, r_nb: F64, gps_t_s: F64, gps_vel_ned_m_s: F64
) -> tuple[F64, NDArray[np.bool_]] | None:
    """Down in body axes (n, 3, unit) at ``imu_t_s`` from the specific force and the GNSS velocity (module
    docstring), and where it is fresh (n,) bool; None when the log has too little GNSS velocity.

    accel_b_m_s2 : (n, 3) specific force, body FRD. r_nb : (n, 3, 3) rotation at ``imu_t_s``.
    gps_t_s, gps_vel_ned_m_s : (m,), (m, 3) m/s north, east, down (a NaN down is taken as no vertical
    acceleration).
    """
    t_g = np.asarray(gps_t_s, dtype=np.float64)
    v = np.asarray(gps_vel_ned_m_s, dtype=np.float64).copy()
    ok = np.isfinite(t_g) & np.all(np.isfinite(v[:, :2]), axis=1)
    t_g, v = t_g[ok], v[ok]
    # one row per time stamp (the last), inside the IMU's span
    keep = np.concatenate([np.diff(t_g) > 0, [True]]) if t_g.size else np.zeros(0, dtype=bool)
    t_g, v = t_g[keep], v[keep]
    inside = (t_g >= imu_t_s[0]) & (t_g <= imu_t_s[-1])
    t_g, v = t_g[inside], v[inside]
    if t_g.size < MIN_GPS_SAMPLES:
        return None
    v[~np.isfinite(v[:, 2]), 2] = 0.0
    f_n = np.einsum("nij,nj->ni", r_nb, accel_b_m_s2)
    dt = np.diff(imu_t_s)
    u_n = np.zeros_like(f_n)
    u_n[1:] = np.cumsum(0.5 * (f_n[1:] + f_n[:-1]) * dt[:, None], axis=0)
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
    fresh &= (norm[:, 0] > 0.5 * 9.80665) & (norm[:, 0] < 1.5 * 9.80665)
    return ref, fresh
