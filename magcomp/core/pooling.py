"""Partial pooling of a vehicle's per-flight estimates (its theta, flight after flight): each flight's value
with a posterior interval that borrows strength from the flights that share its level.

Pure statistics: arrays in, results out (no I/O, no clock).

Between two changes (:mod:`magcomp.core.changes`) a vehicle's flights share theta up to a small
flight-to-flight variation. Per component, the normal random-effects model (the hierarchical normal model
of Gelman et al., *Bayesian Data Analysis*, 3rd ed., section 5.4), with one addition:

    y_i = theta_i + b + e_i,   e_i ~ N(0, s_i^2)   (the flight's own estimate and standard deviation)
    theta_i = mu + u_i,        u_i ~ N(0, tau^2)   (the flight's true value around the segment's level)
    b ~ N(0, sigma_sys^2)                          (an error every flight of the segment shares)

with a flat prior on ``mu`` and a uniform prior on ``tau`` over ``[0, tau_max]``. ``tau`` is not fixed at an
estimate: the posterior ``p(tau | y)`` is evaluated on a grid (BDA eq. 5.21) and each flight's posterior is
the mixture over it, so a between-flight variance the data cannot pin down widens the interval instead of
being taken as known. Given ``tau`` (``mu`` integrated out):

    B_i = s_i^2 / (s_i^2 + tau^2)
    E[theta_i | tau, y]   = (1 - B_i) y_i + B_i mu_hat(tau)
    Var[theta_i | tau, y] = (1 - B_i) s_i^2 + B_i^2 V_mu(tau) + sigma_sys^2

where ``mu_hat`` and ``V_mu`` are the precision-weighted mean of the ``y_i`` with weights
``1 / (s_i^2 + tau^2)`` and its variance. ``b`` cannot be told from ``mu`` by the flights themselves (it is
the per-flight estimator's own bias, the same on every flight: averaging removes none of it), so it only
widens. A segment of one flight with ``sigma_sys = 0`` gives back that flight's own estimate and standard
deviation; flights that agree within their intervals pull each other towards their common level and the
random part of the interval narrows roughly as ``1 / sqrt(n)``; flights that scatter more than their
intervals say get a large ``tau`` and keep most of their own value and width.

:func:`pooled_track` gives equal-tailed intervals at a level per flight and component;
:func:`family_level` the level at which a whole track (every flight, every component) holds at once with a
stated probability (Bonferroni). A band from draws of the joint posterior (its flights share ``mu`` and
``b``) was tried: on the simulated fleets of ``benchmarks/fleet_changes.py`` it was no narrower, because
with ten-odd flights per segment ``tau`` stays uncertain enough to keep the flights nearly independent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import ndtr

#: points of the grid over tau (0 included)
TAU_GRID = 161


@dataclass(frozen=True)
class PooledTrack:
    """Per flight and component: the posterior mean, the interval's ends, and the posterior standard
    deviation; per segment and component, the posterior median of tau (the flight-to-flight standard
    deviation of the true value)."""

    mean: NDArray[np.float64]  # (n, m)
    lower: NDArray[np.float64]  # (n, m)
    upper: NDArray[np.float64]  # (n, m)
    std: NDArray[np.float64]  # (n, m)
    level: float  # two-sided, per flight and component
    segments: list[tuple[int, int]]  # [start, end) of each segment
    tau: NDArray[np.float64]  # (segments, m)


def family_level(family: float, n_flights: int, n_components: int) -> float:
    """The two-sided level per flight and component at which ``n_flights x n_components`` intervals hold
    all their truths at once with probability at least ``family`` (Bonferroni)."""
    _check_level(family)
    return 1.0 - (1.0 - family) / max(1, n_flights * n_components)


@dataclass(frozen=True)
class _Mixture:
    """One component of one segment: the posterior of each flight's value as a mixture over the tau grid."""

    weights: NDArray[np.float64]  # (k,) p(tau | y) on the grid
    means: NDArray[np.float64]  # (k, n)
    var: NDArray[np.float64]  # (k, n), sigma_sys^2 not included
    tau_median: float

    @property
    def mean(self) -> NDArray[np.float64]:
        return np.asarray((self.weights[:, None] * self.means).sum(axis=0), dtype=float)

    def std(self, sys_var: float) -> NDArray[np.float64]:
        second = (self.weights[:, None] * (self.var + sys_var + self.means**2)).sum(axis=0)
        return np.asarray(np.sqrt(np.maximum(second - self.mean**2, 0.0)), dtype=float)


def _segment_mixture(y: NDArray[np.float64], s: NDArray[np.float64]) -> _Mixture:
    """The posterior of each flight's value given its segment's flights (module doc), one component."""
    # tau's prior reaches well past anything the flights could show: their spread and their widths
    tau_max = 3.0 * float(np.ptp(y)) + 3.0 * float(s.max())
    taus = np.linspace(0.0, tau_max, TAU_GRID)
    v = s[None, :] ** 2 + taus[:, None] ** 2  # (k, n)
    w = 1.0 / v
    v_mu = 1.0 / w.sum(axis=1)
    mu = v_mu * (w * y[None, :]).sum(axis=1)
    # p(tau | y), BDA eq. 5.21 (flat prior on mu, uniform on tau)
    logp = (
        0.5 * np.log(v_mu)
        - 0.5 * np.log(v).sum(axis=1)
        - 0.5 * (w * (y[None, :] - mu[:, None]) ** 2).sum(axis=1)
    )
    p = np.exp(logp - logp.max())
    p /= p.sum()
    b = s[None, :] ** 2 / v  # the shrinkage towards the segment's level
    means = (1.0 - b) * y[None, :] + b * mu[:, None]
    var = (1.0 - b) * s[None, :] ** 2 + b**2 * v_mu[:, None]
    tau_median = float(taus[min(int(np.searchsorted(np.cumsum(p), 0.5)), taus.size - 1)])
    return _Mixture(p, means, var, tau_median)


def _mixture_quantile(
    q: float, weights: NDArray[np.float64], means: NDArray[np.float64], stds: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The ``q`` quantile of each column's normal mixture: weights (k,), means and stds (k, n)."""
    lo = (means - 9.0 * stds).min(axis=0)
    hi = (means + 9.0 * stds).max(axis=0)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        cdf = (weights[:, None] * ndtr((mid[None, :] - means) / stds)).sum(axis=0)
        below = cdf < q
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    return np.asarray(0.5 * (lo + hi), dtype=float)


def _check_level(level: float) -> None:
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), not {level}")


def _segments(
    x: ArrayLike, s: ArrayLike, starts: list[int], systematic_rel: float, systematic_abs: float
) -> tuple[NDArray[np.float64], list[tuple[int, int]], list[list[_Mixture]], list[float]]:
    """The checked series, its segments, each segment's mixtures (one per
    component) and the variance of the error its flights share."""
    xa = np.atleast_2d(np.asarray(x, dtype=float))
    sa = np.atleast_2d(np.asarray(s, dtype=float))
    if xa.shape != sa.shape:
        raise ValueError(f"estimates {xa.shape} and standard deviations {sa.shape} differ in shape")
    if xa.size == 0:
        raise ValueError("pooling needs at least one flight")
    if not (np.all(np.isfinite(xa)) and np.all(np.isfinite(sa)) and np.all(sa > 0)):
        raise ValueError("every flight needs a finite estimate and a finite, positive standard deviation")
    if systematic_rel < 0 or systematic_abs < 0:
        raise ValueError("systematic errors cannot be negative")
    n, m = xa.shape
    cuts = sorted({0, *(int(i) for i in starts if 0 < int(i) < n)})
    segments = [(a, b) for a, b in zip(cuts, [*cuts[1:], n], strict=True) if b > a]
    mixtures, sys_vars = [], []
    for a, b in segments:
        mix = [_segment_mixture(xa[a:b, j], sa[a:b, j]) for j in range(m)]
        size = float(np.linalg.norm([float(np.mean(c.mean)) for c in mix]))
        mixtures.append(mix)
        sys_vars.append((systematic_rel * size) ** 2 + systematic_abs**2)
    return xa, segments, mixtures, sys_vars


def pooled_track(
    x: ArrayLike,
    s: ArrayLike,
    starts: list[int],
    level: float,
    systematic_rel: float = 0.0,
    systematic_abs: float = 0.0,
) -> PooledTrack:
    """The partially pooled track of a series (rows in flight order, one column per component) whose
    segments begin at ``starts`` (0 is added; e.g. the flights of the changes); each component pooled on
    its own, equal-tailed intervals at ``level`` (two-sided) per flight and component.

    ``systematic_rel``, ``systematic_abs``: the error the flights of a segment share (``b`` in the module
    doc), standard deviation per component ``hypot(systematic_rel * |segment's value|, systematic_abs)``,
    |.| the vector's length."""
    _check_level(level)
    xa, segments, mixtures, sys_vars = _segments(x, s, starts, systematic_rel, systematic_abs)
    n, m = xa.shape
    mean, lower, upper, std = (np.empty((n, m)) for _ in range(4))
    tau = np.zeros((len(segments), m))
    alpha = 1.0 - level
    for k, ((a, b), mix, sys_var) in enumerate(zip(segments, mixtures, sys_vars, strict=True)):
        for j, c in enumerate(mix):
            stds = np.sqrt(np.maximum(c.var + sys_var, 1e-300))
            mean[a:b, j], std[a:b, j] = c.mean, c.std(sys_var)
            lower[a:b, j] = _mixture_quantile(alpha / 2.0, c.weights, c.means, stds)
            upper[a:b, j] = _mixture_quantile(1.0 - alpha / 2.0, c.weights, c.means, stds)
            tau[k, j] = c.tau_median
    return PooledTrack(mean, lower, upper, std, level, segments, tau)
