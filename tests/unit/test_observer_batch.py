"""The batch solve of theta over a whole log (core/observer_batch.py): its rotations are the online step's,
standing still it is the paper's offline fit (eq. (14a)), its stated 1-sigma is the spread of its error on
the model's own data, and on seeded simulated flights its theta and the recursive solver's final theta agree
within their stated uncertainty (issue 24: "At the end of a log the two agree within their stated
uncertainty")."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.adapters.mavlink_source import open_source
from magcomp.core import observer_batch as ob
from magcomp.core.bias_fit import fit_bias_offline, least_squares
from magcomp.core.observer import ObserverParams, rotation_increment, rotation_increments
from magcomp.core.rotations import dcm_from_rotvec, dcms_from_rotvecs
from magcomp.service.pipeline import Pipeline
from magcomp.sim import SimConfig, simulate

THETA = np.array([-61.0, 26.4, -1.2])


def test_rotations_over_arrays_are_the_online_steps() -> None:
    rng = np.random.default_rng(1)
    n = 300
    t = np.cumsum(rng.uniform(0.018, 0.022, n))
    w = np.cumsum(rng.normal(0.0, 0.2, (n, 3)), axis=0)
    dt = np.diff(t)
    h0 = np.concatenate([[math.nan], dt[:-1]])  # the first step has no interval before it: the trapezoid
    w0 = np.concatenate([w[:1], w[:-2]])
    ph = rotation_increments(w0, w[:-1], w[1:], h0, dt, ObserverParams())
    a = dcms_from_rotvecs(-ph)
    for k in range(n - 1):
        ref = rotation_increment(tuple(w0[k]), tuple(w[k]), tuple(w[k + 1]), h0[k], dt[k], "quadratic")
        np.testing.assert_allclose(ph[k], ref, rtol=0.0, atol=1e-15)
        np.testing.assert_allclose(a[k].ravel(), dcm_from_rotvec((-ref[0], -ref[1], -ref[2])), atol=1e-15)


def test_standing_still_it_is_the_offline_fit_of_eq_14a() -> None:
    """No rotation, one window: the windows' field is eq. (12)'s constant u, and theta is eq. (14a)'s."""
    rng = np.random.default_rng(2)
    n = 400  # 8 s at 50 Hz: one window
    t = np.arange(n) * 0.02
    thr = np.linspace(0.0, 1.0, n)
    u = np.array([120.0, -40.0, 380.0])
    field = np.outer(thr**2, THETA) + u + rng.normal(0.0, 8.0, (n, 3))
    p = ObserverParams(excitation_min_rad2_s2=1e-12)  # the throttle sweep alone excites (barely)
    rows = ob.model_rows(t, np.zeros((n, 3)), field, thr, np.zeros(n), p)
    assert rows.n_windows == 1
    got = ob.batch_theta(ob.batch_add(ob.batch_init(), rows), p)
    ref = fit_bias_offline(thr, field, n_monte_carlo=0)
    np.testing.assert_allclose(got.theta_mgauss, ref.theta_mgauss, rtol=0.0, atol=1e-9)
    # eq. (15) pooled over the axes (one noise variance, 3n - 6 degrees of freedom; per axis: n - 2)
    pooled = ref.covariance[:, 0, 0] / ref.sigma_mgauss**2 * np.mean(ref.sigma_mgauss**2)
    np.testing.assert_allclose(got.theta_std_mgauss, np.sqrt(pooled), rtol=1e-9)


def _rotating_flight(n: int) -> tuple[np.ndarray, ...]:
    """Samples of eq. (12) on a vehicle turning about all axes (the attitude integrated finely), varying
    throttle, the Earth field fixed in NED; no noise."""
    dt, sub = 0.02, 20
    t = np.arange(n) * dt
    rate = lambda s: 1.5 * np.array([np.sin(0.7 * s), np.cos(0.5 * s), 0.3 * np.sin(0.3 * s + 1.0)])  # noqa: E731
    r = np.eye(3)
    field = np.empty((n, 3))
    u_e = np.array([240.0, -27.0, 386.0])
    thr = 0.6 + 0.35 * np.sin(0.4 * t)
    for i in range(n):
        field[i] = r.T @ u_e + thr[i] ** 2 * THETA
        for j in range(sub):  # body-to-NED rotation, R' = R [omega]_x, at the sub-step's midpoint rate
            h = dt / sub
            r = r @ np.array(dcm_from_rotvec(tuple(rate(t[i] + (j + 0.5) * h) * h))).reshape(3, 3)
    omega = np.array([rate(s) for s in t])
    return t, omega, field, thr


def test_stated_sigma_is_the_spread_of_the_error_on_the_models_own_data() -> None:
    rng = np.random.default_rng(3)
    t, omega, clean, thr = _rotating_flight(1500)
    z = []
    p = ObserverParams()
    for _ in range(12):
        field = clean + rng.normal(0.0, 8.0, clean.shape)
        rows = ob.model_rows(t, omega, field, thr, np.zeros(t.size), p)
        got = ob.batch_theta(ob.batch_add(ob.batch_init(), rows), p)
        assert all(got.converged)
        z.append((got.theta_mgauss - THETA) / got.theta_std_mgauss)
    zz = np.concatenate(z)
    assert 0.6 < float(np.std(zz)) < 1.6  # 36 draws of N(0, 1), and the rotation's integration error
    assert float(np.abs(np.mean(zz))) < 0.7


def test_compressed_parts_solve_as_the_rows_and_a_row_log_in_chunks_as_one() -> None:
    """The rows reduced part by part (the R of their QR) give the rows' own least squares; a learn-only row
    log reduced every few samples (a window ends at each cut, one step lost) gives nearly the same theta."""
    from magcomp.service.theta import ObserverRowLog

    rng = np.random.default_rng(6)
    t, omega, clean, thr = _rotating_flight(1500)
    field = clean + rng.normal(0.0, 8.0, clean.shape)
    p = ObserverParams()
    rows = ob.model_rows(t, omega, field, thr, np.zeros(t.size), p)
    whole = ob.batch_theta(ob.batch_add(ob.batch_init(), rows), p)
    k, m = 700, rows.dt_s.size // 2  # any cut: the rows' windows are solved out already
    first = rows._replace(x=rows.x[:k], y_mgauss=rows.y_mgauss[:k], n_windows=2, dt_s=rows.dt_s[:m],
                          observable=rows.observable[:m])  # fmt: skip
    second = rows._replace(x=rows.x[k:], y_mgauss=rows.y_mgauss[k:], n_windows=rows.n_windows - 2,
                           dt_s=rows.dt_s[m:], observable=rows.observable[m:])  # fmt: skip
    parts = ob.batch_theta(ob.batch_add(ob.batch_add(ob.batch_init(), first), second), p)
    np.testing.assert_allclose(parts.theta_mgauss, whole.theta_mgauss, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(parts.theta_std_mgauss, whole.theta_std_mgauss, rtol=1e-9)
    for chunk in (10_000, 400):
        log = ObserverRowLog(p, chunk=chunk)
        for i in range(t.size):
            log.add(float(t[i]), tuple(omega[i]), tuple(field[i]), float(thr[i]))
        got = log.solve(np.zeros(3))
        assert got.n_samples == t.size
        if chunk > t.size:  # one part: the rows themselves
            np.testing.assert_allclose(got.theta_mgauss, whole.theta_mgauss, rtol=0.0, atol=1e-9)
        else:  # other windows (cut at the chunks too): within the stated 1-sigma
            assert np.all(np.abs(got.theta_mgauss - whole.theta_mgauss) < whole.theta_std_mgauss)


def test_a_non_finite_sample_is_left_out_and_the_next_one_starts_a_window() -> None:
    rng = np.random.default_rng(4)
    t, omega, field, thr = _rotating_flight(100)
    field = field + rng.normal(0.0, 8.0, field.shape)
    field[50, 1] = math.nan
    start = np.zeros(t.size)
    start[20] = ob.START_RESET
    rows = ob.model_rows(t, omega, field, thr, start, ObserverParams())
    assert rows.n_windows == 3 and rows.y_mgauss.shape == (99, 3)
    assert rows.dt_s.size == 19 + 29 + 48  # the online steps: none into 20, into 50 or into 51
    assert np.isfinite(rows.y_mgauss).all()


def test_least_squares_is_the_offline_fits() -> None:
    """One implementation of eqs. (14a), (14b), (15): the offline fit's own numbers."""
    rng = np.random.default_rng(5)
    thr = np.linspace(0.0, 1.0, 200)
    u = np.array([100.0, 50.0, -300.0])
    field = np.outer(thr**2, [-40.0, 17.0, -1.0]) + u + rng.normal(0.0, 5.0, (200, 3))
    fit = fit_bias_offline(thr, field, n_monte_carlo=0)
    ls = least_squares(np.column_stack([thr**2, np.ones_like(thr)]), field)
    np.testing.assert_array_equal(fit.theta_mgauss, ls.beta[0])
    np.testing.assert_array_equal(fit.covariance, ls.covariance)


def _pipeline(path: Path, learn_only: bool) -> Pipeline:
    pipe = Pipeline(Config(), learn_only=learn_only)
    src = open_source(path, throttle_source="auto", pipeline_only=True)
    try:
        for s in src.samples():
            pipe.feed(s)
    finally:
        src.close()
        pipe.close()
    return pipe


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_batch_and_recursive_theta_agree_within_their_uncertainty(tmp_path: Path, seed: int) -> None:
    """The paper's scenario (hand rotation, then flight): the learn-only pass's batch theta and the per-sample
    observer's final theta, each compass, differ by less than 3 combined sigmas (each solver's own 1-sigma);
    and the batch theta is within 4 % of the simulated theta (the learned calibration's error part of it)."""
    result = simulate(SimConfig(scenario="paper", duration_s=133.0, seed=seed))
    path = tmp_path / "paper.tlog"
    write_tlog(result, path)
    batch = _pipeline(path, learn_only=True)
    live = _pipeline(path, learn_only=False)
    for idx, c in batch.correctors.items():
        b = c.theta.batch
        assert b is not None and b.n_samples > 3000
        assert all(b.converged)
        np.testing.assert_allclose(c.theta.est.theta_values(), b.theta_mgauss)  # what the pass hands on
        tr = live.correctors[idx].theta
        assert tr.batch is None and tr.last_info is not None  # the live path stepped the observer
        online = np.array(tr.est.theta_values())
        sd_online = np.array(tr.last_info.theta_std_mgauss)
        combined = np.sqrt(b.theta_std_mgauss**2 + sd_online**2)
        assert np.all(np.abs(b.theta_mgauss - online) <= 3.0 * combined), (idx, b, online, sd_online)
        truth = np.asarray(result.compasses[idx].theta_mgauss)
        assert np.linalg.norm(b.theta_mgauss - truth) <= 0.04 * np.linalg.norm(THETA), (idx, b, truth)
