"""Offline least-squares fit of the throttle-squared bias model on a stationary sweep, eqs. (11)-(15).

Reference: M. Silic and K. Mohseni, "Correcting Current-Induced Magnetometer Errors on UAVs: An Online
Model-Based Approach", IEEE Sensors J. 20(2), 2020, sec. II-C-1 and Table II.

With the vehicle at rest the field ``u`` is constant, so each axis of eq. (12), ``v = u + delta^2 theta``,
is a straight line in ``delta^2``:  ``v_x = [delta^2  1] [theta_x  u_x]^T``, solved by eq. (14a);
its covariance is eq. (14b) with the noise variance of eq. (15) (``p = 2`` parameters per axis).

Table II also lists, per axis, R^2, an SNR and a Monte-Carlo "benchmark R^2". The paper says "the signal
is assumed to be the coefficient of the bias model"; ``SNR_dB = 20 log10(|theta| / sigma_hat)`` reproduces
its rows (-40.7/5.3 -> 17.7 dB, 17.6/5.4 -> 10.3 dB, -0.8/5.6 -> -16.9 dB; the table prints 10.2 and
-17.0, consistent with rounding of theta and sigma). The benchmark simulates the same regressor with the
fitted theta and Gaussian noise of variance sigma_hat^2, refits, and reports the mean and 2 standard
deviations of R^2 (Table II: "listed with their 2 sigma error bounds").

Symbol table (paper -> code, unit, frame):
    delta_t            -> throttle_01 (n,), 0..1
    v                  -> field_mgauss (n, 3), mgauss, magnetometer frame (calibrated or raw)
    theta, u           -> OfflineFit.theta_mgauss, OfflineFit.u_mgauss (3,), mgauss
    P (eq. 14b)        -> OfflineFit.covariance (3, 2, 2): per axis, order (theta, u)
    sigma_hat (eq. 15) -> OfflineFit.sigma_mgauss (3,)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcomp.errors import MagcompError

F64 = NDArray[np.float64]
N_PARAMS = 2  # p of eq. (15): theta and u per axis


class FitError(MagcompError):
    """The data cannot support the offline fit (too few samples, no throttle variation)."""


@dataclass(frozen=True)
class OfflineFit:
    """Per-axis results of :func:`fit_bias_offline`; every array has one entry per magnetometer axis."""

    theta_mgauss: F64  # (3,) eq. (11) coefficient, mgauss at full throttle
    u_mgauss: F64  # (3,) constant field during the sweep
    covariance: F64  # (3, 2, 2) eq. (14b), order (theta, u)
    theta_std_mgauss: F64  # (3,) sqrt(P_00)
    sigma_mgauss: F64  # (3,) eq. (15)
    r2: F64  # (3,) coefficient of determination
    snr_db: F64  # (3,) 20 log10(|theta| / sigma)
    benchmark_r2_mean: F64  # (3,) Monte-Carlo R^2 mean
    benchmark_r2_two_sd: F64  # (3,) 2 standard deviations of the Monte-Carlo R^2
    residuals_mgauss: F64  # (n, 3) y - X beta
    n: int


class LeastSquares(NamedTuple):
    """What :func:`least_squares` returns (``k`` observation columns, ``p`` parameters)."""

    beta: F64  # (p,) or (p, k), eq. (14a)
    covariance: F64  # (p, p) or (k, p, p), eq. (14b)
    sigma2: F64  # () or (k,), eq. (15)
    residuals: F64  # y - X beta, the shape of y


def least_squares(x: F64, y: F64, eliminated: int = 0, n_obs: int | None = None) -> LeastSquares:
    """The least-squares estimator of ``y = X beta`` and its covariance, eqs. (14a), (14b), with the noise
    variance of eq. (15); ``y`` (n,) or (n, k) (one fit per column, one X). ``eliminated``: parameters
    solved out of ``X`` and ``y`` before the call (they count in eq. (15)'s ``p``). ``n_obs``: the number
    of observations when ``[X y]`` is a compressed form of them with the same normal equations (the R of
    their QR factorisation: the same beta, covariance and sum of squared residuals; the residuals returned
    are then the compressed rows'). The one implementation of these equations: the offline fit on a
    stationary sweep (:func:`fit_bias_offline`) and the batch solve of a whole log
    (:mod:`magcomp.core.observer_batch`) both call it."""
    n, n_params = x.shape
    n = n if n_obs is None else n_obs
    beta, *_ = np.linalg.lstsq(x, y, rcond=None)  # eq. (14a)
    resid = y - x @ beta
    sigma2 = np.sum(resid**2, axis=0) / (n - n_params - eliminated)  # eq. (15)
    xtx_inv = np.linalg.inv(x.T @ x)
    cov = xtx_inv * sigma2 if np.ndim(sigma2) == 0 else xtx_inv[None, :, :] * sigma2[:, None, None]  # (14b)
    return LeastSquares(np.asarray(beta, dtype=np.float64), cov, np.asarray(sigma2, dtype=np.float64), resid)


def design_matrix(throttle_01: F64) -> F64:
    """Regressor of eq. (12) per axis: rows ``[delta^2, 1]``, shape (n, 2)."""
    return np.column_stack([throttle_01**2, np.ones_like(throttle_01)])


class ThetaU(NamedTuple):
    """The two rows of eq. (14a)'s ``beta``."""

    theta_mgauss: F64  # (3,) motor coefficient of eq. (11)
    u_mgauss: F64  # (3,) the throttle-free field of eq. (12)


def unpack_beta(beta: F64) -> ThetaU:
    """``beta`` (2, 3) from eq. (14a) -> (theta (3,), u (3,))."""
    return ThetaU(beta[0].copy(), beta[1].copy())


def snr_db(theta_mgauss: ArrayLike, sigma_mgauss: ArrayLike) -> F64:
    """Table II SNR: the bias-model coefficient over the noise standard deviation, in dB."""
    th = np.abs(np.asarray(theta_mgauss, dtype=float))
    sg = np.asarray(sigma_mgauss, dtype=float)
    with np.errstate(divide="ignore"):
        return 20.0 * np.log10(th / sg)


def _r2(y: F64, resid: F64) -> F64:
    """R^2 along axis -2 (samples): ``1 - SSE / SST``; y, resid (..., n, k)."""
    sse = np.sum(resid**2, axis=-2)
    sst = np.sum((y - y.mean(axis=-2, keepdims=True)) ** 2, axis=-2)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(sst > 0, 1.0 - sse / sst, 0.0)


#: numbers per Monte-Carlo array (each 8 bytes; a few such arrays live at once)
MC_CHUNK_ELEMENTS = 2_000_000


def benchmark_r2(
    throttle_01: F64,
    theta_mgauss: F64,
    sigma_mgauss: F64,
    rng: np.random.Generator,
    n_monte_carlo: int,
    chunk: int = 200,
) -> tuple[F64, F64]:
    """Table II benchmark: R^2 of refits on ``theta delta^2 + N(0, sigma^2)``. Returns (mean, 2 sd) per axis.

    The constant field does not change R^2, so it is left out of the simulated data.
    """
    x = design_matrix(throttle_01)
    q, _ = np.linalg.qr(x)  # fitted values = Q Q^T y, eq. (14a) in projection form
    signal = np.outer(throttle_01**2, theta_mgauss)  # eq. (11), (n, 3)
    values: list[F64] = []
    done = 0
    # refits per chunk bounded by memory too: a 1 h window at 50 Hz is 180k samples, and 200 refits of
    # it held 3.4 GiB (issue 12); the draws, hence the result, do not depend on the chunk size
    chunk = max(1, min(chunk, MC_CHUNK_ELEMENTS // max(1, signal.size)))
    while done < n_monte_carlo:
        m = min(chunk, n_monte_carlo - done)
        y = signal[None] + rng.standard_normal((m, *signal.shape)) * sigma_mgauss
        fitted = np.einsum("ij,mjk->mik", q, np.einsum("ji,mjk->mik", q, y))
        values.append(_r2(y, y - fitted))
        done += m
    r2 = np.concatenate(values, axis=0)
    return r2.mean(axis=0), 2.0 * r2.std(axis=0, ddof=1)


def fit_bias_offline(
    throttle_01: ArrayLike,
    field_mgauss: ArrayLike,
    rng: np.random.Generator | None = None,
    n_monte_carlo: int = 1000,
    min_throttle_span: float = 0.1,
) -> OfflineFit:
    """Least squares of eq. (12) on a stationary throttle sweep, eqs. (14a), (14b), (15) and Table II.

    Parameters
    ----------
    throttle_01 : (n,) throttle command 0..1 at the magnetometer sample times
    field_mgauss : (n, 3) magnetometer field, mgauss (any fixed frame; results are in that frame)
    rng : generator for the Monte-Carlo benchmark; default ``np.random.default_rng(0)``
    n_monte_carlo : number of simulated refits; 0 skips the benchmark (NaN)
    min_throttle_span : refuse when max - min of the throttle is smaller (theta not observable)
    """
    d = np.asarray(throttle_01, dtype=float)
    y = np.asarray(field_mgauss, dtype=float)
    if d.ndim != 1 or y.shape != (d.shape[0], 3):
        raise FitError(f"expected throttle (n,) and field (n, 3), got {d.shape} and {y.shape}")
    ok = np.isfinite(d) & np.all(np.isfinite(y), axis=1)
    d, y = d[ok], y[ok]
    n = int(d.shape[0])
    if n < 10:
        raise FitError(f"only {n} usable samples for the offline fit (need at least 10)")
    span = float(d.max() - d.min())
    if span < min_throttle_span:
        raise FitError(
            f"throttle spans only {span:.2f} (need >= {min_throttle_span}): theta is not observable"
        )
    x = design_matrix(d)  # N_PARAMS columns, p of eq. (15)
    fit = least_squares(x, y)  # eqs. (14a), (14b), (15)
    theta, u = unpack_beta(fit.beta)
    resid, cov = fit.residuals, fit.covariance
    sigma = np.sqrt(fit.sigma2)
    r2 = _r2(y, resid)
    if n_monte_carlo > 0:
        bm_mean, bm_2sd = benchmark_r2(d, theta, sigma, rng or np.random.default_rng(0), n_monte_carlo)
    else:
        bm_mean, bm_2sd = np.full(3, np.nan), np.full(3, np.nan)
    return OfflineFit(
        theta_mgauss=theta,
        u_mgauss=u,
        covariance=cov,
        theta_std_mgauss=np.sqrt(cov[:, 0, 0]),
        sigma_mgauss=sigma,
        r2=r2,
        snr_db=snr_db(theta, sigma),
        benchmark_r2_mean=bm_mean,
        benchmark_r2_two_sd=bm_2sd,
        residuals_mgauss=resid,
        n=n,
    )
