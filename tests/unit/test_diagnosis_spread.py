"""The per-motor spread (magcomp.diagnosis.spread): a mean of norms of noisy vectors is biased up; the
Neyman construction on the fitted shape removes the bias (median) and its 95 % interval covers the truth."""

from __future__ import annotations

import numpy as np

from magcomp.diagnosis.spread import spread_interval

THETA = np.array([-122.0, 52.0, -4.0])  # mgauss, the held-out per-motor case's size


def _draw(
    rng: np.random.Generator, value: float, sd: float
) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """A true spread (the simulator's way: VALUE x |theta| x four unit offsets centred on their mean) and one
    fit of it: theta and delta with correlated Gaussian errors of a known covariance, per axis."""
    dirs = rng.normal(size=(4, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dirs -= dirs.mean(axis=0)
    delta = value * float(np.linalg.norm(THETA)) * dirs
    truth = float(np.mean(np.linalg.norm(delta, axis=1)) / np.linalg.norm(THETA))
    corr = -0.3  # the motor differences share the last motor: their errors are correlated
    base = np.array([[0.3, 0, 0, 0], [0, 1, corr, corr], [0, corr, 1, corr], [0, corr, corr, 1]]) * sd**2
    cov = np.stack([base * f for f in (1.0, 0.6, 1.5)])  # unequal axes
    e = np.einsum("ajk,ak->aj", np.linalg.cholesky(cov), rng.standard_normal((3, 4)))
    d = delta[:3] + e[:, 1:].T
    return truth, THETA + e[:, 0], np.vstack([d, -d.sum(axis=0)]), cov


def test_spread_is_median_unbiased_and_its_interval_covers() -> None:
    rng = np.random.default_rng(7)
    rows = [_draw(rng, 0.6, 45.0) for _ in range(120)]
    est = [spread_interval(theta, delta, cov) for _, theta, delta, cov in rows]
    truth = np.array([r[0] for r in rows])
    raw = np.array([e.raw for e in est]) / truth
    fixed = np.array([e.spread for e in est]) / truth
    inside = np.array([e.ci95[0] <= t <= e.ci95[1] for e, t in zip(est, truth, strict=True)])
    # the plain mean of norms: noise of ~75 mgauss per vector against |delta_i| ~ 80 makes it ~1.6x too large
    assert np.median(raw) > 1.3
    assert abs(float(np.median(fixed)) - 1.0) < 0.1
    # 95 % nominal; 120 draws: at 95 % fewer than 90 % inside has probability < 1 %
    assert inside.mean() >= 0.9, inside.mean()


def test_spread_of_noise_alone_is_zero_and_the_interval_starts_at_zero() -> None:
    rng = np.random.default_rng(8)
    zero = [spread_interval(theta, delta, cov) for _, theta, delta, cov in (_draw(rng, 0.0, 45.0),)]
    e = zero[0]
    assert e.raw > 0.3  # the noise alone looks like a spread
    assert e.ci95[0] == 0.0 and e.spread < 0.5 * e.raw
