"""Forward model of one compass driven by the log's own inputs, and its joint least-squares fit.

Measurement model (compass frame, mgauss), eqs. (1), (11), (12) combined::

    v(t) = A h_b(t) + c + sum_j beta_j D_j(t) + noise
    h_b(t) = R_nb(t)^T Rz(-drift (t - t_mid)) m_hat(inc, dec)

Symbol table (paper -> code):
    v (sensor output, eq. (1))        -> field_mgauss (n, 3), compass frame, mgauss
    K (distortion matrix, eq. (1))    -> A = K |u| (3, 3): K times the Earth field strength, mgauss
    b (hard iron, eq. (1))            -> c (3,), mgauss
    u^e / |u| (Earth field direction) -> m_hat: unit NED vector, inclination ``inc``, declination ``dec``
    R = R_b^e (eq. (13))              -> r_nb (n, 3, 3) from :mod:`magcomp.diagnosis.attitude`
    theta (eq. (11))                  -> beta of the "throttle" column, compass frame, mgauss at full throttle
    delta_t^2 (eq. (11))              -> drive column D (see :mod:`magcomp.diagnosis.effects`)

Departures from the paper: (i) the field is not first calibrated with eq. (3) and then fitted with eq. (14);
all of K, b, theta (and extension parameters) are fitted jointly, because the DPI reference "down" would have
to be compass-free anyway and a joint fit lets the calibration not absorb throttle effects; (ii) a heading
drift ``drift`` (rad/s) models the gyro bias about the vertical, which no compass-free sensor observes.

Fitting is variable projection: for given nonlinear parameters (inc, dec, drift, extension values) the model
is linear in (A, c, beta), solved per axis by least squares; :func:`scipy.optimize.least_squares` moves the
few nonlinear ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from magcomp.core.heading import declination_rad
from magcomp.diagnosis.effects import EFFECTS, DriveInputs, ExtensionParams, drive_columns, set_value

F64 = NDArray[np.float64]
B64 = NDArray[np.bool_]


@dataclass(frozen=True)
class CompassData:
    """Everything the forward model needs for one compass, at its own sample times.

    field_mgauss: (n, 3) measured field, compass frame. r_nb: (n, 3, 3) compass-free rotation.
    attitude_source / attitude_note: how r_nb was obtained (see :mod:`magcomp.diagnosis.attitude`).
    """

    mag_index: int
    t_s: F64
    field_mgauss: F64
    r_nb: F64
    drive: DriveInputs
    attitude_source: str
    attitude_note: str
    #: nuisance parameters of the attitude that ended on their bounds, one sentence each (e.g. a gyro bias at
    #: its +-50 mrad/s limit): the data wanted more than the nuisance can physically be
    nuisance_flags: tuple[str, ...] = ()

    @property
    def n(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def throttle_01(self) -> F64:
        """Logged throttle (0..1) at the compass sample times, linearly interpolated from the drive grid."""
        return np.asarray(np.interp(self.t_s, self.drive.grid_t_s, self.drive.throttle_grid), dtype=float)


@dataclass(frozen=True)
class ModelFit:
    """A fitted model of one compass.

    effects: names of the extensions switched on (empty: the paper's model). ext: their values.
    a_mgauss: A (3, 3); c_mgauss: (3,); coefs: (k, 3) bias vector per drive column (``columns`` names them).
    residual_mgauss: (n, 3) measured - predicted on the samples the fit used. rms_mgauss: root mean square
    over samples and the three axes. n_params: fitted parameters (linear + nonlinear). bic: Bayesian
    information criterion of the Gaussian likelihood (lower is better).
    """

    effects: tuple[str, ...]
    ext: ExtensionParams
    inc_rad: float
    dec_rad: float
    drift_rad_s: float
    a_mgauss: F64
    c_mgauss: F64
    coefs: F64
    columns: tuple[str, ...]
    residual_mgauss: F64
    rms_mgauss: float
    n_params: int
    bic: float
    success: bool
    message: str

    @property
    def theta_mgauss(self) -> F64:
        """theta of eq. (11): the bias at full throttle on every motor, compass frame, mgauss."""
        rows = [i for i, c in enumerate(self.columns) if c == "throttle"]
        return np.sum(self.coefs[rows], axis=0) if rows else np.zeros(3)

    @property
    def field_strength_mgauss(self) -> float:
        """Earth-field strength seen through A (geometric mean of its singular values)."""
        sv = np.linalg.svd(self.a_mgauss, compute_uv=False)
        return float(np.prod(np.abs(sv)) ** (1.0 / 3.0))


def _nonlinear_names(effects: tuple[str, ...]) -> list[str]:
    names = ["inc", "dec", "drift"]
    for e in effects:
        p = EFFECTS[e].param
        if p is not None:
            names.append(p)
    return names


def pack(inc: float, dec: float, drift: float, ext: ExtensionParams, effects: tuple[str, ...]) -> F64:
    """Nonlinear parameter vector (inc, dec, drift, then each nonlinear extension in ``effects`` order)."""
    vals = [inc, dec, drift]
    for e in effects:
        p = EFFECTS[e].param
        if p is not None:
            vals.append(float(getattr(ext, p)))
    return np.array(vals)


def unpack(
    z: F64, effects: tuple[str, ...], base: ExtensionParams
) -> tuple[float, float, float, ExtensionParams]:
    """Inverse of :func:`pack`; linear effects are switched on in ``base``."""
    ext = base
    i = 3
    for e in effects:
        p = EFFECTS[e].param
        if p is None:
            ext = replace(ext, temperature=True) if e == "temperature_drift" else replace(ext, per_motor=True)
        else:
            ext = set_value(ext, p, float(z[i]))
            i += 1
    return float(z[0]), float(z[1]), float(z[2]), ext


def _bounds(effects: tuple[str, ...]) -> tuple[F64, F64]:
    lo = [-math.pi / 2, -4 * math.pi, -0.05]
    hi = [math.pi / 2, 4 * math.pi, 0.05]
    for e in effects:
        eff = EFFECTS[e]
        if eff.param is not None:
            lo.append(eff.bounds[0])
            hi.append(eff.bounds[1])
    return np.array(lo), np.array(hi)


def earth_dir_body(data: CompassData, inc: float, dec: float, drift: float) -> F64:
    """h_b (n, 3): unit Earth-field direction in body axes, with the heading drift applied."""
    t_mid = 0.5 * (float(data.t_s[0]) + float(data.t_s[-1]))
    if data.attitude_source == "stationary":
        drift = 0.0  # nothing rotates, nothing drifts: the rotation is constant, not integrated
    psi = dec - drift * (data.t_s - t_mid)
    m_n = np.column_stack(
        [math.cos(inc) * np.cos(psi), math.cos(inc) * np.sin(psi), np.full(data.n, math.sin(inc))]
    )
    return np.einsum("nji,nj->ni", data.r_nb, m_n)  # R_nb^T m_n, eq. (13) read backwards


def design(
    data: CompassData, inc: float, dec: float, drift: float, ext: ExtensionParams
) -> tuple[F64, tuple[str, ...]]:
    """Design matrix [h_b (3), 1, drive columns (k)] of shape (n, 4 + k) and the drive column names."""
    h = earth_dir_body(data, inc, dec, drift)
    cols, names = drive_columns(data.drive, ext)
    return np.column_stack([h, np.ones(data.n), cols]), names


class _DesignParts:
    """:func:`design`'s matrix with its two parts kept from the last call: a finite-difference step of the
    fit moves either the field direction (inc, dec, drift) or one extension, so the other part is the
    same array as before (the same numbers, not computed again). The matrix is one buffer whose parts are
    overwritten in place: valid until the next call."""

    def __init__(self, data: CompassData) -> None:
        self.data = data
        self._x: F64 | None = None
        self._h_key: tuple[float, float, float] | None = None
        self._ext: ExtensionParams | None = None

    def design(self, inc: float, dec: float, drift: float, ext: ExtensionParams) -> F64:
        """``design(data, inc, dec, drift, ext)[0]`` (the buffer: valid until the next call)."""
        x = self._x
        if x is None or self._ext != ext:
            cols = drive_columns(self.data.drive, ext)[0]
            if x is None or x.shape[1] != 4 + cols.shape[1]:
                x = self._x = np.empty((self.data.n, 4 + cols.shape[1]))
                x[:, 3] = 1.0
                self._h_key = None
            x[:, 4:] = cols
            self._ext = ext
        if self._h_key != (inc, dec, drift):
            x[:, 0:3] = earth_dir_body(self.data, inc, dec, drift)
            self._h_key = (inc, dec, drift)
        return x


def _solve(x: F64, v: F64, rows: B64) -> F64:
    beta, *_ = np.linalg.lstsq(x[rows], v[rows], rcond=1e-10)
    return np.asarray(beta)


def fit_model(
    data: CompassData,
    effects: tuple[str, ...] = (),
    start: ModelFit | None = None,
    train: B64 | None = None,
    max_nfev: int = 200,
    init: dict[str, float] | None = None,
) -> ModelFit:
    """Fit the forward model with the extensions ``effects`` on the samples ``train`` (default: all).

    ``start`` warm-starts the nonlinear parameters (its extension values are reused where they apply);
    nonlinear extension parameters not in ``start`` are started from the best point of their grid.
    The returned residual covers *all* samples (prediction outside ``train``); rms/bic use ``train`` only.
    """
    rows = np.ones(data.n, dtype=bool) if train is None else train
    if start is None:
        start = initial_fit(data, rows)
    ext0 = ExtensionParams()
    seeded = set(start.effects)
    for e in start.effects:
        p = EFFECTS[e].param
        if p is not None:
            ext0 = set_value(ext0, p, float(getattr(start.ext, p)))
    for e, value in (init or {}).items():
        p = EFFECTS[e].param
        if p is not None:
            ext0 = set_value(ext0, p, float(value))
            seeded.add(e)
    # the training rows taken once (all of them: the arrays as they are, no copy per evaluation)
    all_rows = bool(rows.all())
    v_rows = data.field_mgauss if all_rows else data.field_mgauss[rows]
    parts = _DesignParts(data)

    def residual(z: F64) -> F64:
        inc, dec, drift, ext = unpack(z, effects, ext0)
        x = parts.design(inc, dec, drift, ext)
        x_rows = x if all_rows else x[rows]
        beta, *_ = np.linalg.lstsq(x_rows, v_rows, rcond=1e-10)
        return np.asarray((x_rows @ np.asarray(beta) - v_rows).ravel())

    z0 = pack(start.inc_rad, start.dec_rad, start.drift_rad_s, ext0, effects)
    # grid-start each nonlinear extension parameter that the start point does not carry
    for j, name in enumerate(_nonlinear_names(effects)[3:], start=3):
        eff = next(e for e in effects if EFFECTS[e].param == name)
        if eff in seeded:
            continue
        best = (float(np.sum(residual(z0) ** 2)), float(z0[j]))
        for g in EFFECTS[eff].grid:
            z = z0.copy()
            z[j] = g
            cost = float(np.sum(residual(z) ** 2))
            if cost < best[0]:
                best = (cost, g)
        z0[j] = best[1]
    lo, hi = _bounds(effects)
    z0 = np.clip(z0, lo + 1e-9, hi - 1e-9)
    sol = least_squares(residual, z0, bounds=(lo, hi), x_scale="jac", max_nfev=max_nfev, diff_step=1e-4)
    return _finish(data, effects, sol.x, ext0, rows, bool(sol.success), str(sol.message))


def _finish(
    data: CompassData,
    effects: tuple[str, ...],
    z: F64,
    ext0: ExtensionParams,
    rows: B64,
    success: bool,
    message: str,
) -> ModelFit:
    inc, dec, drift, ext = unpack(z, effects, ext0)
    if data.attitude_source == "stationary":
        drift = 0.0
    x, names = design(data, inc, dec, drift, ext)
    beta = _solve(x, data.field_mgauss, rows)
    if np.linalg.det(beta[0:3].T) < 0.0:
        # A and m_hat are defined up to a common sign; keep det(A) > 0 (a proper sensor frame)
        inc, dec = -inc, dec + math.pi
        dec = math.atan2(math.sin(dec), math.cos(dec))
        z = np.array([inc, dec, *z[2:]])
        x, names = design(data, inc, dec, drift, ext)
        beta = _solve(x, data.field_mgauss, rows)
    res = data.field_mgauss - x @ beta
    n_obs = 3 * int(np.count_nonzero(rows))
    rss = float(np.sum(res[rows] ** 2))
    k = 3 * x.shape[1] + len(z)
    bic = n_obs * math.log(max(rss, 1e-300) / n_obs) + k * math.log(n_obs)
    return ModelFit(
        effects=effects,
        ext=ext,
        inc_rad=inc,
        dec_rad=dec,
        drift_rad_s=drift,
        a_mgauss=beta[0:3].T.copy(),
        c_mgauss=beta[3].copy(),
        coefs=beta[4:].copy(),
        columns=names,
        residual_mgauss=res,
        rms_mgauss=math.sqrt(rss / n_obs),
        n_params=k,
        bic=bic,
        success=success,
        message=message,
    )


def initial_fit(data: CompassData, rows: B64 | None = None) -> ModelFit:
    """Start point without any guess: a linear fit on all nine elements of R_nb gives the field direction.

    v_i = sum_jk W_ijk R_kj + c_i + theta_i delta^2 is linear; W_ijk = A_ij m_k has rank one in (j, k) per
    axis, so the dominant right singular vector of the stacked W is m_hat (inc, dec). Then the nonlinear
    fit of the paper's model refines it.
    """
    rows = np.ones(data.n, dtype=bool) if rows is None else rows
    cols, _ = drive_columns(data.drive, ExtensionParams())
    x = np.column_stack([data.r_nb.reshape(data.n, 9), np.ones(data.n), cols])
    beta = _solve(x, data.field_mgauss, rows)
    w = beta[:9].T.reshape(3, 3, 3)  # w[i, k, j] multiplies R[k, j]
    stacked = np.concatenate([w[i].T for i in range(3)], axis=0)  # rows (i, j), columns k
    _, _, vt = np.linalg.svd(stacked)
    m = vt[0]
    if m[2] < 0:  # choose the sign that points the field down in the northern sense of the fit
        m = -m
    inc = math.asin(float(np.clip(m[2], -1.0, 1.0)))
    dec = declination_rad(m)
    z = np.array([inc, dec, 0.0])
    ext = ExtensionParams()

    def residual(zz: F64) -> F64:
        xx, _ = design(data, float(zz[0]), float(zz[1]), float(zz[2]), ext)
        b = _solve(xx, data.field_mgauss, rows)
        return np.asarray((xx[rows] @ b - data.field_mgauss[rows]).ravel())

    best = z
    best_cost = float(np.sum(residual(z) ** 2))
    for cand in (np.array([-inc, dec, 0.0]), np.array([inc, dec + math.pi, 0.0])):
        c = float(np.sum(residual(cand) ** 2))
        if c < best_cost:
            best, best_cost = cand, c
    lo, hi = _bounds(())
    sol = least_squares(
        residual,
        np.clip(best, lo + 1e-9, hi - 1e-9),
        bounds=(lo, hi),
        x_scale="jac",
        diff_step=1e-4,
        max_nfev=200,
    )
    return _finish(data, (), sol.x, ext, rows, bool(sol.success), str(sol.message))
