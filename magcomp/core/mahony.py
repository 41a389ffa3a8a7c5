"""Mahony explicit complementary filter (gyro + accelerometer, with gyro-bias estimate).

The paper (sec. II-A) takes the DPI reference vector from the attitude of the nonlinear complementary
filter of ref. [23]: R. Mahony, T. Hamel, J.-M. Pflimlin, "Nonlinear complementary filters on the special
orthogonal group", IEEE TAC 53(5), 2008. The reference "down" vector is the third column of R_e^b, i.e.
:func:`magcomp.core.rotations.down_b_from_quat`. Equation numbers ``eq. (..)`` refer to Silic & Mohseni,
IEEE Sensors J. 20(2), 2020; ``[23, ...]`` names the Mahony filter's own terms.

Filter, with one vector measurement (gravity):
    v_hat   = R_hat^T e_3                      predicted down direction, body            [23] explicit CF
    v       = -a / |a|                         measured down direction (specific force)
    w_mes   = v x v_hat                        correction rate
    R_hat'  = R_hat [omega_y - b_hat + k_P w_mes]_x                                    eq. (18) form
    b_hat'  = -k_I w_mes

Symbol table (paper/ref -> code, unit, frame):
    R_hat (R_b^e)      -> q_nb (quaternion w, x, y, z), body FRD -> NED
    omega_y            -> gyro_b_rad_s, rad/s, body FRD
    a                  -> accel_b_m_s2, specific force, m/s^2, body FRD
    b_hat              -> gyro_bias_b_rad_s, rad/s, body FRD
    k_P, k_I           -> MahonyParams.kp (1/s), MahonyParams.ki (1/s^2)

Departures: the accelerometer correction is gated (applied only when | |a| - g | is small, so inertial
accelerations do not corrupt the reference, which the paper addresses by fusing the accelerometer at
25 Hz); the gyro-bias integral is clamped to ``max_bias_rad_s``; each step is split into a gyro
prediction and an accelerometer correction evaluated at the predicted attitude (a first-order splitting
of [23]'s single ODE, which removes a one-sample lag); rotations use the exact exponential for a rate
held over dt and are renormalised.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcomp.core.rotations import down_b_from_quat, quat_from_euler, quat_integrate_body_rate
from magcomp.core.types import STANDARD_GRAVITY_M_S2, ImuSample

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class MahonyParams:
    """Gains and gates of the filter.

    kp: proportional gain on the attitude error (1/s); ~1 gives a ~1 s tilt time constant.
    ki: integral gain for the gyro bias (1/s^2); 0 disables bias estimation.
    accel_gate_frac: use the accelerometer only when | |a| - g | <= accel_gate_frac * g.
    max_bias_rad_s: clamp of each gyro-bias component.
    """

    kp: float = 1.0
    ki: float = 0.1
    gravity_m_s2: float = STANDARD_GRAVITY_M_S2
    accel_gate_frac: float = 0.1
    max_bias_rad_s: float = 0.2

    def __post_init__(self) -> None:
        if self.kp < 0.0 or self.ki < 0.0:
            raise ValueError(f"Mahony gains must be >= 0, got kp={self.kp}, ki={self.ki}")
        if not self.accel_gate_frac > 0.0:
            raise ValueError(f"accel_gate_frac must be > 0, got {self.accel_gate_frac}")


@dataclass(frozen=True)
class MahonyState:
    """Attitude ``q_nb`` (body FRD -> NED, w, x, y, z) and gyro-bias estimate (rad/s, body FRD)."""

    q_nb: F64
    gyro_bias_b_rad_s: F64

    @property
    def down_b(self) -> F64:
        """Reference 'down' vector in body axes (third column of R_e^b, sec. II-A)."""
        return down_b_from_quat(self.q_nb)


@dataclass(frozen=True)
class MahonyTrack:
    """Batch output: one row per input sample, *after* that sample was fused."""

    q_nb: F64  # (n, 4)
    gyro_bias_b_rad_s: F64  # (n, 3)
    down_b: F64  # (n, 3) unit vectors
    accel_used: NDArray[np.bool_]  # (n,) whether the accelerometer passed the gate


def tilt_from_accel(accel_b_m_s2: ArrayLike) -> tuple[float, float]:
    """Roll and pitch (rad) of a vehicle at rest from its specific force (FRD: level -> (0, 0, -g))."""
    fx, fy, fz = np.asarray(accel_b_m_s2, dtype=float)
    roll = math.atan2(-fy, -fz)
    pitch = math.atan2(fx, math.hypot(fy, fz))
    return roll, pitch


def mahony_init(accel_b_m_s2: ArrayLike, yaw_rad: float = 0.0) -> MahonyState:
    """State from the first accelerometer sample (roll, pitch) and a given yaw; zero gyro bias."""
    a = np.asarray(accel_b_m_s2, dtype=float)
    if not np.all(np.isfinite(a)) or float(np.linalg.norm(a)) == 0.0:
        raise ValueError("cannot initialise attitude from a zero or non-finite accelerometer sample")
    roll, pitch = tilt_from_accel(a)
    return MahonyState(q_nb=quat_from_euler(roll, pitch, yaw_rad), gyro_bias_b_rad_s=np.zeros(3))


def accel_gate_ok(accel_b_m_s2: F64, p: MahonyParams) -> bool:
    """True when the specific-force magnitude is within the gate around g."""
    norm = float(np.linalg.norm(accel_b_m_s2))
    return bool(np.isfinite(norm) and abs(norm - p.gravity_m_s2) <= p.accel_gate_frac * p.gravity_m_s2)


def mahony_update(
    state: MahonyState,
    gyro_b_rad_s: ArrayLike,
    accel_b_m_s2: ArrayLike,
    dt_s: float,
    p: MahonyParams,
) -> tuple[MahonyState, bool]:
    """One filter step over ``dt_s`` with arrays; returns (new state, accelerometer used)."""
    if not dt_s > 0.0:
        raise ValueError(f"dt must be > 0, got {dt_s}")
    gyro = np.asarray(gyro_b_rad_s, dtype=float)
    accel = np.asarray(accel_b_m_s2, dtype=float)
    used = accel_gate_ok(accel, p)
    # predict with the bias-corrected gyro, then correct against the accelerometer sampled at the end of
    # the step (comparing with the start-of-step attitude would leave a lag of |omega| dt in the tilt)
    q_pred = quat_integrate_body_rate(state.q_nb, gyro - state.gyro_bias_b_rad_s, dt_s)  # eq. (18)
    if used:
        v_meas = -accel / float(np.linalg.norm(accel))  # measured down, body
        v_hat = down_b_from_quat(q_pred)  # predicted down: third column of R_e^b
        w_mes = np.cross(v_meas, v_hat)  # [23] correction term
        q_new = quat_integrate_body_rate(q_pred, p.kp * w_mes, dt_s)  # [23] explicit complementary filter
    else:
        w_mes = np.zeros(3)
        q_new = q_pred
    b_new = state.gyro_bias_b_rad_s - p.ki * w_mes * dt_s  # [23] bias adaptation
    b_new = np.clip(b_new, -p.max_bias_rad_s, p.max_bias_rad_s)  # clamp: not in [23]
    return MahonyState(q_nb=q_new, gyro_bias_b_rad_s=b_new), used


def mahony_step(state: MahonyState, imu: ImuSample, dt_s: float, p: MahonyParams) -> MahonyState:
    """One filter step for an :class:`ImuSample` taken ``dt_s`` after the previous one."""
    new_state, _ = mahony_update(state, imu.gyro_b_rad_s, imu.accel_b_m_s2, dt_s, p)
    return new_state


def mahony_batch(
    t_s: ArrayLike,
    gyro_b_rad_s: ArrayLike,
    accel_b_m_s2: ArrayLike,
    p: MahonyParams,
    state0: MahonyState | None = None,
    max_dt_s: float = 0.5,
) -> MahonyTrack:
    """Run the filter over arrays: ``t_s`` (n,) s, gyro (n, 3) rad/s, accel (n, 3) m/s^2, body FRD.

    Starts from ``state0`` or, if None, from the first accelerometer sample (:func:`mahony_init`). A
    time step that is not positive or exceeds ``max_dt_s`` (a log gap) is not integrated: the sample
    only refreshes the output row.
    """
    t = np.asarray(t_s, dtype=float)
    gyro = np.asarray(gyro_b_rad_s, dtype=float)
    accel = np.asarray(accel_b_m_s2, dtype=float)
    n = t.shape[0]
    if gyro.shape != (n, 3) or accel.shape != (n, 3):
        raise ValueError(f"expected gyro and accel of shape ({n}, 3), got {gyro.shape} and {accel.shape}")
    q_out = np.empty((n, 4))
    b_out = np.empty((n, 3))
    used_out = np.zeros(n, dtype=bool)
    if n == 0:
        return MahonyTrack(q_out, b_out, np.empty((0, 3)), used_out)
    st = state0 if state0 is not None else mahony_init(accel[0])
    for i in range(n):
        dt = t[i] - t[i - 1] if i > 0 else 0.0
        if 0.0 < dt <= max_dt_s:
            st, used_out[i] = mahony_update(st, gyro[i], accel[i], dt, p)
        q_out[i] = st.q_nb
        b_out[i] = st.gyro_bias_b_rad_s
    # third row of R_nb for every sample: down vector in body axes
    w, x, y, z = q_out.T
    down = np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=1)
    return MahonyTrack(q_out, b_out, down, used_out)
