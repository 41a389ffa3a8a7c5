"""Dot-product-invariance (DPI) magnetometer calibration, eqs. (1)-(3), with an attitude-coverage check.

Reference: M. Silic and K. Mohseni, "Correcting Current-Induced Magnetometer Errors on UAVs: An Online
Model-Based Approach", IEEE Sensors J. 20(2), 2020, sec. II-A (after X. Li and Z. Li, ref. [20]).

Sensor model, eq. (1): ``v = K u + b``; inverse, eq. (2): ``u = L v - d`` with ``L = K^-1``, ``d = K^-1 b``.
With the reference "down" vector ``w`` (unit, body axes: third column of R_e^b from the attitude filter),
eq. (3): ``w^T L v - w^T d = c`` is linear in the 12 unknowns of ``L`` and ``d``.

The constant ``c``: since ``w = R^T e_3`` and ``u = R^T u^e``, ``w . u = e_3 . u^e = Z``, the down component
of the Earth field (WMM, :mod:`magcomp.geomag`). Fixing ``c = Z`` removes both the trivial solution
``L = 0, d = 0`` and the scale ambiguity of the homogeneous form, so ``L`` and ``d`` come out of one linear
least-squares solve, in the units of ``u`` (mgauss). Eq. (3) fails when ``Z = 0`` (``w`` perpendicular to
``u``, the magnetic equator), which the paper notes; we refuse when ``|Z|`` is below 5 % of ``|u|``.

Identifiability: the 12 columns ``[w (x) v, -w]`` are independent only when the down vector visits enough
directions in body axes. Rotating about the vertical alone (yaw only) keeps ``w`` fixed and determines
just ``w^T L``; rotating about one body axis keeps ``w`` in a plane and leaves a row of ``L`` free. We
report that as :class:`CalibrationCoverage` and refuse (``success=False``) when it is too thin.

Optional refinement (departure from the paper): a nonlinear least squares over the same 12 numbers that
also asks ``|L v - d| = F`` (the WMM field norm). It uses information eq. (3) ignores (the horizontal
field) and is less sensitive to errors in the reference vector ``w``. Solved by
:func:`refine_with_norm_lm`, a Levenberg-Marquardt with the analytic Jacobian in numpy (scipy.optimize would
add 0.28 s to the start-up of every replay that calibrates; tests/unit/test_dpi.py checks it against scipy's
``least_squares(method="lm")``).

Symbol table (paper -> code, unit, frame):
    v    -> field_raw_mgauss (n, 3), raw magnetometer, mgauss, sensor frame
    w    -> down_b (n, 3), unit down vector, body FRD
    u    -> L v - d, calibrated field, mgauss, body FRD
    L, d -> CalibrationResult.L (3, 3, dimensionless), CalibrationResult.d (3,) mgauss
    c    -> field_down_mgauss (WMM Z), mgauss
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcomp.errors import MagcompError

F64 = NDArray[np.float64]


class CalibrationError(MagcompError):
    """The data cannot determine the calibration (too little rotation, too few samples, bad inputs)."""


@dataclass(frozen=True)
class DpiParams:
    """Acceptance thresholds of :func:`calibrate_dpi`.

    min_samples: fewer pairs are refused (the paper collects at least 10k).
    min_down_spread: refuse below this :attr:`CalibrationCoverage.down_spread` (1 = isotropic sphere).
    max_condition: refuse when the column-scaled design matrix is worse conditioned than this.
    refine_with_norm: run the |L v - d| = F refinement (needs ``field_norm_mgauss``).
    norm_weight: weight of the norm residuals relative to the eq. (3) residuals in the refinement.
    """

    min_samples: int = 100
    min_down_spread: float = 0.05
    max_condition: float = 200.0
    min_vertical_fraction: float = 0.05
    refine_with_norm: bool = False
    norm_weight: float = 1.0


@dataclass(frozen=True)
class CalibrationCoverage:
    """How well the down vectors cover the sphere.

    down_spread: 3 x smallest eigenvalue of mean(w w^T): 1 for isotropic coverage, 0 when ``w`` stays in
        a plane or at a point.
    octant_fraction: share of the 8 sign-octants of ``w`` holding at least 0.5 % of the samples.
    condition: condition number of the column-scaled eq. (3) design matrix (inf when rank deficient).
    """

    down_spread: float
    octant_fraction: float
    condition: float


@dataclass(frozen=True)
class CalibrationResult:
    """Outcome of :func:`calibrate_dpi`. ``L``/``d`` are NaN when ``success`` is False for lack of data.

    residual_rms_mgauss: RMS of eq. (3) residuals ``w^T (L v - d) - Z``.
    norm_residual_rms_mgauss: RMS of ``|L v - d| - F`` (NaN when no field norm was given).
    """

    L: F64
    d: F64
    residual_rms_mgauss: float
    coverage: CalibrationCoverage
    n: int
    success: bool
    message: str
    norm_residual_rms_mgauss: float = float("nan")
    refined: bool = False
    extra: dict[str, float] = field(default_factory=dict)

    def raise_if_failed(self) -> CalibrationResult:
        if not self.success:
            raise CalibrationError(f"magnetometer calibration refused: {self.message}")
        return self


def apply_calibration(L: ArrayLike, d: ArrayLike, field_raw_mgauss: ArrayLike) -> F64:
    """Eq. (2): ``u = L v - d`` for one vector (3,) or rows (n, 3), mgauss."""
    v = np.asarray(field_raw_mgauss, dtype=float)
    return v @ np.asarray(L, dtype=float).T - np.asarray(d, dtype=float)  # eq. (2)


def pack(L: ArrayLike, d: ArrayLike) -> F64:
    """Parameter vector ``x = [L row-major (9), d (3)]``; inverse of :func:`unpack`."""
    return np.concatenate([np.asarray(L, dtype=float).reshape(9), np.asarray(d, dtype=float).reshape(3)])


class SoftHard(NamedTuple):
    """Soft-iron matrix ``L`` and hard-iron offset ``d`` of eq. (2)."""

    L: F64  # (3, 3)
    d_mgauss: F64  # (3,)


def unpack(x: ArrayLike) -> SoftHard:
    """Parameter vector ``[L row-major (9), d (3)]`` -> (L, d); inverse of :func:`pack`."""
    xv = np.asarray(x, dtype=float)
    return SoftHard(xv[:9].reshape(3, 3).copy(), xv[9:12].copy())


def dpi_design(down_b: F64, field_raw_mgauss: F64) -> F64:
    """Rows ``[w (x) v, -w]`` of eq. (3), so that ``design @ pack(L, d) = w^T L v - w^T d``: (n, 12)."""
    wv = (down_b[:, :, None] * field_raw_mgauss[:, None, :]).reshape(-1, 9)  # eq. (3): w^T L v
    return np.hstack([wv, -down_b])  # eq. (3): - w^T d


def field_error_dilution(down_b: F64, field_raw_mgauss: F64) -> float:
    """How much of one sample's noise a calibration fitted on these pairs carries into the calibrated field:
    the rms over the samples (and the three axes) of the standard error of ``u = L v - d`` (eq. (2)) when
    eq. (3) is solved by least squares on them, divided by the standard deviation of eq. (3)'s residual.

    With the residual's variance s^2, Cov(pack(L, d)) = s^2 (A^T A)^-1 for the eq. (3) design A
    (:func:`dpi_design`), and u's error at a sample v is G dx with G = d u / d pack(L, d) = [I (x) v^T, -I].
    So the ratio is sqrt(mean_t tr(G_t (A^T A)^-1 G_t^T)): a number of the rotation's geometry alone, not of
    the noise, that falls as 1 / sqrt(n) for more pairs of the same rotation and grows when the down vector
    visits few directions (the Earth field's dilution of precision of a calibration). 1: the calibration is
    known as well as one sample is measured. inf when eq. (3) cannot be solved (rank deficient)."""
    w = np.asarray(down_b, dtype=float)
    v = np.asarray(field_raw_mgauss, dtype=float)
    if w.shape[0] < 12:
        return float("inf")
    a = dpi_design(w, v)
    scale = np.linalg.norm(a, axis=0)
    if not np.all(scale > 0.0):
        return float("inf")
    gram = (a / scale).T @ (a / scale)
    if np.linalg.cond(gram) > 1e12:
        return float("inf")
    inv = np.linalg.inv(gram) / np.outer(scale, scale)  # (A^T A)^-1
    # tr(G inv G^T) = sum_i (v^T inv_LiLi v - 2 v^T inv_Li,di + inv_di,di), L row-major: L_i = x[3i:3i+3]
    total = np.zeros(w.shape[0])
    for i in range(3):
        li = slice(3 * i, 3 * i + 3)
        total += np.einsum("tj,jk,tk->t", v, inv[li, li], v) - 2.0 * v @ inv[li, 9 + i] + inv[9 + i, 9 + i]
    return float(np.sqrt(max(float(np.mean(total)), 0.0) / 3.0))


def coverage_of(down_b: F64, design: F64 | None = None) -> CalibrationCoverage:
    """Attitude coverage of a set of unit down vectors (n, 3) and, if given, of the design matrix."""
    n = down_b.shape[0]
    if n == 0:
        return CalibrationCoverage(0.0, 0.0, float("inf"))
    scatter = down_b.T @ down_b / n
    spread = float(3.0 * max(np.linalg.eigvalsh(scatter)[0], 0.0))
    codes = (down_b[:, 0] > 0) * 4 + (down_b[:, 1] > 0) * 2 + (down_b[:, 2] > 0) * 1
    counts = np.bincount(codes.astype(int), minlength=8)
    octants = float(np.mean(counts >= max(1.0, 0.005 * n)))
    cond = float("inf")
    if design is not None:
        scale = np.linalg.norm(design, axis=0)
        if np.all(scale > 0):
            s = np.linalg.svd(design / scale, compute_uv=False)
            cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    return CalibrationCoverage(spread, octants, cond)


def _residuals(x: F64, down_b: F64, v: F64, z_mgauss: float, f_mgauss: float, w_norm: float) -> F64:
    """Residuals of the refinement: eq. (3) rows ``w^T (L v - d) - Z``, then ``w_norm (|L v - d| - F)``."""
    L, d = unpack(x)
    u = apply_calibration(L, d, v)
    r_dot = np.sum(down_b * u, axis=1) - z_mgauss  # eq. (3)
    r_norm = np.linalg.norm(u, axis=1) - f_mgauss  # |u| = F: refinement, not in the paper
    return np.concatenate([r_dot, w_norm * r_norm])


class RefineResult(NamedTuple):
    """Outcome of :func:`refine_with_norm_lm`: the parameters, their residuals, whether it converged."""

    x: F64  # [L row-major (9), d (3)]
    fun: F64  # _residuals at x
    converged: bool
    iterations: int


def refine_with_norm_lm(
    x0: F64,
    down_b: F64,
    field_raw_mgauss: F64,
    z_mgauss: float,
    f_mgauss: float,
    w_norm: float = 1.0,
    max_iter: int = 100,
    ftol: float = 1e-10,
    xtol: float = 1e-10,
) -> RefineResult:
    """Levenberg-Marquardt on eq. (3) plus the field-norm rows ``|L v - d| = F`` (departure from the paper).

    The Jacobian is analytic: the eq. (3) rows are linear in ``x = [L, d]`` with the fixed rows
    ``[w (x) v, -w]`` of :func:`dpi_design`; a norm row's gradient is the same form with ``w`` replaced by
    the unit calibrated field ``n = u / |u|`` (``d|u| / dL_jk = n_j v_k``, ``d|u| / dd_j = -n_j``), times
    ``w_norm``. So ``J^T J = A^T A + w_norm^2 N^T N`` with ``A^T A`` formed once. The step solves
    ``(Js^T Js + lam I) s = -Js^T r`` on the column-scaled Jacobian ``Js = J / D`` (``D``: the running
    maximum of ``J``'s column norms, Marquardt's scaling, as MINPACK's ``lmder`` with ``x_scale="jac"``);
    ``lam = 0`` (a Gauss-Newton step) while steps lower the cost, raised tenfold when one does not.
    Stops when an accepted step lowers the cost by less than ``ftol`` of it, or moves the scaled
    parameters by less than ``xtol`` of their size. Pure numpy: 12 unknowns, a 12 x 12 solve per step.
    """
    w, v = down_b, field_raw_mgauss
    a = dpi_design(w, v)  # eq. (3) rows, constant
    ata = a.T @ a

    def evaluate(x: F64) -> tuple[F64, F64, F64]:
        """Residuals, J^T J, J^T r at x."""
        L, d = unpack(x)
        u = v @ L.T - d  # eq. (2)
        norm_u = np.sqrt(np.einsum("ij,ij->i", u, u))
        r_dot = np.einsum("ij,ij->i", w, u) - z_mgauss  # eq. (3)
        r_norm = w_norm * (norm_u - f_mgauss)
        nb = dpi_design(u / np.maximum(norm_u, 1e-300)[:, None], v)  # d|u|/dx rows
        jtj = ata + (w_norm * w_norm) * (nb.T @ nb)
        jtr = a.T @ r_dot + w_norm * (nb.T @ r_norm)
        return np.concatenate([r_dot, r_norm]), jtj, jtr

    x = np.asarray(x0, dtype=float).copy()
    r, jtj, jtr = evaluate(x)
    cost = float(r @ r)
    scale = np.sqrt(np.diag(jtj))
    lam = 0.0
    converged = False
    it = 0
    while it < max_iter:
        it += 1
        scale = np.maximum(scale, np.sqrt(np.diag(jtj)))
        s_safe = np.where(scale > 0, scale, 1.0)
        h = jtj / np.outer(s_safe, s_safe)
        g = jtr / s_safe
        accepted = False
        while True:
            try:
                step_s = np.linalg.solve(h + lam * np.eye(12), -g)
            except np.linalg.LinAlgError:
                step_s = np.full(12, np.nan)
            x_new = x + step_s / s_safe
            if np.all(np.isfinite(x_new)):
                r_new, jtj_new, jtr_new = evaluate(x_new)
                cost_new = float(r_new @ r_new)
                if cost_new <= cost:
                    accepted = True
                    break
            if lam > 1e16 * max(1.0, float(np.max(np.diag(h)))):
                break
            lam = max(1e-3 * float(np.max(np.diag(h))), 10.0 * lam)
        if not accepted:  # no step, however short, lowers the cost: a minimum to working precision
            converged = True
            break
        small_step = float(np.linalg.norm(step_s)) <= xtol * (xtol + float(np.linalg.norm(x * s_safe)))
        small_drop = cost - cost_new <= ftol * cost
        x, r, jtj, jtr, cost = x_new, r_new, jtj_new, jtr_new, cost_new
        lam = lam / 10.0 if lam > 1e-3 * float(np.max(np.diag(h))) else 0.0
        if small_step or small_drop:
            converged = True
            break
    return RefineResult(x=x, fun=r, converged=converged, iterations=it)


def _nan_result(n: int, cov: CalibrationCoverage, message: str) -> CalibrationResult:
    return CalibrationResult(
        L=np.full((3, 3), np.nan), d=np.full(3, np.nan), residual_rms_mgauss=float("nan"),
        coverage=cov, n=n, success=False, message=message,
    )


def calibrate_dpi(
    down_b: ArrayLike,
    field_raw_mgauss: ArrayLike,
    field_down_mgauss: float,
    field_norm_mgauss: float | None = None,
    p: DpiParams | None = None,
) -> CalibrationResult:
    """Least-squares solution of eq. (3) for ``L`` and ``d``.

    Parameters
    ----------
    down_b : (n, 3) reference down vectors in body axes (normalised here)
    field_raw_mgauss : (n, 3) raw magnetometer readings ``v``, mgauss, taken at the same instants
    field_down_mgauss : ``c`` of eq. (3), the Earth field's down component Z (WMM), mgauss
    field_norm_mgauss : total intensity F (WMM), mgauss; used for the norm residual and the refinement
    p : thresholds; default :class:`DpiParams`

    Returns a :class:`CalibrationResult`; ``success`` is False (with the reason) when the data cannot
    determine ``L`` and ``d``. Raises :class:`CalibrationError` only for malformed inputs.
    """
    p = p or DpiParams()
    w = np.asarray(down_b, dtype=float)
    v = np.asarray(field_raw_mgauss, dtype=float)
    if w.ndim != 2 or w.shape[1] != 3 or v.shape != w.shape:
        raise CalibrationError(
            f"expected down vectors and field of equal shape (n, 3), got {w.shape} and {v.shape}"
        )
    keep = np.all(np.isfinite(w), axis=1) & np.all(np.isfinite(v), axis=1) & (np.linalg.norm(w, axis=1) > 0.5)
    w = w[keep] / np.linalg.norm(w[keep], axis=1, keepdims=True)
    v = v[keep]
    n = int(w.shape[0])
    z = float(field_down_mgauss)
    if n < p.min_samples:
        return _nan_result(n, coverage_of(w), f"only {n} valid samples, need at least {p.min_samples}")
    if field_norm_mgauss is not None and abs(z) < p.min_vertical_fraction * float(field_norm_mgauss):
        return _nan_result(n, coverage_of(w), (
            f"the Earth field is nearly horizontal here (Z = {z:.1f} of F = {field_norm_mgauss:.1f} mgauss): "
            "eq. (3) needs the down vector not perpendicular to the field"))
    if z == 0.0:
        return _nan_result(n, coverage_of(w), "the down component Z of the Earth field must be non-zero")
    a = dpi_design(w, v)
    cov = coverage_of(w, a)
    if cov.down_spread < p.min_down_spread or not cov.condition <= p.max_condition:
        return _nan_result(n, cov, (
            f"too little rotation to determine L and d: down-vector spread {cov.down_spread:.3f} "
            f"(need >= {p.min_down_spread}), design condition {cov.condition:.3g} "
            f"(need <= {p.max_condition:.3g}), "
            f"{cov.octant_fraction * 8:.0f}/8 octants visited; rotate the vehicle through all attitudes"))
    scale = np.linalg.norm(a, axis=0)
    xs, *_ = np.linalg.lstsq(a / scale, np.full(n, z), rcond=None)  # eq. (3) least squares
    x = xs / scale
    L, d = unpack(x)
    u = apply_calibration(L, d, v)
    rms_dot = float(np.sqrt(np.mean((np.sum(w * u, axis=1) - z) ** 2)))
    f = float(field_norm_mgauss) if field_norm_mgauss is not None else float("nan")
    rms_norm = float(np.sqrt(np.mean((np.linalg.norm(u, axis=1) - f) ** 2)))
    message = "ok"
    refined = False
    extra = {"linear_residual_rms_mgauss": rms_dot, "linear_norm_residual_rms_mgauss": rms_norm}
    if p.refine_with_norm and field_norm_mgauss is not None:
        sol = refine_with_norm_lm(x, w, v, z, f, p.norm_weight)
        r0 = _residuals(x, w, v, z, f, p.norm_weight)
        if sol.converged and float(np.sum(sol.fun**2)) < float(np.sum(r0**2)):
            L, d = unpack(sol.x)
            u = apply_calibration(L, d, v)
            rms_dot = float(np.sqrt(np.mean((np.sum(w * u, axis=1) - z) ** 2)))
            rms_norm = float(np.sqrt(np.mean((np.linalg.norm(u, axis=1) - f) ** 2)))
            refined = True
            message = "ok (refined with the field-norm constraint)"
        else:
            message = "ok (field-norm refinement did not lower the cost; linear solution kept)"
    if not np.all(np.isfinite(L)) or abs(float(np.linalg.det(L))) < 1e-6:
        return _nan_result(n, cov, "least squares gave a singular L")
    return CalibrationResult(
        L=L, d=d, residual_rms_mgauss=rms_dot, coverage=cov, n=n, success=True, message=message,
        norm_residual_rms_mgauss=rms_norm, refined=refined, extra=extra,
    )


def down_at(t_query_s: ArrayLike, t_s: ArrayLike, down_b: ArrayLike) -> F64:
    """Down vectors (n, 3) at ``t_query_s`` by linear interpolation of a track, renormalised.

    Queries outside the track get NaN rows (dropped by :func:`calibrate_dpi`).
    """
    tq = np.asarray(t_query_s, dtype=float)
    t = np.asarray(t_s, dtype=float)
    dn = np.asarray(down_b, dtype=float)
    out = np.column_stack([np.interp(tq, t, dn[:, i]) for i in range(3)])
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    out[(tq < t[0]) | (tq > t[-1])] = np.nan
    return out


def calibrate_dpi_from_imu(
    imu_t_s: ArrayLike,
    gyro_b_rad_s: ArrayLike,
    accel_b_m_s2: ArrayLike,
    mag_t_s: ArrayLike,
    field_raw_mgauss: ArrayLike,
    earth_field_ned_mgauss: ArrayLike,
    settle_s: float = 20.0,
    p: DpiParams | None = None,
) -> CalibrationResult:
    """Sec. II-A end to end: Mahony filter on the IMU -> down vectors at the compass times -> eq. (3).

    The first ``settle_s`` seconds after the first IMU sample are skipped while the filter (and its
    gyro-bias estimate) converges. ``earth_field_ned_mgauss`` (3,) gives Z (eq. (3) constant) and F.
    """
    from magcomp.core.mahony import MahonyParams, mahony_batch

    t_imu = np.asarray(imu_t_s, dtype=float)
    if t_imu.shape[0] < 2:
        raise CalibrationError("calibration needs IMU samples (gyro and accelerometer)")
    track = mahony_batch(t_imu, gyro_b_rad_s, accel_b_m_s2, MahonyParams())
    t_mag = np.asarray(mag_t_s, dtype=float)
    v = np.asarray(field_raw_mgauss, dtype=float)
    keep = t_mag >= t_imu[0] + settle_s
    w = down_at(t_mag[keep], t_imu, track.down_b)
    u_n = np.asarray(earth_field_ned_mgauss, dtype=float)
    return calibrate_dpi(w, v[keep], float(u_n[2]), float(np.linalg.norm(u_n)), p)
