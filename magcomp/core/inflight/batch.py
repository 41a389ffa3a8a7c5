"""The batch solver of the in-flight problem: the same rows as the recursive estimator
(:class:`~magcomp.core.inflight.estimator.InflightEstimator`), stacked for a whole log and solved at once.

The rows (eqs. (1), (2), (11), (13), :mod:`~magcomp.core.inflight.rows`) with their nuisance windows are
summed per window as Gram matrices of their augmented columns ``[rows | common | z | nuisance]`` (numpy
over all samples), each window's nuisance is eliminated by its Schur complement with the nuisance's prior
at the residual scale, the unknown common to the flight likewise, and the MAP estimate under the same
Gaussian prior is the solution; the residual scale is iterated to its fixed point (the recursive solver
weighs each window at the scale of the moment it closed). No gate: the batch trusts its rows (a caller
cleans them first). Its uncertainty is the white one (no variance inflation, no split check). No I/O.
"""

from __future__ import annotations

import math

import numpy as np

from magcomp.core.inflight.base import (
    F64,
    NUISANCE_PRIOR_RAD_S,
    InflightMode,
    InflightParams,
    InflightSolution,
    identity,
    lapack,
)
from magcomp.core.inflight.solve import GaussianPrior, common_schur, map_estimate
from magcomp.core.inflight.uncertainty import HeadingSigma, SampleStats, build_solution


def _window_starts(windows: F64 | np.ndarray) -> np.ndarray:
    """Where each nuisance window starts in the samples (a new key closes the previous window, as in the
    recursive solver)."""
    w = np.asarray(windows)
    return np.flatnonzero(np.r_[True, w[1:] != w[:-1]])


def batch_solve(
    mode: InflightMode,
    n_motors: int,
    rows: F64,
    z: F64,
    x0: F64,
    nuisance: F64 | None = None,
    windows: F64 | np.ndarray | None = None,
    common: F64 | None = None,
    p: InflightParams | None = None,
    prior_sd: float | F64 = NUISANCE_PRIOR_RAD_S,
    field_ned_mgauss: F64 | None = None,
    warm: tuple[F64, F64] | None = None,
    rounds: int = 4,
) -> InflightSolution:
    """The MAP estimate of ``N`` samples' rows (N, 3, n), right-hand sides (N, 3) and collective regressors
    ``x0`` (N,: delta^2), with optional nuisance columns (N, 3, k) held constant over each run of equal
    ``windows`` keys (N,) and the column of the unknown common to the flight (N, 3). ``prior_sd``: the
    nuisance's prior standard deviation (one value or k); ``field_ned_mgauss``: the Earth field of the
    heading uncertainty (default: the recursive estimator's, 500 mgauss at 60 deg of inclination);
    ``rounds``: iterations of the residual scale at which the windows' nuisance priors are weighed."""
    p = p or InflightParams()
    prior = GaussianPrior(mode, n_motors, p, warm)
    n = prior.mean.shape[0]
    n_s = rows.shape[0]
    if nuisance is None:
        nuisance = np.zeros((n_s, 3, 0))
        windows = np.zeros(n_s)
    assert windows is not None
    k = nuisance.shape[2]
    c = np.zeros((n_s, 3)) if common is None else np.asarray(common, dtype=np.float64)
    aug = np.concatenate((rows, c[:, :, None], z[:, :, None], nuisance), axis=2)
    gram = np.add.reduceat(np.einsum("nia,nib->nab", aug, aug), _window_starts(windows), axis=0)
    n_win = gram.shape[0] if k > 0 else 0
    sd = np.broadcast_to(np.asarray(prior_sd, dtype=np.float64), (k,))
    n_common = 1 if float(np.einsum("ni,ni->", c, c)) > 0.0 else 0
    n_dof = 3 * n_s - n - k * n_win - n_common
    theta = prior.mean.copy()
    s2 = max(p.noise_floor_mgauss, 10.0) ** 2
    cho = None
    for _ in range(max(1, rounds)):
        tot = _eliminated(gram, n, math.sqrt(s2), sd)
        pp, pc, bp = tot[:n, :n], tot[:n, n], tot[:n, n + 1]
        info, rhs, zz = common_schur(
            pp, pc, float(tot[n, n]), bp, float(tot[n, n + 1]), float(tot[n + 1, n + 1])
        )
        # the noise scale weighs data against the prior, and is the residual at the estimate
        for _ in range(2):
            s2 = _sigma2(info, rhs, zz, theta, n_s, n_dof, p.noise_floor_mgauss)
            got = map_estimate(info, rhs, s2, prior)
            if got is None:
                raise ValueError("in-flight batch estimate is singular")
            cho, theta = got
        s2 = _sigma2(info, rhs, zz, theta, n_s, n_dof, p.noise_floor_mgauss)
    assert cho is not None
    cov, fail = lapack().dpotrs(cho, identity(n))  # the posterior covariance from its Cholesky factor
    if fail != 0:
        raise ValueError("in-flight batch estimate is singular")
    stats = SampleStats()
    for v in np.asarray(x0, dtype=np.float64).tolist():
        stats.add(v)
    h_ned = (
        500.0 * np.array([0.5, 0.0, math.sqrt(0.75)])
        if field_ned_mgauss is None
        else np.asarray(field_ned_mgauss, dtype=np.float64)
    )
    grads = HeadingSigma(mode, prior.k).grads(h_ned, n, stats)
    return build_solution(mode, prior.k, theta, cov, s2, 1.0, grads, n_s)


def _eliminated(gram: F64, n: int, s_ref: float, sd: F64) -> F64:
    """The windows' Gram matrices (W, m, m) with each window's nuisance eliminated (Schur complement, its
    prior ``diag((s_ref / sd)^2)`` at unit weight), summed: (n + 2, n + 2) over [parameters, common, z]."""
    k = gram.shape[1] - n - 2
    if k == 0:
        return np.asarray(gram.sum(axis=0), dtype=np.float64)
    hee = gram[:, n + 2 :, n + 2 :] + np.diag((s_ref / sd) ** 2)
    x = np.linalg.solve(hee, gram[:, n + 2 :, : n + 2])
    sc = gram[:, : n + 2, : n + 2] - np.einsum("wka,wkb->wab", gram[:, n + 2 :, : n + 2], x)
    return np.asarray(sc.sum(axis=0), dtype=np.float64)


def _sigma2(info: F64, rhs: F64, zz: float, p: F64, n_s: int, n_dof: int, floor: float) -> float:
    """The residual variance per component at ``p`` (floored; as the recursive solver's)."""
    if n_s < 10 or n_dof < 10:
        return max(floor, 10.0) ** 2
    rss = zz - 2.0 * float(p @ rhs) + float(p @ info @ p)
    return max(floor, math.sqrt(max(rss, 0.0) / n_dof)) ** 2
