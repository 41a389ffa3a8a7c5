"""The normal equations of the in-flight problem and their solution: the rows' information and right-hand
side (unit weight), the blocks of the one unknown common to the flight (eliminated by a Schur complement),
the Gaussian prior (the autopilot's calibration, or a stored run's estimate), and the conditioning of an
estimate on another estimator's theta. Recursive least squares in information form; no I/O."""

from __future__ import annotations

import numpy as np

from magcomp.core.inflight.base import F64, THETA_MODEL_SPREAD, InflightMode, InflightParams, lapack
from magcomp.core.inflight.rows import N_SOFT, N_SYM, n_params
from magcomp.core.inflight.window import WindowSchur


def common_schur(pp: F64, pc: F64, cc: float, bp: F64, bc: float, zz: float) -> tuple[F64, F64, float]:
    """(info, rhs, z'z) with the unknown common to the flight eliminated (none yet: as they are)."""
    if cc <= 0.0:
        return pp, bp, zz
    k_p = pc / cc
    return pp - np.outer(k_p, pc), bp - k_p * bc, zz - bc * bc / cc


class NormalEquations:
    """The data information ``sum rows' rows`` and right-hand side ``sum rows' z`` (unit weight) with z'z,
    the closed nuisance windows folded in, and the blocks of the one unknown common to the flight (the field
    norm of the norm rows, or the vertical Earth field of window-field rows), eliminated when solving (a
    Schur complement, like a window that never closes)."""

    def __init__(self, n: int) -> None:
        self.info = np.zeros((n, n))
        self.rhs = np.zeros(n)
        self.zz = 0.0  # sum of z'z (for the residual sum of squares)
        # the norm rows' parameter blocks and z'z; the common unknown's blocks (norm rows and closed windows)
        self.norm_pp = np.zeros((n, n))
        self.norm_bp = np.zeros(n)
        self.norm_zz = 0.0
        self.common_pc = np.zeros(n)
        self.common_cc = 0.0
        self.common_bc = 0.0
        self.n_norm = 0

    def add_rows(self, rows: F64, z: F64) -> None:
        """One sample's rows without nuisance."""
        self.zz += float(z @ z)
        self.info += rows.T @ rows
        self.rhs += rows.T @ z

    def add_window(self, ws: WindowSchur) -> None:
        """A closed window's rows with its nuisance eliminated (``OpenWindow.schur``)."""
        info, rhs, zz, pc, cc, bc = ws
        self.info += info
        self.rhs += rhs
        self.zz += zz
        self.common_pc += pc
        self.common_cc += cc
        self.common_bc += bc

    def add_norm(self, g: F64, z: float, c: float) -> None:
        """One field-norm row (``rows.norm_row``): parameters ``g``, right-hand side ``z``, the common
        unknown's coefficient ``c``."""
        self.norm_pp += np.outer(g, g)
        self.common_pc += g * c
        self.common_cc += c * c
        self.norm_bp += g * z
        self.common_bc += c * z
        self.norm_zz += z * z
        self.n_norm += 1

    def effective(self, ws: WindowSchur | None) -> tuple[F64, F64, float]:
        """(info, rhs, z'z) of every row so far, the norm rows and the open nuisance window's ``ws`` (None:
        no window open) included, the unknown common to the flight eliminated."""
        pp, bp, zz = self.info + self.norm_pp, self.rhs + self.norm_bp, self.zz + self.norm_zz
        pc, cc, bc = self.common_pc, self.common_cc, self.common_bc
        if ws is not None:
            w_pp, w_bp, w_zz, w_pc, w_cc, w_bc = ws
            pp, bp, zz = pp + w_pp, bp + w_bp, zz + w_zz
            pc, cc, bc = pc + w_pc, cc + w_cc, bc + w_bc
        return common_schur(pp, pc, cc, bp, bc, zz)

    def common_value(self, p: F64, ws: WindowSchur | None) -> float:
        """The common unknown's least-squares value at parameters ``p`` (back-substitution of its Schur
        complement; 0 when there is none); ``ws``: the open window's share (None: none)."""
        pc, cc, bc = self.common_pc, self.common_cc, self.common_bc
        if ws is not None:
            _, _, _, w_pc, w_cc, w_bc = ws
            pc, cc, bc = pc + w_pc, cc + w_cc, bc + w_bc
        return 0.0 if cc <= 0.0 else float((bc - pc @ p) / cc)


class GaussianPrior:
    """The parameters' prior: the autopilot's calibration (A = I, d = 0, theta = 0, with the standard
    deviations of :class:`InflightParams`) or a stored run's (mean, standard deviation)."""

    def __init__(
        self, mode: InflightMode, n_motors: int, p: InflightParams, warm: tuple[F64, F64] | None
    ) -> None:
        n = n_params(mode, n_motors)
        prior_mean = np.zeros(n)
        prior_sd = np.empty(n)
        if mode == "absolute":
            prior_mean[0:9] = np.eye(3).ravel()
            prior_sd[0:9] = p.sigma_a
            k = 9
        else:
            prior_sd[0:N_SOFT] = p.sigma_a
            prior_sd[N_SYM:N_SOFT] = min(p.sigma_a, p.sigma_rot_rad)
            k = N_SOFT
        prior_sd[k : k + 3] = p.sigma_d_mgauss
        prior_sd[k + 3 : k + 6] = p.sigma_theta_mgauss
        prior_sd[k + 6 :] = p.sigma_motor_mgauss
        #: where the hard iron starts in the parameter vector (theta 3 later, the motors' thetas after it)
        self.k = k
        #: the physical prior bounds every later run's: an unobserved parameter's inflated sd stops there
        self.sd_max = prior_sd.copy()
        if warm is not None and warm[0].shape == (n,) and warm[1].shape == (n,):
            prior_mean = np.asarray(warm[0], dtype=float).copy()
            prior_sd = np.maximum(np.asarray(warm[1], dtype=float), 1e-6)
        self.mean = prior_mean
        self.info = np.diag(1.0 / prior_sd**2)
        self._rhs: F64 | None = None

    def rhs(self) -> F64:
        """``info @ mean``, the prior's right-hand side (computed once)."""
        if self._rhs is None:
            self._rhs = self.info @ self.mean
        return self._rhs


def map_estimate(info: F64, rhs: F64, s2: float, prior: GaussianPrior) -> tuple[F64, F64] | None:
    """The MAP estimate of the normal equations (unit weight) at the noise scale ``s2`` (mgauss^2) under
    ``prior``: (Cholesky factor of the posterior information, the estimate); None when it is not positive
    definite. LAPACK's Cholesky solve (its factor kept for the covariance)."""
    lam = info / s2 + prior.info
    b = rhs / s2 + prior.rhs()
    cho, theta, fail = lapack().dposv(lam, b)
    return None if fail != 0 else (cho, theta)


def condition_on_theta(p: F64, cov: F64, k: int, p_o: F64, c_o: F64) -> tuple[F64, F64] | None:
    """The estimate ``p`` (covariance ``cov``) conditioned on theta = another estimator's theta ``p_o[th]``
    (a Schur complement, no second pass; ``k``: where the hard iron starts): ``p + G (theta_o - theta_p)``,
    ``G = C[:, th] C[th, th]^-1``, with the covariance ``C - G C[th, :] + G C_o G^T`` (``c_o``, the other's
    theta covariance, taken as an independent measurement of it; with THETA_MODEL_SPREAD plus the outer
    product of the two thetas' difference). None when the block is singular. Departure from the paper: its
    observer has one model."""
    th = slice(k + 3, k + 6)
    if THETA_MODEL_SPREAD:
        dth = p_o[th] - p[th]
        c_o = c_o + np.outer(dth, dth)
    _, g_t, fail = lapack().dposv(cov[th, th], cov[th, :])  # LAPACK's Cholesky: numpy's solve costs 5x
    if fail != 0:  # not positive definite: a general solve, as singular as it is
        try:
            g_t = np.linalg.solve(cov[th, th], cov[th, :])
        except np.linalg.LinAlgError:
            return None
    g = g_t.T
    mean = p + g @ (p_o[th] - p[th])
    cov_c = cov - g @ cov[th, :] + g @ c_o @ g.T
    return mean, 0.5 * (cov_c + cov_c.T)
