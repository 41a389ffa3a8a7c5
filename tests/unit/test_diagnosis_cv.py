"""Model selection that holds on unseen data (issue 26): the held-out test measures prediction within the
conditions the model was fitted on, and a significant gain, not a fixed 1 %.

The synthetic compass hovers at throttle 0.46-0.56 for 100 s and climbs once to 0.98 (t = 100-116 s) inside a
120 s log, with the bias growing as throttle^2.8. With one contiguous fifth of the log per fold, the climb is
held out whole: the exponent is refitted on hover throttle alone (where theta x^p and theta' x^2 are the same
curve) and extrapolated to the climb, and the held-out error of the exponent came out 43 % *worse* than the
paper model's while its delta BIC was -110 (the pattern of the issue's held-out logs: -243 and -24 %); the
offset, 0.6 % better held out with delta BIC -107, was refused by the fixed 1 % gain.
"""

from __future__ import annotations

import numpy as np
import pytest

from magcomp.diagnosis.model import CompassData, fit_model
from magcomp.diagnosis.search import diagnose_compass
from magcomp.diagnosis.selection import (
    CVScore,
    SelectionParams,
    correlation_samples,
    cv_score,
    cv_t,
    design_folds,
    folds_for,
)
from tests.synthetic_compass import stationary_compass

TRUE_EXPONENT = 2.8


def hover_with_one_climb(seed: int, exponent: float = TRUE_EXPONENT, noise: float = 3.0) -> CompassData:
    """A stationary compass (no rotation), 20 Hz for 120 s, throttle hovering then one climb."""
    rng = np.random.default_rng(seed)
    dt, n = 0.05, 2400
    t = dt * np.arange(n, dtype=np.float64)
    thr = 0.5 + 0.04 * np.sin(2 * np.pi * t / 9.0) + 0.02 * np.sin(2 * np.pi * t / 2.3)
    climb = (t >= 100.0) & (t < 116.0)
    thr[climb] += 0.42 * np.sin(np.pi * (t[climb] - 100.0) / 16.0)
    theta = np.array([-61.0, 26.4, -12.0])
    a = np.array([[430.0, 10.0, -5.0], [8.0, 410.0, 12.0], [-6.0, 9.0, 445.0]])
    h = np.array([0.5, -0.05, 0.86])
    h /= np.linalg.norm(h)
    field = a @ h + np.array([40.0, -25.0, 60.0]) + np.outer(thr**exponent, theta)
    field = field + rng.normal(0.0, noise, (n, 3))
    return stationary_compass(t, field, dt, thr)


def test_every_fold_trains_on_the_climb() -> None:
    """Interleaved blocks: each fold's training set reaches the climb's throttle, so no fold extrapolates."""
    data = hover_with_one_climb(0)
    base = fit_model(data, ())
    folds = folds_for(data, base, SelectionParams())
    assert folds.blocks_per_fold > 1
    thr = data.throttle_01
    for held, train in zip(folds.held, folds.train, strict=True):
        assert not np.any(held & train)
        assert float(np.max(thr[train])) > 0.9
    assert np.all(np.sum(np.stack(folds.held), axis=0) == 1)  # every sample held out exactly once


def test_buffer_is_one_correlation_time() -> None:
    """An AR(1) residual with a 20-sample correlation time gets a buffer of about that and longer blocks."""
    rng = np.random.default_rng(3)
    e = rng.normal(size=(4000, 3))
    x = np.empty_like(e)
    x[0] = e[0]
    rho = np.exp(-1.0 / 20.0)
    for k in range(1, len(e)):
        x[k] = rho * x[k - 1] + e[k]
    h = correlation_samples(x)
    assert 14 <= h <= 28
    folds = design_folds(4000, 5, h)
    assert folds.buffer_samples == h
    block = 4000 / (5 * folds.blocks_per_fold)
    assert block >= 4 * h


@pytest.mark.parametrize("seed", [0, 1])
def test_exponent_found_when_the_climb_is_the_only_excursion(seed: int) -> None:
    data = hover_with_one_climb(seed)
    c = diagnose_compass(data, "synthetic", open_search=False)
    assert c.findings, f"no finding; rejected: {c.rejected}"
    top = c.findings[0]
    names = top.candidates or [top.effect]
    assert "throttle_exponent" in names, names
    params = top.params if top.effect == "throttle_exponent" else top.candidate_params["throttle_exponent"]
    lo, hi = params["exponent_ci95"]
    assert lo <= TRUE_EXPONENT <= hi, params
    ev = top.evidence
    assert ev["cv_t"] is not None and ev["cv_t"] >= ev["cv_t_critical"]


@pytest.mark.parametrize("seed", [10, 11, 12])
def test_no_held_out_significance_without_the_effect(seed: int) -> None:
    """eq. (11) exact (exponent 2): the exponent's held-out statistic stays below its 1.96 critical value."""
    data = hover_with_one_climb(seed, exponent=2.0)
    p = SelectionParams()
    base = fit_model(data, ())
    ext = fit_model(data, ("throttle_exponent",), start=base)
    folds = folds_for(data, base, p)
    t = cv_t(cv_score(data, base, p, folds), cv_score(data, ext, p, folds))
    assert t < 1.96


def test_cv_t_sign_and_degenerate_inputs() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(size=500) ** 2 + 1.0
    ok = np.ones(500, dtype=bool)
    better = CVScore(1.0, 0.5 * a, ok)
    worse = CVScore(1.0, a, ok)
    assert cv_t(worse, better) > 10.0
    assert cv_t(better, worse) < -10.0
    assert cv_t(worse, worse) == 0.0
    assert cv_t(worse, CVScore(1.0, a[:100], ok[:100])) == 0.0
