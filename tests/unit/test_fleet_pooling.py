"""Partial pooling of a vehicle's per-flight estimates (magcomp/core/pooling.py): what one flight gives back,
the strength a flight borrows from agreeing siblings (and does not from scattered ones), the shared
systematic error, and the simultaneous band's coverage on seeded segments."""

from __future__ import annotations

import numpy as np
import pytest

from magcomp.core.pooling import family_level, pooled_track


def test_one_flight_gives_back_its_own_interval() -> None:
    t = pooled_track([[10.0, -5.0, 0.0]], [[4.0, 2.0, 1.0]], [], 0.95)
    assert t.mean[0] == pytest.approx([10.0, -5.0, 0.0], abs=1e-9)
    assert (t.upper[0] - t.mean[0]) == pytest.approx(1.959964 * np.array([4.0, 2.0, 1.0]), rel=1e-3)
    assert (t.mean[0] - t.lower[0]) == pytest.approx(1.959964 * np.array([4.0, 2.0, 1.0]), rel=1e-3)


def test_a_poorly_determined_flight_borrows_strength_from_agreeing_siblings() -> None:
    """Twelve flights of one theta, one of them poorly excited (sigma 40 instead of 8): its pooled 95 %
    interval is less than half its own and still holds the truth."""
    rng = np.random.default_rng(3)
    s = np.full(12, 8.0)
    s[5] = 40.0
    y = 50.0 + s * rng.standard_normal(12)
    t = pooled_track(y[:, None], s[:, None], [], 0.95)
    own = 1.959964 * 40.0
    assert (t.upper[5, 0] - t.lower[5, 0]) / 2.0 < 0.5 * own
    assert t.lower[5, 0] <= 50.0 <= t.upper[5, 0]


def test_scattered_flights_keep_their_own_values() -> None:
    """Flights whose true values differ by far more than their intervals (tau 60, sigma 5): little pooling."""
    rng = np.random.default_rng(4)
    truth = 60.0 * rng.standard_normal(10)
    y = truth + 5.0 * rng.standard_normal(10)
    t = pooled_track(y[:, None], np.full((10, 1), 5.0), [], 0.95)
    assert np.all(np.abs(t.mean[:, 0] - y) < 0.5 * 5.0)
    assert np.all((t.upper[:, 0] - t.lower[:, 0]) / 2.0 > 0.9 * 1.959964 * 5.0)


def test_segments_do_not_share_strength_across_a_change() -> None:
    y = np.r_[np.zeros(6), np.full(6, 100.0)][:, None]
    t = pooled_track(y, np.full((12, 1), 5.0), [6], 0.95)
    assert t.segments == [(0, 6), (6, 12)]
    assert np.all(np.abs(t.mean[:6, 0]) < 1e-6) and np.all(np.abs(t.mean[6:, 0] - 100.0) < 1e-6)


def test_the_shared_systematic_error_widens_and_does_not_move() -> None:
    rng = np.random.default_rng(5)
    y = np.array([30.0, 40.0, 0.0]) + 6.0 * rng.standard_normal((8, 3))
    s = np.full((8, 3), 6.0)
    plain = pooled_track(y, s, [], 0.9)
    sys = pooled_track(y, s, [], 0.9, systematic_rel=0.05, systematic_abs=1.0)
    size = float(np.linalg.norm(plain.mean.mean(axis=0)))
    assert sys.mean == pytest.approx(plain.mean, abs=1e-9)
    assert sys.std**2 == pytest.approx(plain.std**2 + (0.05 * size) ** 2 + 1.0, rel=1e-6)
    assert np.all(sys.upper - sys.lower > plain.upper - plain.lower)


@pytest.mark.parametrize("tau_true", [0.0, 8.0])
def test_intervals_hold_at_their_level_on_seeded_segments(tau_true: float) -> None:
    """300 seeded segments of 10 flights (sigma 5-15, the true values scattered by tau): the 95 % intervals
    hold 93-99.5 % of the flights, and at the track's level (95 % for the whole segment, Bonferroni) every
    flight of >= 93 % of the segments."""
    rng = np.random.default_rng(11 if tau_true else 12)
    per_flight, whole = [], []
    for _ in range(300):
        s = rng.uniform(5.0, 15.0, (10, 1))
        truth = 20.0 + tau_true * rng.standard_normal((10, 1))
        y = truth + s * rng.standard_normal((10, 1))
        t = pooled_track(y, s, [], 0.95)
        per_flight += ((t.lower <= truth) & (truth <= t.upper)).ravel().tolist()
        band = pooled_track(y, s, [], family_level(0.95, 10, 1))
        whole.append(bool(np.all((band.lower <= truth) & (truth <= band.upper))))
    assert 0.93 <= float(np.mean(per_flight)) <= 0.995
    assert float(np.mean(whole)) >= 0.93


def test_family_level_is_bonferroni() -> None:
    assert family_level(0.95, 17, 3) == pytest.approx(1.0 - 0.05 / 51)
    with pytest.raises(ValueError, match="level must be in"):
        family_level(1.0, 3, 3)


@pytest.mark.parametrize(
    ("x", "s", "level", "match"),
    [
        ([[1.0, 2.0]], [[1.0]], 0.95, "differ in shape"),
        ([[1.0]], [[0.0]], 0.95, "positive standard deviation"),
        ([[float("nan")]], [[1.0]], 0.95, "finite estimate"),
        ([[1.0]], [[1.0]], 1.5, "level must be in"),
    ],
)
def test_bad_input_is_a_clear_error(
    x: list[list[float]], s: list[list[float]], level: float, match: str
) -> None:
    with pytest.raises(ValueError, match=match):
        pooled_track(x, s, [], level)


def test_a_bias_the_flights_share_needs_the_systematic_term() -> None:
    """200 seeded segments of 12 flights of one theta (|theta| ~ 170 mgauss, sigma 5-12 per axis) whose
    estimates share a bias of 3 % of |theta| per axis (diagnose's, docs/fleet.md): pooled without the
    systematic term the 95 % intervals hold far fewer flights than stated (the pooled width shrinks below
    the bias); with it, at least 93 %."""
    rng = np.random.default_rng(21)
    held: dict[bool, list[bool]] = {False: [], True: []}
    for _ in range(200):
        theta = np.array([100.0, -100.0, 90.0])
        s = rng.uniform(5.0, 12.0, (12, 3))
        bias = 0.03 * float(np.linalg.norm(theta)) * rng.standard_normal(3)
        y = theta + bias + s * rng.standard_normal((12, 3))
        for sys in (False, True):
            t = pooled_track(y, s, [], 0.95, systematic_rel=0.03 if sys else 0.0)
            held[sys] += ((t.lower <= theta) & (theta <= t.upper)).ravel().tolist()
    assert float(np.mean(held[False])) < 0.9
    assert float(np.mean(held[True])) >= 0.93
