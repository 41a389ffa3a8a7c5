"""One model, two solvers (issue 24): the same absolute-form rows with the reference's yaw nuisance per
window, fed row by row to the recursive solver (InflightEstimator) and stacked for the batch solver
(core/inflight/batch.py), agree at the end of a seeded simulated flight within their stated uncertainty,
and both find the simulated truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from magcomp.core.inflight import (
    InflightEstimator,
    InflightParams,
    absolute_rows,
    reference_yaw_error_rows,
    regressors,
)
from magcomp.core.inflight.batch import batch_solve
from magcomp.core.rotations import dcm_from_euler
from tests.unit.test_inflight import A_TRUE, D_TRUE, H_NED, THETA, _flight, _measure

DT_S = 0.1
PRIOR_SD_RAD = 0.035


def _rows(seed: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rows, right-hand sides, regressors, nuisance columns and window keys of a flight whose reference
    yaw carries a slowly varying error (the nuisance's job)."""
    r, thr, _ = _flight(n, seed)
    y = _measure(r, thr, A_TRUE, D_TRUE, seed, noise=3.0)
    rng = np.random.default_rng(seed + 7)
    yaw_err = np.radians(1.5) * np.sin(0.02 * np.arange(n) * DT_S * 2 * np.pi + rng.uniform(0, 6))
    ref = np.array([dcm_from_euler(0.0, 0.0, float(e)) @ rk for e, rk in zip(yaw_err, r, strict=True)])
    rows, z, cols = [], [], []
    for k in range(n):
        a, b = absolute_rows(ref[k].T @ H_NED, y[k], regressors(float(thr[k]), None))
        rows.append(a)
        z.append(b)
        cols.append(reference_yaw_error_rows(ref[k], H_NED))
    windows = np.floor(np.arange(n) * DT_S / 2.0)
    return np.array(rows), np.array(z), thr**2, np.array(cols), windows


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recursive_and_batch_solvers_agree_within_their_uncertainty(seed: int) -> None:
    rows, z, x0, cols, windows = _rows(seed, 3000)
    p = InflightParams(sigma_a=0.1)
    est = InflightEstimator("absolute", 0, p, float(np.linalg.norm(H_NED)))
    est.set_earth_field(H_NED)
    for k in range(len(x0)):
        est.add(rows[k], z[k], float(x0[k]), cols[k], float(windows[k]), prior_sd=PRIOR_SD_RAD)
        if k % 100 == 99:
            est.solve()  # as the stage does: the windows close at the scale of the latest solution
    rec = est.solve()
    bat = batch_solve("absolute", 0, rows, z, x0, cols, windows, None, p, PRIOR_SD_RAD, H_NED)
    assert est.n == len(x0) and est.n_gated == 0  # the same rows went into both
    # both find the truth within their own uncertainty (the test can fail: the prior is 600 mgauss wide)
    for sol in (rec, bat):
        assert np.all(np.abs(sol.theta_mgauss - THETA) < 4.0 * sol.theta_sigma_mgauss + 0.5), sol.theta_mgauss
    # and each other within a fraction of it: the same model, two ways of solving it
    sigma = np.minimum(rec.theta_sigma_mgauss, bat.theta_sigma_mgauss)
    apart = np.abs(rec.theta_mgauss - bat.theta_mgauss)
    assert np.all(apart < 0.2 * sigma), (apart, sigma)
    assert np.all(sigma < 5.0)  # stated uncertainty small enough for the comparison to mean something
    np.testing.assert_allclose(rec.calib_l, bat.calib_l, atol=2e-3)
    np.testing.assert_allclose(rec.calib_d, bat.calib_d, atol=1.0)
    assert rec.residual_rms_mgauss == pytest.approx(bat.residual_rms_mgauss, rel=0.05)
    # the heading sigma from the covariance alike (the recursive one adds its split check's spread, which the
    # batch has no halves for)
    white = math.sqrt(max(rec.heading_sigma_deg**2 - rec.heading_split_deg**2, 0.0))
    assert white == pytest.approx(bat.heading_sigma_deg, rel=0.2)
    assert rec.variance_inflation < 1.5  # white residuals: the recursive sigma is not inflated either


def test_batch_solver_without_nuisance_equals_the_recursive_one_to_rounding() -> None:
    """No windows, no gate (a fresh estimator's gate is off until it converges), the same scale: the two
    solvers solve the same normal equations."""
    rows, z, x0, _, _ = _rows(3, 400)
    p = InflightParams(sigma_a=0.1)
    est = InflightEstimator("absolute", 0, p)
    for k in range(len(x0)):
        est.add(rows[k], z[k], float(x0[k]), gate=False)
    rec = est.solve()
    bat = batch_solve("absolute", 0, rows, z, x0, p=p, rounds=1)
    np.testing.assert_allclose(bat.theta_mgauss, rec.theta_mgauss, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(bat.calib_l, rec.calib_l, rtol=1e-10, atol=1e-10)
