"""The published heading's filter (core/heading_filter.HeadingFilter): its yaw-rate bias loop and
its time constant that shortens while the vehicle turns fast."""

from __future__ import annotations

import math

import numpy as np

from magcomp.core.heading_filter import GYRO_SCALE_ERROR, HeadingFilter


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


def _run(
    f: HeadingFilter, rate_true_deg_s: np.ndarray, dt_s: float, bias_deg_s: float, scale_error: float,
    noise_deg: float, seed: int,
) -> np.ndarray:  # fmt: skip
    """Heading error (deg) of the filter at each sample: truth integrated from the true rate, the gyro reads
    rate * (1 + scale_error) + bias, the compass the truth plus white noise."""
    rng = np.random.default_rng(seed)
    psi_true = np.cumsum(rate_true_deg_s) * dt_s
    err = np.empty(psi_true.size)
    for k, (p, r) in enumerate(zip(psi_true, rate_true_deg_s, strict=True)):
        gyro = math.radians(r * (1.0 + scale_error) + bias_deg_s)
        out = f.update(float(p + rng.normal(0.0, noise_deg)), gyro, dt_s)
        err[k] = out - p
    return np.asarray(_wrap(err))


def test_gyro_bias_is_learned_and_leaves_no_standing_error() -> None:
    # 0.5 deg/s of yaw-rate bias (an uncalibrated MEMS gyro), 10 Hz compass with 3 deg of noise, 5 s filter:
    # a first-order filter stands off by bias x tau = 2.5 deg; the loop learns the bias and removes it
    dt, tau, bias = 0.1, 5.0, 0.5
    rate = np.full(3000, 0.0)
    rate[1000:1200] = 20.0  # a slow turn
    first = _run(HeadingFilter(tau, gyro_bias=False), rate, dt, bias, 0.0, 3.0, seed=1)
    loop = HeadingFilter(tau)
    both = _run(loop, rate, dt, bias, 0.0, 3.0, seed=1)
    late = slice(2000, None)
    assert abs(float(np.mean(first[late])) - bias * tau) < 0.6
    assert abs(float(np.mean(both[late]))) < 0.4
    assert abs(loop.bias_deg_s - bias) < 0.1
    # and the noise is filtered: the error's rms well under the compass's 3 deg
    assert float(np.sqrt(np.mean(both[late] ** 2))) < 1.2


def test_fast_turns_shorten_the_time_constant() -> None:
    # a spin at 200 deg/s with a 2 % scale error: the gyro alone would be 4 deg/s off; a fixed 5 s filter
    # stands off by ~rate x scale x tau = 20 deg, the filter that trusts the compass more while turning fast
    # stays within a few degrees, and its bias loop is not wound up by the spin
    dt, tau = 0.02, 5.0
    rate = np.zeros(4000)
    rate[500:2500] = 200.0
    f = HeadingFilter(tau)
    err = _run(f, rate, dt, 0.0, 2.0 * GYRO_SCALE_ERROR, 1.0, seed=2)
    spin = slice(1000, 2500)
    assert float(np.max(np.abs(err[spin]))) < 4.0
    assert abs(f.bias_deg_s) < 0.2
    assert float(np.max(np.abs(err[3000:]))) < 1.0
