"""The simulated autopilot's attitude estimate (what ATTITUDE carries): a complementary filter.

Gyro integration (exact exponential, eq. (18)) corrected toward the accelerometer's down direction and,
for yaw only, toward the heading of the compass. The compass is calibrated with the motor-off K and b
(as an autopilot's COMPASS_OFS/DIA/ODI would be) but NOT corrected for the current-induced bias, so the
estimated yaw carries the throttle-driven error of Fig. 9. This is a plausible autopilot, not the Mahony
filter of the paper's estimator (that lives in :mod:`magcomp.core`). Which compass it fuses, and with which
calibration, is the caller's choice (:func:`magcomp.sim.simulate.simulate`); with ``yaw_ref_rad`` it steers
its yaw by a GPS heading instead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magcomp.core import heading
from magcomp.core.rotations import dcm_from_quat, quat_integrate_body_rate
from magcomp.core.types import STANDARD_GRAVITY_M_S2

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class AutopilotParams:
    """kp_tilt (1/s): accelerometer correction; kp_yaw (1/s): compass-heading correction;
    accel_gate_frac: ignore the accelerometer when | |f| - g | > accel_gate_frac * g."""

    kp_tilt: float = 1.0
    kp_yaw: float = 0.5
    accel_gate_frac: float = 0.15


def run_autopilot(
    q0_nb: F64,
    gyro_b_rad_s: F64,
    accel_b_m_s2: F64,
    mag_cal_b_mgauss: F64,
    accel_n_m_s2: F64,
    dt_s: float,
    declination_rad: float,
    p: AutopilotParams,
    yaw_ref_rad: F64 | None = None,
) -> F64:
    """Attitude estimates (n, 4) from sensor samples (n, 3) each at a fixed step dt_s; starts at q0_nb.

    accel_n_m_s2 (n, 3): the vehicle's kinematic acceleration (NED) as GPS velocity gives it; it is removed
    from the specific force before the tilt correction (as ArduPilot's GPS-aided AHRS does), so turns and
    accelerations do not tilt the estimate.

    yaw_ref_rad (n,): when given, the yaw is corrected toward it (GPS yaw / moving-baseline heading)
    instead of toward the compass heading, and the compass is not used.
    """
    n = gyro_b_rad_s.shape[0]
    out = np.empty((n, 4))
    q = np.asarray(q0_nb, dtype=float)
    e3 = np.array([0.0, 0.0, 1.0])
    for k in range(n):
        out[k] = q
        r = dcm_from_quat(q)
        corr = np.zeros(3)
        f = accel_b_m_s2[k] - r.T @ accel_n_m_s2[k]
        fn = float(np.linalg.norm(f))
        if abs(fn - STANDARD_GRAVITY_M_S2) <= p.accel_gate_frac * STANDARD_GRAVITY_M_S2:
            down_meas = -f / fn
            down_est = r[2, :]  # R^T e3
            corr = corr + p.kp_tilt * np.cross(down_meas, down_est)
        if yaw_ref_rad is not None:
            err = math.atan2(r[1, 0], r[0, 0]) - float(yaw_ref_rad[k])  # yaw_est - yaw_ref
            err = (err + math.pi) % (2.0 * math.pi) - math.pi
            corr = corr + r.T @ (-p.kp_yaw * err * e3)
            q = quat_integrate_body_rate(q, gyro_b_rad_s[k] + corr, dt_s)  # eq. (18)
            continue
        m_n = r @ mag_cal_b_mgauss[k]
        if math.hypot(m_n[0], m_n[1]) > 1e-6:
            err = heading.declination_rad(m_n) - declination_rad  # = yaw_est - yaw_compass
            err = (err + math.pi) % (2.0 * math.pi) - math.pi
            corr = corr + r.T @ (-p.kp_yaw * err * e3)
        q = quat_integrate_body_rate(q, gyro_b_rad_s[k] + corr, dt_s)  # eq. (18)
    return out
