"""Bounded memory (issue 12, item 12): the Monte-Carlo benchmark runs in chunks sized by memory, with
results that do not depend on the chunk size. (Peak memory itself is measured in benchmarks/memory.py.)"""

from __future__ import annotations

import numpy as np
import pytest

import magcomp.core.bias_fit as bias_fit


def test_monte_carlo_chunks_by_memory_give_the_same_numbers(monkeypatch: pytest.MonkeyPatch) -> None:
    thr = np.random.default_rng(1).uniform(0.0, 1.0, 3000)
    theta, sigma = np.array([50.0, 20.0, 5.0]), np.array([3.0, 3.0, 3.0])
    big = bias_fit.benchmark_r2(thr, theta, sigma, np.random.default_rng(0), 300)
    seen: list[int] = []

    class Spy:
        def __init__(self, rng: np.random.Generator) -> None:
            self.rng = rng

        def standard_normal(self, size: tuple[int, ...]) -> np.ndarray:
            seen.append(int(np.prod(size)))
            return self.rng.standard_normal(size)

    monkeypatch.setattr(bias_fit, "MC_CHUNK_ELEMENTS", 3000 * 3 * 7)  # 7 refits per chunk
    small = bias_fit.benchmark_r2(thr, theta, sigma, Spy(np.random.default_rng(0)), 300)  # type: ignore[arg-type]
    assert max(seen) <= 3000 * 3 * 7 and len(seen) == -(-300 // 7)
    np.testing.assert_allclose(small, big, rtol=1e-12)


def test_attitude_filter_in_row_blocks_gives_the_same_quaternions(monkeypatch: pytest.MonkeyPatch) -> None:
    import magcomp.diagnosis.attitude as attitude

    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.015, 0.025, 500))
    t[200] = t[199]  # a repeated time stamp, and a gap, as real logs have
    t[300:] += 1.0
    gyro = rng.normal(0.0, 0.5, (500, 3))
    down = rng.normal(0.0, 0.1, (500, 3)) + np.array([0.0, 0.0, 1.0])
    q0 = np.array([1.0, 0.0, 0.0, 0.0])
    whole = attitude.propagate_attitude(t, gyro, t, down, q0)
    monkeypatch.setattr(attitude, "_ROW_BLOCK", 7)
    blocks = attitude.propagate_attitude(t, gyro, t, down, q0)
    np.testing.assert_array_equal(blocks, whole)
    assert np.allclose(np.linalg.norm(whole, axis=1), 1.0)
