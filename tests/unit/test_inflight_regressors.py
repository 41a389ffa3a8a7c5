"""The in-flight regressors (``core/inflight/rows.py`` ``regressors``): x_0 = delta^2 (eq. (11)) and, with
motor outputs, x_j = m_j^2 - delta^2, built from floats with the same bits as the array arithmetic."""

from __future__ import annotations

import numpy as np

from magcomp.core.inflight.rows import regressors


def test_regressors_are_throttle_squared_then_mean_free_motor_squares() -> None:
    rng = np.random.default_rng(11)
    for _ in range(300):
        thr = float(rng.uniform(0.0, 1.0))
        m = rng.uniform(0.0, 1.0, size=int(rng.integers(2, 9)))
        for motors in (tuple(m.tolist()), tuple(m)):  # Python floats, numpy scalars
            x = regressors(thr, motors)
            assert x.dtype == np.float64 and x.shape == (m.shape[0] + 1,)
            ref = np.concatenate(([thr * thr], np.square(m) - thr * thr))
            assert np.array_equal(x, ref)  # bit for bit the array form
            assert abs(x[1:].mean() + thr * thr - float(np.mean(m**2))) < 1e-12
    assert regressors(0.5, None).tolist() == [0.25]
    assert regressors(0.5, ()).tolist() == [0.25]
