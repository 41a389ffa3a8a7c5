"""Persistent changes in a per-flight series with intervals (magcomp/core/changes.py)."""

from __future__ import annotations

import numpy as np
import pytest

from magcomp.core.changes import disagree, find_changes, level_after, weighted_level


def _series(
    levels: list[tuple[float, float, float]], sigma: float = 3.0, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = np.array(levels, dtype=float) + rng.normal(0.0, sigma, (len(levels), 3))
    return x, np.full_like(x, sigma)


def test_a_step_that_stays_is_found_at_its_flight() -> None:
    a, b = (-60.0, 25.0, 0.0), (40.0, -20.0, 30.0)
    x, s = _series([a] * 6 + [b] * 5, seed=1)
    changes = find_changes(x, s)
    assert [c.index for c in changes] == [6]
    assert changes[0].confirmed
    np.testing.assert_allclose(changes[0].before.mean, a, atol=10.0)
    np.testing.assert_allclose(changes[0].after.mean, b, atol=10.0)
    lvl = level_after(x, s, changes)
    assert lvl is not None and lvl.n == 5


def test_a_lone_outlier_is_not_a_change() -> None:
    a = (-60.0, 25.0, 0.0)
    x, s = _series([a] * 10, seed=2)
    x[4] += (80.0, 0.0, 0.0)  # one flight far off, the next ones back at the old level
    assert find_changes(x, s) == []


def test_a_change_in_the_last_flight_is_pending_not_confirmed() -> None:
    a, b = (-60.0, 25.0, 0.0), (40.0, -20.0, 30.0)
    x, s = _series([a] * 5 + [b], seed=3)
    changes = find_changes(x, s)
    assert len(changes) == 1 and changes[0].index == 5 and not changes[0].confirmed


def test_two_changes_in_a_row_are_both_found() -> None:
    a, b, c = (0.0, 0.0, 0.0), (100.0, 0.0, 0.0), (100.0, 100.0, 0.0)
    x, s = _series([a] * 4 + [b] * 4 + [c] * 4, seed=4)
    assert [ch.index for ch in find_changes(x, s)] == [4, 8]


@pytest.mark.parametrize("seed", range(5))
def test_noise_alone_flags_nothing(seed: int) -> None:
    x, s = _series([(-60.0, 25.0, 0.0)] * 40, seed=seed)
    assert find_changes(x, s) == []


def test_a_change_inside_the_intervals_is_not_flagged() -> None:
    x, s = _series([(0.0, 0.0, 0.0)] * 5 + [(8.0, 0.0, 0.0)] * 5, sigma=3.0, seed=5)
    s[:] = 10.0  # wide intervals: 8 mgauss is within them
    assert find_changes(x, s) == []


def test_scatter_beyond_the_intervals_widens_the_level() -> None:
    x = np.array([[0.0], [10.0], [0.0], [10.0]])
    s = np.full_like(x, 1.0)
    lvl = weighted_level(x, s)
    assert lvl.mean[0] == pytest.approx(5.0)
    assert lvl.std[0] > 1.0 / np.sqrt(4) * 5  # the Birge ratio (chi2/dof = 33) widened it


def test_disagree_is_about_non_overlapping_intervals() -> None:
    assert not disagree([0.0], [1.0], [3.9], [1.0])
    assert disagree([0.0], [1.0], [4.1], [1.0])


def test_bad_input_is_refused() -> None:
    with pytest.raises(ValueError, match="shape"):
        find_changes(np.zeros((3, 3)), np.ones((3, 2)))
    with pytest.raises(ValueError, match="finite"):
        find_changes(np.zeros((3, 3)), np.array([[1.0, 1.0, np.nan]] * 3))
    assert find_changes(np.zeros((0, 3)), np.zeros((0, 3))) == []
