"""95 % intervals on the fitted parameters.

Linear parameters (theta, the temperature coefficient, the per-motor vectors, A, c) are exactly linear given
the nonlinear ones (inc, dec, drift, extension values), so their profile likelihood is the Gaussian one:
half-width 1.96 sqrt(diag((X^T X)^-1)) sigma per axis. The residual of a forward model is not white (slow
model errors, sensor low-pass filters), so sigma^2 is inflated by the AR(1) factor (1 + rho) / (1 - rho),
rho the lag-one autocorrelation of the residual: the variance of a mean of n AR(1) samples is that factor
times the white-noise one. Departure: the uncertainty of inc/dec/drift is not propagated into the linear
parameters.

Nonlinear extension parameters get a profile-likelihood interval: the parameter is fixed at trial values, the
rest of the model (inc, dec, drift and every linear parameter) refitted, and the interval is where
n_eff log(RSS(value) / RSS(best)) stays below 3.84 (chi^2, one degree of freedom, 95 %), with
n_eff = 3 n / inflation. Other nonlinear extension parameters of the same model are held at their optimum.
Delays (current_lag, time_skew) are widened by half the logged throttle's sampling interval (see the code).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from magcomp.diagnosis.effects import EFFECTS, set_value
from magcomp.diagnosis.model import CompassData, ModelFit, design, fit_model

F64 = NDArray[np.float64]

CHI2_1_95 = 3.841
Z_95 = 1.96


def ar1_inflation(residual_mgauss: F64) -> float:
    """(1 + rho) / (1 - rho) with rho the lag-one autocorrelation of the residual (mean over axes), >= 1."""
    r = residual_mgauss - residual_mgauss.mean(axis=0)
    if r.shape[0] < 3:
        return 1.0
    den = float(np.sum(r**2))
    if den <= 0.0:
        return 1.0
    rho = float(np.sum(r[1:] * r[:-1])) / den
    rho = min(max(rho, 0.0), 0.99)
    return (1.0 + rho) / (1.0 - rho)


def linear_halfwidths(data: CompassData, fit: ModelFit) -> tuple[F64, F64]:
    """(cov_unscaled (p, p), sigma2 (3,)): (X^T X)^-1 of the design and the inflated noise variance per axis.

    Rows of the design: 3 Earth-direction columns, the constant, then ``fit.columns``.
    """
    x, _ = design(data, fit.inc_rad, fit.dec_rad, fit.drift_rad_s, fit.ext)
    n, p = x.shape
    cov = np.asarray(np.linalg.pinv(x.T @ x), dtype=float)
    rss = np.sum(fit.residual_mgauss**2, axis=0)
    sigma2 = np.asarray(rss / max(n - p, 1) * ar1_inflation(fit.residual_mgauss), dtype=float)
    return cov, sigma2


def column_halfwidth(data: CompassData, fit: ModelFit, weights: dict[str, float]) -> F64:
    """95 % half-width (3,) of sum_c weights[c] * beta_c (drive columns by name), per axis."""
    cov, sigma2 = linear_halfwidths(data, fit)
    w = np.zeros(cov.shape[0])
    for name, v in weights.items():
        w[4 + list(fit.columns).index(name)] += v
    var = float(w @ cov @ w) * sigma2
    return np.asarray(Z_95 * np.sqrt(np.maximum(var, 0.0)))


def theta_halfwidth(data: CompassData, fit: ModelFit) -> F64:
    return column_halfwidth(data, fit, {"throttle": 1.0})


def profile_interval(
    data: CompassData, fit: ModelFit, effect: str, max_nfev: int = 60
) -> tuple[float, float] | None:
    """95 % profile-likelihood interval of ``effect``'s nonlinear parameter in ``fit`` (None: linear)."""
    eff = EFFECTS[effect]
    if eff.param is None or effect not in fit.effects:
        return None
    best = float(getattr(fit.ext, eff.param))
    lo_b, hi_b = eff.bounds
    rss0 = float(np.sum(fit.residual_mgauss**2))
    n_eff = 3.0 * data.n / ar1_inflation(fit.residual_mgauss)
    others = tuple(e for e in fit.effects if e != effect)

    def excess(v: float) -> float:
        start = replace(fit, ext=set_value(fit.ext, eff.param or "", v))
        linear_only = tuple(e for e in others if EFFECTS[e].param is None)
        f = fit_model(data, linear_only, start=start, max_nfev=max_nfev)
        rss = float(np.sum(f.residual_mgauss**2))
        return n_eff * math.log(max(rss, 1e-300) / max(rss0, 1e-300)) - CHI2_1_95

    span = max(abs(best) * 0.05, 0.01 * (hi_b - lo_b))

    def edge(direction: float) -> float:
        inside, step = best, span
        limit = hi_b if direction > 0 else lo_b
        for _ in range(12):
            trial = min(max(best + direction * step, lo_b), hi_b)
            if excess(trial) > 0.0:
                outside = trial
                break
            inside = trial
            if trial == limit:
                return limit
            step *= 2.0
        else:
            return limit
        for _ in range(8):  # bisection between the last inside and the first outside point
            mid = 0.5 * (inside + outside)
            if excess(mid) > 0.0:
                outside = mid
            else:
                inside = mid
        return inside

    lo, hi = edge(-1.0), edge(+1.0)
    if effect in ("current_lag", "time_skew"):
        # the logged throttle is known only at its samples: whether the ESC held each value until the next one
        # (zero-order hold) or ramped (what the model's interpolation assumes) shifts a delay by up to half an
        # interval, a systematic error the likelihood cannot see
        half = 0.5 * data.drive.throttle_dt_s
        lo, hi = max(lo - half, lo_b), min(hi + half, hi_b)
    return lo, hi
