"""The pipeline's scalar fast paths agree with the core steps they mirror, sample by sample."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from magcomp.core.heading import tilt_compensated_heading_deg
from magcomp.core.mahony import MahonyParams, mahony_init, mahony_update
from magcomp.core.observer import ObserverParams, excitation, observer_init, observer_reset, observer_step
from magcomp.core.rotations import dcm_from_quat, quat_from_euler, quat_integrate_body_rate
from magcomp.service.estimators import heading_deg
from magcomp.service.fastpath import FastMahony, FastObserver, _excitation, supports


def _stream(rng: np.random.Generator, n: int, irregular: bool) -> tuple[np.ndarray, ...]:
    """A hand rotation at changing throttle with noise: times, gyro, field (mgauss), throttle, accel."""
    theta = np.array([-61.0, 26.4, -8.0])
    b_ned = np.array([240.0, -20.0, 420.0])
    q = quat_from_euler(0.2, -0.1, 1.0)
    t = (
        np.cumsum(rng.choice([0.02, 0.04, 0.3, 0.0005], size=n, p=[0.85, 0.1, 0.03, 0.02]))
        if irregular
        else np.arange(n) * 0.02
    )
    f = rng.uniform(0.2, 0.8, (3, 2))
    gyro, field, thr, acc = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n), np.zeros((n, 3))
    for k in range(n):
        w = np.sin(2 * np.pi * f[:, 0] * t[k]) + 0.5 * np.cos(2 * np.pi * f[:, 1] * t[k])
        if k:
            q = quat_integrate_body_rate(q, w, t[k] - t[k - 1])
        r = dcm_from_quat(q)
        thr[k] = 0.0 if (k // 300) % 3 == 0 else min(1.0, 0.3 + 0.7 * ((k // 100) % 2))
        field[k] = r.T @ b_ned + thr[k] ** 2 * theta + rng.normal(0, 5.0, 3)
        gyro[k] = w + rng.normal(0, 0.003, 3)
        acc[k] = r.T @ np.array([0, 0, -9.80665]) + rng.normal(0, 0.3, 3)
    return t, gyro, field, thr, acc


@pytest.mark.parametrize("irregular", [False, True])
def test_fast_observer_matches_core_observer_step(irregular: bool) -> None:
    rng = np.random.default_rng(21)
    t, gyro, field, thr, _ = _stream(rng, 1500, irregular)
    p = ObserverParams()
    assert supports(p)
    st = observer_init(p, np.array([5.0, -3.0, 1.0]))
    fast = FastObserver(p, st)
    for k in range(len(t)):
        dt = t[k] - t[k - 1] if k else 0.02
        if k in (700, 701):  # a soft reset in the middle, as the pipeline does after a gap
            st = observer_reset(st, p, keep_theta=True)
            fast.reset()
        st, info = observer_step(st, gyro[k], field[k], float(thr[k]), dt, p)
        fi = fast.step(list(gyro[k]), list(field[k]), float(thr[k]), dt)
        assert fi.status == info.status
        assert fi.flags == info.flags, k
        assert fi.converged == all(info.converged)
        assert fi.z_unobservable == info.z_unobservable
        if np.isfinite(info.residual_norm_mgauss):
            assert_allclose(fi.residual_norm_mgauss, info.residual_norm_mgauss, rtol=1e-7, atol=1e-9)
        assert_allclose(fi.excitation, info.excitation_min_rad2_s2, rtol=1e-6, atol=1e-9)
        assert_allclose(fast.theta, st.theta_hat_mgauss, rtol=1e-8, atol=1e-8)
    back = fast.to_state()
    assert_allclose(back.info, st.info, rtol=1e-9)
    assert_allclose(back.v_hat_mgauss, st.v_hat_mgauss, rtol=1e-8, atol=1e-8)
    assert np.linalg.norm(st.theta_hat_mgauss - np.array([-61.0, 26.4, -8.0])) < 10.0  # it did learn


def test_fast_mahony_matches_core_mahony_update() -> None:
    rng = np.random.default_rng(4)
    t, gyro, _, _, acc = _stream(rng, 800, False)
    p = MahonyParams()
    st = mahony_init(acc[0])
    fast = FastMahony(p, st.q_nb, st.gyro_bias_b_rad_s)
    for k in range(1, len(t)):
        st, used = mahony_update(st, gyro[k], acc[k], t[k] - t[k - 1], p)
        g, a = gyro[k], acc[k]
        assert fast.update(g[0], g[1], g[2], a[0], a[1], a[2], t[k] - t[k - 1]) == used
        assert_allclose(fast.q, st.q_nb, rtol=0, atol=1e-12)
        assert_allclose(fast.b, st.gyro_bias_b_rad_s, rtol=0, atol=1e-14)
    assert_allclose(fast.down_b(), st.down_b, atol=1e-12)


def test_scalar_heading_matches_core_heading() -> None:
    rng = np.random.default_rng(8)
    m = rng.normal(0, 300, (200, 3))
    roll, pitch = rng.uniform(-1.2, 1.2, 200), rng.uniform(-1.2, 1.2, 200)
    core = tilt_compensated_heading_deg(m, roll, pitch)
    fast = np.array([heading_deg(m[i], roll[i], pitch[i]) for i in range(200)])
    assert_allclose(np.mod(fast - core + 180, 360) - 180, 0.0, atol=1e-9)


def test_closed_form_excitation_matches_core() -> None:
    rng = np.random.default_rng(2)
    for _ in range(50):
        a = rng.normal(0, 1, (3, 3))
        g = a @ a.T * rng.uniform(0.01, 10)
        if rng.random() < 0.3:
            g[2, :] = g[:, 2] = 0.0  # pure yaw: z unobservable
        lam, _, obs = excitation(g, 0.05)
        lam_f, obs_f = _excitation(list(g.ravel()), 0.05)
        assert obs_f == obs
        assert_allclose(lam_f, lam, atol=1e-9 * max(1.0, abs(lam)) + 1e-12)
