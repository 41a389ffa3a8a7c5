"""theta of eq. (11) from a whole log at once: the batch counterpart of the online estimator's final theta.

Reference: M. Silic and K. Mohseni, "Correcting Current-Induced Magnetometer Errors on UAVs: An Online
Model-Based Approach", IEEE Sensors J., 2019, sec. II-C (equation numbers as in
``/work/shared/paper/silic-mohseni-2019.md``).

The paper's offline estimator (sec. II-C-1) holds the vehicle still, so that the field ``u`` of eq. (12),
``v = u + delta^2 theta``, is one constant and each axis is a straight line in ``delta^2`` (eq. (14a)).
Moving, eq. (13) says what stays constant instead: the field in the Earth frame, ``u^e = R (v - delta^2
theta)``. Over a window of samples with the body's rotation from the window's first sample, ``C_i``
(the gyro integrated step by step exactly as the online step does: :func:`magcomp.core.observer.
rotation_increment`, a quadratic through three gyro samples plus the coning term), eq. (12) becomes

    v_i = C_i^T u_w + delta_i^2 theta          (u_w: the window's field at its first sample, body)

linear in theta and in one ``u_w`` per window. ``u_w`` is solved out of each window (its least-squares
value for a given theta is the window's mean of ``C_i (v_i - delta_i^2 theta)``), which leaves rows
``y_i = X_i theta`` with ``X_i = delta_i^2 I - C_i^T mean_w(delta^2 C)`` and ``y_i = v_i - C_i^T
mean_w(C v)``, solved by the least squares of eqs. (14a), (14b), (15) (:func:`magcomp.core.bias_fit.
least_squares`, the windows' fields counted in eq. (15)'s ``p``). Standing still (``C_i = I``) this is
eq. (14a) itself, per axis. The measurement noise enters each row once (not differenced, as in the online
regression ``y_k = v_{k+1} - A_k v_k``), so no low-pass is needed and eq. (14b) states the noise's share
of the uncertainty (not the calibration's: theta is found in the frame of the calibration it is given).

What the batch takes from the online estimator: the samples (those it would step on, with its re-anchor
and skip markers: a window starts at each, as the online regression does not step across them), the
accepted intervals ``[dt_min_s, dt_max_s]``, the throttle clip, and the excitation Gramian of eq. (21)
that decides which axes are observable (on the online step's ``Phi_k``). A window also ends after
``WINDOW_S`` (the gyro's error, integrated, grows with the window). An axis the log never excites keeps
its prior value. On the same samples the two solvers agree within their stated uncertainty
(tests/unit/test_observer_batch.py).

Symbol table (paper -> code, unit, frame): v -> field_b_mgauss (n, 3), mgauss, body; omega ->
omega_b_rad_s (n, 3), rad/s, body; delta_t -> throttle_01 (n,); X_i, y_i -> BatchRows.x (n, 3, 3),
BatchRows.y_mgauss (n, 3); Phi_k -> the online step's regressor, for the Gramian only.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcomp.core.bias_fit import least_squares
from magcomp.core.observer import ObserverParams, rotation_increments
from magcomp.core.rotations import dcms_from_rotvecs

F64 = NDArray[np.float64]

#: what precedes a sample, as the online estimator's input queue marks it (service/theta.py)
START_CONTINUE, START_SKIP, START_RESET = 0, 1, 2
#: longest window of one field u_w, s: the gyro integrated over it (its bias of ~0.01 rad/s at most,
#: uncorrected) stays below ~0.1 rad
WINDOW_S = 10.0
#: the excitation window's exponential weights are cut below this fraction
_TAIL = 1e-12


class BatchRows(NamedTuple):
    """A log's rows of eq. (12) with each window's field solved out, and the excitation at each step."""

    x: F64  # (n, 3, 3) X_i
    y_mgauss: F64  # (n, 3) y_i
    n_windows: int  # windows with two samples or more (three parameters each, in eq. (15)'s p)
    dt_s: F64  # (k,) the online estimator's steps' intervals
    observable: NDArray[np.bool_]  # (k, 3) per step and axis, from the windowed Gramian of eq. (21)
    #: the windowed Gramian's sum and weight after the last step (10,): where the next part of the log goes on
    excitation_carry: F64


class BatchSums(NamedTuple):
    """A log's rows so far, compressed (:func:`batch_add`): the R of the QR factorisation of ``[X y]`` per
    part, stacked (the same normal equations as the rows, so the same least squares), the numbers of
    observations and windows, each axis's excited time and the Gramian's carry."""

    r: F64  # (k, 4)
    n_obs: int
    n_windows: int
    excited_s: F64  # (3,)
    excitation_carry: F64  # (10,)
    n_samples: int


def batch_init() -> BatchSums:
    """Nothing seen yet."""
    return BatchSums(np.zeros((0, 4)), 0, 0, np.zeros(3), np.zeros(10), 0)


def batch_add(sums: BatchSums, rows: BatchRows) -> BatchSums:
    """``sums`` with one more part of the log (the parts in time order): its rows compressed to 4 numbers
    a column, so that a long log is solved in bounded memory."""
    m = np.column_stack([rows.x.reshape(-1, 3), rows.y_mgauss.reshape(-1)])
    r: F64 = np.linalg.qr(m, mode="r") if m.shape[0] > 4 else m  # type: ignore[assignment]
    excited = (rows.observable * rows.dt_s[:, None]).sum(axis=0) if rows.dt_s.size else np.zeros(3)
    n = rows.y_mgauss.shape[0]
    return BatchSums(np.concatenate([sums.r, r]), sums.n_obs + 3 * n, sums.n_windows + rows.n_windows,
                     sums.excited_s + excited, rows.excitation_carry, sums.n_samples + n)  # fmt: skip


class BatchTheta(NamedTuple):
    """What :func:`batch_theta` found."""

    theta_mgauss: F64  # (3,)
    theta_std_mgauss: F64  # (3,) 1-sigma of eq. (14b) (inf: not solved)
    excited_s: F64  # (3,) time each axis was observable
    converged: tuple[bool, bool, bool]
    n_samples: int


def _observable(phi: F64, dt: F64, carry: F64, p: ObserverParams) -> tuple[NDArray[np.bool_], F64]:
    """Per step and axis: the exponentially windowed Gramian of ``Phi^T Phi / dt`` (eq. (21), window
    ``excitation_window_s``, going on from ``carry``: its sum and weight before the first step) gives the
    axis at least ``excitation_min_rad2_s2`` of information, the other axes marginalised
    (:func:`magcomp.core.observer.excitation`'s rule). Returns the flags and the carry after the last step."""
    m = dt.size
    if m == 0:
        return np.zeros((0, 3), dtype=bool), carry
    q = np.einsum("mki,mkj->mij", phi, phi) / dt[:, None, None]
    lam = math.exp(-float(np.median(dt)) / p.excitation_window_s)
    h = np.power(lam, np.arange(min(m, int(math.log(_TAIL) / math.log(lam)) + 1)), dtype=np.float64)
    x = np.concatenate([q.reshape(-1, 9), dt[:, None]], axis=1)
    n_fft = 1 << (m + h.size - 2).bit_length()  # the exponential window by FFT: as the recursion to ~1e-14
    spectrum = np.fft.rfft(x, n=n_fft, axis=0) * np.fft.rfft(h, n=n_fft)[:, None]
    filt = np.fft.irfft(spectrum, n=n_fft, axis=0)[:m]
    filt += np.power(lam, np.arange(1, m + 1), dtype=np.float64)[:, None] * carry
    g = filt[:, :9].reshape(-1, 3, 3) / filt[:, 9][:, None, None]
    tr = np.trace(g, axis1=1, axis2=2)
    g = g + (1e-9 * np.maximum(tr, 1e-12))[:, None, None] * np.eye(3)
    det = np.linalg.det(g)
    cof = np.stack([g[:, 1, 1] * g[:, 2, 2] - g[:, 1, 2] * g[:, 2, 1],
                    g[:, 0, 0] * g[:, 2, 2] - g[:, 0, 2] * g[:, 2, 0],
                    g[:, 0, 0] * g[:, 1, 1] - g[:, 0, 1] * g[:, 1, 0]], axis=1)  # fmt: skip
    with np.errstate(divide="ignore", invalid="ignore"):
        info = det[:, None] / cof  # 1 / [G^-1]_ii
    return np.asarray(info >= p.excitation_min_rad2_s2), filt[-1].copy()


I64 = NDArray[np.int64]


def _finite(t: F64, w: F64, v: F64, thr: F64, code: I64) -> tuple[F64, F64, F64, F64, I64]:
    """The samples with every input finite; the one after a left-out sample re-anchors (with its marks)."""
    ok = np.isfinite(t) & np.isfinite(thr) & np.isfinite(w).all(axis=1) & np.isfinite(v).all(axis=1)
    if ok.all():
        return t, w, v, thr, code
    rank = np.cumsum(ok)  # a left-out sample's marks go to the kept one after it
    pend = np.zeros(int(rank[-1]) + 1, dtype=np.int64)
    np.maximum.at(pend, rank[~ok], np.maximum(code[~ok], START_SKIP))
    return t[ok], w[ok], v[ok], thr[ok], np.maximum(code[ok], pend[:-1])


def _window_rotations(da: F64, first: NDArray[np.bool_]) -> F64:
    """``C_i = C_{i-1} dR_i`` from each window's first sample (``C = I`` there), by a segmented scan:
    (n, 3, 3) from the steps' ``dR_i`` (n, 3, 3; the identity at a window's first sample)."""
    n = da.shape[0]
    starts = np.flatnonzero(first)
    pos = np.arange(n) - starts[np.cumsum(first) - 1]
    c = da.copy()
    s = 1
    while n and s <= int(pos.max()):
        k = np.flatnonzero(pos >= s)
        c[k] = c[k - s] @ c[k]
        s *= 2
    return c


def model_rows(
    t_s: ArrayLike, omega_b_rad_s: ArrayLike, field_b_mgauss: ArrayLike, throttle_01: ArrayLike,
    start: ArrayLike, p: ObserverParams, window_s: float = WINDOW_S, excitation_carry: F64 | None = None,
) -> BatchRows:
    """The rows of eq. (12) over a whole log, each window's field solved out (see the module's doc).

    Parameters
    ----------
    t_s : (n,) sample times, s, increasing
    omega_b_rad_s : (n, 3) body rate at each sample, rad/s, body
    field_b_mgauss : (n, 3) calibrated field (eq. (2)), mgauss, body
    throttle_01 : (n,) throttle at each sample's own time, 0..1
    start : (n,) START_CONTINUE, or START_RESET / START_SKIP: the online estimator re-anchors at the sample
    p : the online estimator's parameters (intervals, rotation interpolation, excitation window)
    window_s : longest window of one field
    excitation_carry : where the excitation Gramian stands before the first sample (the previous part's
        ``excitation_carry``; None: at the log's start)
    """
    t, w, v, thr, code = _finite(
        np.asarray(t_s, dtype=float), np.asarray(omega_b_rad_s, dtype=float).reshape(-1, 3),
        np.asarray(field_b_mgauss, dtype=float).reshape(-1, 3), np.asarray(throttle_01, dtype=float),
        np.asarray(start, dtype=np.int64),
    )
    n = t.size
    d2 = np.clip(thr, 0.0, 1.0) ** 2
    dt = np.full(n, math.nan)
    dt[1:] = np.diff(t)
    step = (code == START_CONTINUE) & (dt >= p.dt_min_s) & (dt <= p.dt_max_s)
    step[:1] = False
    idx = np.flatnonzero(step)
    prev_step = np.zeros(n, dtype=bool)
    prev_step[1:] = step[:-1]
    h0 = np.where(prev_step[idx], dt[idx - 1], math.nan)
    w0 = np.where(prev_step[idx][:, None], w[np.maximum(idx - 2, 0)], w[idx - 1])
    a = dcms_from_rotvecs(-rotation_increments(w0, w[idx - 1], w[idx], h0, dt[idx], p))  # A_k = dR_k^T
    phi = d2[idx][:, None, None] * np.eye(3) - d2[idx - 1][:, None, None] * a  # the online Phi_k, eq. (16)
    carry = np.zeros(10) if excitation_carry is None else excitation_carry
    observable, carry = _observable(phi, dt[idx], carry, p)
    # windows: from each anchor, cut every window_s
    anchor = ~step
    t_anchor = t[np.flatnonzero(anchor)][np.cumsum(anchor) - 1] if n else t
    part = np.floor((t - t_anchor) / window_s)
    first = anchor.copy()
    first[1:] |= part[1:] != part[:-1]
    da = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    da[idx] = np.transpose(a, (0, 2, 1))  # dR_k
    da[first] = np.eye(3)
    c = _window_rotations(da, first)
    # u_w solved out of each window: y_i = v_i - C_i^T mean(C v), X_i = d2_i I - C_i^T mean(d2 C)
    starts = np.flatnonzero(first)
    wid = np.cumsum(first) - 1
    count = np.diff(np.append(starts, n)).astype(float)
    mean_cv = np.add.reduceat(np.einsum("nij,nj->ni", c, v), starts, axis=0) / count[:, None] if n else v
    mean_dc = np.add.reduceat(d2[:, None, None] * c, starts, axis=0) / count[:, None, None] if n else c
    ct = np.transpose(c, (0, 2, 1))
    keep = count[wid] >= 2.0
    y = v - np.einsum("nij,nj->ni", ct, mean_cv[wid])
    x = d2[:, None, None] * np.eye(3) - ct @ mean_dc[wid]
    return BatchRows(x[keep], y[keep], int((count >= 2.0).sum()), dt[idx], observable, carry)


def batch_theta(sums: BatchSums, p: ObserverParams, theta0_mgauss: ArrayLike | None = None) -> BatchTheta:
    """theta by the least squares of eqs. (14a), (14b), (15) on every row gathered in ``sums``. An axis never
    observable in the log keeps ``theta0_mgauss`` (default 0) and is left out of the solve; theta is clipped
    to ``+-theta_max_mgauss``. Converged per axis as the online rule says (excited at least
    ``converge_min_excited_s`` and 1-sigma below ``converge_std_mgauss + converge_rel |theta|``)."""
    theta0 = np.zeros(3) if theta0_mgauss is None else np.asarray(theta0_mgauss, dtype=float).reshape(3)
    excited = sums.excited_s
    free = excited > 0.0
    n_free = int(free.sum())
    theta = theta0.copy()
    std = np.full(3, math.inf)
    if n_free == 0 or sums.n_obs <= n_free + 3 * sums.n_windows:
        return BatchTheta(theta, std, excited, (False, False, False), sums.n_samples)
    xs, ys = sums.r[:, :3], sums.r[:, 3]
    y = ys - xs[:, ~free] @ theta0[~free]  # a column operation: the compressed rows stay exact
    fit = least_squares(xs[:, free], y, eliminated=3 * sums.n_windows, n_obs=sums.n_obs)  # (14a), (14b), (15)
    theta[free] = np.clip(fit.beta, -p.theta_max_mgauss, p.theta_max_mgauss)
    std[free] = np.sqrt(np.diag(fit.covariance))
    tol = p.converge_std_mgauss + p.converge_rel * float(np.linalg.norm(theta))
    conv = (excited >= p.converge_min_excited_s) & (std <= tol)
    return BatchTheta(theta, std, excited, (bool(conv[0]), bool(conv[1]), bool(conv[2])), sums.n_samples)
