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
The HAC variance sees only the residual, and a slow column absorbs the slow part of a model error (the
compass-free attitude's): over 20 seeds of that held-out case (5000-5019) the temperature coefficient's error
had sd 1.04 / 0.56 / 0.62 mgauss/degC per axis against a HAC standard error of 0.52 / 0.27 / 0.29 (per-axis
coverage 60-70 %); with the simulator's true attitude the two agree. So the temperature interval, like
theta's, is at least the block jackknife's (:func:`block_jackknife_halfwidth`): per-axis coverage 18 / 20 /
16 of 20 in ``benchmarks/diagnosis_heldout.py --effects temperature_drift --seeds 20``.
Over 40 seeds (5000-5019, 5100-5119) its joint box still held only 34: the errors were 1.2-2.0 times the
jackknife's standard errors too, because the temperature rises through the whole log and takes up the wander
of a random-walk noise (the compass's, the gyro-integrated heading's), which the residual then no longer
shows. It is now also at least the variance under white noise plus a random walk fitted to the residual
(:func:`walk_variance`): 39 of 40, and 20 of 20 on fresh seeds 5200-5219.
The Earth field's inclination, declination and the heading drift are linearised into the design (their
derivative columns per axis), so a column partly collinear with them (a temperature that rises with time,
like a drifting heading) gets the wider interval it has.

Nonlinear extension parameters get a profile-likelihood interval: the parameter is fixed at trial values, the
rest of the model (inc, dec, drift and every linear parameter) refitted, and the interval is where
n_eff log(RSS(value) / RSS(best)) stays below 3.84 (chi^2, one degree of freedom, 95 %), with
n_eff = 3 n / Bartlett's factor of the residual against the change of the prediction that moving the
parameter makes (``selection.bartlett_factor``; formerly the lag-one AR(1) factor of the residual alone).
Other nonlinear extension parameters of the same model are held at their optimum.
Delays (current_lag, time_skew) are widened by half the logged throttle's sampling interval and half the
compass samples' timing range (``DriveInputs.compass_timing_s``). Both are systematic: a delay is read off
the few throttle steps of a log, and where every step falls at one phase of the throttle's and the compass's
sampling, the error is the same at each step and does not average out. Measured (``benchmarks/
diagnosis_heldout.py --rates``, time_skew 0.15 s on onboard logs, seeds 7000-7039): the simulated flight's
throttle steps fall on its 25 Hz SERVO_OUTPUT_RAW samples, which the interpolation places 20 ms early, and a
compass held in a 20-25 Hz RAW_IMU adds its hold's timing error (+5-10 ms on average, the value read at
the loop row before its update); the skew was fitted 13-41 ms high, and with the throttle's half-interval
alone the interval held 0.15 s in 23 of 32 onboard logs.

Vector parameters (theta, the temperature coefficient, the per-motor vectors) are reported twice: per axis at
95 % each (the marginal half-widths every decision uses: identifiability, the fleet's standard deviations,
the flight-pair overlaps) and as a joint 95 % box (``*_joint_halfwidth``): the whole vector is inside the box
in at least 95 % of logs. Three honest per-axis 95 % intervals all hold only 0.95^3 = 86 % of the time when
the axes' errors are independent, so "every axis inside" read off the marginal ones overstates the
confidence. The joint box is Bonferroni's (Dunn 1961, "Multiple comparisons among means", JASA 56:52-64):
each of the k coordinates at 1 - 0.05/k (two-sided: the 1 - 0.025/k quantile; z 2.39 instead of 1.96 for
k = 3), by Boole's inequality P(any outside) <= sum of the k per-axis 0.05/k, whatever the correlation
between the axes. It needs only the per-axis variances this module estimates (HAC and block jackknife);
the alternative, the chi-square ellipsoid projected on the axes (sqrt(chi2_3(0.95)) = 2.80 standard
errors per axis), needs the cross-axis covariance that neither estimate gives and its box holds about 99 %
for independent axes, so it is both harder and wider; for independent axes Bonferroni's box holds 95.1 %.
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


def box_quantile(axes: int = 1, dof: int | None = None) -> float:
    """Two-sided quantile of a 95 % box over ``axes`` coordinates (Bonferroni, module docstring): the normal
    (``dof`` None) or Student-t quantile at 1 - 0.025 / axes; 1.96 for one axis."""
    from scipy.stats import norm
    from scipy.stats import t as student_t

    q = 1.0 - 0.025 / max(int(axes), 1)
    if dof is None:
        return Z_95 if axes <= 1 else float(norm.ppf(q))
    return float(student_t.ppf(q, dof))


def column_halfwidth(
    data: CompassData, fit: ModelFit, weights: dict[str, float], blocks: bool = False, axes: int = 1
) -> F64:
    """95 % half-width (3,) of sum_c weights[c] * beta_c (drive columns by name), per axis, with the
    residual's autocorrelation and the Earth field's direction and heading drift free (module docstring);
    ``blocks``: at least the delete-one-block jackknife half-width (:func:`block_jackknife_halfwidth`);
    ``axes``: the number of coordinates of the 95 % box it is one side of (3: a joint box for a vector,
    Bonferroni; 1: per axis)."""
    return column_halfwidths(data, fit, weights, blocks, (axes,))[0]


def column_halfwidths(
    data: CompassData,
    fit: ModelFit,
    weights: dict[str, float],
    blocks: bool,
    axes: tuple[int, ...],
    walk: bool = False,
) -> list[F64]:
    """:func:`column_halfwidth` for each box size in ``axes`` from one variance computation; ``walk``: the
    variance at least the one under a random walk plus white noise fitted to the residual
    (:func:`walk_variance`), for a column as slow as the log (the temperature's)."""
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
    jk = np.zeros(3)
    jk_dof = 1
    for a in range(3):
        jac = np.column_stack([d @ fit.a_mgauss[a] for d in dh])
        xa = np.column_stack([x, jac])
        z = xa @ (np.linalg.pinv(xa.T @ xa) @ w)  # influence vector: w^T beta = z^T v
        var[a] = hac_variance(fit.residual_mgauss[:, a : a + 1], z)[0]
        if walk:
            var[a] = max(var[a], walk_variance(data.t_s, fit.residual_mgauss[:, a], xa, z))
        if blocks:
            jk[a], jk_dof = block_jackknife_se(data.t_s, xa, fit.residual_mgauss[:, a], w)
    var *= n / max(n - p - 3, 1)
    sd = np.sqrt(np.maximum(var, 0.0))
    return [np.maximum(box_quantile(k) * sd, box_quantile(k, jk_dof) * jk) for k in axes]


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


def walk_variance(t_s: F64, residual: F64, x: F64, z: F64) -> float:
    """Variance of z^T v when v's noise is white plus a random walk, the walk's share fitted to the residual
    by restricted maximum likelihood on time bins (the walk is what a slow column hides from the HAC).

    Why: a column as slow as the log (a temperature that rises through the flight) takes up the slow part of
    the noise, so the residual no longer shows it, and the HAC variance (lags to n/4, the residual's own
    autocovariance) then misses the long-range covariance of a noise that wanders: the compass's own random
    walk and above all the forward model's heading, a gyro integral whose white rate noise is an angle random
    walk. Measured on the held-out temperature case (``benchmarks/diagnosis_heldout.py``, 40 seeds): the
    coefficient's errors were 2.3-2.8 times their HAC standard errors (1.9-2.7 with the simulator's rotation),
    the block jackknife's 1.2-2.0; under this model 1.0-1.6 (docs/diagnosis.md, helper diag8).

    The model: per bin b (:data:`WALK_BIN_S` long, at most :data:`WALK_MAX_BINS` bins) the mean noise has
    covariance s2 (diag(1 / count_b) + lam min(t_b, t_b')), t from the log's start. The restricted likelihood
    (REML, Patterson and Thompson 1971) of the binned residual against the binned design ``x`` (the same for
    the binned data, whatever the fitted coefficients) is maximised over lam (a grid, then Brent's method)
    with s2 profiled out; the variance is then Z^T Cov Z for Z the bin sums of ``z`` (exact when z is
    constant within a bin; a column as slow as this one nearly is). ``x`` (n, p), ``z`` (n,): the design and
    the influence vector of the combination (:func:`column_halfwidths`)."""
    from scipy.optimize import minimize_scalar

    n = t_s.shape[0]
    dur = float(t_s[-1] - t_s[0]) if n > 1 else 0.0
    if dur <= 0.0:
        return 0.0
    width = max(WALK_BIN_S, dur / WALK_MAX_BINS)
    b = np.minimum(((t_s - t_s[0]) / width).astype(int), int(dur / width))
    count = np.bincount(b).astype(float)
    used = count > 0
    idx = (np.cumsum(used) - 1)[b]
    count = count[used]
    nb = count.shape[0]
    t_b = np.bincount(idx, t_s) / count - float(t_s[0])
    r_b = np.bincount(idx, residual) / count
    x_b = np.column_stack([np.bincount(idx, x[:, j]) / count for j in range(x.shape[1])])
    z_b = np.bincount(idx, z)
    u, sv, _ = np.linalg.svd(x_b, full_matrices=False)
    q = u[:, sv > 1e-9 * sv[0]]  # an orthonormal basis of the binned design's columns
    dof = nb - q.shape[1]
    if dof < 5:
        return 0.0
    walk = np.minimum(t_b[:, None], t_b[None, :])
    white = np.diag(1.0 / count)

    def profile(log_lam: float) -> tuple[float, float]:
        """(-2 restricted log-likelihood with s2 profiled out, s2) at lam = exp(log_lam)."""
        cov = white + math.exp(log_lam) * walk
        chol = np.linalg.cholesky(cov)
        cq = np.linalg.solve(chol, q)
        cr = np.linalg.solve(chol, r_b)
        g = np.linalg.cholesky(cq.T @ cq)
        proj = np.linalg.solve(g, cq.T @ cr)
        s2 = max(float(cr @ cr - proj @ proj), 1e-300) / dof
        logdet = 2.0 * float(np.sum(np.log(np.diag(chol))) + np.sum(np.log(np.diag(g))))
        return dof * math.log(s2) + logdet, s2

    # lam (1/s) from a walk a millionth of the white noise per second to one a hundred times it
    grid = np.linspace(math.log(1e-6 / dur), math.log(100.0), 25)
    values = [profile(float(g))[0] for g in grid]
    k = int(np.argmin(values))
    lo, hi = float(grid[max(k - 1, 0)]), float(grid[min(k + 1, grid.shape[0] - 1)])
    best = minimize_scalar(lambda v: profile(v)[0], bounds=(lo, hi), method="bounded") if hi > lo else None
    log_lam = float(best.x) if best is not None and best.fun <= values[k] else float(grid[k])
    s2 = profile(log_lam)[1]
    return float(s2 * (z_b @ ((white + math.exp(log_lam) * walk) @ z_b)))


#: bin length (s) of :func:`walk_variance`: a second averages the fast noise while keeping the walk's shape
WALK_BIN_S = 1.0
#: most bins of :func:`walk_variance` (longer logs get longer bins): a 120 x 120 covariance per likelihood
WALK_MAX_BINS = 120


def block_jackknife_halfwidth(
    t_s: F64, x: F64, residual: F64, w: F64, prior: F64 | None = None, axes: int = 1
) -> float:
    """95 % half-width of w^T beta from the delete-one-block jackknife (:func:`block_jackknife_se`): t(0.975,
    K - 1) times its standard error (``axes`` > 1: one side of a joint 95 % box over that many coordinates,
    t(1 - 0.025 / axes, K - 1), module docstring)."""
    se, dof = block_jackknife_se(t_s, x, residual, w, prior)
    return box_quantile(axes, dof) * se


def block_jackknife_se(
    t_s: F64, x: F64, residual: F64, w: F64, prior: F64 | None = None
) -> tuple[float, int]:
    """Standard error of w^T beta from the delete-one-block jackknife over contiguous blocks of the log, and
    its degrees of freedom K - 1 (0.0 when the log is too short for the blocks).

    The HAC variance above sees the residual; it cannot see a model error that the fit has absorbed into
    theta (a heading that wanders away from its linear drift while the throttle is high, a throttle sampled
    too slowly for the field's steps, a compass frame that is not the model's). Such an error differs from
    one manoeuvre to the next, so refitting without each block of the log moves theta by as much as the
    manoeuvre in that block contributed. The refit is the exact one-step update of the linear least squares
    (the nonlinear parameters, linearised in ``x``, stay free): beta_-k - beta = (X_-k^T X_-k)^+ X_-k^T r_-k.
    Blocks: :data:`JACKKNIFE_BLOCK_S` long (whole manoeuvres: a paper-scenario throttle step, a turn), between
    :data:`JACKKNIFE_MIN_BLOCKS` and :data:`JACKKNIFE_MAX_BLOCKS` of them; the jackknife variance is
    (K - 1) / K sum_k (d_k - mean d)^2.

    ``prior``: the precision P of a Gaussian prior on the coefficients (a maximum a posteriori fit, as
    :mod:`magcomp.diagnosis.partial`'s calibration prior): beta = (X^T X + P)^-1 (X^T v + P beta0), and
    without block k, beta_-k - beta = (X^T X + P - X_k^T X_k)^-1 (X^T r - P (beta - beta0) - X_k^T r_k),
    whose first two terms cancel at the posterior mode; the prior is kept whole in every refit."""
    dur = float(t_s[-1] - t_s[0]) if t_s.shape[0] > 1 else 0.0
    k = int(min(max(round(dur / JACKKNIFE_BLOCK_S), JACKKNIFE_MIN_BLOCKS), JACKKNIFE_MAX_BLOCKS))
    if t_s.shape[0] < 4 * k:
        return 0.0, k - 1
    edges = np.linspace(float(t_s[0]), float(t_s[-1]), k + 1)
    which = np.clip(np.searchsorted(edges, t_s, side="right") - 1, 0, k - 1)
    g = x.T @ x
    xr = x.T @ residual
    if prior is not None:
        g = g + prior
        xr = np.zeros_like(xr)
    d = np.empty(k)
    for b in range(k):
        xb = x[which == b]
        rb = residual[which == b]
        d[b] = float(w @ (np.linalg.pinv(g - xb.T @ xb) @ (xr - xb.T @ rb)))
    var = (k - 1) / k * float(np.sum((d - d.mean()) ** 2))
    return math.sqrt(var), k - 1


#: jackknife block length (s): tens of seconds, so a block holds whole manoeuvres
JACKKNIFE_BLOCK_S = 10.0
#: fewest / most blocks (a jackknife over fewer than 5 has too few degrees of freedom to be stable)
JACKKNIFE_MIN_BLOCKS = 6
JACKKNIFE_MAX_BLOCKS = 20


def theta_halfwidth(data: CompassData, fit: ModelFit, axes: int = 1) -> F64:
    """95 % half-width of theta per axis: the HAC one, at least the block jackknife's (between-manoeuvre
    model error; measured in ``benchmarks/diagnosis_flight_pairs.py``); ``axes`` 3: the joint box."""
    return column_halfwidth(data, fit, {"throttle": 1.0}, blocks=True, axes=axes)


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
        # interval, a systematic error the likelihood cannot see. The compass's samples are placed in time
        # only to within their own timing range (a hold's midpoint, an unheld sample's fitted mean age): a
        # delay is read off the few throttle steps of a log, where the samples' timing errors do not average
        # out, and both errors can have one sign at every step, so the two half-ranges add (module docstring)
        half = 0.5 * (data.drive.throttle_dt_s + data.drive.compass_timing_s)
        lo, hi = max(lo - half, lo_b), min(hi + half, hi_b)
    return lo, hi
