"""In-flight calibration jointly with theta: no motors-off hand rotation needed.

The paper calibrates soft and hard iron (eqs. (1)-(3)) with the motors off and only then learns theta
(eqs. (16)-(20)). Real flights have no motors-off rotation, so here the calibration and theta are one
linear least-squares problem on ordinary flight data, in one of two forms chosen per compass by what the
attitude reference can be trusted for:

``absolute`` (the vehicle's yaw comes from something this compass does not disturb: an external primary
compass, GPS yaw, or truth). The measurement model of eqs. (1)-(2) and (11) with the earth-frame field
``h_n`` of eq. (13) from the WMM at the vehicle's position::

    y = A R_nb^T h_n + d + sum_r theta_r x_r                                   (eqs. (1), (11), (13))

``y`` the field as received (mgauss, compass frame), ``A`` = L^-1 of eq. (2) (soft iron, scale,
misalignment; 9 unknowns), ``d`` the hard iron (3), ``x_r`` the current regressors: ``x_0 = delta^2`` is the
paper's eq. (11); with motor outputs known, ``x_j = m_j^2 - delta^2`` add one vector per motor (the per-motor
extension; their prior mean is 0, so with no evidence the model is the paper's). Linear in every unknown.

``relative`` (the vehicle's yaw is fused from this very compass, so an absolute yaw would hide the bias).
Only the body rotation between two samples is used, from the gyro (or the autopilot's attitude when the
gyro is too slow to integrate). With an earth-fixed field, ``u_k = L (y_k - d - theta x_k)`` obeys
``u_{k+1} = Q_k u_k``, ``Q_k = R_{nb,k+1}^T R_{nb,k}``; with ``L = I + E`` (the autopilot's calibration
plus a small symmetric, traceless correction E, linearised)::

    y_{k+1} - Q_k y_k = (I - Q_k) d + sum_r (x_{r,k+1} I - x_{r,k} Q_k) theta_r - (E v_{k+1} - Q_k E v_k)
                                                                                  (eq. (13) differenced)

the exact discrete form of the paper's eq. (16) with the hard iron added. It needs rotation (yaw turns)
*and* throttle changes; it does not need the yaw itself, so a compass cannot fool it through the
autopilot's yaw.

Departures from the paper: the calibration is not a separate motors-off step, theta may be accompanied by
per-motor vectors, and both are recursive least squares in information form with a prior (the autopilot's
own calibration: A = I, d = 0, theta = 0, with the standard deviations of :class:`InflightParams`), so
the estimate is defined from the first sample and its covariance says how far to trust it.

Units: mgauss, throttle 0..1; frames: body FRD, earth NED. No I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import ModuleType
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]

InflightMode = Literal["absolute", "relative"]

#: chi-square quantile, 3 degrees of freedom, p = 1e-6: the innovation gate (a false rejection once per
#: million clean samples)
GATE_CHI2_3DOF = 30.66
#: the smallest residual scale the gate assumes (mgauss): unmodelled effects of 10-20 mgauss are common on
#: real vehicles (docs/measured-data.md), and a glitch worth rejecting is larger than that
GATE_SIGMA_FLOOR_MGAUSS = 20.0
#: prior standard deviation of the relative form's rotation-rate nuisance (rad/s): the gyro-bias clamp of an
#: attitude filter (MahonyParams.max_bias_rad_s); only keeps a window without rotation solvable
NUISANCE_PRIOR_RAD_S = 0.2
#: a stored estimate's standard deviation is widened by this factor when a new run starts from it
WARM_INFLATE = 2.0
#: residual batches for the variance inflation (see InflightEstimator.variance_inflation): a batch lasts
#: about this long (s; longer than the slow errors the rows carry: the autopilot's yaw loop, 2-5 s, and a
#: manoeuvre's tilt error, 5-30 s), and at least this many batches come in before it is used
VIF_BATCH_S = 30.0
VIF_MIN_BATCHES = 4
#: a solution conditioned on another estimator's theta (``InflightEstimator.theta_from``) counts the two
#: thetas' difference as a model uncertainty of the one it takes (its covariance plus the difference's
#: outer product)
THETA_MODEL_SPREAD = True
#: ... and the heading the two models' whole calibrations (L, d, theta) give apart, rms over the heading grid
#: of ``_heading_sd_deg``, as a model uncertainty of the published heading sigma (in quadrature; it is
#: always reported as ``InflightSolution.heading_model_deg``)
HEADING_MODEL_SPREAD = True
#: the published heading sigma also counts the spread of the estimate over time (``InflightEstimator.
#: split_heading_deg``): the closed nuisance windows are dealt alternately, VIF_BATCH_S at a time, to two
#: halves, each solved on its own, and the heading their calibrations give apart (rms over the heading grid,
#: halved: the sd of the whole-data estimate when the halves are independent) is added in quadrature. It sees
#: what biases the parameters without leaving a residual (the autopilot's tilt error that the hard iron
#: absorbs in turns, docs/inflight.md "Short flights"), which the variance inflation cannot. Both forms
#: report it; only the relative form's apply decision uses it (``InflightStage.output``: on log171's
#: absolute-form compasses it delayed the causal correction by 30 s)
SPLIT_CHECK = True


_LAPACK: ModuleType | None = None


def _lapack() -> ModuleType:
    """scipy's LAPACK wrappers (Cholesky solves), imported at the first solve: importing scipy.linalg costs
    ~0.19 s of CPU, and the main process of a two-pass replay never solves (its first pass's in-flight
    stages run in forked children, which import it themselves, beside the parse)."""
    global _LAPACK
    if _LAPACK is None:
        from scipy.linalg import lapack

        _LAPACK = lapack
    return _LAPACK


@dataclass(frozen=True, slots=True)
class InflightParams:
    """Prior standard deviations (the autopilot's calibration is the prior mean) and noise floor.

    sigma_a: soft-iron/scale entries of A, dimensionless (a compass calibrated by the autopilot is within a
    few %; an uncalibrated one within ~30 %). sigma_d_mgauss: hard iron left after the autopilot's
    offsets (a vehicle's hard iron is at most a few hundred mgauss). sigma_theta_mgauss: theta of eq. (11)
    (the paper's Table II: up to ~200 mgauss; measured vehicles up to ~600). sigma_motor_mgauss: each
    per-motor deviation. sigma_rot_rad: the compass's misalignment to the IMU (relative form; a board or
    mast is mounted within a few degrees). noise_floor_mgauss: lower bound on the residual standard
    deviation (quantisation of 1-3 mgauss and the field's local disturbances). heading_ok_deg: the heading
    uncertainty (1 sigma, from the covariance) below which the estimate is used for correction;
    heading_converged_deg: below which theta is flagged converged.
    """

    sigma_a: float = 0.3
    sigma_d_mgauss: float = 300.0
    sigma_theta_mgauss: float = 600.0
    sigma_motor_mgauss: float = 150.0
    sigma_rot_rad: float = 0.05
    noise_floor_mgauss: float = 3.0
    heading_ok_deg: float = 2.0
    heading_converged_deg: float = 1.0


@dataclass(frozen=True, slots=True)
class InflightSolution:
    """The estimate: ``calib_l`` = A^-1 and ``calib_d`` = A^-1 d (the L and d of eq. (2): u = L y - d),
    ``theta_mgauss`` in the calibrated frame (A^-1 theta_0), ``motor_theta_mgauss`` (m, 3) likewise,
    ``theta_sigma_mgauss`` its 1-sigma per axis, ``heading_sigma_deg`` the heading uncertainty the
    parameters' covariance implies at the throttle seen so far, ``residual_rms_mgauss`` the fit's residual.
    Both sigmas include ``variance_inflation`` (>= 1: the residual's correlation in time, see
    :meth:`InflightEstimator.variance_inflation`)."""

    calib_l: F64
    calib_d: F64
    theta_mgauss: F64
    motor_theta_mgauss: F64
    theta_sigma_mgauss: F64
    heading_sigma_deg: float
    residual_rms_mgauss: float
    n: int
    variance_inflation: float = 1.0
    #: heading (deg) the two models' calibrations give apart (0 without a second model; see
    #: HEADING_MODEL_SPREAD): included in ``heading_sigma_deg`` when that flag is on
    heading_model_deg: float = 0.0
    #: heading (deg) the two alternate-batch halves' estimates give apart, halved (SPLIT_CHECK): included in
    #: ``heading_sigma_deg`` when that flag is on
    heading_split_deg: float = 0.0


#: basis of the relative form's soft-iron correction E (L = I + E): symmetric and traceless (x-y, x+y-2z
#: scale differences and the three off-diagonal terms). A common scale is left out: rotations cannot see
#: it (L -> 0 would fit every pair), and heading does not need it.
_SYM_BASIS = np.array(
    [
        [[0.5, 0, 0], [0, -0.5, 0], [0, 0, 0]],
        [[1 / 6, 0, 0], [0, 1 / 6, 0], [0, 0, -1 / 3]],
        [[0, 1, 0], [1, 0, 0], [0, 0, 0]],
        [[0, 0, 1], [0, 0, 0], [1, 0, 0]],
        [[0, 0, 0], [0, 0, 1], [0, 1, 0]],
    ],
    dtype=float,
)
#: the antisymmetric part (a compass-to-IMU misalignment, rotations about x, y, z): the relative form
#: sees x and y from yaw turns, z only through tilt
_ROT_BASIS = np.array(
    [
        [[0, 0, 0], [0, 0, -1], [0, 1, 0]],
        [[0, 0, 1], [0, 0, 0], [-1, 0, 0]],
        [[0, -1, 0], [1, 0, 0], [0, 0, 0]],
    ],
    dtype=float,
)
_SOFT_BASIS = np.concatenate([_SYM_BASIS, _ROT_BASIS])
#: the identity, built once (read only): the per-sample rows copy it rather than call np.eye each time
_EYE3 = np.eye(3)
_EYE3.flags.writeable = False
_ZERO3 = np.zeros(3)
_ZERO3.flags.writeable = False
#: the eight headings of the heading-sigma rms (rad)
_PSI8_RAD = np.radians(np.arange(0.0, 360.0, 45.0))
N_SYM = _SYM_BASIS.shape[0]
N_SOFT = _SOFT_BASIS.shape[0]
#: minus the soft-iron basis as one (3 N_SOFT, 3) matrix, rows in (i, k) order: ``(_NEG_SOFT_ROWS @ v)
#: .reshape(3, N_SOFT)`` is the (3, N_SOFT) block ``-[S_k v]`` in one product
_NEG_SOFT_ROWS = -_SOFT_BASIS.transpose(1, 0, 2).reshape(3 * N_SOFT, 3)
_NEG_SOFT_ROWS.flags.writeable = False
#: per number of regressors: the window-field rows' template (zeros, the hard iron's identity block) and the
#: flat positions of the ``x_r I`` blocks' diagonals (regressor-major)
_WINDOW_ROWS_TEMPLATE: dict[int, tuple[F64, NDArray[np.intp]]] = {}


_IDENTITY: dict[int, F64] = {}


def _identity(n: int) -> F64:
    """The n x n identity, built once per size (read only: LAPACK's dpotrs copies its right-hand side)."""
    eye = _IDENTITY.get(n)
    if eye is None:
        eye = _IDENTITY[n] = np.eye(n)
        eye.flags.writeable = False
    return eye


def _window_rows_template(n_r: int) -> tuple[F64, NDArray[np.intp]]:
    t = _WINDOW_ROWS_TEMPLATE.get(n_r)
    if t is None:
        k = N_SOFT
        m = k + 3 + 3 * n_r
        rows = np.zeros((3, m))
        rows[:, k : k + 3] = _EYE3
        pos = np.array([i * m + k + 3 + 3 * r + i for r in range(n_r) for i in range(3)], dtype=np.intp)
        rows.flags.writeable = False
        t = _WINDOW_ROWS_TEMPLATE[n_r] = (rows, pos)
    return t


#: the largest magnitude a row, target or nuisance entry may have (mgauss, or mgauss per unit regressor):
#: a million gauss, far beyond any magnetometer's range, and far below where the normal equations'
#: products of up to ~10^4 rows of 30 such entries would overflow a float64
ROW_ENTRY_MAX = 1e9


_MAX_REDUCE = np.maximum.reduce  # ndarray.max without its Python wrapper (a NaN propagates alike)


def _bounded(a: F64) -> bool:
    """Every entry finite and within :data:`ROW_ENTRY_MAX` (a NaN compares False)."""
    return bool(_MAX_REDUCE(np.abs(a), axis=None) <= ROW_ENTRY_MAX)


def _augmented(rows: F64, z: F64, nuisance: F64, common: F64 | None) -> F64:
    """A sample's augmented columns ``[rows | common | z | nuisance]`` (3, n + 2 + k): what the open window's
    Gram matrix sums (``InflightEstimator._window_blocks``), checked whole by :func:`_bounded`."""
    c = _ZERO3 if common is None else common
    return np.concatenate((rows, c.reshape(3, 1), z.reshape(3, 1), nuisance), axis=1)


def n_params(mode: InflightMode, n_motors: int) -> int:
    """Size of the parameter vector: [A (9, row-major) if absolute | E (5) if relative] + d (3)
    + theta (3) + motors (3 m)."""
    return (9 if mode == "absolute" else N_SOFT) + 6 + 3 * n_motors


def soft_iron_matrix(e: F64) -> F64:
    """E (3x3, symmetric, traceless) of the relative form's soft-iron parameters."""
    return np.asarray(e @ _SOFT_BASIS.reshape(N_SOFT, 9), dtype=np.float64).reshape(3, 3)


def regressors(throttle_01: float, motors_01: tuple[float, ...] | None) -> F64:
    """x_0 = delta^2 (eq. (11)) and, when motor outputs are known, x_j = m_j^2 - delta^2 (mean-free, so the
    per-motor vectors only add what the collective throttle^2 cannot explain)."""
    d2 = throttle_01 * throttle_01
    if not motors_01:
        return np.array([d2])
    m2 = np.square(np.asarray(motors_01, dtype=float))
    return np.concatenate(([d2], m2 - d2))


def absolute_rows(field_ref_b_mgauss: F64, field_mgauss: F64, x: F64) -> tuple[F64, F64]:
    """Rows (3, n) and right-hand side (3,) of ``y = A u_ref + d + sum theta_r x_r`` (absolute form).
    ``field_ref_b_mgauss`` = R_nb^T h_n, the Earth field in body axes from the trusted attitude."""
    n_r = x.shape[0]
    rows = np.zeros((3, 12 + 3 * n_r))
    for i in range(3):
        rows[i, 3 * i : 3 * i + 3] = field_ref_b_mgauss
        rows[i, 9 + i] = 1.0
        rows[i, 12 + i :: 3] = x
    return rows, np.asarray(field_mgauss, dtype=float)


def rotation_error_rows(q_b1b0: F64, v0_mgauss: F64, dt_s: float) -> F64:
    """Columns (3, 3) of a rotation-rate error ``e`` (rad/s, body axes) held over a pair ``dt_s`` long:
    the rotation the pair was given is off by ``e dt`` (a gyro-bias error, the autopilot's compass-driven
    yaw correction), so ``u1 = Q u0 - dt [Q u0]x e`` to first order. A nuisance of the relative form (see
    :meth:`InflightEstimator.add`)."""
    w = q_b1b0 @ v0_mgauss
    return -dt_s * np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def reference_yaw_error_rows(r_nb: F64, field_ref_n_mgauss: F64) -> F64:
    """Column (3, 1) of a small yaw error ``e`` (rad) of the absolute form's reference attitude: with the
    true attitude ``Rz(e) R_nb``, the Earth field in body axes is ``R_nb^T (h - e [e_3]x h)`` to first order
    (A ~ I). A nuisance of the absolute form (see :meth:`InflightEstimator.add`)."""
    return np.asarray(r_nb.T @ np.array(_yaw_error_ned(field_ref_n_mgauss)), dtype=np.float64).reshape(3, 1)


def _yaw_error_ned(h_ned: F64) -> tuple[float, float, float]:
    """``-(e_3 x h)`` (NED): the Earth field's first-order change per radian of yaw error of the attitude
    (``Rz(e) R_nb`` for ``R_nb``)."""
    return (float(h_ned[1]), -float(h_ned[0]), 0.0)


def window_nuisance_cols(
    r_nb: F64, h_w: F64, tau: float, tilt: bool = True, vh: tuple[float, float, float] | None = None
) -> F64:
    """A window-field row's nuisance columns (3, k) (:func:`window_field_rows`), all ``R_nb^T c`` for NED
    vectors ``c``, so one product: the window's horizontal field (``R^T e_N``, ``R^T e_E``: the row's
    ``field_cols``); the rotation source's yaw-rate error about the window's field ``h_w`` (yaw error = rate x
    ``tau``, the time from the window's middle: ``R^T (-(e_3 x h)) tau``, the column of
    :func:`reference_yaw_error_rows`); with ``tilt``, its tilt error about north and east (``R^T (e_N x h)``,
    ``R^T (e_E x h)``: the vertical carries it); with ``vh`` (the tilt that the autopilot's yaw error makes,
    ``v x h``: ``InflightStage._ap_yaw_tilt``) its column ``R^T (v x h)`` last, added times ``tau`` to the
    yaw-rate column too (the window's yaw rate tilts it as well)."""
    h1, h2, h3 = float(h_w[0]), float(h_w[1]), float(h_w[2])
    e1, e2, e3 = _yaw_error_ned(h_w)
    y1, y2, y3 = e1 * tau, e2 * tau, e3 * tau
    if vh is not None:
        y1, y2, y3 = y1 + vh[0] * tau, y2 + vh[1] * tau, y3 + vh[2] * tau
    # rows N, E, D; columns e_N, e_E, the yaw rate's, then e_N x h = (0, -h3, h2), e_E x h = (h3, 0, -h1)
    if tilt:
        c = [[1.0, 0.0, y1, 0.0, h3], [0.0, 1.0, y2, -h3, 0.0], [0.0, 0.0, y3, h2, -h1]]
    else:
        c = [[1.0, 0.0, y1], [0.0, 1.0, y2], [0.0, 0.0, y3]]
    if vh is not None:
        for row, v in zip(c, vh, strict=True):
            row.append(v)
    return np.asarray(r_nb.T @ np.array(c), dtype=np.float64)


def relative_rows(
    q_b1b0: F64,
    y0_mgauss: F64,
    y1_mgauss: F64,
    x0: F64,
    x1: F64,
    v0: F64 | None = None,
    v1: F64 | None = None,
) -> tuple[F64, F64]:
    """Rows (3, n) and right-hand side (3,) of the differenced form with L = I + E::

        (I + E)(y1 - d - Theta x1) = Q (I + E)(y0 - d - Theta x0),   Q = R_nb(t1)^T R_nb(t0)

    linearised in the small symmetric soft-iron correction E at the current hard iron and theta
    (``v0``/``v1`` = y - d - Theta x at the current estimate; None: y itself)::

        -(E v1 - Q E v0) + (I - Q) d + sum_r (x1_r I - x0_r Q) theta_r = y1 - Q y0

    E is traceless (see _SOFT_BASIS): a common scale would fit every pair with L -> 0."""
    n_r = x0.shape[0]
    eye = np.eye(3)
    k = N_SOFT
    rows = np.empty((3, k + 3 + 3 * n_r))
    a = y1_mgauss if v1 is None else v1
    b = y0_mgauss if v0 is None else v0
    # column k: -(S_k a - Q S_k b)
    rows[:, 0:k] = -(np.einsum("kij,j->ik", _SOFT_BASIS, a) - q_b1b0 @ np.einsum("kij,j->ik", _SOFT_BASIS, b))
    rows[:, k : k + 3] = eye - q_b1b0
    for r in range(n_r):
        rows[:, k + 3 + 3 * r : k + 6 + 3 * r] = x1[r] * eye - x0[r] * q_b1b0
    return rows, y1_mgauss - q_b1b0 @ y0_mgauss


class WindowFieldRows(NamedTuple):
    """One sample's rows of the window-field form (:func:`window_field_rows`): ``rows`` (3, n) over the
    relative form's parameters, right-hand side ``z`` (3,), ``field_cols`` (3, 2) of the window's
    horizontal Earth field (a nuisance per window) and ``common`` (3,) the column of the vertical Earth
    field (one unknown for the flight)."""

    rows: F64
    z: F64
    field_cols: F64
    common: F64


def window_field_rows(
    r_nb: F64, y_mgauss: F64, x: F64, v: F64, like: WindowFieldRows | None = None
) -> WindowFieldRows:
    """Rows of the relative form's unknowns written against the Earth field of a short window instead of
    an earlier sample (eqs. (2), (11), (13))::

        y = d + sum_r theta_r x_r + (I - E) R_nb^T n_w,   n_w = (a_w, b_w, h_D)

    ``R_nb`` the rotation source's attitude, whose yaw is trusted only within a window: the window's
    horizontal field ``(a_w, b_w)`` (its direction *and* size) is a free nuisance, so a yaw error constant
    over the window (the autopilot's compass-driven yaw) costs nothing; the vertical ``h_D`` is one
    unknown common to the flight, since a yaw error leaves it alone (the DPI invariance of eq. (3)). The
    soft-iron term is linearised at the current estimate, ``E R^T n ~ E v`` with ``v = y - d - Theta x``
    (as :func:`relative_rows`). Unlike the 0.3 s pairs, every throttle change within a window and every
    one along the vertical, however slow, informs theta.

    ``like``: this sample's rows at another linearisation point (another estimator's ``v``): only the
    soft-iron columns differ, the rest is copied from it."""
    k = N_SOFT
    if like is not None:
        rows = like.rows.copy()
        rows[:, 0:k] = (_NEG_SOFT_ROWS @ v).reshape(3, k)
        return WindowFieldRows(rows, like.z, like.field_cols, like.common)
    template, pos = _window_rows_template(x.shape[0])
    rows = template.copy()
    rows[:, 0:k] = (_NEG_SOFT_ROWS @ v).reshape(3, k)
    # the x_r I blocks' diagonals (one regressor: its value broadcast, no repeated array)
    rows.ravel()[pos] = x[0] if x.shape[0] == 1 else np.repeat(x, 3)
    r = np.asarray(r_nb, dtype=np.float64)
    # views of R_nb (read only here and by the estimator, never written)
    return WindowFieldRows(rows, np.asarray(y_mgauss, dtype=np.float64), r[0:2].T, r[2])


class ResidualBatches:
    """The closed residual batches of :attr:`InflightEstimator.variance_inflation`, stacked: batch b's
    residual sum at parameters p and common unknown c0 is ``c_b - M_b p - g_b c0`` over ``n_b`` samples.

    The batch-means ratio is evaluated over all batches at once (numpy over the stack), and the white
    expectation's fit share ``sum_b tr(M_b cov M_b') / n_b = tr(cov S)`` through ``S = sum_b M_b' M_b / n_b``,
    updated once per batch: the estimator re-solves ~10 times a second, and a loop over every batch at
    every solve grew with the square of the log's length (20 of 81 s CPU on a simulated 60 min flight).
    tests/oracles.py keeps the per-batch loop it replaces (the same sums in another order)."""

    def __init__(self, n: int) -> None:
        self._c = np.zeros((8, 3))
        self._m = np.zeros((8, 3, n))
        self._g = np.zeros((8, 3))
        self._inv_n = np.zeros(8)
        self._mm = np.zeros((n, n))
        self.count = 0

    def append(self, c: F64, m: F64, g: F64, n_b: int) -> None:
        """A closed batch (copied)."""
        i = self.count
        if i == self._inv_n.shape[0]:  # amortised doubling (grows with the log, ~100 floats a batch)
            self._c, self._m, self._g, self._inv_n = (
                np.concatenate([a, np.zeros_like(a)]) for a in (self._c, self._m, self._g, self._inv_n)
            )
        self._c[i], self._m[i], self._g[i], self._inv_n[i] = c, m, g, 1.0 / n_b
        self._mm += (m.T @ m) / n_b
        self.count = i + 1

    def inflation(self, p: F64, c0: float, cov: F64 | None, s2: float) -> float:
        """``sum_b |c_b - M_b p - g_b c0|^2 / n_b`` over its white expectation ``sum_b (3 s2 - tr(M_b cov
        M_b') / n_b)`` (the unit-weight Lambda^-1 is cov / s2; without the fit's share the estimate is ~25 %
        low), at least 1; 1 when the expectation is not positive."""
        b = self.count
        e = self._c[:b] - self._m[:b] @ p - self._g[:b] * c0
        num = float(np.einsum("bi,bi,b->", e, e, self._inv_n[:b]))
        fit = 0.0 if cov is None else float(np.einsum("jk,jk->", cov, self._mm))
        den = 3.0 * s2 * b - fit
        return max(1.0, num / den) if den > 0.0 else 1.0


#: the open window's contribution with its nuisance eliminated (:meth:`InflightEstimator._window_schur`)
WindowSchur = tuple[F64, F64, float, F64, float, float]


class InflightEstimator:
    """Recursive least squares in information form for one compass (no I/O; the state is numpy arrays).

    ``add`` accumulates ``rows^T rows / s^2`` and ``rows^T z / s^2``; ``solve`` returns the MAP estimate
    under the Gaussian prior. The residual scale ``s`` is estimated from the a-priori residuals (floor
    :attr:`InflightParams.noise_floor_mgauss`), so the covariance is in real units.
    """

    def __init__(
        self,
        mode: InflightMode,
        n_motors: int,
        p: InflightParams | None = None,
        field_norm_mgauss: float = 500.0,
        warm: tuple[F64, F64] | None = None,
    ) -> None:
        """``warm``: (mean, standard deviation) of every parameter from an earlier run (the state store),
        used as the prior instead of the autopilot's calibration."""
        self.mode: InflightMode = mode
        self.field_norm_mgauss = field_norm_mgauss
        #: the Earth field (NED, mgauss) for the heading uncertainty; the stage sets the WMM's. Default: the
        #: norm at 60 deg of inclination
        self.field_ned_mgauss: F64 = field_norm_mgauss * np.array([0.5, 0.0, math.sqrt(0.75)])
        self.n_motors = n_motors
        self.p = p or InflightParams()
        n = n_params(mode, n_motors)
        prior_mean = np.zeros(n)
        prior_sd = np.empty(n)
        if mode == "absolute":
            prior_mean[0:9] = np.eye(3).ravel()
            prior_sd[0:9] = self.p.sigma_a
            k = 9
        else:
            prior_sd[0:N_SOFT] = self.p.sigma_a
            prior_sd[N_SYM:N_SOFT] = min(self.p.sigma_a, self.p.sigma_rot_rad)
            k = N_SOFT
        prior_sd[k : k + 3] = self.p.sigma_d_mgauss
        prior_sd[k + 3 : k + 6] = self.p.sigma_theta_mgauss
        prior_sd[k + 6 :] = self.p.sigma_motor_mgauss
        self._k = k
        # the physical prior bounds every later run's: an unobserved parameter's inflated sd stops there
        self._prior_sd_max = prior_sd.copy()
        if warm is not None and warm[0].shape == (n,) and warm[1].shape == (n,):
            prior_mean = np.asarray(warm[0], dtype=float).copy()
            prior_sd = np.maximum(np.asarray(warm[1], dtype=float), 1e-6)
        self.prior_mean = prior_mean
        self.prior_info = np.diag(1.0 / prior_sd**2)
        self._prior_b_cache: tuple[F64, F64, F64] | None = None
        self.info = np.zeros((n, n))  # data information, unit weight
        self.rhs = np.zeros(n)
        self.n = 0
        self._zz = 0.0  # sum of z'z (for the residual sum of squares)
        self.x0_max = 0.0  # largest delta^2 seen (for the heading uncertainty)
        self._x0_sum = 0.0
        self._x0_sq = 0.0
        self._theta: F64 = prior_mean.copy()
        self._cov: F64 | None = np.asarray(np.linalg.inv(self.prior_info), dtype=np.float64)
        self.n_gated = 0
        #: rows left out as not finite (:meth:`_take`, :meth:`add_norm`)
        self.n_nonfinite = 0
        self._solution: InflightSolution | None = None
        self._dirty = True
        self._clear_blocks(n)
        #: prior standard deviation of the nuisance (its units: rad/s for a rotation-rate error), one value
        #: for every column or one per column
        self.nuisance_prior_sd: float | F64 = NUISANCE_PRIOR_RAD_S
        #: another estimator of the same parameters from other rows whose theta the published solution
        #: takes, the rest conditioned on it (``_conditioned``); this one's own estimate stays the
        #: linearisation point and the gate's
        self.theta_from: InflightEstimator | None = None
        #: the published (conditioned) mean and covariance (inflated) when ``theta_from`` is set
        self._pub: tuple[F64, F64] | None = None
        #: ``theta_from`` is re-solved at every this many solutions of this one (its cost: a second set of
        #: normal equations solved), and whenever ``sync_theta_from`` asks
        self.theta_from_every = 1
        self._n_refresh = 0
        self._sync = False

    def _clear_blocks(self, n: int) -> None:
        """Empty nuisance-window and common-unknown blocks (``__init__``)."""
        # the open window of the rotation-rate nuisance (see add): its rows' blocks, folded into info/rhs
        # by a Schur complement when the window closes
        self._win: object = None
        # the window's blocks (``_window_blocks``): parameters x parameters, x nuisance, nuisance x nuisance,
        # their right-hand sides and z'z, and with the unknown common to the flight (``common`` in add)
        self._window_blocks(n, 0)
        self.n_windows = 0
        # the blocks of the one unknown common to the flight (the field norm of add_norm, or the vertical
        # Earth field of window-field rows: add(common=...)), eliminated when solving (a Schur complement,
        # like a window that never closes). Its rows' parameter block goes to info / _n_pp alike.
        self._n_pp = np.zeros((n, n))
        self._n_pc = np.zeros(n)
        self._n_cc = 0.0
        self._n_bp = np.zeros(n)
        self._n_bc = 0.0
        self._n_zz = 0.0
        self.n_norm = 0
        #: the unknown common to the flight at the last solution (mgauss; 0 before any)
        self.common_estimate = 0.0
        #: bumped whenever the parameters, the solution or the open window's blocks change (the open
        #: window's nuisance estimate is cached against it)
        self._rev = 0
        self._open_cache: tuple[tuple[int, bool, tuple[float, ...]], tuple[F64, F64]] | None = None
        self._ridge_cache: tuple[tuple[float, tuple[float, ...]], F64] | None = None
        self._coef_cache: tuple[tuple[F64, float, int], F64] | None = None
        self._unc_cache: tuple[F64, F64, F64] | None = None  # uncalibrated(): theta's d and Theta views
        self._grad_cache: tuple[tuple[float, float, float, int], F64, F64] | None = None
        self._sd_key_cache: tuple[F64, int, tuple[float, ...]] | None = None
        self._eff_cache: tuple[tuple[int, float | None, tuple[float, ...]], tuple[F64, F64, float]] | None
        self._eff_cache = None
        # residual batches for variance_inflation: the open window's sums of z, rows, nuisance and common
        # columns; the open batch's residual sum as c - M p - g common (per closed window, the nuisance
        # eliminated), its sample and window counts; the closed batches
        self._w_n = 0
        self._b_c = np.zeros(3)
        self._b_m = np.zeros((3, n))
        self._b_g = np.zeros(3)
        self._b_n = 0
        self._b_windows = 0
        self._batches = ResidualBatches(n)
        #: the closed windows' Schur complements dealt to two halves, alternately per batch (SPLIT_CHECK):
        #: per half [info, rhs, z'z, parameters x common, common x common, common rhs, windows]
        self._halves: list[list[object]] = [[np.zeros((n, n)), np.zeros(n), 0.0, np.zeros(n), 0.0, 0.0, 0]
                                            for _ in range(2)]  # fmt: skip
        self._split_cache: tuple[int, float] | None = None  # (closed windows, split_heading_deg)
        #: nuisance windows per batch (the stage sets it from its window length: VIF_BATCH_S / window)
        self.vif_batch_windows = 15

    def _window_blocks(self, n: int, k: int) -> None:
        """The open window's sums for ``k`` nuisance columns, zero: the Gram matrix ``sum A'A`` and the sum
        ``sum A`` of its samples' augmented rows ``A = [rows | common | z | nuisance]`` (3, n + 2 + k), one
        matrix product per sample; the blocks the window's algebra reads are views of them."""
        m = n + 2 + k
        self._w_gram = np.zeros((m, m))
        self._w_sum = np.zeros((3, m))
        self._window_views(n)

    def _window_views(self, n: int) -> None:
        """The views of the open window's sums that its algebra reads (``_window_blocks``)."""
        g, sa = self._w_gram, self._w_sum
        m = g.shape[0]
        c, z, e = n, n + 1, slice(n + 2, m)
        self._w_pp, self._w_pe, self._w_ee = g[:n, :n], g[:n, e], g[e, e]
        self._w_bp, self._w_be, self._w_pc, self._w_ec = g[:n, z], g[e, z], g[:n, c], g[e, c]
        self._w_srows, self._w_sn, self._w_scom, self._w_sz = sa[:, :n], sa[:, e], sa[:, c], sa[:, z]

    def __setstate__(self, state: dict[str, object]) -> None:
        """Unpickled (the in-flight stage sent to its process and taken back, service/inflight_process.py):
        the window's views made again. Pickle copies a view as an array of its own, so the views would no
        longer follow the window's sums: a row added after the round trip would go into ``_w_gram`` while
        ``_w_ee`` and the others kept their old values."""
        self.__dict__.update(state)
        self._window_views(self.info.shape[0])

    @property
    def _w_zz(self) -> float:
        n = self.info.shape[0]
        return float(self._w_gram[n + 1, n + 1])

    @property
    def _w_cc(self) -> float:
        n = self.info.shape[0]
        return float(self._w_gram[n, n])

    @property
    def _w_bc(self) -> float:
        n = self.info.shape[0]
        return float(self._w_gram[n, n + 1])

    @property
    def sigma_mgauss(self) -> float:
        """Residual standard deviation per component at the current estimate (floored): the least-squares
        residual sum of squares from the information form, ``z'z - 2 p'b + p'Ip``, over its degrees of
        freedom. (A running mean of a-priori residuals would keep the large residuals of the first samples,
        when the estimate was still the prior, and overstate the noise tenfold.)"""
        return self._sigma_at(None)

    def _sigma_at(self, eff: tuple[F64, F64, float] | None) -> float:
        """:attr:`sigma_mgauss` with :meth:`_effective` given when known (None: computed here if needed)."""
        n_common = 1 if self._n_cc + self._w_cc > 0.0 else 0
        n_dof = (
            3 * self.n + self.n_norm - self.info.shape[0] - self._w_ee.shape[0] * self.n_windows - n_common
        )
        if self.n < 10 or n_dof < 10:
            return max(self.p.noise_floor_mgauss, 10.0)
        p = self._theta
        info, rhs, zz = self._effective_now() if eff is None else eff
        rss = zz - 2.0 * float(p @ rhs) + float(p @ info @ p)
        return max(self.p.noise_floor_mgauss, math.sqrt(max(rss, 0.0) / n_dof))

    @property
    def throttle2_std(self) -> float:
        """Standard deviation of delta^2 over the samples used: the throttle excitation theta needs."""
        if self.n < 2:
            return 0.0
        m = self._x0_sum / self.n
        return math.sqrt(max(0.0, self._x0_sq / self.n - m * m))

    def add(
        self,
        rows: F64,
        z: F64,
        x0: float,
        nuisance: F64 | None = None,
        window: object = None,
        common: F64 | None = None,
        gate: bool = True,
    ) -> float:
        """Add one sample's rows; returns its a-priori residual norm (mgauss) against the current estimate
        (NaN with ``gate`` False: the caller has judged the sample, e.g. with another estimator's gate).

        ``nuisance`` (3, 3): columns of a rotation-rate error held constant over ``window`` (any hashable
        key; a new key closes the previous window), estimated with the window's rows and eliminated
        (Schur complement) so that what it can explain informs nothing else. The relative form's
        rotations carry such slowly varying errors: a gyro bias the attitude filter mis-estimates in
        accelerated flight, the autopilot's compass-driven yaw correction (docs/inflight.md).

        Innovation gate: a sample whose residual is implausible under the predictive covariance
        (noise plus the parameters' own uncertainty; chi-square, 3 dof, p = 1e-6 -> 30.7) is counted in
        :attr:`n_gated` and not used, so one glitch cannot move a converged estimate, while a change the
        current uncertainty allows (e.g. the first throttle) is learned.

        ``common`` (3,): the column of the one unknown common to the whole flight (window-field rows: the
        vertical Earth field), eliminated when solving; only with a ``nuisance`` window."""
        # with a nuisance window, its augmented columns are built here and checked at once (one reduction,
        # not four), then summed as they are
        aug = None if nuisance is None else _augmented(rows, z, nuisance, common)
        if not (
            _bounded(aug)
            if aug is not None
            else _bounded(rows) and _bounded(z) and (common is None or _bounded(common))
        ):
            # a NaN, an infinity or a value whose square products overflow (a damaged record upstream):
            # left out. In the normal equations it would make every later solution NaN (LAPACK's
            # Cholesky does not report a NaN matrix as a failure) or its heading sigma 0
            self.n_nonfinite += 1
            return math.nan
        if not gate:
            self._take(rows, z, x0, nuisance, window, common, aug)
            return math.nan
        r = z - rows @ self._theta
        if common is not None:
            r = r - common * self.common_estimate
        if nuisance is not None:
            e_hat, h_ee = self._nuisance_estimate(nuisance, r, window, common is not None)
            r = r - nuisance @ e_hat
        rn2 = float(r @ r)
        sol = self._solution
        if self._cov is not None and sol is not None and sol.heading_sigma_deg < self.p.heading_converged_deg:
            # only once converged, and with the model error allowed for (the floor below): before that, a
            # large residual is the model learning, not a glitch. The noise scale is the last solution's.
            s2 = max(sol.residual_rms_mgauss**2, GATE_SIGMA_FLOOR_MGAUSS**2)
            # pred >= s2 I, so r' pred^-1 r <= |r|^2 / s2: most samples pass without the 3x3 solve
            pred = s2 * np.eye(3) + rows @ self._cov @ rows.T if rn2 > GATE_CHI2_3DOF * s2 else None
            if pred is not None and nuisance is not None and h_ee is not None:
                # the window's nuisance is uncertain too (its covariance H_ee^-1, unit weight)
                pred = pred + s2 * (nuisance @ np.linalg.solve(h_ee, nuisance.T))
            try:
                m2 = 0.0 if pred is None else float(r @ np.linalg.solve(pred, r))
            except np.linalg.LinAlgError:
                m2 = 0.0
            if m2 > GATE_CHI2_3DOF:
                self.n_gated += 1
                return math.sqrt(rn2)
        self._take(rows, z, x0, nuisance, window, common, aug)
        return math.sqrt(rn2)

    def _take(
        self,
        rows: F64,
        z: F64,
        x0: float,
        nuisance: F64 | None,
        window: object,
        common: F64 | None,
        aug: F64 | None = None,
    ) -> None:
        """One row into the normal equations and the throttle statistics (the gate passed or not asked)."""
        self._accumulate(rows, z, nuisance, window, common, aug)
        self.n += 1
        self.x0_max = max(self.x0_max, x0)
        self._x0_sum += x0
        self._x0_sq += x0 * x0
        self._dirty = True

    @property
    def variance_inflation(self) -> float:
        """How much the residual's correlation in time inflates the parameters' variance (>= 1; 1 until
        :data:`VIF_MIN_BATCHES` batches are in).

        The information form weighs every sample as independent. The rows' residuals are not: the
        autopilot's yaw and tilt errors, the gyro's bias and unmodelled field changes last seconds to tens of
        seconds, so 50 samples a second carry far fewer independent pieces of information (measured on
        varied simulated flights, docs/inflight.md: theta's errors were 3-15x the white-noise sigma). The
        batch-means estimate over batches of :data:`VIF_BATCH_S`: ``sum_b |S_b|^2 / n_b`` over what white
        residuals would give, where ``S_b`` is a batch's residual sum at the current estimate (each batch
        keeps it as a linear function of the parameters, the windows' nuisance eliminated as in the normal
        equations) and the white expectation has the fit's own share removed. 1 for white residuals, the
        number of samples a batch effectively counts as one for lasting ones. Batches form over nuisance
        windows only. Departure from the paper: its observer has no covariance to inflate."""
        return self._vif_at(None)

    @property
    def split_checked(self) -> bool:
        """Both halves of ``split_heading_deg`` hold a closed window: the estimate has met data one of its
        halves did not use (SPLIT_CHECK, relative form; always True with the check off or the absolute
        form)."""
        return not SPLIT_CHECK or self.mode != "relative" or min(int(h[6]) for h in self._halves) > 0  # type: ignore[call-overload]

    def _vif_at(self, s2: float | None) -> float:
        """:attr:`variance_inflation` with ``sigma_mgauss**2`` given when known (None: computed here)."""
        if self._batches.count < VIF_MIN_BATCHES:
            return 1.0
        if s2 is None:
            s2 = self.sigma_mgauss**2  # per component, at the estimate
        return self._batches.inflation(self._theta, self.common_estimate, self._cov, s2)

    def _prior_sd_k(self, k: int) -> F64:
        """The nuisance prior's standard deviations as k numbers (the stage sets an array of k per row)."""
        sd = self.nuisance_prior_sd
        if isinstance(sd, np.ndarray) and sd.shape == (k,) and sd.dtype == np.float64:
            return sd
        return np.broadcast_to(np.asarray(sd, dtype=float), (k,))

    def _prior_sd_key(self, k: int) -> tuple[float, ...]:
        """:meth:`_prior_sd_k` as a tuple (a cache key); the same read-only array as the last call (the
        stage's) is not read again."""
        sd = self.nuisance_prior_sd
        cached = self._sd_key_cache
        if cached is not None and cached[0] is sd and cached[1] == k:
            return cached[2]
        out = tuple(self._prior_sd_k(k).tolist())
        if isinstance(sd, np.ndarray) and not sd.flags.writeable:
            self._sd_key_cache = (sd, k, out)
        return out

    def _nuisance_estimate(
        self, nuisance: F64, r: F64, window: object, with_common: bool
    ) -> tuple[F64, F64 | None]:
        """The window's nuisance at the current parameters and its unit-weight information ``H_ee`` (the
        inverse of its covariance: so that the gate judges what the nuisance cannot explain, with its
        uncertainty: a window-field row's residual is the whole Earth field before it, and a window's yaw
        rate is poorly known from its first samples). The open window's own estimate when this row belongs
        to it; else the least-squares value for this row alone (information None: the residual is then
        what no nuisance value explains)."""
        k = nuisance.shape[1]
        if window == self._win and self._w_ee.shape[0] == k:
            out = self._open_nuisance(k, with_common)
            if out is not None:
                return out
        return np.asarray(np.linalg.lstsq(nuisance, r, rcond=None)[0], dtype=np.float64), None

    def _open_nuisance(self, k: int, with_common: bool) -> tuple[F64, F64] | None:
        """The open window's nuisance estimate and information (``_nuisance_estimate``; None when the
        window has no rows with nuisance columns yet, or H_ee is singular)."""
        # the stage asks twice per row with nothing changed in between (window_nuisance, then add): the
        # second answer is the first (same inputs, same numbers); _rev changes with every input
        key = (self._rev, with_common, self._prior_sd_key(k))
        cached = self._open_cache
        if cached is not None and cached[0] == key:
            return cached[1]
        if self._w_n == 0 or not self._w_ee.any():
            return None
        hee = self._window_hee(key[2])
        # b_e = w_be - W_pe' p - w_ec c as one product with the window's Gram rows of the nuisance (their
        # nuisance block times 0): [W_ep | w_ec | w_be | H_ee] [-p, -c, 1, 0]
        b_e = self._w_gram[self._theta.shape[0] + 2 :] @ self._b_e_coef(k, with_common)
        # LAPACK's Cholesky solve directly (numpy's solve costs 6x more in checks for a 5x5)
        _, e_hat, info = _lapack().dposv(hee, b_e)
        if info != 0:
            return None
        out = np.asarray(e_hat, dtype=np.float64), hee
        self._open_cache = (key, out)
        return out

    def _b_e_coef(self, k: int, with_common: bool) -> F64:
        """``[-p, -c, 1, 0_k]`` at the current parameters p and common unknown c (0 without ``with_common``):
        the window Gram's nuisance rows times it are the nuisance's right-hand side. Built once per
        solution (the parameters change only there)."""
        c = self.common_estimate if with_common else 0.0
        key = (self._theta, c, k)
        cached = self._coef_cache
        if cached is not None and cached[0][0] is key[0] and cached[0][1:] == key[1:]:
            return cached[1]
        n = self._theta.shape[0]
        coef = np.zeros(n + 2 + k)
        coef[:n] = -self._theta
        coef[n] = -c
        coef[n + 1] = 1.0
        self._coef_cache = (key, coef)
        return coef

    def _window_hee(self, sd: tuple[float, ...]) -> F64:
        """The open window's nuisance information H_ee with its prior, at the residual scale of the last
        solution (the noise floor, at least 10 mgauss, before one)."""
        sol = self._solution
        s_ref = max(self.p.noise_floor_mgauss, 10.0) if sol is None else sol.residual_rms_mgauss
        return self._w_ee + self._ridge(s_ref, sd)

    def _ridge(self, s_ref: float, sd: tuple[float, ...]) -> F64:
        """The nuisance prior's information at unit weight, ``diag((s_ref / sd)^2)`` (the data rows are not
        divided by s), built once per residual scale and prior."""
        key = (s_ref, sd)
        if self._ridge_cache is None or self._ridge_cache[0] != key:
            self._ridge_cache = (key, np.diag((s_ref / np.asarray(sd)) ** 2))
        return self._ridge_cache[1]

    def _window_solve(self) -> F64 | None:
        """``H_ee^-1 [W_ep | w_ec | w_be]`` of the open window (H_ee with the nuisance's prior; None when
        it is singular): what its Schur complement and its residual sum both need. The nuisance has a weak
        prior (0.2 rad/s, an attitude filter's gyro-bias clamp, at the noise floor) so that a window
        without rotation information stays solvable."""
        n = self.info.shape[0]
        hee = self._window_hee(self._prior_sd_key(self._w_ee.shape[0]))
        _, x, info = _lapack().dposv(hee, self._w_gram[n + 2 :, : n + 2])
        return None if info != 0 else np.asarray(x, dtype=np.float64)

    def window_nuisance(self, window: object) -> F64 | None:
        """The open window's nuisance estimate at the current parameters when ``window`` is the open one
        and has rows (window-field rows: its horizontal Earth field first), else None."""
        k = self._w_ee.shape[0]
        if window != self._win or k == 0:
            return None
        out = self._open_nuisance(k, True)
        if out is None:  # no rows with nuisance columns (or singular: what the last row alone gives, 0)
            return None if self._w_n == 0 or not self._w_ee.any() else np.zeros(k)
        return out[0]

    def add_norm(self, y_mgauss: F64, x: F64) -> None:
        """One field-norm row (relative form): ``|u| = c`` with ``u = (I + E)(y - d - sum theta_r x_r)``
        and ``c`` one unknown common to the whole flight, linearised at the current estimate.

        The differenced pairs see theta only through the throttle change within a pair (0.3 s); the norm
        of the calibrated field is the Earth field's whatever the attitude (eq. (2): ``|L(y - d)| = |h|``,
        the paper's calibration constraint, with eq. (11)'s bias removed), so every throttle change, however
        slow (a climb, forward flight), tells theta's component along the field. ``c`` rather than the
        WMM's |h|: the relative form has no common scale (a traceless E) and a WMM norm is off by a few %
        locally; eliminating ``c`` keeps only the norm's variation. Weighted by sqrt(2): a pair's
        component has the noise of two samples, a norm row that of one sample projected on the field."""
        if not (_bounded(y_mgauss) and _bounded(x)):  # as in add
            self.n_nonfinite += 1
            return
        k = self._k
        th = self._theta[k + 3 :].reshape(-1, 3)
        v = np.asarray(y_mgauss - self._theta[k : k + 3] - x[: th.shape[0]] @ th, dtype=np.float64)
        l_mat = np.eye(3) + soft_iron_matrix(self._theta[0:N_SOFT])
        u = l_mat @ v
        nu = float(np.linalg.norm(u))
        if nu < 1.0:
            return
        e = u / nu
        g = np.empty(self.info.shape[0])
        g[0:N_SOFT] = e @ np.einsum("kij,j->ik", _SOFT_BASIS, v)
        el = e @ l_mat
        g[k : k + 3] = -el
        for r in range(th.shape[0]):
            g[k + 3 + 3 * r : k + 6 + 3 * r] = -float(x[r]) * el
        w = math.sqrt(2.0)
        g *= w
        z = w * (float(g @ self._theta) / w - nu)
        c = -w  # the column of the common norm c
        self._n_pp += np.outer(g, g)
        self._n_pc += g * c
        self._n_cc += c * c
        self._n_bp += g * z
        self._n_bc += c * z
        self._n_zz += z * z
        self.n_norm += 1
        self._rev += 1
        self._dirty = True

    @staticmethod
    def _common_schur(pp: F64, pc: F64, cc: float, bp: F64, bc: float, zz: float) -> tuple[F64, F64, float]:
        """(info, rhs, z'z) with the unknown common to the flight eliminated (none yet: as they are)."""
        if cc <= 0.0:
            return pp, bp, zz
        k_p = pc / cc
        return pp - np.outer(k_p, pc), bp - k_p * bc, zz - bc * bc / cc

    def _window_schur(self, x: F64 | None = None) -> WindowSchur:
        """The open window's contribution with its nuisance eliminated: (info, rhs, z'z) of the parameters
        and the blocks of the common unknown (parameters x common, common x common, its rhs): the Schur
        complement ``G_rr - G_re H_ee^-1 G_er`` of its Gram matrix, ``r`` = [parameters, common, z].
        ``x``: :meth:`_window_solve` when already computed."""
        n = self.info.shape[0]
        x = self._window_solve() if x is None else x
        if x is None:
            return self._w_pp, self._w_bp, self._w_zz, self._w_pc, self._w_cc, self._w_bc
        g = self._w_gram
        sc = g[: n + 2, : n + 2] - g[n + 2 :, : n + 2].T @ x
        zz, cc, bc = float(sc[n + 1, n + 1]), float(sc[n, n]), float(sc[n, n + 1])
        return sc[:n, :n], sc[:n, n + 1], zz, sc[:n, n], cc, bc

    def _close_window(self) -> None:
        if self._win is None:
            return
        self._rev += 1
        x = self._window_solve()
        self._batch_window(x)
        info, rhs, zz, pc, cc, bc = self._window_schur(x)
        self._split_add(info, rhs, zz, pc, cc, bc)
        self.info += info
        self.rhs += rhs
        self._zz += zz
        self._n_pc += pc
        self._n_cc += cc
        self._n_bc += bc
        self.n_windows += 1
        self._w_gram[...] = 0.0
        self._win = None

    def refill_open_window(self, samples: list[tuple[F64, F64, F64, F64 | None]]) -> None:
        """Replace the open window's rows by ``samples`` (rows, z, nuisance, common): the same samples with
        their nuisance columns written again (relinearised at the window's final estimate). Sample counts
        and throttle statistics stay as they were; nothing happens without an open window."""
        if self._win is None:
            return
        self._rev += 1
        self._w_gram[...] = 0.0
        self._w_sum[...] = 0.0
        self._w_n = 0
        for rows, z, nuisance, common in samples:
            self._accumulate(rows, z, nuisance, self._win, common)
        self._dirty = True

    def _accumulate(
        self,
        rows: F64,
        z: F64,
        nuisance: F64 | None,
        window: object,
        common: F64 | None,
        aug: F64 | None = None,
    ) -> None:
        """Fold one used sample into the normal equations, or into the open nuisance window's blocks
        (``aug``: its :func:`_augmented` columns when already built)."""
        self._rev += 1
        if nuisance is None:
            self._zz += float(z @ z)
            self.info += rows.T @ rows
            self.rhs += rows.T @ z
        else:
            if window != self._win:
                self._close_window()
                self._win = window
            n, k = rows.shape[1], nuisance.shape[1]
            if self._w_ee.shape[0] != k:  # a new nuisance size: the nuisance's sums start again
                g, sa = self._w_gram, self._w_sum
                self._window_blocks(n, k)
                self._w_gram[: n + 2, : n + 2] = g[: n + 2, : n + 2]
                self._w_sum[:, : n + 2] = sa[:, : n + 2]
            a = _augmented(rows, z, nuisance, common) if aug is None else aug
            self._w_gram += a.T @ a
            self._w_sum += a
            self._w_n += 1

    def _batch_window(self, x: F64 | None) -> None:
        """Add the closing window's residual sum to the open batch (``variance_inflation``): with the
        window's nuisance at its least-squares value e = H^-1 (b_e - W_ep p - w_ec c), the sum over the
        window of z - rows p - common c - N e is c_w - M_w p - g_w c. ``x``: :meth:`_window_solve`."""
        k = self._w_ee.shape[0]
        n = self.info.shape[0]
        if self._w_n > 0 and self._w_sn.shape[1] == k and x is not None:
            self._b_c += self._w_sz - self._w_sn @ x[:, n + 1]
            self._b_m += self._w_srows - self._w_sn @ x[:, :n]
            self._b_g += self._w_scom - self._w_sn @ x[:, n]
            self._b_n += self._w_n
            self._b_windows += 1
            if self._b_windows >= self.vif_batch_windows:
                self._batches.append(self._b_c, self._b_m, self._b_g, self._b_n)
                for a in (self._b_c, self._b_m, self._b_g):
                    a[...] = 0.0
                self._b_n = self._b_windows = 0
        for a in (self._w_sz, self._w_srows, self._w_sn, self._w_scom):
            a[...] = 0.0
        self._w_n = 0

    def _split_add(self, info: F64, rhs: F64, zz: float, pc: F64, cc: float, bc: float) -> None:
        """A closing window's Schur complement into its half (SPLIT_CHECK): halves alternate every
        ``vif_batch_windows`` windows, the residual batches' length (the slow errors' correlation time)."""
        h = self._halves[(self.n_windows // max(1, self.vif_batch_windows)) % 2]
        h[0] = h[0] + info  # type: ignore[operator]
        h[1] = h[1] + rhs  # type: ignore[operator]
        h[2] = h[2] + zz  # type: ignore[operator]
        h[3] = h[3] + pc  # type: ignore[operator]
        h[4] = h[4] + cc  # type: ignore[operator]
        h[5] = h[5] + bc  # type: ignore[operator]
        h[6] = h[6] + 1  # type: ignore[operator]

    def split_heading_deg(self, s2: float) -> float:
        """The heading (deg, rms over the heading grid of ``_heading_sd_deg``) that the two halves' own
        estimates give apart, halved: each half solved alone with the prior at the noise scale ``s2``
        (mgauss^2). Two independent halves of equal information differ by twice the whole estimate's
        standard deviation, so this estimates it from data each half did not use, whatever the cause of
        the spread (a bias the residual cannot show: the hard iron taking the autopilot's tilt error in
        turns). A half with no closed window is the prior: a large spread, honestly. Departure from the
        paper: its observer has no uncertainty."""
        est = []
        prior_b = self._prior_rhs()
        for h in self._halves:
            info, rhs, _ = self._common_schur(h[0], h[3], h[4], h[1], h[5], h[2])  # type: ignore[arg-type]
            try:
                est.append(np.linalg.solve(info / s2 + self.prior_info, rhs / s2 + prior_b))
            except np.linalg.LinAlgError:
                return 0.0
        dp = est[0] - est[1]
        return 0.5 * self._heading_sd_deg(np.outer(dp, dp))

    def _common_value(self, p: F64, ws: WindowSchur | None = None) -> float:
        """The common unknown's least-squares value at parameters ``p`` (back-substitution of its Schur
        complement; 0 when there is none). ``ws``: :meth:`_window_schur` when already computed."""
        pc, cc, bc = self._n_pc, self._n_cc, self._n_bc
        if self._win is not None and self._w_cc > 0.0:
            _, _, _, w_pc, w_cc, w_bc = self._window_schur() if ws is None else ws
            pc, cc, bc = pc + w_pc, cc + w_cc, bc + w_bc
        return 0.0 if cc <= 0.0 else float((bc - pc @ p) / cc)

    def _effective_now(self) -> tuple[F64, F64, float]:
        """:meth:`_effective` at the current state, kept until something it reads changes (the rows, the
        solution: ``_rev``; the residual scale and the nuisance prior of the open window's H_ee). A replay's
        final ``state()`` is asked in the child that learned it and again in the main process, which then
        solves nothing (and never imports scipy's LAPACK: ``_lapack``)."""
        sol = self._solution
        key = (self._rev, None if sol is None else sol.residual_rms_mgauss,
               self._prior_sd_key(self._w_ee.shape[0]))  # fmt: skip
        cached = self._eff_cache
        if cached is not None and cached[0] == key:
            return cached[1]
        eff = self._effective()
        self._eff_cache = (key, eff)
        return eff

    def _effective(self, ws: WindowSchur | None = None) -> tuple[F64, F64, float]:
        """(info, rhs, z'z) of every row so far, the open nuisance window and the norm rows included, the
        unknown common to the flight eliminated. ``ws``: :meth:`_window_schur` when already computed."""
        pp, bp, zz = self.info + self._n_pp, self.rhs + self._n_bp, self._zz + self._n_zz
        pc, cc, bc = self._n_pc, self._n_cc, self._n_bc
        if self._win is not None:
            w_pp, w_bp, w_zz, w_pc, w_cc, w_bc = self._window_schur() if ws is None else ws
            pp, bp, zz = pp + w_pp, bp + w_bp, zz + w_zz
            pc, cc, bc = pc + w_pc, cc + w_cc, bc + w_bc
        return self._common_schur(pp, pc, cc, bp, bc, zz)

    def _refresh(self) -> None:
        """Re-solve the normal equations (called by :meth:`solve`; cheap, n <= 30)."""
        # two rounds: the noise scale weighs data against the prior, and is itself the residual at the
        # estimate (the first round's scale comes from the previous estimate)
        # nothing the open window's Schur complement depends on changes here (only theta does): computed
        # once for the refresh (it was six times, 18 small solves)
        ws = self._window_schur() if self._win is not None else None
        eff = self._effective(ws)
        info, rhs, _ = eff
        prior_b = self._prior_rhs()
        for _ in range(2):
            s2 = self._sigma_at(eff) ** 2
            lam = info / s2 + self.prior_info
            b = rhs / s2 + prior_b
            # LAPACK's Cholesky solve (its factor kept for the covariance below)
            cho, theta, fail = _lapack().dposv(lam, b)
            if fail != 0:
                return
            self._theta = theta
            self._rev += 1
        self.common_estimate = self._common_value(theta, ws)
        s2 = self._sigma_at(eff) ** 2
        # lam^-1 from its factor (LAPACK's dpotri is as fast single-threaded, but 100x slower under
        # OpenBLAS threads on a small matrix)
        cov, fail = _lapack().dpotrs(cho, _identity(cho.shape[0]))
        if fail != 0:
            return
        self._cov = cov  # white: the gate's predictive covariance
        vif = self._vif_at(s2)
        self._pub = None
        self._n_refresh += 1
        if self.theta_from is not None and self.theta_from.n > 0:
            self._pub = self._conditioned(theta, cov * vif, self.theta_from)
        if self._pub is not None:
            assert self.theta_from is not None
            # the two models' own estimates apart (L, d, theta and the motors' thetas; departure from the
            # paper: its observer has one model, and its heading sigma no model uncertainty)
            dp = self.theta_from._theta - theta
            self._solution = self._build(self._pub[0], self._pub[1] / vif, s2, vif, dp)
        else:
            self._solution = self._build(theta, cov, s2, vif)
        if SPLIT_CHECK and self.n_windows > 0:
            # the halves change only when a window closes: recomputed then (the noise scale and the
            # throttle statistics of that moment), not at every solution (+17 % CPU on log171's replay)
            if self._split_cache is None or self._split_cache[0] != self.n_windows:
                self._split_cache = (self.n_windows, self.split_heading_deg(s2))
            split = self._split_cache[1]
            sol = self._solution
            # the fields written out (``dataclasses.replace`` costs 6 us a solution in introspection)
            self._solution = InflightSolution(
                calib_l=sol.calib_l, calib_d=sol.calib_d, theta_mgauss=sol.theta_mgauss,
                motor_theta_mgauss=sol.motor_theta_mgauss, theta_sigma_mgauss=sol.theta_sigma_mgauss,
                heading_sigma_deg=math.hypot(sol.heading_sigma_deg, split),
                residual_rms_mgauss=sol.residual_rms_mgauss, n=sol.n,
                variance_inflation=sol.variance_inflation, heading_model_deg=sol.heading_model_deg,
                heading_split_deg=split,
            )  # fmt: skip
        self._rev += 1
        self._dirty = False

    def _prior_rhs(self) -> F64:
        """``prior_info @ prior_mean``, the prior's right-hand side (computed once per prior)."""
        c = self._prior_b_cache
        if c is None or c[0] is not self.prior_info or c[1] is not self.prior_mean:
            c = self._prior_b_cache = (self.prior_info, self.prior_mean, self.prior_info @ self.prior_mean)
        return c[2]

    def _conditioned(self, p: F64, cov: F64, other: InflightEstimator) -> tuple[F64, F64] | None:
        """This estimate conditioned on theta = ``other``'s theta (a Schur complement, no second pass):
        ``p + G (theta_o - theta_p)``, ``G = C[:, th] C[th, th]^-1``, with the covariance
        ``C - G C[th, :] + G C_o G^T`` (``other``'s theta taken as an independent measurement of it; with
        THETA_MODEL_SPREAD, ``C_o`` plus the outer product of the two thetas' difference). Both covariances
        inflated. None when the block is singular. Departure from the paper: its observer has one model."""
        k = self._k
        th = slice(k + 3, k + 6)
        if self._sync or other._solution is None or self._n_refresh % max(1, self.theta_from_every) == 0:
            other.solve()
        self._sync = False
        p_o = other._theta
        if other._cov is None or p_o.shape != p.shape:
            return None
        c_o = other._cov[th, th] * other.variance_inflation
        if THETA_MODEL_SPREAD:
            dth = p_o[th] - p[th]
            c_o = c_o + np.outer(dth, dth)
        _, g_t, fail = _lapack().dposv(cov[th, th], cov[th, :])  # LAPACK's Cholesky: numpy's solve costs 5x
        if fail != 0:  # not positive definite: a general solve, as singular as it is
            try:
                g_t = np.linalg.solve(cov[th, th], cov[th, :])
            except np.linalg.LinAlgError:
                return None
        g = g_t.T
        mean = p + g @ (p_o[th] - p[th])
        cov_c = cov - g @ cov[th, :] + g @ c_o @ g.T
        return mean, 0.5 * (cov_c + cov_c.T)

    def sync_theta_from(self) -> None:
        """The next solution takes ``theta_from``'s latest theta, whatever ``theta_from_every`` says (the
        final state of a log, the state stored for a later run)."""
        if self.theta_from is not None and self.theta_from._dirty:
            self._sync = True
            self._dirty = True

    def _build(
        self, p: F64, cov: F64, s2: float, vif: float = 1.0, spread: F64 | None = None
    ) -> InflightSolution:
        """The solution at parameters ``p``; its sigmas from ``cov`` times the variance inflation ``vif``;
        ``spread``: another model's parameters minus these (the heading they give apart is a model
        uncertainty, HEADING_MODEL_SPREAD)."""
        cov = cov * vif
        grads = self._heading_grads()
        model_deg = 0.0 if spread is None else self._heading_sd_deg(None, grads, spread)
        sd_deg = self._heading_sd_deg(cov, grads)
        if HEADING_MODEL_SPREAD:
            sd_deg = math.hypot(sd_deg, model_deg)
        k = self._k
        if self.mode == "absolute":
            a = p[0:9].reshape(3, 3)
            try:
                l_mat = np.asarray(np.linalg.inv(a), dtype=np.float64)
            except np.linalg.LinAlgError:
                l_mat = np.eye(3)
        else:
            l_mat = np.eye(3) + soft_iron_matrix(p[0:N_SOFT])
        d_raw = p[k : k + 3]
        th_raw = p[k + 3 : k + 6]
        mot_raw = p[k + 6 :].reshape(-1, 3)
        th_cov = cov[k + 3 : k + 6, k + 3 : k + 6]
        th_sd = np.sqrt(np.maximum(np.diag(l_mat @ th_cov @ l_mat.T), 0.0))

        return InflightSolution(
            calib_l=l_mat,
            calib_d=l_mat @ d_raw,
            theta_mgauss=l_mat @ th_raw,
            motor_theta_mgauss=mot_raw @ l_mat.T,
            theta_sigma_mgauss=th_sd,
            heading_sigma_deg=sd_deg,
            residual_rms_mgauss=math.sqrt(s2),
            n=self.n,
            variance_inflation=vif,
            heading_model_deg=model_deg,
        )

    def _heading_grads(self) -> F64:
        """The heading's gradients (rad per unit parameter) of :meth:`_heading_sd_deg`: (2, 8, n), at the
        mean and at the largest delta^2 seen, for each of the eight headings.

        The corrected field is ``u = (I + E)(y - d - theta x)`` (relative form; ``u = A^-1 (...)``,
        absolute), so ``du = dE u - dd - x dtheta`` and the heading moves by ``(u_x du_y - u_y du_x) /
        H^2``, i.e. by ``w . du`` with ``w = (-u_y, u_x, 0) / H^2``."""
        h_ned = self.field_ned_mgauss
        k = self._k
        n = self.info.shape[0]
        mean_x0 = self._x0_sum / self.n if self.n else 0.0
        # all but theta's columns depend on the Earth field only: built once per field
        key = (float(h_ned[0]), float(h_ned[1]), float(h_ned[2]), n)
        cached = self._grad_cache
        if cached is None or cached[0] != key:
            cached = self._grad_cache = (key, *self._heading_grads_field(n))
        _, base, w = cached
        g = np.empty((2, 8, n))
        g[:] = base
        for i, x0 in enumerate((mean_x0, self.x0_max)):  # only theta's columns depend on delta^2
            g[i, :, k + 3 : k + 6] = -x0 * w
        return g

    def _heading_grads_field(self, n: int) -> tuple[F64, F64]:
        """:meth:`_heading_grads` but theta's columns (8, n), and ``w`` (8, 3)."""
        h_ned = self.field_ned_mgauss
        h = max(float(np.hypot(h_ned[0], h_ned[1])), 50.0)
        v_z = float(h_ned[2])
        k = self._k
        u = np.empty((8, 3))
        u[:, 0] = h * np.cos(_PSI8_RAD)
        u[:, 1] = -h * np.sin(_PSI8_RAD)
        u[:, 2] = v_z
        w = np.zeros((8, 3))
        w[:, 0] = -u[:, 1] / (h * h)
        w[:, 1] = u[:, 0] / (h * h)
        g = np.zeros((8, n))
        if self.mode == "absolute":
            for r in range(3):
                g[:, 3 * r : 3 * r + 3] = -w[:, r : r + 1] * u
        else:
            g[:, :N_SOFT] = np.einsum("pi,kij,pj->pk", w, _SOFT_BASIS, u)
            # a yaw offset of the mount is neither seen by rotations nor corrected (its estimate stays 0):
            # it is the same in the corrected and the uncorrected heading
            g[:, N_SOFT - 1] = 0.0
        g[:, k : k + 3] = -w
        return g, w

    def _heading_sd_deg(self, cov: F64 | None, grads: F64 | None = None, spread: F64 | None = None) -> float:
        """Heading standard deviation (deg) the parameters' joint covariance ``cov`` leaves on a level
        vehicle, rms over eight headings, at the mean and at the largest delta^2 seen (the larger of the
        two); ``spread`` instead of ``cov``: the covariance ``outer(spread, spread)``. ``grads``:
        :meth:`_heading_grads` when already computed.

        The joint covariance matters: in level yaw turns a compass tilted on its mount leaks the vertical
        field into a constant horizontal offset, exactly as a hard iron does, so either alone is poorly
        known while their sum, which is what the heading sees when level, is well known."""
        g = self._heading_grads() if grads is None else grads
        if spread is not None:
            var = np.square(g @ spread).sum(axis=1)
        else:
            assert cov is not None
            var = np.einsum("ipa,ipa->i", g @ cov, g)
        worst = max(0.0, float(var[0]) / 8.0)
        worst = max(worst, float(var[1]) / 8.0)
        return math.degrees(math.sqrt(worst))

    def solve(self) -> InflightSolution:
        """The current estimate (recomputed only when data came in since the last call)."""
        if self._dirty or self._solution is None:
            self._refresh()
        if self._solution is None:  # a singular system even with the prior: cannot happen with finite data
            raise ValueError("in-flight estimate is singular")
        return self._solution

    def state(self, inflate: float = WARM_INFLATE) -> tuple[F64, F64]:
        """(mean, standard deviation) of the parameters to start a later run from: the posterior, its
        standard deviation multiplied by ``inflate`` (the vehicle may have changed since: a new battery
        position, a moved wire) and never below a tenth of the prior's, nor above the physical prior of a
        first run (InflightParams: what nothing was learned about stays as uncertain as it was, instead of
        doubling with every run). The covariance includes the variance inflation: a later run must not be
        held to this one's estimate more firmly than its correlated residuals allow."""
        self.solve()
        cov = self._cov * self.variance_inflation if self._cov is not None else np.linalg.inv(self.prior_info)
        mean = self._theta
        if self._pub is not None:  # conditioned on another estimator's theta: what was published
            mean, cov = self._pub
        sd = np.sqrt(np.maximum(np.diag(cov), 0.0)) * inflate
        floor = 0.1 / np.sqrt(np.diag(self.prior_info))
        return mean.copy(), np.minimum(np.maximum(sd, floor), np.maximum(self._prior_sd_max, floor))

    def uncalibrated(self, y_mgauss: F64, x: F64) -> F64:
        """``y - d - sum theta_r x_r`` at the current estimate (raw frame, before L): the linearisation
        point of the relative form's soft-iron columns."""
        cached = self._unc_cache
        if cached is None or cached[0] is not self._theta:
            k = self._k
            p = self._theta
            cached = self._unc_cache = (p, p[k : k + 3], p[k + 3 :].reshape(-1, 3))
        _, d, th = cached
        return np.asarray(y_mgauss - d - x[: th.shape[0]] @ th, dtype=np.float64)


# ----------------------------------------------------------------------------------------------------------
# which form a compass gets: does the autopilot's yaw come from something this compass does not disturb?

#: ArduPilot's per-compass "external" flags (0 internal, 1 external, 2 forced external), by compass index
ARDUPILOT_EXTERNAL_PARAMS = ("COMPASS_EXTERNAL", "COMPASS_EXTERN2", "COMPASS_EXTERN3")
#: ArduPilot's hard-iron offsets by compass index (any non-zero: the autopilot calibrated that compass)
ARDUPILOT_OFFSET_PARAMS = ("COMPASS_OFS_", "COMPASS_OFS2_", "COMPASS_OFS3_")


#: ArduPilot's EKF3 yaw sources that are not a compass (EK3_SRC1_YAW, AP_NavEKF_Source): 3 falls back to the
#: compass only while the GPS yaw is lost
EK3_YAW_NOT_COMPASS = {
    2: "GPS",
    3: "GPS",
    6: "external navigation",
    8: "the GSF yaw estimator (GPS velocity and the IMU)",
}


def yaw_reference(params: dict[str, float], mag_index: int) -> tuple[InflightMode, str]:
    """The form for compass ``mag_index`` from the autopilot's parameters, and why (one phrase).

    absolute: the autopilot's yaw comes from no compass (ArduPilot EK3_SRC1_YAW = 2, 3, 6 or 8 with EKF3
    active; PX4 EKF2_GPS_CTRL bit 3, EKF2_MAG_TYPE = 5) or from another compass that is external
    (ArduPilot COMPASS_PRIMARY, instance 0 since 4.1 orders compasses by COMPASS_PRIOn_ID, and
    COMPASS_EXTERNAL*).
    relative: the yaw is fused from this compass, or from an internal one that sees the same currents, or
    the parameters do not say (a tlog without PARAM_VALUE): the safe form.
    """
    src = params.get("EK3_SRC1_YAW")
    ekf3 = int(params.get("AHRS_EKF_TYPE", 3.0)) == 3  # EKF3's sources matter only when it flies
    if ekf3 and src is not None and int(src) in EK3_YAW_NOT_COMPASS:
        why = f"the autopilot's yaw comes from {EK3_YAW_NOT_COMPASS[int(src)]} (EK3_SRC1_YAW = {int(src)})"
        return "absolute", why
    gps_ctrl = params.get("EKF2_GPS_CTRL")
    if gps_ctrl is not None and int(gps_ctrl) & 8:
        return "absolute", "the autopilot's yaw comes from GPS (EKF2_GPS_CTRL bit 3)"
    mag_type = params.get("EKF2_MAG_TYPE")
    if mag_type is not None and int(mag_type) == 5:  # PX4 EKF2: no magnetometer fused (GPS / vision yaw)
        return "absolute", "the autopilot fuses no magnetometer (EKF2_MAG_TYPE = 5)"
    if "COMPASS_PRIMARY" not in params and not any(k in params for k in ARDUPILOT_EXTERNAL_PARAMS):
        return "relative", "the autopilot's yaw source is unknown (no compass parameters): rotations only"
    primary = ardupilot_primary_compass(params)
    if primary == mag_index:
        return "relative", f"the autopilot's yaw is fused from this compass (primary {primary})"
    ext_key = ARDUPILOT_EXTERNAL_PARAMS[primary] if 0 <= primary < len(ARDUPILOT_EXTERNAL_PARAMS) else ""
    ext = params.get(ext_key)
    if ext is not None and int(ext) in (1, 2):
        why = f"the autopilot's yaw comes from compass {primary}, external ({ext_key} = {int(ext)})"
        return "absolute", why
    return "relative", f"the autopilot's yaw comes from compass {primary}, internal: rotations only"


#: ArduPilot's per-compass "use for yaw" flags, by compass index
ARDUPILOT_USE_PARAMS = ("COMPASS_USE", "COMPASS_USE2", "COMPASS_USE3")


def ardupilot_primary_compass(params: dict[str, float]) -> int:
    """The compass ArduPilot's EKF takes its yaw from: COMPASS_PRIMARY (up to 4.0) when that compass is used
    for yaw, else the first compass with COMPASS_USEn set (4.1 on has no COMPASS_PRIMARY: it orders the
    compasses by COMPASS_PRIOn_ID, so the first usable one is the primary); 0 when nothing says."""
    primary = int(params.get("COMPASS_PRIMARY", 0.0))
    usable = [i for i, k in enumerate(ARDUPILOT_USE_PARAMS) if params.get(k, 1.0) != 0.0]
    if primary in usable or not usable:
        return primary
    return usable[0]


def calibrated_by_autopilot(params: dict[str, float], mag_index: int) -> bool | None:
    """True when the autopilot's own hard-iron offsets for this compass are set (its calibration is the
    prior), False when they are all zero, None when the parameters do not say."""
    if 0 <= mag_index < len(ARDUPILOT_OFFSET_PARAMS):
        pre = ARDUPILOT_OFFSET_PARAMS[mag_index]
        vals = [params.get(pre + a) for a in "XYZ"]
        if all(v is not None for v in vals):
            return any(abs(float(v)) > 0.0 for v in vals if v is not None)
    pre_px4 = f"CAL_MAG{mag_index}_"
    vals = [params.get(pre_px4 + a + "OFF") for a in "XYZ"]
    if all(v is not None for v in vals):
        return any(abs(float(v)) > 0.0 for v in vals if v is not None)
    return None


def external_compass(params: dict[str, float], mag_index: int) -> bool | None:
    """True when the autopilot's parameters mark compass ``mag_index`` external (mounted away from the power
    wires, e.g. on a GPS mast), False when internal, None when they do not say."""
    if not 0 <= mag_index < len(ARDUPILOT_EXTERNAL_PARAMS):
        return None
    v = params.get(ARDUPILOT_EXTERNAL_PARAMS[mag_index])
    return None if v is None else int(v) in (1, 2)


def relative_rotation_source(params: dict[str, float], mag_index: int) -> tuple[str, str]:
    """Where the relative form takes its rotations from: ``attitude`` (the autopilot's) whenever it
    streams. Its roll and pitch are GPS-aided; its yaw may follow a disturbed compass, but only slowly
    (the compass correction of its filter), and the relative form carries that slow yaw-rate error as a
    nuisance (InflightEstimator.add). The pipeline's own gyro integral is the fallback: its bias comes
    from an accelerometer-only attitude filter, which in accelerated flight takes the thrust axis for
    down and moves the bias by degrees per second (docs/inflight.md)."""
    if external_compass(params, mag_index):
        return "attitude", "this compass is external (little disturbed): the autopilot's GPS-aided attitude"
    return "attitude", "the autopilot's attitude (GPS-aided tilt; its compass-driven yaw drift estimated)"
