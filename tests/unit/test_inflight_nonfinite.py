"""A row with a NaN, an infinity or a square that overflows (a damaged record upstream) is left out of the
in-flight normal equations (``InflightEstimator.add``, ``add_norm``): the solution is the one without it, not
NaN (LAPACK's Cholesky, ``lapack.dposv``, does not report a NaN matrix as a failure) and not a
heading sigma of 0."""

from __future__ import annotations

import math

import numpy as np
import pytest

from magcomp.core import inflight as core


def _rows(n_params: int, count: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    truth = np.linspace(-1.0, 1.0, n_params)
    out = []
    for _ in range(count):
        rows = rng.standard_normal((3, n_params))
        out.append((rows, rows @ truth + rng.standard_normal(3)))
    return out


@pytest.mark.parametrize("mode", ["absolute", "relative"])
def test_nonfinite_rows_are_left_out(mode: core.InflightMode) -> None:
    n = core.n_params(mode, 0)
    good = _rows(n, 300, seed=4)
    nan_z = (good[0][0], np.array([1.0, math.nan, 0.0]))
    inf_row = (np.where(np.arange(n) == 2, math.inf, good[1][0]), good[1][1])
    huge = (good[2][0] * 1e160, good[2][1])  # finite, but its square overflows
    bad = [nan_z, inf_row, huge]
    clean, damaged = core.InflightEstimator(mode, 0), core.InflightEstimator(mode, 0)
    for k, (rows, z) in enumerate(good):
        clean.add(rows, z, 0.5)
        damaged.add(rows, z, 0.5)
        if k in (100, 150, 200):
            damaged.add(*bad[(k - 100) // 50], 0.5)
    damaged.add(*bad[2], 0.5, gate=False)
    for y in (np.array([math.nan, 200.0, 400.0]), np.array([1e200, 0.0, 0.0])):
        damaged.add_norm(y, np.array([0.5]))
    a, b = clean.solve(), damaged.solve()
    assert a is not None and b is not None
    assert np.isfinite(b.theta_mgauss).all() and np.isfinite(b.calib_l).all()
    assert math.isfinite(b.heading_sigma_deg) and b.heading_sigma_deg > 0.0
    assert damaged.n == clean.n
    assert damaged.n_nonfinite == 6
    np.testing.assert_allclose(b.theta_mgauss, a.theta_mgauss, rtol=0, atol=1e-9)
