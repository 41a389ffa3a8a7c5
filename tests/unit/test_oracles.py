"""The per-sample core steps (Python floats) agree with their numpy forms in tests/oracles.py, sample by
sample, in every observer configuration; the small float algebra agrees with numpy's linear algebra."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from numpy.testing import assert_allclose

from magcomp.core import linalg3
from magcomp.core.heading import tilt_compensated_heading_deg
from magcomp.core.mahony import MahonyParams, mahony_init, mahony_update
from magcomp.core.observer import ObserverParams, excitation, observer_init, observer_reset, observer_step
from magcomp.core.rotations import dcm_from_quat, dcm_from_rotvec, quat_from_euler, quat_step_body_rate
from magcomp.service.estimators import heading_deg
from tests import oracles

F64 = np.ndarray


def _full(s: linalg3.Sym3) -> list[float]:
    """The nine entries of the symmetric 3x3 whose upper triangle is ``s``."""
    a, b, c, e, f, i = s
    return [a, b, c, b, e, f, c, f, i]


def _stream(rng: np.random.Generator, n: int, irregular: bool) -> tuple[F64, F64, F64, F64, F64]:
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
            q = oracles.quat_step(q, w, t[k] - t[k - 1])
        r = oracles.dcm(q)
        # throttle off for the first 100 samples, then on/off steps and a ramp (eq. (16)'s delta_dot term)
        on = k >= 100 and (k // 300) % 3 != 0
        thr[k] = min(1.0, 0.3 + 0.7 * ((k // 100) % 2) + 1e-3 * (k % 50)) if on else 0.0
        field[k] = r.T @ b_ned + thr[k] ** 2 * theta + rng.normal(0, 5.0, 3)
        gyro[k] = w + rng.normal(0, 0.003, 3)
        acc[k] = r.T @ np.array([0, 0, -9.80665]) + rng.normal(0, 0.3, 3)
    return t, gyro, field, thr, acc


FORMS = [
    ObserverParams(),
    ObserverParams(scheme="observer", variant="delta_dot", prefilter="inputs"),
    ObserverParams(scheme="observer", variant="paper", prefilter="inputs", k2=1.0),
    ObserverParams(scheme="observer", prefilter="field", rate_interp="trapezoid"),
    ObserverParams(scheme="regression", variant="paper", prefilter="none", rate_interp="hold"),
    ObserverParams(theta_max_mgauss=30.0, lowpass=ObserverParams().lowpass.__class__(corner_hz=3.0, order=1)),
]


@pytest.mark.parametrize(("p", "irregular"), list(itertools.product(FORMS, [False, True])))
def test_observer_step_matches_numpy_oracle(p: ObserverParams, irregular: bool) -> None:
    rng = np.random.default_rng(21)
    t, gyro, field, thr, _ = _stream(rng, 1200, irregular)
    theta0 = np.array([5.0, -3.0, 1.0])
    st, ref = observer_init(p, theta0), oracles.init(p, theta0)
    statuses = set()
    for k in range(len(t)):
        dt = float(t[k] - t[k - 1]) if k else 0.02
        if k in (700, 701):  # a soft reset in the middle, as the pipeline does after a gap
            st, ref = observer_reset(st, p), oracles.reset(ref)
        ref, r_info = oracles.step(ref, gyro[k], field[k], float(thr[k]), dt, p)
        st, info = observer_step(st, gyro[k], field[k], float(thr[k]), dt, p)
        statuses.add(info.status)
        assert info.status == r_info.status, k
        assert info.flags == r_info.flags, k
        assert info.observable == r_info.observable, k
        if np.isfinite(r_info.residual_norm):
            assert_allclose(info.residual_norm_mgauss, r_info.residual_norm, rtol=1e-7, atol=1e-9)
        assert_allclose(info.excitation_min_rad2_s2, r_info.excitation_min, rtol=1e-6, atol=1e-9)
        assert_allclose(st.theta_hat_mgauss, ref.theta, rtol=1e-8, atol=1e-8)
        assert_allclose(st.v_hat_mgauss, ref.v_hat, rtol=1e-9, atol=1e-8)
    assert_allclose(_full(st.info), ref.info.ravel(), rtol=1e-9)
    assert statuses >= {"ok", "init"}
    if p == ObserverParams() and not irregular:  # the default form did learn
        assert np.linalg.norm(np.subtract(st.theta_hat_mgauss, [-61.0, 26.4, -8.0])) < 10.0


def test_mahony_update_matches_numpy_oracle() -> None:
    rng = np.random.default_rng(4)
    t, gyro, _, _, acc = _stream(rng, 800, False)
    acc[300] = [30.0, 0.0, -9.8]  # rejected by the gate
    p = MahonyParams()
    st = mahony_init(acc[0])
    q, b = np.array(st.q_nb), np.zeros(3)
    for k in range(1, len(t)):
        st, used = mahony_update(st, gyro[k], acc[k], t[k] - t[k - 1], p)
        q, b, used_ref = oracles.mahony_update(q, b, gyro[k], acc[k], t[k] - t[k - 1], p)
        assert used == used_ref
        assert_allclose(st.q_nb, q, rtol=0, atol=1e-12)
        assert_allclose(st.gyro_bias_b_rad_s, b, rtol=0, atol=1e-14)
    assert_allclose(st.down_b, oracles.dcm(q)[2], atol=1e-12)


def test_scalar_heading_matches_numpy_oracle() -> None:
    """The one eq. (24) (core.heading.heading_from_trig_deg, per sample and through its array form) against
    rotation matrices in numpy."""
    rng = np.random.default_rng(8)
    m = rng.normal(0, 300, (200, 3))
    roll, pitch = rng.uniform(-1.2, 1.2, 200), rng.uniform(-1.2, 1.2, 200)
    ref = oracles.heading_deg(m, roll, pitch)
    fast = np.array([heading_deg(m[i], roll[i], pitch[i]) for i in range(200)])
    arrays = tilt_compensated_heading_deg(m, roll, pitch)
    for got in (fast, arrays):
        assert_allclose(np.mod(got - ref + 180, 360) - 180, 0.0, atol=1e-9)


def test_excitation_matches_numpy_eigvalsh_and_inverse() -> None:
    rng = np.random.default_rng(2)
    for _ in range(200):
        a = rng.normal(0, 1, (3, 3))
        g = a @ a.T * rng.uniform(0.01, 10)
        if rng.random() < 0.3:
            g[2, :] = g[:, 2] = 0.0  # pure yaw: z unobservable
        lam_ref, obs_ref = oracles.excitation(g, 0.05)
        ex = excitation(g, 0.05)
        assert ex.observable == obs_ref
        assert_allclose(ex.lam_min_rad2_s2, lam_ref, atol=1e-9 * max(1.0, abs(lam_ref)) + 1e-12)


def test_float_algebra_matches_numpy() -> None:
    rng = np.random.default_rng(5)
    for _ in range(200):
        m = rng.normal(0, 1, (3, 3))
        u, v = rng.normal(0, 1, 3), rng.normal(0, 1, 3)
        assert_allclose(linalg3.cross(u, v), np.cross(u, v), atol=1e-14)
        assert_allclose(linalg3.minus_matvec(u, m.ravel(), v), u - m @ v, atol=1e-13)
        assert_allclose(linalg3.matTvec(m.ravel(), v), m.T @ v, atol=1e-13)
        s = m @ m.T
        up = (s[0, 0], s[0, 1], s[0, 2], s[1, 1], s[1, 2], s[2, 2])
        assert_allclose(linalg3.sym3_eigvals(up), np.linalg.eigvalsh(s), rtol=1e-9, atol=1e-9)
        s_inv = np.linalg.inv(s).ravel()
        assert_allclose(_full(linalg3.sym3_inv(up)), s_inv, rtol=1e-7, atol=1e-9)
        assert_allclose(_full(linalg3.gram(m.ravel())), (m.T @ m).ravel(), atol=1e-12)
        phi = rng.normal(0, 1, 3) * rng.choice([1e-10, 1e-3, 1.0])
        assert_allclose(dcm_from_rotvec(phi), oracles.so3_exp(phi).ravel(), atol=1e-14)
        q = quat_from_euler(*rng.uniform(-3, 3, 3))
        assert_allclose(quat_step_body_rate(q, v, 0.01), oracles.quat_step(q, v, 0.01), atol=1e-15)
        assert_allclose(dcm_from_quat(q), oracles.dcm(q), atol=1e-15)
    assert linalg3.sym3_eigvals((2.0, 0.0, 0.0, 1.0, 0.0, 3.0)) == (1.0, 2.0, 3.0)  # diagonal: exact


@pytest.mark.parametrize("n_batches", [1, 8, 9, 40])
def test_residual_batches_match_the_per_batch_loop(n_batches: int) -> None:
    """The stacked variance inflation (numpy over every batch, the fit share through sum M'M / n) equals
    the per-batch loop, across the stack's growth, with and without a covariance."""
    from magcomp.core.inflight import ResidualBatches

    rng = np.random.default_rng(n_batches)
    n = 17
    stack = ResidualBatches(n)
    kept = []
    for _ in range(n_batches):
        n_b = int(rng.integers(50, 2000))
        c, m, g = rng.normal(0, 30, 3), rng.normal(0, 5, (3, n)), rng.normal(0, 1, 3)
        stack.append(c, m, g, n_b)
        kept.append((c.copy(), m.copy(), g.copy(), n_b))
        c[...] = 0.0  # appended copies: the caller reuses its arrays
    p, c0 = rng.normal(0, 1, n), float(rng.normal(0, 100))
    a = rng.normal(0, 0.01, (n, n))
    for cov in (None, a @ a.T):
        s2 = 1.0 if cov is None else 4.0
        want = oracles.variance_inflation_loop(kept, p, c0, cov, s2)
        assert stack.count == n_batches
        assert_allclose(stack.inflation(p, c0, cov, s2), want, rtol=1e-12)
    assert want > 1.0  # residual sums far above the white expectation: the ratio itself, not its floor
