"""Which extensions to keep: held-out error in blocked time folds plus an information criterion.

An extension is kept only when *both* hold, relative to the model it extends:

- blocked cross-validation: the log is cut into ``n_folds`` contiguous time blocks; each block is predicted
  by a model fitted (nonlinear and linear parameters) on the others. Blocks in time, not random samples,
  because neighbouring samples share slow errors and a random split would reward overfitting. The held-out
  RMS must improve by at least ``min_cv_gain`` (relative).
- BIC (Bayesian information criterion) of the in-sample fit must fall by at least ``min_delta_bic``.

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
    n_folds: int = 5
    min_cv_gain: float = 0.01
    min_delta_bic: float = 50.0
    max_nfev: int = 200


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


def compare(
    data: CompassData, reference: ModelFit, extended: ModelFit, cv_reference: float, p: SelectionParams
) -> Comparison:
    cv_ext = cv_rms(data, extended, p)
    gain = 1.0 - cv_ext / cv_reference if cv_reference > 0 else 0.0
    dbic = extended.bic - reference.bic
    ok = gain >= p.min_cv_gain and dbic <= -p.min_delta_bic
    return Comparison(extended, reference, cv_reference, cv_ext, dbic, gain, ok)
