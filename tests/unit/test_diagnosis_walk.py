"""The temperature coefficient's variance under a wandering noise (magcomp.diagnosis.intervals.walk_variance).

A column as slow as the log (a temperature rising through the flight) takes up the slow part of a random-walk
noise (the compass's own, the gyro-integrated heading's angle random walk), so the residual no longer shows
it and the HAC variance, built on the residual's autocovariance to n/4 lags, is too small. Seeded regressions
with that structure: the 95 % interval of the slow column's coefficient must cover about 95 % with the
random-walk floor, where the HAC alone covers far less."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from magcomp.diagnosis.intervals import hac_variance, walk_variance


def _draw(rng: np.random.Generator, n: int = 1200, dur_s: float = 60.0) -> tuple[np.ndarray, ...]:
    """A 60 s log: constant, a slow temperature-like rise, a fast throttle-like column; noise = white 2
    mgauss + a random walk of 0.5 mgauss / sqrt(s) (a gyro-integrated heading's wander at this size)."""
    t = np.linspace(0.0, dur_s, n)
    temp = 1.0 - np.exp(-t / 40.0)  # rises through the log, as the powertrain warms
    fast = (np.sin(2 * np.pi * t / 7.0) > 0).astype(float) + 0.2 * rng.standard_normal(n)
    x = np.column_stack([np.ones(n), temp, fast])
    walk = np.cumsum(rng.standard_normal(n)) * 0.5 * math.sqrt(dur_s / n)
    v = x @ np.array([5.0, 3.0, -2.0]) + walk + 2.0 * rng.standard_normal(n)
    return t, x, v


def _coverage(floor: bool, trials: int = 200) -> float:
    rng = np.random.default_rng(20261128)
    inside = 0
    for _ in range(trials):
        t, x, v = _draw(rng)
        beta, *_ = np.linalg.lstsq(x, v, rcond=None)
        resid = v - x @ beta
        z = x @ (np.linalg.pinv(x.T @ x) @ np.array([0.0, 1.0, 0.0]))  # influence of the slow coefficient
        var = float(hac_variance(resid[:, None], z)[0])
        if floor:
            var = max(var, walk_variance(t, resid, x, z))
        inside += abs(beta[1] - 3.0) <= 1.96 * math.sqrt(var)
    return inside / trials


def test_a_slow_column_under_a_random_walk_is_covered_with_the_walk_floor() -> None:
    hac_only = _coverage(floor=False)
    with_walk = _coverage(floor=True)
    assert hac_only < 0.85, hac_only  # the HAC misses the walk the slow column absorbs
    assert 0.90 <= with_walk <= 0.995, with_walk


def test_walk_variance_of_white_noise_is_the_white_variance() -> None:
    """No walk in the noise: the fitted walk's share is near 0 and the variance near sigma^2 |z|^2 (within
    the estimate's scatter), so the floor does not widen an honest interval."""
    rng = np.random.default_rng(7)
    ratios = []
    for _ in range(40):
        n = 1200
        t = np.linspace(0.0, 60.0, n)
        x = np.column_stack([np.ones(n), 1.0 - np.exp(-t / 40.0)])
        v = x @ np.array([1.0, 2.0]) + 2.0 * rng.standard_normal(n)
        beta, *_ = np.linalg.lstsq(x, v, rcond=None)
        z = x @ (np.linalg.pinv(x.T @ x) @ np.array([0.0, 1.0]))
        ratios.append(walk_variance(t, v - x @ beta, x, z) / (4.0 * float(z @ z)))
    assert 0.8 <= float(np.median(ratios)) <= 1.5, np.median(ratios)


@pytest.mark.slow
def test_held_out_temperature_coefficient_inside_its_joint_box_on_twenty_seeds() -> None:
    """The held-out temperature case (``benchmarks/diagnosis_heldout.py``: 75 Hz compass held in a 100 Hz
    RAW_IMU, a compass random walk, a noisy gyro), seeds 5100-5119: the logged-frame coefficient inside the
    joint 95 % box on at least 18 of 20 (15 of 20 with the HAC and jackknife alone: 5105, 5111, 5116, 5117,
    5119 missed, each 1.0-1.2 joint half-widths off)."""
    sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))
    from diagnosis_heldout import run_case

    rows = [run_case("temperature_drift", seed, None) for seed in range(5100, 5120)]
    assert all(r["is_top"] for r in rows), [r["findings"] for r in rows]
    inside = sum(r["inside"] for r in rows)
    assert inside >= 18, [(r["seed"], r["error_over_joint_halfwidth"]) for r in rows if not r["inside"]]
