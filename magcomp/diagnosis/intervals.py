"""95 % intervals on the fitted parameters.

Linear parameters (theta, the temperature coefficient, the per-motor vectors, A, c) are exactly linear given
the nonlinear ones (inc, dec, drift, extension values), so their profile likelihood is the Gaussian one:
half-width 1.96 sqrt(diag((X^T X)^-1)) sigma per axis for white noise. The residual of a forward model is
not white (slow model errors, coloured sensor noise, a random walk), and how much that matters depends on
the parameter: a combination w^T beta is z^T v with the influence vector z = X (X^T X)^-1 w, so its variance
is sum_k gamma_res(k) sum_t z_t z_(t+k) (a heteroscedasticity-and-autocorrelation-consistent variance with
the residual's own autocovariance, Bartlett-tapered to n/4 lags, as in ``selection.bartlett_factor``). A fast
regressor (per-motor differences) is barely inflated by slow noise; a slow one (temperature, theta in a
log whose throttle changes slowly) is inflated by as much as the noise wanders over its time scale.
Measured (``benchmarks/diagnosis_heldout.py``, random-walk compass noise): the former AR(1) factor
(1 + rho) / (1 - rho) from the lag-one autocorrelation, with the heading drift held fixed, left a temperature
coefficient 4.1x its half-width from the truth; with both changes below it is 2.0x (not yet covered).
The Earth field's inclination, declination and the heading drift are linearised into the design (their
derivative columns per axis), so a column partly collinear with them (a temperature that rises with time,
like a drifting heading) gets the wider interval it has.

Nonlinear extension parameters get a profile-likelihood interval: the parameter is fixed at trial values, the
rest of the model (inc, dec, drift and every linear parameter) refitted, and the interval is where
n_eff log(RSS(value) / RSS(best)) stays below 3.84 (chi^2, one degree of freedom, 95 %), with
n_eff = 3 n / Bartlett's factor of the residual against the change of the prediction that moving the
parameter makes (``selection.bartlett_factor``; formerly the lag-one AR(1) factor of the residual alone).
Other nonlinear extension parameters of the same model are held at their optimum.
Delays (current_lag, time_skew) are widened by half the logged throttle's sampling interval (see the code).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from magcomp.diagnosis.effects import EFFECTS, set_value
from magcomp.diagnosis.model import CompassData, ModelFit, design, earth_dir_body, fit_model
from magcomp.diagnosis.selection import bartlett_factor

F64 = NDArray[np.float64]

CHI2_1_95 = 3.841
Z_95 = 1.96


def column_halfwidth(data: CompassData, fit: ModelFit, weights: dict[str, float]) -> F64:
    """95 % half-width (3,) of sum_c weights[c] * beta_c (drive columns by name), per axis, with the
    residual's autocorrelation and the Earth field's direction and heading drift free (module docstring)."""
    x, _ = design(data, fit.inc_rad, fit.dec_rad, fit.drift_rad_s, fit.ext)
    n, p = x.shape
    w = np.zeros(p + 3)
    for name, v in weights.items():
        w[4 + list(fit.columns).index(name)] += v
    # d(prediction)/d(inc, dec, drift) per axis: a slow column (temperature) is partly collinear with the
    # heading drift, so holding the drift fixed would understate its interval
    h0 = earth_dir_body(data, fit.inc_rad, fit.dec_rad, fit.drift_rad_s)
    steps = (1e-4, 1e-4, 1e-6)
    dh = []
    for k, eps in enumerate(steps):
        z3 = [fit.inc_rad, fit.dec_rad, fit.drift_rad_s]
        z3[k] += eps
        dh.append((earth_dir_body(data, z3[0], z3[1], z3[2]) - h0) / eps)
    var = np.zeros(3)
    for a in range(3):
        jac = np.column_stack([d @ fit.a_mgauss[a] for d in dh])
        xa = np.column_stack([x, jac])
        z = xa @ (np.linalg.pinv(xa.T @ xa) @ w)  # influence vector: w^T beta = z^T v
        var[a] = hac_variance(fit.residual_mgauss[:, a : a + 1], z)[0]
    var *= n / max(n - p - 3, 1)
    return np.asarray(Z_95 * np.sqrt(np.maximum(var, 0.0)))


def hac_variance(residual: F64, z: F64) -> F64:
    """Variance (3,) of z^T v per axis when v's noise has the autocovariance of ``residual`` (n, 3):
    sum over lags k <= n/4 of (1 - k/n) gamma(k) (2 - [k = 0]) sum_t z_t z_(t+k); at least the white-noise
    variance gamma(0) |z|^2 (a negatively correlated residual is not taken as extra information)."""
    n = residual.shape[0]
    r = residual - residual.mean(axis=0)
    max_lag = max(n // 4, 1)
    m = 2 * n
    fr = np.fft.rfft(r, n=m, axis=0)
    gamma = np.fft.irfft(fr * np.conj(fr), n=m, axis=0)[: max_lag + 1] / n  # (L, 3)
    fz = np.fft.rfft(z, n=m)
    zz = np.fft.irfft(fz * np.conj(fz), n=m)[: max_lag + 1]  # sum_t z_t z_(t+k)
    taper = 1.0 - np.arange(max_lag + 1) / n
    mult = np.full(max_lag + 1, 2.0)
    mult[0] = 1.0
    var = np.sum((taper * mult * zz)[:, None] * gamma, axis=0)
    return np.asarray(np.maximum(var, gamma[0] * zz[0]))


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
    others = tuple(e for e in fit.effects if e != effect)

    def excess(v: float) -> float:
        start = replace(fit, ext=set_value(fit.ext, eff.param or "", v))
        linear_only = tuple(e for e in others if EFFECTS[e].param is None)
        f = fit_model(data, linear_only, start=start, max_nfev=max_nfev)
        rss = float(np.sum(f.residual_mgauss**2))
        # effective sample size against what moving the parameter changes (its own time scale)
        n_eff = 3.0 * data.n / bartlett_factor(fit.residual_mgauss, f.residual_mgauss - fit.residual_mgauss)
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
