"""How fast the autopilot's yaw follows a compass: the gain of its compass correction, measured from a log.

An attitude filter propagates its yaw with the gyro and pulls it toward the compass's heading:
``d psi_ap / dt = psi_dot_gyro + b + k (psi_compass - psi_ap)`` (a complementary filter with gain ``k``, 1/s;
an EKF's magnetometer update acts the same way to first order, with ``b`` the part of the gyro bias it has
not learned). So the autopilot's yaw minus the gyro's integral, ``D = psi_ap - integral(psi_dot_gyro)``,
changes at ``b + k (psi_compass - psi_ap)``: one straight-line fit over short windows gives ``k``.

Why it matters: the relative form's nuisance models of the autopilot's yaw error (docs/inflight.md) assume
how fast that yaw follows the disturbed compass; the simulator's autopilot (``ap_kp_yaw``, default 0.5/s)
is one such assumption. Measured on log171 (ArduCopter 3.3, external compass 0): about 0.02 /s on the
ground and in flight, a time constant of tens of seconds (docs/measured-data.md).

Pure, no I/O: arrays in, a :class:`YawFollow` out. Frames: body FRD, NED; angles in rad.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from magcomp.core.heading import tilt_compensated_heading_deg
from magcomp.core.rotations import euler_yaw_rate_coefs
from magcomp.core.yaw_follow import (
    MIN_SAMPLES_PER_WINDOW,
    YawFollow,
    fit_follow_gain,
    window_follow_terms,
)

F64 = NDArray[np.float64]

#: the window (s) over which the yaw-rate difference is taken: short against the time constants sought
#: (seconds to minutes), long against the attitude's message interval (0.02-0.1 s)
WINDOW_S = 2.0
#: tilt (rad) above which the tilt-compensated compass heading is left out (near 90 deg it is undefined)
MAX_TILT_RAD = math.radians(45.0)
def gyro_yaw_integral(t_imu_s: F64, gyro_rad_s: F64, t_att_s: F64, attitude_rad: F64) -> F64:
    """The gyro's yaw (rad, 0 at the first IMU sample) as the pipeline integrates it
    (service/attitude.py): the Euler yaw rate ``q c0 + r c1`` with the coefficients of the latest attitude
    sample (core.rotations.euler_yaw_rate_coefs), trapezoids between IMU samples."""
    coefs = np.array([euler_yaw_rate_coefs(float(r), float(p)) for r, p in attitude_rad[:, :2]])
    k = np.clip(np.searchsorted(t_att_s, t_imu_s, side="right") - 1, 0, len(t_att_s) - 1)
    rate = gyro_rad_s[:, 1] * coefs[k, 0] + gyro_rad_s[:, 2] * coefs[k, 1]
    return np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(t_imu_s))])


def _finite_increasing(t_s: F64, values: F64) -> tuple[F64, F64]:
    """The rows with a finite time and finite values, in time order, repeated times dropped (a log's
    series may hold NaN or out-of-order rows; np.interp needs increasing times)."""
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(values, dtype=float).reshape(len(t), -1)
    ok = np.isfinite(t) & np.all(np.isfinite(v), axis=1)
    t, v = t[ok], v[ok]
    order = np.argsort(t, kind="stable")
    t, v = t[order], v[order]
    keep = np.concatenate([[True], np.diff(t) > 0.0]) if t.size else np.zeros(0, dtype=bool)
    return t[keep], v[keep]


def yaw_follow_gain(
    t_att_s: F64,
    attitude_rad: F64,
    t_imu_s: F64,
    gyro_rad_s: F64,
    t_mag_s: F64,
    field_b_mgauss: F64,
    t_start_s: float = -math.inf,
    t_end_s: float = math.inf,
    window_s: float = WINDOW_S,
) -> YawFollow | None:
    """Fit ``dD/dt = b + k (psi_compass - psi_ap)`` over ``window_s`` windows in [t_start_s, t_end_s).

    attitude_rad: the autopilot's (roll, pitch, yaw) at ``t_att_s``; gyro_rad_s: body rates at ``t_imu_s``;
    field_b_mgauss: the compass the autopilot fuses, as logged, at ``t_mag_s``. None when fewer than 5
    windows hold data. A constant offset between the compass's heading and the autopilot's yaw (the
    declination, a mounting angle) adds ``k`` times itself to the rate, which the intercept takes.
    """
    t_att_s, attitude_rad = _finite_increasing(t_att_s, attitude_rad)
    t_imu_s, gyro_rad_s = _finite_increasing(t_imu_s, gyro_rad_s)
    t_mag_s, field_b_mgauss = _finite_increasing(t_mag_s, field_b_mgauss)
    if len(t_att_s) < 2 or len(t_imu_s) < 2 or len(t_mag_s) < 2:
        return None
    g = np.interp(t_att_s, t_imu_s, gyro_yaw_integral(t_imu_s, gyro_rad_s, t_att_s, attitude_rad))
    psi_ap = np.unwrap(attitude_rad[:, 2])
    m = np.column_stack([np.interp(t_att_s, t_mag_s, field_b_mgauss[:, k]) for k in range(3)])
    # eq. (24), tilt-compensated: the one implementation in core
    psi_c = np.radians(tilt_compensated_heading_deg(m, attitude_rad[:, 0], attitude_rad[:, 1]))
    level = np.hypot(attitude_rad[:, 0], attitude_rad[:, 1]) < MAX_TILT_RAD
    lo = max(t_start_s, float(t_att_s[0]), float(t_imu_s[0]), float(t_mag_s[0]))
    hi = min(t_end_s, float(t_att_s[-1]), float(t_imu_s[-1]), float(t_mag_s[-1]))
    starts = np.arange(lo, hi - window_s, window_s)
    # each window's samples t in [a, a + window_s): a slice of the increasing times; the level ones get an id
    first = np.searchsorted(t_att_s, starts, side="left")
    end = np.searchsorted(t_att_s, starts + window_s, side="left")
    ids = np.full(t_att_s.size, -1, dtype=np.int64)
    k = 0
    for i0, i1 in zip(first.tolist(), end.tolist(), strict=True):
        if i1 - i0 >= MIN_SAMPLES_PER_WINDOW and bool(level[i0:i1].all()):
            ids[i0:i1] = k
            k += 1
    sel = ids >= 0
    rates, offs = window_follow_terms(t_att_s[sel], psi_c[sel], psi_ap[sel], g[sel], ids[sel])
    return fit_follow_gain(rates, offs)
