"""theta of eq. (11) from a whole log at once: the batch counterpart of the online estimator's final theta.

Reference: M. Silic and K. Mohseni, "Correcting Current-Induced Magnetometer Errors on UAVs: An Online
Model-Based Approach", IEEE Sensors J., 2019, sec. II-C (equation numbers as in
``/work/shared/paper/silic-mohseni-2019.md``).

The online estimator (:func:`magcomp.core.observer.observer_step`, regression form) solves, one sample at
a time, the exact discrete model of eqs. (13), (16) and (18),

    y_k := v_{k+1} - A_k v_k = (d2_{k+1} I - d2_k A_k) theta = Phi_k theta,

its rows low-passed alike (sec. II-D), by recursive least squares with forgetting. Where the whole log is
known (the first pass of a two-pass replay), the same rows, built here over arrays, are stacked and
solved once by the least squares of eqs. (14a), (14b), (15) (:func:`magcomp.core.bias_fit.least_squares`:
the paper's offline estimator, with the stacked ``Phi_k`` as its regressor instead of ``[delta^2, 1]``).
Every row of the log weighs the same; the recursive solver forgets rows older than ``forget_s``. On the
same samples the two agree within their stated uncertainty (tests/unit/test_observer_batch.py).

What is the same as the online step: the samples (the caller gives those the online estimator would step
on, with its re-anchor and skip markers), the step's rotation
(:func:`magcomp.core.observer.rotation_increment` written over arrays: a quadratic through three gyro
samples plus the coning term), the re-anchor on an
interval outside ``[dt_min_s, dt_max_s]``, the regression low-pass restarting where the online one restarts
(a reset, an interval out of range; kept across a skip) and the excitation Gramian of eq. (21) that decides
which axes are observable. What differs (not in the paper either way): the low-pass of a run of steps uses
the run's median interval (the online filter is re-designed when the interval changes); an axis the log
never excites keeps its prior value (the online step holds it sample by sample); the 1-sigma of eq. (14b)
is scaled for the low-pass's correlation of neighbouring rows (:func:`_noise_factor`).

Symbol table (paper -> code, unit, frame): v -> field_b_mgauss (n, 3), mgauss, body; omega ->
omega_b_rad_s (n, 3), rad/s, body; delta_t -> throttle_01 (n,); Phi_k, y_k -> BatchRows.phi (m, 3, 3),
BatchRows.y_mgauss (m, 3).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcomp.core.bias_fit import least_squares
from magcomp.core.lowpass import lowpass_coefficients
from magcomp.core.observer import ObserverParams

F64 = NDArray[np.float64]

#: what precedes a sample, as the online estimator's input queue marks it (service/theta.py)
START_CONTINUE, START_SKIP, START_RESET = 0, 1, 2


class BatchRows(NamedTuple):
    """The regression rows of a log, one per step of the online estimator, low-passed (sec. II-D)."""

    y_mgauss: F64  # (m, 3)
    phi: F64  # (m, 3, 3)
    dt_s: F64  # (m,) the step's interval
    observable: NDArray[np.bool_]  # (m, 3) per axis, from the windowed Gramian of eq. (21) at the step


class BatchTheta(NamedTuple):
    """What :func:`batch_theta` found."""

    theta_mgauss: F64  # (3,)
    theta_std_mgauss: F64  # (3,) 1-sigma, eq. (14b) scaled by the low-pass's noise factor
    excited_s: F64  # (3,) time each axis was observable
    converged: tuple[bool, bool, bool]
    n_steps: int


def supported(p: ObserverParams) -> bool:
    """The batch solve is the counterpart of the regression form (the default), not of eq. (20)'s gains."""
    return p.scheme == "regression" and p.prefilter in ("regression", "none")


def _rotation_increments(w0: F64, w1: F64, w2: F64, h0: F64, h1: F64, p: ObserverParams) -> F64:
    """:func:`magcomp.core.observer.rotation_increment` over arrays: rows of (omega_{k-1}, omega_k,
    omega_{k+1}) and the intervals before and of the step; (m, 3) rotation vectors, rad."""
    if p.rate_interp == "hold":
        return w2 * h1[:, None]
    quad = np.isfinite(h0) & (h0 > 0.0) if p.rate_interp == "quadratic" else np.zeros(h1.shape, dtype=bool)
    hq = np.where(quad, h0, 1.0)[:, None]
    hn = h1[:, None]
    c = (hq * (w2 - w1) + hn * (w0 - w1)) / (hq * hn * (hq + hn))
    integral_q = w1 * hn + ((w2 - w1) / hn - c * hn) * (hn * hn / 2.0) + c * (hn**3 / 3.0)
    integral_t = 0.5 * hn * (w1 + w2)
    integral = np.where(quad[:, None], integral_q, integral_t)
    return integral + (hn * hn / 12.0) * np.cross(w1, w2)  # two-sample coning term


def _dcms_from_rotvecs(phi: F64) -> F64:
    """:func:`magcomp.core.rotations.dcm_from_rotvec` over rows: (m, 3) -> (m, 3, 3)."""
    ang = np.sqrt(np.einsum("ij,ij->i", phi, phi))
    small = ang < 1e-8
    a = np.where(small, 1.0, ang)
    s1 = np.where(small, 1.0, np.sin(a) / a)
    s2 = np.where(small, 0.5, (1.0 - np.cos(a)) / (a * a))
    k = np.zeros((phi.shape[0], 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -phi[:, 2], phi[:, 1], -phi[:, 0]
    k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = phi[:, 2], -phi[:, 1], phi[:, 0]
    return np.eye(3) + s1[:, None, None] * k + s2[:, None, None] * (k @ k)


#: an impulse response is cut where its samples have fallen below this fraction of its largest
TAIL = 1e-13


def _impulse_response(num: tuple[float, float, float], den: tuple[float, float], n_max: int) -> F64:
    """The impulse response of ``(b0 + b1 z^-1 + b2 z^-2) / (1 + a1 z^-1 + a2 z^-2)``, cut where two samples
    in a row are below ``TAIL`` of its peak (or at ``n_max``)."""
    b0, b1, b2 = num
    a1, a2 = den
    h: list[float] = []
    y1 = y2 = 0.0
    peak = 0.0
    for k in range(n_max):
        x = b0 if k == 0 else b1 if k == 1 else b2 if k == 2 else 0.0
        y = x - a1 * y1 - a2 * y2
        h.append(y)
        peak = max(peak, abs(y))
        if k > 2 and abs(y) < TAIL * peak and abs(y1) < TAIL * peak:
            break
        y1, y2 = y, y1
    return np.asarray(h)


def _convolve(x: F64, h: F64) -> F64:
    """The first ``len(x)`` samples of ``x`` (m, k) convolved with ``h`` along the rows (by FFT: the same
    numbers as the recursion to ~1e-14 of their size)."""
    m = x.shape[0]
    n = 1 << max(1, (m + h.size - 1 - 1).bit_length())
    fx = np.fft.rfft(x, n=n, axis=0)
    fh = np.fft.rfft(h, n=n)
    return np.fft.irfft(fx * fh[:, None], n=n, axis=0)[:m]


def _lowpass_runs(regs: F64, dt: F64, restart: NDArray[np.bool_], p: ObserverParams) -> F64:
    """The regression low-pass (sec. II-D) over each run of steps between restarts, started at rest on the
    run's first row (as :func:`magcomp.core.lowpass.biquad_step` starts: the run minus its first row,
    filtered from zero, plus the first row)."""
    if p.prefilter == "none" or regs.shape[0] == 0:
        return regs
    out = np.empty_like(regs)
    starts = np.flatnonzero(restart).tolist()
    if not starts or starts[0] != 0:
        starts.insert(0, 0)
    memo: dict[float, F64] = {}
    for a, b in zip(starts, [*starts[1:], regs.shape[0]], strict=True):
        dt_run = float(np.median(dt[a:b]))
        h = memo.get(dt_run)
        if h is None:
            c = lowpass_coefficients(p.lowpass, dt_run)
            h = memo[dt_run] = _impulse_response((c.b0, c.b1, c.b2), (c.a1, c.a2), 1 << 16)
        x0 = regs[a]
        out[a:b] = _convolve(regs[a:b] - x0, h[: b - a]) + x0
    return out


def _observable(phi: F64, dt: F64, p: ObserverParams) -> NDArray[np.bool_]:
    """Per step and axis: the exponentially windowed Gramian of ``Phi^T Phi / dt`` (eq. (21), window
    ``excitation_window_s``, from zero at the log's start) gives the axis at least
    ``excitation_min_rad2_s2`` of information, the other axes marginalised
    (:func:`magcomp.core.observer.excitation`'s rule)."""
    q = np.einsum("mki,mkj->mij", phi, phi) / dt[:, None, None]
    lam = math.exp(-float(np.median(dt)) / p.excitation_window_s)
    n_tail = min(dt.size, int(math.log(TAIL) / math.log(lam)) + 1)
    h = np.power(lam, np.arange(n_tail), dtype=np.float64)
    filt = _convolve(np.concatenate([q.reshape(-1, 9), dt[:, None]], axis=1), h)
    g = filt[:, :9].reshape(-1, 3, 3) / filt[:, 9][:, None, None]
    tr = np.trace(g, axis1=1, axis2=2)
    g = g + (1e-9 * np.maximum(tr, 1e-12))[:, None, None] * np.eye(3)
    det = np.linalg.det(g)
    cof = np.stack([g[:, 1, 1] * g[:, 2, 2] - g[:, 1, 2] * g[:, 2, 1],
                    g[:, 0, 0] * g[:, 2, 2] - g[:, 0, 2] * g[:, 2, 0],
                    g[:, 0, 0] * g[:, 1, 1] - g[:, 0, 1] * g[:, 1, 0]], axis=1)  # fmt: skip
    with np.errstate(divide="ignore", invalid="ignore"):
        info = det[:, None] / cof  # 1 / [G^-1]_ii
    return np.asarray(info >= p.excitation_min_rad2_s2)


def regression_rows(
    t_s: ArrayLike, omega_b_rad_s: ArrayLike, field_b_mgauss: ArrayLike, throttle_01: ArrayLike,
    start: ArrayLike, p: ObserverParams,
) -> BatchRows:
    """The rows ``y_k = Phi_k theta`` the online estimator would step on, over a whole log.

    Parameters
    ----------
    t_s : (n,) sample times, s, increasing
    omega_b_rad_s : (n, 3) body rate at each sample, rad/s, body
    field_b_mgauss : (n, 3) calibrated field (eq. (2)), mgauss, body
    throttle_01 : (n,) throttle at each sample's own time, 0..1
    start : (n,) START_CONTINUE, or START_RESET / START_SKIP: the sample re-anchors the model after a reset
        of the filters (the low-pass restarts) or after samples missing (the low-pass keeps its memory)
    p : the online estimator's parameters (intervals, rotation interpolation, variant, low-pass, window)
    """
    t = np.asarray(t_s, dtype=float)
    w = np.asarray(omega_b_rad_s, dtype=float).reshape(-1, 3)
    v = np.asarray(field_b_mgauss, dtype=float).reshape(-1, 3)
    thr = np.asarray(throttle_01, dtype=float)
    code = np.asarray(start, dtype=np.int64).copy()
    ok = np.isfinite(t) & np.isfinite(thr) & np.isfinite(w).all(axis=1) & np.isfinite(v).all(axis=1)
    if not ok.all():  # a non-finite sample is not stepped on: the next one re-anchors (keeping its marks)
        rank = np.cumsum(ok)  # a dropped sample's marks go to the kept one after it
        pend = np.zeros(int(rank[-1]) + 1, dtype=np.int64)
        np.maximum.at(pend, rank[~ok], np.maximum(code[~ok], START_SKIP))
        code = np.maximum(code[ok], pend[:-1])
        t, w, v, thr = t[ok], w[ok], v[ok], thr[ok]
    n = t.size
    d2 = np.clip(thr, 0.0, 1.0) ** 2
    dt = np.full(n, math.nan)
    dt[1:] = np.diff(t)
    step = (code == START_CONTINUE) & (dt >= p.dt_min_s) & (dt <= p.dt_max_s)
    if n:
        step[0] = False
    # the low-pass restarts at an anchor that is not a skip (a reset, an interval out of range, the start)
    restart_at_anchor = ~step & (code != START_SKIP)
    idx = np.flatnonzero(step)
    prev_step = np.zeros(n, dtype=bool)
    prev_step[1:] = step[:-1]
    h0 = np.where(prev_step[idx], dt[idx - 1], math.nan)
    w0 = np.where(prev_step[idx][:, None], w[np.maximum(idx - 2, 0)], w[idx - 1])
    ph = _rotation_increments(w0, w[idx - 1], w[idx], h0, dt[idx], p)
    a = _dcms_from_rotvecs(-ph)  # A_k = dR_k^T
    eye = np.eye(3)
    if p.variant == "delta_dot":  # eq. (16), discrete and exact: d2_{k+1} I - d2_k A_k
        phi = d2[idx][:, None, None] * eye - d2[idx - 1][:, None, None] * a
    else:  # eq. (19): the throttle held at its mean over the step
        phi = (0.5 * (d2[idx] + d2[idx - 1]))[:, None, None] * (eye - a)
    y = v[idx] - np.einsum("mij,mj->mi", a, v[idx - 1])
    # the run of steps that follows a restarting anchor starts the low-pass again
    seg = np.cumsum(restart_at_anchor)[idx]
    restart = np.ones(idx.size, dtype=bool)
    restart[1:] = seg[1:] != seg[:-1]
    regs = _lowpass_runs(np.concatenate([y, phi.reshape(-1, 9)], axis=1), dt[idx], restart, p)
    obs = _observable(phi, dt[idx], p) if idx.size else np.zeros((0, 3), dtype=bool)
    return BatchRows(regs[:, :3], regs[:, 3:].reshape(-1, 3, 3), dt[idx], obs)


def _noise_factor(p: ObserverParams, dt_s: float) -> float:
    """How much the low-pass's correlation of neighbouring rows widens eq. (14b)'s 1-sigma, which assumes
    independent rows: ``sqrt(sum(rho_k))`` over the autocorrelation of the filter's impulse response (the
    variance of a mean of correlated samples, relative to independent ones)."""
    if p.prefilter == "none" or not dt_s > 0.0:
        return 1.0
    c = lowpass_coefficients(p.lowpass, dt_s)
    h = _impulse_response((c.b0, c.b1, c.b2), (c.a1, c.a2), 1 << 16)
    acf = np.correlate(h, h, mode="full")
    return math.sqrt(max(1.0, float(acf.sum() / acf[h.size - 1])))


def batch_theta(rows: BatchRows, p: ObserverParams, theta0_mgauss: ArrayLike | None = None) -> BatchTheta:
    """theta by the least squares of eqs. (14a), (14b), (15) on every row of ``rows``: the stacked
    ``Phi_k`` the regressor, the stacked ``y_k`` the observations. An axis never observable in the log
    keeps ``theta0_mgauss`` (default 0) and is left out of the solve; theta is clipped to
    ``+-theta_max_mgauss``. Converged per axis as the online rule says (excited at least
    ``converge_min_excited_s`` and 1-sigma below ``converge_std_mgauss + converge_rel |theta|``)."""
    theta0 = np.zeros(3) if theta0_mgauss is None else np.asarray(theta0_mgauss, dtype=float).reshape(3)
    m = rows.dt_s.size
    excited = (rows.observable * rows.dt_s[:, None]).sum(axis=0) if m else np.zeros(3)
    free = excited > 0.0
    theta = theta0.copy()
    std = np.full(3, math.inf)
    if m == 0 or not free.any() or 3 * m <= int(free.sum()):
        return BatchTheta(theta, std, excited, (False, False, False), m)
    x = rows.phi[:, :, free].reshape(-1, int(free.sum()))
    y = (rows.y_mgauss - np.einsum("mij,j->mi", rows.phi[:, :, ~free], theta0[~free])).reshape(-1)
    fit = least_squares(x, y)  # eqs. (14a), (14b), (15)
    theta[free] = np.clip(fit.beta, -p.theta_max_mgauss, p.theta_max_mgauss)
    std[free] = np.sqrt(np.diag(fit.covariance)) * _noise_factor(p, float(np.median(rows.dt_s)))
    tol = p.converge_std_mgauss + p.converge_rel * float(np.linalg.norm(theta))
    conv = (excited >= p.converge_min_excited_s) & (std <= tol)
    return BatchTheta(theta, std, excited, (bool(conv[0]), bool(conv[1]), bool(conv[2])), m)
