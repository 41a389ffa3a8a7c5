"""Mahony complementary filter (ref. [23] of the paper, sec. II-A): tilt and gyro-bias convergence."""

from __future__ import annotations

import numpy as np
import pytest

from magcomp.core.mahony import (
    STANDARD_GRAVITY_M_S2,
    MahonyParams,
    MahonyState,
    mahony_batch,
    mahony_init,
    mahony_step,
    mahony_update,
    tilt_from_accel,
)
from magcomp.core.rotations import (
    down_b_from_quat,
    euler_from_quat,
    quat_from_euler,
    quat_integrate_body_rate,
)
from magcomp.core.types import ImuSample


def _rotating_vehicle(
    rng: np.random.Generator,
    duration_s: float,
    rate_hz: float,
    bias_b: np.ndarray,
    gyro_noise: float,
    accel_noise: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Hand-rotation-like motion: smooth body rates on all axes. Returns t, q_true, gyro, accel."""
    dt = 1.0 / rate_hz
    t = np.arange(0.0, duration_s, dt)
    n = len(t)
    freqs = np.array([0.13, 0.21, 0.17])
    phases = rng.uniform(0, 2 * np.pi, 3)
    omega = 0.6 * np.sin(2 * np.pi * freqs * t[:, None] + phases)
    q = np.empty((n, 4))
    q[0] = quat_from_euler(0.3, -0.2, 1.0)
    for i in range(1, n):
        q[i] = quat_integrate_body_rate(q[i - 1], omega[i - 1], dt)
    down = np.array([down_b_from_quat(qi) for qi in q])
    # gyro sample i is the rate held over (t[i-1], t[i]] -> use omega[i-1]; first row unused
    gyro = np.vstack([omega[:1], omega[:-1]]) + bias_b + gyro_noise * rng.standard_normal((n, 3))
    accel = -STANDARD_GRAVITY_M_S2 * down + accel_noise * rng.standard_normal((n, 3))
    return t, q, gyro, accel


def _tilt_error_deg(q_est: np.ndarray, q_true: np.ndarray) -> np.ndarray:
    d_est = np.array([down_b_from_quat(q) for q in q_est])
    d_true = np.array([down_b_from_quat(q) for q in q_true])
    return np.degrees(np.arccos(np.clip(np.sum(d_est * d_true, axis=1), -1.0, 1.0)))


def test_tilt_from_accel_recovers_roll_pitch_at_rest() -> None:
    rng = np.random.default_rng(1)
    for _ in range(50):
        roll, pitch = rng.uniform(-3.0, 3.0), rng.uniform(-1.4, 1.4)
        q = quat_from_euler(roll, pitch, rng.uniform(-3, 3))
        f_b = -STANDARD_GRAVITY_M_S2 * np.array(down_b_from_quat(q))
        r, p = tilt_from_accel(f_b)
        assert abs(r - roll) < 1e-9 and abs(p - pitch) < 1e-9


def test_mahony_converges_to_true_roll_pitch_and_gyro_bias_with_noise() -> None:
    rng = np.random.default_rng(7)
    bias = np.array([0.02, -0.015, 0.01])
    t, q_true, gyro, accel = _rotating_vehicle(rng, 120.0, 100.0, bias, gyro_noise=0.005, accel_noise=0.05)
    track = mahony_batch(t, gyro, accel, MahonyParams())  # default gains kp=1/s, ki=0.1/s^2
    settled = t > 50.0
    err = _tilt_error_deg(track.q_nb[settled], q_true[settled])
    assert err.max() < 0.5, err.max()
    roll_pitch_err = []
    for qe, qt in zip(track.q_nb[settled][::50], q_true[settled][::50], strict=True):
        re, pe, _ = euler_from_quat(qe)
        rt, pt, _ = euler_from_quat(qt)
        if abs(pt) < np.radians(70):  # roll is ill-defined near gimbal lock
            d_roll = abs(np.degrees(np.angle(np.exp(1j * (re - rt)))))
            roll_pitch_err.append(max(d_roll, abs(np.degrees(pe - pt))))
    assert len(roll_pitch_err) > 50
    assert max(roll_pitch_err) < 0.5
    b_hat = track.gyro_bias_b_rad_s[settled].mean(axis=0)
    np.testing.assert_allclose(b_hat, bias, atol=2e-3)
    # the output down vector is the third row of R_nb (unit)
    np.testing.assert_allclose(np.linalg.norm(track.down_b, axis=1), 1.0, atol=1e-12)


def test_without_accel_correction_gyro_bias_makes_tilt_drift() -> None:
    """Control experiment: kp = ki = 0 is pure gyro integration and must drift with the same bias."""
    rng = np.random.default_rng(7)
    bias = np.array([0.02, -0.015, 0.01])
    t, q_true, gyro, accel = _rotating_vehicle(rng, 60.0, 100.0, bias, gyro_noise=0.005, accel_noise=0.05)
    track = mahony_batch(t, gyro, accel, MahonyParams(kp=0.0, ki=0.0))
    assert _tilt_error_deg(track.q_nb[-100:], q_true[-100:]).max() > 5.0


def test_accel_gate_rejects_inertial_acceleration() -> None:
    p = MahonyParams(kp=2.0, ki=0.0, accel_gate_frac=0.1)
    st = mahony_init(np.array([0.0, 0.0, -STANDARD_GRAVITY_M_S2]))
    # 2 g of lateral push: far outside the gate, must not tilt the estimate
    st2, used = mahony_update(st, np.zeros(3), np.array([20.0, 0.0, -STANDARD_GRAVITY_M_S2]), 0.01, p)
    assert not used
    np.testing.assert_allclose(st2.q_nb, st.q_nb, atol=1e-12)
    # inside the gate the same direction error is corrected
    f_tilted = -STANDARD_GRAVITY_M_S2 * np.array(down_b_from_quat(quat_from_euler(0.2, 0.0, 0.0)))
    st3, used3 = mahony_update(st, np.zeros(3), f_tilted, 0.01, p)
    assert used3
    assert euler_from_quat(st3.q_nb)[0] > 0.001


def test_step_with_imu_sample_matches_array_update() -> None:
    p = MahonyParams()
    q0 = quat_from_euler(0.1, 0.2, 0.3)
    st = MahonyState(q_nb=(q0[0], q0[1], q0[2], q0[3]), gyro_bias_b_rad_s=(0.0, 0.0, 0.0))
    gyro, accel = np.array([0.1, -0.2, 0.05]), np.array([0.5, -0.3, -9.7])
    a = mahony_step(st, ImuSample(t_s=0.0, gyro_b_rad_s=gyro, accel_b_m_s2=accel), 0.01, p)
    b, _ = mahony_update(st, gyro, accel, 0.01, p)
    np.testing.assert_array_equal(a.q_nb, b.q_nb)
    np.testing.assert_array_equal(a.gyro_bias_b_rad_s, b.gyro_bias_b_rad_s)
    with pytest.raises(ValueError):
        mahony_update(st, gyro, accel, 0.0, p)
