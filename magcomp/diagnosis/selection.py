"""Which extensions to keep: held-out error in blocked time folds plus an information criterion.

An extension is kept only when *both* hold, relative to the model it extends:

- blocked cross-validation: the log is cut into ``n_folds`` contiguous time blocks; each block is predicted
  by a model fitted (nonlinear and linear parameters) on the others. Blocks in time, not random samples,
  because neighbouring samples share slow errors and a random split would reward overfitting. The held-out
  RMS must improve by at least ``min_cv_gain`` (relative).
- BIC (Bayesian information criterion) of the in-sample fit must fall by ``min_delta_bic`` (30). The BIC
  is computed with an effective sample size, 3 n divided by Bartlett's variance factor of the regression of
  the reference residual on what the extension explains (:func:`bartlett_factor`), because a Gaussian
  likelihood over n correlated samples counts the same slow error many times: with coloured sensor noise or
  a slow model error the raw BIC rewards any slowly varying column (measured: 10 % false alarms on varied
  clean simulations, ``benchmarks/diagnosis_false_alarm.py``).

On clean data neither holds for any extension, so the diagnosis reports no finding. Winners are then
combined greedily, strongest first, each kept only if it still passes both tests against the model that
already holds the previous winners, and the combination is refitted jointly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magcomp.diagnosis.model import CompassData, ModelFit, fit_model

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class SelectionParams:
    """n_folds: blocked cross-validation folds; min_cv_gain: relative held-out RMS gain an extension needs;
    min_delta_bic: effective-BIC drop a named cause needs; min_delta_bic_structure: the same for a field step
    of the open search (plus ln(3n) for its searched time); max_nfev: nonlinear fit budget.

    min_delta_bic = 30 is set from the measured false-alarm tail, not tuned for power: with it at 10, 3 of
    100 observable clean varied simulations (``benchmarks/diagnosis_false_alarm.py``, seeds 10000-10059 and
    10100-10159) gave a named finding, at effective delta BIC -15, -19 and -27, and none beyond; 30 is the
    first round margin past that tail. The false-alarm rate is then measured on clean seeds not used for the
    choice (10200 on). The open search keeps 50: a step is not one of the named causes and needs no power
    bought at the price of clean-log structure (at 10, 3 of 100 clean logs showed a step)."""

    n_folds: int = 5
    min_cv_gain: float = 0.01
    min_delta_bic: float = 30.0
    max_nfev: int = 200
    min_delta_bic_structure: float = 50.0


@dataclass(frozen=True)
class Comparison:
    """An extended model against the model it extends.

    cv_rms_*: held-out RMS (mgauss) over all folds; delta_bic: BIC(extended) - BIC(reference) (negative:
    extended better); cv_gain: 1 - cv_rms_extended / cv_rms_reference; significant: passes both tests.
    """

    fit: ModelFit
    reference: ModelFit
    cv_rms_reference: float
    cv_rms_extended: float
    delta_bic: float
    cv_gain: float
    significant: bool


def fold_masks(n: int, n_folds: int) -> list[NDArray[np.bool_]]:
    """Held-out masks of ``n_folds`` contiguous, equal blocks of ``n`` time-ordered samples."""
    edges = np.linspace(0, n, n_folds + 1).round().astype(int)
    out = []
    for i in range(n_folds):
        m = np.zeros(n, dtype=bool)
        m[edges[i] : edges[i + 1]] = True
        out.append(m)
    return out


def cv_rms(data: CompassData, full: ModelFit, p: SelectionParams) -> float:
    """Blocked cross-validated RMS (mgauss) of the model with ``full.effects``, warm-started from ``full``."""
    sq = 0.0
    count = 0
    for held in fold_masks(data.n, p.n_folds):
        f = fit_model(data, full.effects, start=full, train=~held, max_nfev=p.max_nfev // 2)
        r = f.residual_mgauss[held]
        sq += float(np.sum(r**2))
        count += r.size
    return math.sqrt(sq / max(count, 1))


def _acf(x: F64, max_lag: int) -> F64:
    """Autocorrelation (lags 0..max_lag) of each column of x (n, k), by FFT; shape (max_lag + 1, k)."""
    n = x.shape[0]
    xc = x - x.mean(axis=0)
    f = np.fft.rfft(xc, n=2 * n, axis=0)
    ac = np.fft.irfft(f * np.conj(f), axis=0)[: max_lag + 1]
    return np.asarray(ac / np.maximum(ac[0], 1e-300))


def bartlett_factor(residual: F64, explained: F64) -> float:
    """Variance inflation of a regression of ``residual`` on ``explained`` (both (n, 3)) from their
    autocorrelations: 1 + 2 sum_k (1 - k/n) rho_res(k) rho_x(k) (Bartlett's formula for the correlation of two
    autocorrelated series), axes weighted by the explained power, >= 1. A white residual gives 1 whatever the
    regressor; a residual that wanders slowly inflates only slow regressors (temperature, long lags)."""
    n = residual.shape[0]
    if n < 10:
        return 1.0
    max_lag = n // 4
    ry = _acf(residual, max_lag)[1:]
    rx = _acf(explained, max_lag)[1:]
    w = np.var(explained, axis=0)
    if float(np.sum(w)) <= 0.0:
        return 1.0
    taper = (1.0 - np.arange(1, max_lag + 1) / n)[:, None]
    per_axis = 1.0 + 2.0 * np.sum(taper * ry * rx, axis=0)
    return max(1.0, float(np.sum(w * per_axis) / np.sum(w)))


def effective_delta_bic(reference: ModelFit, extended: ModelFit) -> float:
    """BIC(extended) - BIC(reference) with the effective sample size n / (Bartlett factor) of what the
    extension explains against the residual it leaves."""
    n_obs = reference.residual_mgauss.size
    explained = reference.residual_mgauss - extended.residual_mgauss
    # the noise under the extended model is what it leaves: a real effect leaves white noise (factor ~1),
    # a chance match to a slow model error leaves the rest of that error (large factor)
    n_eff = n_obs / bartlett_factor(extended.residual_mgauss, explained)
    ratio = (extended.rms_mgauss / reference.rms_mgauss) ** 2 if reference.rms_mgauss > 0 else 1.0
    return n_eff * math.log(max(ratio, 1e-300)) + (extended.n_params - reference.n_params) * math.log(n_eff)


def compare(
    data: CompassData, reference: ModelFit, extended: ModelFit, cv_reference: float, p: SelectionParams
) -> Comparison:
    cv_ext = cv_rms(data, extended, p)
    gain = 1.0 - cv_ext / cv_reference if cv_reference > 0 else 0.0
    dbic = effective_delta_bic(reference, extended)
    ok = gain >= p.min_cv_gain and dbic <= -p.min_delta_bic
    return Comparison(extended, reference, cv_reference, cv_ext, dbic, gain, ok)
