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
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcomp.core.linalg3 import Vec3, Vec3Like, cross, vec3
from magcomp.core.rotations import down_b_from_quat, quat_from_euler, quat_step_body_rate
from magcomp.core.types import STANDARD_GRAVITY_M_S2, ImuSample

F64 = NDArray[np.float64]
Quat = tuple[float, float, float, float]


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


class MahonyState(NamedTuple):
    """Attitude ``q_nb`` (body FRD -> NED, w, x, y, z) and gyro-bias estimate (rad/s, body FRD), floats."""

    q_nb: Quat
    gyro_bias_b_rad_s: Vec3

    @property
    def down_b(self) -> Vec3:
        """Reference 'down' vector in body axes (third column of R_e^b, sec. II-A)."""
        return down_b_from_quat(self.q_nb)


class MahonyUpdate(NamedTuple):
    """What :func:`mahony_update` returns."""

    state: MahonyState
    accel_used: bool


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
    q = quat_from_euler(roll, pitch, yaw_rad)
    q_nb = (float(q[0]), float(q[1]), float(q[2]), float(q[3]))
    return MahonyState(q_nb=q_nb, gyro_bias_b_rad_s=(0.0, 0.0, 0.0))


def accel_gate_ok(accel_b_m_s2: Sequence[float], p: MahonyParams) -> bool:
    """True when the specific-force magnitude is within the gate around g."""
    ax, ay, az = accel_b_m_s2
    return accel_norm_ok(math.sqrt(ax * ax + ay * ay + az * az), p)


def accel_norm_ok(norm_m_s2: float, p: MahonyParams) -> bool:
    """:func:`accel_gate_ok` of a specific force whose magnitude is ``norm_m_s2``."""
    return math.isfinite(norm_m_s2) and abs(norm_m_s2 - p.gravity_m_s2) <= p.accel_gate_frac * p.gravity_m_s2


def mahony_update(
    state: MahonyState,
    gyro_b_rad_s: Vec3Like,
    accel_b_m_s2: Vec3Like,
    dt_s: float,
    p: MahonyParams,
) -> MahonyUpdate:
    """One filter step over ``dt_s`` (vectors as any three numbers; :func:`mahony_floats`)."""
    if not dt_s > 0.0:
        raise ValueError(f"dt must be > 0, got {dt_s}")
    gx, gy, gz = vec3(gyro_b_rad_s)
    ax, ay, az = vec3(accel_b_m_s2)
    q, bias, used = mahony_floats(state.q_nb, state.gyro_bias_b_rad_s, gx, gy, gz, ax, ay, az, dt_s, p)
    return MahonyUpdate(MahonyState(q, bias), used)


def mahony_floats(
    q_nb: Quat,
    bias_b_rad_s: Vec3,
    gx: float,
    gy: float,
    gz: float,
    ax: float,
    ay: float,
    az: float,
    dt_s: float,
    p: MahonyParams,
) -> tuple[Quat, Vec3, bool]:
    """One filter step over ``dt_s`` > 0 on plain floats: (attitude, gyro bias, whether the accelerometer
    passed the gate) after the step from attitude ``q_nb`` and bias ``bias_b_rad_s`` with the body rate
    ``g*`` (rad/s) and the specific force ``a*`` (m/s^2). The per-IMU-sample path (no named tuples built)."""
    b0, b1, b2 = bias_b_rad_s
    # predict with the bias-corrected gyro, then correct against the accelerometer sampled at the end of
    # the step (comparing with the start-of-step attitude would leave a lag of |omega| dt in the tilt)
    q = quat_step_body_rate(q_nb, (gx - b0, gy - b1, gz - b2), dt_s)  # eq. (18)
    an = math.sqrt(ax * ax + ay * ay + az * az)
    used = accel_norm_ok(an, p)
    if used:
        ex, ey, ez = cross((-ax / an, -ay / an, -az / an), down_b_from_quat(q))  # [23] v x v_hat
        kp = p.kp
        q = quat_step_body_rate(q, (kp * ex, kp * ey, kp * ez), dt_s)  # [23] explicit complementary filter
    else:
        ex = ey = ez = 0.0
    kd, m = p.ki * dt_s, p.max_bias_rad_s
    b0, b1, b2 = b0 - kd * ex, b1 - kd * ey, b2 - kd * ez  # [23] bias adaptation
    bias = (  # clamp to +-m: not in [23]
        m if b0 > m else -m if b0 < -m else b0,
        m if b1 > m else -m if b1 < -m else b1,
        m if b2 > m else -m if b2 < -m else b2,
    )
    return q, bias, used


def mahony_step(state: MahonyState, imu: ImuSample, dt_s: float, p: MahonyParams) -> MahonyState:
    """One filter step for an :class:`ImuSample` taken ``dt_s`` after the previous one."""
    return mahony_update(state, imu.gyro_b_rad_s, imu.accel_b_m_s2, dt_s, p).state


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
    down_out = np.empty((n, 3))
    used_out = np.zeros(n, dtype=bool)
    if n == 0:
        return MahonyTrack(q_out, b_out, down_out, used_out)
    st = state0 if state0 is not None else mahony_init(accel[0])
    ts, gs, acs = t.tolist(), gyro.tolist(), accel.tolist()
    for i in range(n):
        dt = ts[i] - ts[i - 1] if i > 0 else 0.0
        if 0.0 < dt <= max_dt_s:
            st, used_out[i] = mahony_update(st, gs[i], acs[i], dt, p)
        q_out[i] = st.q_nb
        b_out[i] = st.gyro_bias_b_rad_s
        down_out[i] = st.down_b
    return MahonyTrack(q_out, b_out, down_out, used_out)
