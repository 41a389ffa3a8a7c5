"""The measurement rows of the in-flight problem, written once: eqs. (1), (2), (11) and (13) in the absolute
form, their differenced (relative) and window-field forms, the field-norm row and the nuisance columns (the
reference's yaw error, the rotation source's rate and tilt errors). Pure functions of their arguments (no
state; the only caches are read-only templates). Units: mgauss, throttle 0..1; frames: body FRD, earth NED."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from magcomp.core.inflight.base import F64, InflightMode
from magcomp.core.linalg3 import Vec3Like

#: basis of the relative form's soft-iron correction E (L = I + E): symmetric and traceless (x-y, x+y-2z
#: scale differences and the three off-diagonal terms). A common scale is left out: rotations cannot see
#: it (L -> 0 would fit every pair), and heading does not need it.
SYM_BASIS = np.array(
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
ROT_BASIS = np.array(
    [
        [[0, 0, 0], [0, 0, -1], [0, 1, 0]],
        [[0, 0, 1], [0, 0, 0], [-1, 0, 0]],
        [[0, -1, 0], [1, 0, 0], [0, 0, 0]],
    ],
    dtype=float,
)
SOFT_BASIS = np.concatenate([SYM_BASIS, ROT_BASIS])
#: the identity, built once (read only): the per-sample rows copy it rather than call np.eye each time
_EYE3 = np.eye(3)
_EYE3.flags.writeable = False
_I3 = np.arange(3)
_I3.flags.writeable = False
_ZERO3 = np.zeros(3)
_ZERO3.flags.writeable = False
N_SYM = SYM_BASIS.shape[0]
N_SOFT = SOFT_BASIS.shape[0]
#: minus the soft-iron basis as one (3 N_SOFT, 3) matrix, rows in (i, k) order: ``(_NEG_SOFT_ROWS @ v)
#: .reshape(3, N_SOFT)`` is the (3, N_SOFT) block ``-[S_k v]`` in one product
_NEG_SOFT_ROWS = -SOFT_BASIS.transpose(1, 0, 2).reshape(3 * N_SOFT, 3)
_NEG_SOFT_ROWS.flags.writeable = False
#: the largest magnitude a row, target or nuisance entry may have (mgauss, or mgauss per unit regressor):
#: a million gauss, far beyond any magnetometer's range, and far below where the normal equations'
#: products of up to ~10^4 rows of 30 such entries would overflow a float64
ROW_ENTRY_MAX = 1e9


_MAX_REDUCE = np.maximum.reduce  # ndarray.max without its Python wrapper (a NaN propagates alike)


def bounded(a: F64) -> bool:
    """Every entry finite and within :data:`ROW_ENTRY_MAX` (a NaN compares False)."""
    return bool(_MAX_REDUCE(np.abs(a), axis=None) <= ROW_ENTRY_MAX)


def augmented(rows: F64, z: F64, nuisance: F64, common: F64 | None) -> F64:
    """A sample's augmented columns ``[rows | common | z | nuisance]`` (3, n + 2 + k): what the open window's
    Gram matrix sums (:class:`~magcomp.core.inflight.window.OpenWindow`), checked whole by :func:`bounded`."""
    c = _ZERO3 if common is None else common
    return np.concatenate((rows, c.reshape(3, 1), z.reshape(3, 1), nuisance), axis=1)


def n_params(mode: InflightMode, n_motors: int) -> int:
    """Size of the parameter vector: [A (9, row-major) if absolute | E (5) if relative] + d (3)
    + theta (3) + motors (3 m)."""
    return (9 if mode == "absolute" else N_SOFT) + 6 + 3 * n_motors


def soft_iron_matrix(e: F64) -> F64:
    """E (3x3, symmetric, traceless) of the relative form's soft-iron parameters."""
    return np.asarray(e @ SOFT_BASIS.reshape(N_SOFT, 9), dtype=np.float64).reshape(3, 3)


def regressor_values(throttle_01: float, motors_01: tuple[float, ...] | None) -> tuple[float, ...]:
    """x_0 = delta^2 (eq. (11)) and, when motor outputs are known, x_j = m_j^2 - delta^2 (mean-free, so the
    per-motor vectors only add what the collective throttle^2 cannot explain), as floats: what one sample
    carries until its rows are built a block at a time (an array per sample cost ~1 us)."""
    d2 = throttle_01 * throttle_01
    if not motors_01:
        return (d2,)
    return (d2, *[float(m) * float(m) - d2 for m in motors_01])


def regressors(throttle_01: float, motors_01: tuple[float, ...] | None) -> F64:
    """:func:`regressor_values` as an array (n_r,)."""
    return np.array(regressor_values(throttle_01, motors_01))


def absolute_rows(
    field_ref_b_mgauss: F64, field_mgauss: Vec3Like, x: F64 | tuple[float, ...]
) -> tuple[F64, F64]:
    """Rows (3, n) and right-hand side (3,) of ``y = A u_ref + d + sum theta_r x_r`` (absolute form).
    ``field_ref_b_mgauss`` = R_nb^T h_n, the Earth field in body axes from the trusted attitude."""
    n_r = len(x)
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


def _yaw_error_ned(h_ned: Vec3Like) -> tuple[float, float, float]:
    """``-(e_3 x h)`` (NED): the Earth field's first-order change per radian of yaw error of the attitude
    (``Rz(e) R_nb`` for ``R_nb``)."""
    return (float(h_ned[1]), -float(h_ned[0]), 0.0)


def window_nuisance_cols(
    r_nb: F64, h_w: Vec3Like, tau: float, tilt: bool = True, vh: tuple[float, float, float] | None = None
) -> F64:
    """One row's nuisance columns (3, k): :func:`window_nuisance_cols_block` for one sample."""
    vh_b = None if vh is None else np.array([vh], dtype=np.float64)
    return window_nuisance_cols_block(r_nb[None], h_w, np.array([tau]), tilt, vh_b)[0]


def window_nuisance_cols_block(
    r_nb: F64, h_w: Vec3Like, tau: F64, tilt: bool = True, vh: F64 | None = None
) -> F64:
    """The window-field rows' nuisance columns (N, 3, k) of N samples (attitudes ``r_nb`` (N, 3, 3), times
    ``tau`` (N,) from the window's middle) of one window (:func:`window_field_rows`), all ``R_nb^T c`` for
    NED vectors ``c``, so one product per sample: the window's horizontal field (``R^T e_N``, ``R^T e_E``:
    the rows' ``field_cols``); the rotation source's yaw-rate error about the window's field ``h_w`` (yaw
    error = rate x ``tau``: ``R^T (-(e_3 x h)) tau``, the column of :func:`reference_yaw_error_rows`); with
    ``tilt``, its tilt error about north and east (``R^T (e_N x h)``, ``R^T (e_E x h)``: the vertical carries
    it); with ``vh`` (N, 3) (the tilt that the autopilot's yaw error makes, ``v x h``:
    ``yawframe.YawErrorLine``) its column ``R^T (v x h)`` last, added times ``tau`` to the yaw-rate column
    too (the window's yaw rate tilts it as well)."""
    h1, h2, h3 = float(h_w[0]), float(h_w[1]), float(h_w[2])
    n_s = tau.shape[0]
    k = 3 + (2 if tilt else 0) + (0 if vh is None else 1)
    c = np.zeros((n_s, 3, k))
    c[:, 0, 0] = 1.0
    c[:, 1, 1] = 1.0
    yaw_dir = np.array(_yaw_error_ned(h_w))
    if vh is None:
        c[:, :, 2] = tau[:, None] * yaw_dir
    else:
        c[:, :, 2] = tau[:, None] * (yaw_dir + vh)
        c[:, :, k - 1] = vh
    # rows N, E, D; columns e_N, e_E, the yaw rate's, then e_N x h = (0, -h3, h2), e_E x h = (h3, 0, -h1)
    if tilt:
        c[:, :, 3] = (0.0, -h3, h2)
        c[:, :, 4] = (h3, 0.0, -h1)
    return np.asarray(np.matmul(r_nb.transpose(0, 2, 1), c), dtype=np.float64)


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

    E is traceless (see SOFT_BASIS): a common scale would fit every pair with L -> 0."""
    n_r = x0.shape[0]
    eye = np.eye(3)
    k = N_SOFT
    rows = np.empty((3, k + 3 + 3 * n_r))
    a = y1_mgauss if v1 is None else v1
    b = y0_mgauss if v0 is None else v0
    # column k: -(S_k a - Q S_k b)
    rows[:, 0:k] = -(np.einsum("kij,j->ik", SOFT_BASIS, a) - q_b1b0 @ np.einsum("kij,j->ik", SOFT_BASIS, b))
    rows[:, k : k + 3] = eye - q_b1b0
    for r in range(n_r):
        rows[:, k + 3 + 3 * r : k + 6 + 3 * r] = x1[r] * eye - x0[r] * q_b1b0
    return rows, y1_mgauss - q_b1b0 @ y0_mgauss


class WindowFieldRows(NamedTuple):
    """One sample's rows of the window-field form (:func:`window_field_rows`): ``rows`` (3, n) over the
    relative form's parameters, right-hand side ``z`` (3,), ``field_cols`` (3, 2) of the window's
    horizontal Earth field (a nuisance per window) and ``common`` (3,) the column of the vertical Earth
    field (one unknown for the flight); N samples' (:func:`window_field_rows_block`) with a leading axis
    N."""

    rows: F64
    z: F64
    field_cols: F64
    common: F64


def window_field_rows(
    r_nb: F64, y_mgauss: F64, x: F64, v: F64, like: WindowFieldRows | None = None
) -> WindowFieldRows:
    """One sample's rows of the window-field form: :func:`window_field_rows_block` for one sample."""
    like_b = None if like is None else WindowFieldRows(like.rows[None], like.z[None], like.field_cols[None],
                                                       like.common[None])  # fmt: skip
    w = window_field_rows_block(np.asarray(r_nb, dtype=np.float64)[None], np.asarray(y_mgauss)[None],
                                np.asarray(x)[None], np.asarray(v)[None], like_b)  # fmt: skip
    return WindowFieldRows(w.rows[0], w.z[0], w.field_cols[0], w.common[0])


def window_field_rows_block(
    r_nb: F64, y_mgauss: F64, x: F64, v: F64, like: WindowFieldRows | None = None
) -> WindowFieldRows:
    """Rows of the relative form's unknowns written against the Earth field of a short window instead of
    an earlier sample (eqs. (2), (11), (13)), for N samples (attitudes ``r_nb`` (N, 3, 3), fields
    ``y_mgauss`` (N, 3), regressors ``x`` (N, n_r))::

        y = d + sum_r theta_r x_r + (I - E) R_nb^T n_w,   n_w = (a_w, b_w, h_D)

    ``R_nb`` the rotation source's attitude, whose yaw is trusted only within a window: the window's
    horizontal field ``(a_w, b_w)`` (its direction *and* size) is a free nuisance, so a yaw error constant
    over the window (the autopilot's compass-driven yaw) costs nothing; the vertical ``h_D`` is one
    unknown common to the flight, since a yaw error leaves it alone (the DPI invariance of eq. (3)). The
    soft-iron term is linearised at the current estimate, ``E R^T n ~ E v`` with ``v = y - d - Theta x``
    (N, 3) (as :func:`relative_rows`). Unlike the 0.3 s pairs, every throttle change within a window and
    every one along the vertical, however slow, informs theta.

    Returns rows (N, 3, n), z (N, 3), field_cols (N, 3, 2), common (N, 3). ``like``: these samples' rows at
    another linearisation point (another estimator's ``v``): only the soft-iron columns differ, the rest is
    copied from it."""
    k = N_SOFT
    n_s = v.shape[0]
    soft = (v @ _NEG_SOFT_ROWS.T).reshape(n_s, 3, k)
    if like is not None:
        rows = like.rows.copy()
        rows[:, :, 0:k] = soft
        return WindowFieldRows(rows, like.z, like.field_cols, like.common)
    n_r = x.shape[1]
    rows = np.zeros((n_s, 3, k + 3 + 3 * n_r))
    rows[:, :, 0:k] = soft
    rows[:, :, k : k + 3] = _EYE3
    # the x_r I blocks' diagonals
    i3 = _I3
    for j in range(n_r):
        rows[:, i3, k + 3 + 3 * j + i3] = x[:, j : j + 1]
    r = np.asarray(r_nb, dtype=np.float64)
    y = np.asarray(y_mgauss, dtype=np.float64)
    # views of R_nb (read only here and by the estimator, never written)
    return WindowFieldRows(rows, y, r[:, 0:2].transpose(0, 2, 1), r[:, 2])


def norm_row(p: F64, k: int, y_mgauss: F64, x: F64) -> tuple[F64, float, float] | None:
    """One field-norm row of the relative form (eq. (2): ``|L(y - d)| = |h|`` with eq. (11)'s bias removed),
    ``|u| = c`` with ``u = (I + E)(y - d - sum theta_r x_r)`` and ``c`` one unknown common to the flight,
    linearised at the parameters ``p`` (``k``: where the hard iron starts in them). Returns the row ``g``
    (n,), its right-hand side and the common unknown's coefficient, both weighted by sqrt(2) (a pair's
    component has the noise of two samples, a norm row that of one sample projected on the field); None
    when the calibrated field is too weak to have a direction."""
    th = p[k + 3 :].reshape(-1, 3)
    v = np.asarray(y_mgauss - p[k : k + 3] - x[: th.shape[0]] @ th, dtype=np.float64)
    l_mat = np.eye(3) + soft_iron_matrix(p[0:N_SOFT])
    u = l_mat @ v
    nu = float(np.linalg.norm(u))
    if nu < 1.0:
        return None
    e = u / nu
    g = np.empty(p.shape[0])
    g[0:N_SOFT] = e @ np.einsum("kij,j->ik", SOFT_BASIS, v)
    el = e @ l_mat
    g[k : k + 3] = -el
    for r in range(th.shape[0]):
        g[k + 3 + 3 * r : k + 6 + 3 * r] = -float(x[r]) * el
    w = math.sqrt(2.0)
    g *= w
    z = w * (float(g @ p) / w - nu)
    return g, z, -w  # -w: the column of the common norm c
