"""Sensor models: compasses per eq. (1), gyros and accelerometers, with seeded errors.

Compass j measures (departure from eq. (1) only in where the current's field enters: it is a physical field
at the sensor, so the instrument/soft-iron matrix acts on it too)
    v_j = K_j (u + B_j + D_j) + b_j + n_j                          eq. (1) with u -> u + B_j + D_j
    u   = R_nb^T m_n   (Earth field in body axes),  B_j = theta_j * load   (eq. (11) when no effect is on)
    D_j = k (T_powertrain - T_ambient) w_j                         (``temperature_drift``; 0 when off)
then quantised to the sensor's LSB and to the 1 mgauss of the MAVLink message. After the calibration
of eq. (2) (L = K^-1, d = K^-1 b), ``L v - d = u + B + D + L n``: the theta an estimator working on
calibrated data should find is ``theta_j`` itself, and the raw-frame theta is ``K_j theta_j``.

Compasses sit at different distances r_j from the power wires; theta scales as (r_0 / r_j)^2 (a current
loop's near field; ``falloff="inverse"`` gives the long-straight-wire 1/r law of eq. (4)).

Gyro: omega + bias + noise, quantised to 1 mrad/s (RAW_IMU unit). Accelerometer: specific force
R_nb^T (a_n - g_n) + bias + noise, quantised to 1 mG.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magcomp.core.rotations import so3_exp
from magcomp.core.types import STANDARD_GRAVITY_M_S2

F64 = NDArray[np.float64]
MESSAGE_NAMES = ("RAW_IMU", "SCALED_IMU2", "SCALED_IMU3")


@dataclass(frozen=True)
class CompassTruth:
    """Errors of one compass (and of the IMU reported in the same message).

    k_matrix: K of eq. (1) (soft iron x scale x misalignment), 3x3; b_mgauss: hard iron b, raw frame
    theta_mgauss: theta of eq. (11), calibrated frame (= physical field at full load)
    theta_raw_mgauss: K theta, the same in the raw compass frame
    theta_motor_mgauss: (k, 3) per-motor theta_i (``per_motor``), else (1, 3) = theta
    distance_m: from the power wires; noise_mgauss: white noise sigma per axis; lsb_mgauss: sensor resolution
    drift_dir: unit direction of the temperature drift (calibrated frame)
    gyro_bias_rad_s, gyro_noise_rad_s, accel_bias_m_s2, accel_noise_m_s2: the IMU in the same message
    """

    index: int
    message: str
    k_matrix: F64
    b_mgauss: F64
    theta_mgauss: F64
    theta_raw_mgauss: F64
    theta_motor_mgauss: F64
    distance_m: float
    noise_mgauss: float
    lsb_mgauss: float
    drift_dir: F64
    gyro_bias_rad_s: F64
    gyro_noise_rad_s: float
    accel_bias_m_s2: F64
    accel_noise_m_s2: float


DISTANCES_M = (0.05, 0.12, 0.20)
NOISE_MGAUSS = (8.0, 3.0, 5.0)  # compass 0: Table II's ~5.4 LSB at 1.5 mG/LSB
LSB_MGAUSS = (1.5, 1.0, 1.0)
HARD_IRON_SIGMA_MGAUSS = (80.0, 30.0, 40.0)


def make_compasses(
    n: int,
    theta0_mgauss: F64,
    n_motors: int,
    per_motor_spread: float,
    rng: np.random.Generator,
    falloff: str = "inverse_square",
) -> tuple[CompassTruth, ...]:
    """Draw the errors of ``n`` compasses; with ``per_motor_spread`` > 0, ``n_motors`` per-motor thetas each.

    The per-motor directions are drawn for every run (used or not), so switching an effect on does not
    change the other errors of the same seed.
    """
    out = []
    power = 2.0 if falloff == "inverse_square" else 1.0
    for j in range(n):
        soft = np.eye(3) + np.diag(rng.uniform(-0.08, 0.08, 3))
        off = rng.uniform(-0.04, 0.04, 3)
        soft[0, 1] = soft[1, 0] = off[0]
        soft[0, 2] = soft[2, 0] = off[1]
        soft[1, 2] = soft[2, 1] = off[2]
        misalign = so3_exp(rng.normal(0.0, math.radians(1.5), 3))
        k = soft @ misalign
        b = rng.normal(0.0, HARD_IRON_SIGMA_MGAUSS[j], 3)
        if j == 0:
            theta = np.asarray(theta0_mgauss, dtype=float).copy()
        else:  # another place: other wire geometry (direction) and distance (magnitude)
            turn = so3_exp(rng.normal(0.0, math.radians(25.0), 3))
            theta = (turn @ theta0_mgauss) * (DISTANCES_M[0] / DISTANCES_M[j]) ** power
        dirs = rng.normal(0.0, 1.0, (4, 3))
        dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        dirs = dirs - dirs.mean(axis=0)  # sum_i e_i = 0: equal motors give theta exactly
        if n_motors > 1 and per_motor_spread > 0.0:
            theta_motor = theta[None, :] + per_motor_spread * float(np.linalg.norm(theta)) * dirs[:n_motors]
        else:
            theta_motor = theta[None, :].copy()
        drift = rng.normal(0.0, 1.0, 3)
        out.append(
            CompassTruth(
                index=j,
                message=MESSAGE_NAMES[j],
                k_matrix=k,
                b_mgauss=b,
                theta_mgauss=theta,
                theta_raw_mgauss=k @ theta,
                theta_motor_mgauss=theta_motor,
                distance_m=DISTANCES_M[j],
                noise_mgauss=NOISE_MGAUSS[j],
                lsb_mgauss=LSB_MGAUSS[j],
                drift_dir=drift / np.linalg.norm(drift),
                gyro_bias_rad_s=rng.normal(0.0, 0.01, 3),
                gyro_noise_rad_s=0.003,
                accel_bias_m_s2=rng.normal(0.0, 0.05, 3),
                accel_noise_m_s2=0.04,
            )
        )
    return tuple(out)


def quantize(x: F64, step: float) -> F64:
    return np.round(x / step) * step


def measure_mag(
    c: CompassTruth, field_b_mgauss: F64, rng: np.random.Generator, extra_noise_mgauss: F64 | None = None
) -> F64:
    """eq. (1): v = K u' + b + n for the true body field u' (n, 3), quantised; mgauss (integers).

    extra_noise_mgauss (n, 3): coloured noise added to the white noise (raw sensor frame), or None."""
    v = field_b_mgauss @ c.k_matrix.T + c.b_mgauss  # eq. (1)
    v = v + rng.normal(0.0, c.noise_mgauss, v.shape)
    if extra_noise_mgauss is not None:
        v = v + extra_noise_mgauss
    return np.round(quantize(v, c.lsb_mgauss))  # sensor LSB, then the message's 1 mgauss


def coloured_noise(
    n: int, dt_s: float, ar1_sigma: float, ar1_tau_s: float, rw_per_sqrt_s: float, rng: np.random.Generator
) -> F64:
    """(n, 3) AR(1) noise (first-order Gauss-Markov, exact discretisation: stationary sigma ``ar1_sigma``,
    correlation time ``ar1_tau_s``) plus a random walk whose sigma grows as ``rw_per_sqrt_s * sqrt(t)``."""
    from scipy.signal import lfilter

    phi = math.exp(-dt_s / ar1_tau_s)
    w = rng.normal(0.0, 1.0, (n, 3))
    x0 = rng.normal(0.0, ar1_sigma, 3)
    ar, _ = lfilter([ar1_sigma * math.sqrt(1.0 - phi * phi)], [1.0, -phi], w, axis=0, zi=(phi * x0)[None, :])
    walk = np.cumsum(rng.normal(0.0, rw_per_sqrt_s * math.sqrt(dt_s), (n, 3)), axis=0)
    return np.asarray(ar) + walk


@dataclass(frozen=True)
class AutopilotCalibration:
    """The autopilot's own compass calibration and what it leaves (ArduPilot: COMPASS_OFS/DIA/ODI).

    The autopilot logs ``logged = A (v - b_ap)`` for the raw reading v (ArduPilot adds COMPASS_OFS =
    -b_ap, then multiplies by the symmetric DIA/ODI matrix A). With K, b of eq. (1):
        logged = A K (u + B + D) + A (b - b_ap) + A n
    so the true calibration of the LOGGED field, in the sense of eq. (2), is
        L = (A K)^-1,  d = K^-1 (b - b_ap):   L logged - d = u + B + D (+ L A n)
    (:meth:`magcomp.sim.simulate.SimResult.true_calibration`) and theta in the logged frame is
    ``L^-1 theta = A K theta``. An ellipsoid fit cannot see the misalignment part of K, so even a perfect
    autopilot calibration leaves L a small rotation.

    a_matrix: A (symmetric); b_ap_mgauss: the autopilot's hard-iron estimate (raw frame);
    residual_hard_iron_mgauss: A (b - b_ap), the offset error as it appears in the logged frame;
    soft_iron_error: E of A = S^-1/2 (I + E) S^-1/2 (S: the symmetric part of K)
    """

    a_matrix: F64
    b_ap_mgauss: F64
    residual_hard_iron_mgauss: F64
    soft_iron_error: F64

    @property
    def offsets_mgauss(self) -> F64:
        """ArduPilot's COMPASS_OFS (added to the raw reading): -b_ap."""
        return -self.b_ap_mgauss


def autopilot_calibration(
    c: CompassTruth, hard_iron_mgauss: float, soft_iron_rms: float, rng: np.random.Generator
) -> AutopilotCalibration:
    """Draw the autopilot's calibration of compass ``c`` with a residual hard iron of norm
    ``hard_iron_mgauss`` (random direction, logged frame) and a symmetric soft-iron error E with rms
    ``soft_iron_rms`` on the diagonal (half on the off-diagonal). The draws do not depend on the sizes."""
    e = rng.normal(0.0, 1.0, (3, 3))
    e = soft_iron_rms * (e + e.T) / 2.0 * np.where(np.eye(3) > 0, math.sqrt(2.0), 1.0) / math.sqrt(2.0)
    h_dir = rng.normal(0.0, 1.0, 3)
    h = hard_iron_mgauss * h_dir / np.linalg.norm(h_dir)
    w, v = np.linalg.eigh(c.k_matrix @ c.k_matrix.T)  # K K^T = S^2 (S symmetric part of K)
    s_inv_half = v @ np.diag(w**-0.25) @ v.T
    a = s_inv_half @ (np.eye(3) + e) @ s_inv_half
    a = (a + a.T) / 2.0
    b_ap = c.b_mgauss - np.linalg.solve(a, h)
    return AutopilotCalibration(a_matrix=a, b_ap_mgauss=b_ap, residual_hard_iron_mgauss=h, soft_iron_error=e)


def measure_gyro(c: CompassTruth, omega_b_rad_s: F64, rng: np.random.Generator) -> F64:
    g = omega_b_rad_s + c.gyro_bias_rad_s + rng.normal(0.0, c.gyro_noise_rad_s, omega_b_rad_s.shape)
    return quantize(g, 1e-3)


def measure_accel(c: CompassTruth, specific_force_b_m_s2: F64, rng: np.random.Generator) -> F64:
    f = specific_force_b_m_s2 + c.accel_bias_m_s2
    f = f + rng.normal(0.0, c.accel_noise_m_s2, f.shape)
    return quantize(f, STANDARD_GRAVITY_M_S2 * 1e-3)
