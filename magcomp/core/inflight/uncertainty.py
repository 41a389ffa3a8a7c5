"""How far to trust the in-flight estimate: the residual's correlation in time (the variance inflation of
residual batches), the spread of the estimate between two alternate halves of the data (the split check),
and the heading uncertainty the parameters' covariance implies (rms over eight headings at the throttle
seen); the published :class:`~magcomp.core.inflight.base.InflightSolution` built from them. Departure from
the paper: its observer has no covariance. No I/O."""

from __future__ import annotations

import math

import numpy as np

from magcomp.core.inflight.base import (
    F64,
    HEADING_MODEL_SPREAD,
    InflightMode,
    InflightSolution,
)
from magcomp.core.inflight.rows import N_SOFT, SOFT_BASIS, soft_iron_matrix
from magcomp.core.inflight.solve import common_schur

#: I (3x3), read only: built once, not at every solution
_EYE3 = np.eye(3)
_EYE3.flags.writeable = False

#: the eight headings of the heading-sigma rms (rad)
_PSI8_RAD = np.radians(np.arange(0.0, 360.0, 45.0))


class ResidualBatches:
    """The residual batches of the variance inflation (:meth:`~magcomp.core.inflight.solve.Accumulator.
    vif_at`): how much the residual's correlation in time inflates the parameters' variance (>= 1).

    The information form weighs every sample as independent. The rows' residuals are not: the
    autopilot's yaw and tilt errors, the gyro's bias and unmodelled field changes last seconds to tens of
    seconds, so 50 samples a second carry far fewer independent pieces of information (measured on
    varied simulated flights, docs/inflight.md: theta's errors were 3-15x the white-noise sigma). The
    batch-means estimate over batches of :data:`VIF_BATCH_S`: ``sum_b |S_b|^2 / n_b`` over what white
    residuals would give, where ``S_b`` is a batch's residual sum at the current estimate (each batch
    keeps it as a linear function of the parameters, the windows' nuisance eliminated as in the normal
    equations) and the white expectation has the fit's own share removed. 1 for white residuals, the
    number of samples a batch effectively counts as one for lasting ones. Batches form over nuisance
    windows only.

    The closed batches are stacked: batch b's
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
        # the open batch: its residual sum as c - M p - g common (per closed window, the nuisance
        # eliminated), its sample and window counts
        self._b_c = np.zeros(3)
        self._b_m = np.zeros((3, n))
        self._b_g = np.zeros(3)
        self._b_n = 0
        self._b_windows = 0

    def add_window(self, sums: tuple[F64, F64, F64, int] | None, batch_windows: int) -> None:
        """A closed window's residual sum (``OpenWindow.residual_sums``; None: none) into the open batch,
        which closes after ``batch_windows`` windows."""
        if sums is None:
            return
        dc, dm, dg, n_w = sums
        self._b_c += dc
        self._b_m += dm
        self._b_g += dg
        self._b_n += n_w
        self._b_windows += 1
        if self._b_windows >= batch_windows:
            self.append(self._b_c, self._b_m, self._b_g, self._b_n)
            for a in (self._b_c, self._b_m, self._b_g):
                a[...] = 0.0
            self._b_n = self._b_windows = 0

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


class SampleStats:
    """The number of samples used and their throttle statistics (delta^2: its mean and largest value for the
    heading uncertainty, its spread for the excitation theta needs)."""

    def __init__(self) -> None:
        self.n = 0
        self.x0_max = 0.0  # largest delta^2 seen (for the heading uncertainty)
        self._x0_sum = 0.0
        self._x0_sq = 0.0

    def add(self, x0: float) -> None:
        """One used sample whose collective regressor is ``x0`` (delta^2)."""
        self.n += 1
        if x0 > self.x0_max:  # max() without its call
            self.x0_max = x0
        self._x0_sum += x0
        self._x0_sq += x0 * x0

    def add_block(self, x0: F64) -> None:
        """N used samples whose collective regressors are ``x0`` (N,)."""
        if x0.shape[0] == 0:
            return
        self.n += x0.shape[0]
        self.x0_max = max(self.x0_max, float(x0.max()))
        self._x0_sum += float(x0.sum())
        self._x0_sq += float(x0 @ x0)

    @property
    def mean_x0(self) -> float:
        """The mean delta^2 (0 before any sample)."""
        return self._x0_sum / self.n if self.n else 0.0

    @property
    def throttle2_std(self) -> float:
        """Standard deviation of delta^2 over the samples used: the throttle excitation theta needs."""
        if self.n < 2:
            return 0.0
        m = self._x0_sum / self.n
        return math.sqrt(max(0.0, self._x0_sq / self.n - m * m))


class _Half:
    """One half of the split check: the Schur complements of its closed windows, summed."""

    __slots__ = ("bc", "cc", "info", "pc", "rhs", "windows", "zz")

    def __init__(self, n: int) -> None:
        self.info: F64 = np.zeros((n, n))
        self.rhs: F64 = np.zeros(n)
        self.zz = 0.0
        self.pc: F64 = np.zeros(n)
        self.cc = 0.0
        self.bc = 0.0
        self.windows = 0


class SplitHalves:
    """The closed windows' Schur complements dealt to two halves, alternately per residual batch
    (SPLIT_CHECK): the heading the two halves' own estimates give apart, halved, estimates the whole
    estimate's standard deviation from data each half did not use, whatever the cause of the spread (a bias
    the residual cannot show: the hard iron taking the autopilot's tilt error in turns)."""

    def __init__(self, n: int) -> None:
        self._halves = (_Half(n), _Half(n))
        self._cache: tuple[int, float] | None = None  # (closed windows, heading_deg)

    def add(self, n_windows: int, batch_windows: int, ws: tuple[F64, F64, float, F64, float, float]) -> None:
        """A closing window's Schur complement ``ws`` (``OpenWindow.schur``) into its half: halves alternate
        every ``batch_windows`` windows (the residual batches' length: the slow errors' correlation time);
        ``n_windows`` windows closed before it."""
        info, rhs, zz, pc, cc, bc = ws
        h = self._halves[(n_windows // max(1, batch_windows)) % 2]
        h.info = h.info + info
        h.rhs = h.rhs + rhs
        h.zz = h.zz + zz
        h.pc = h.pc + pc
        h.cc = h.cc + cc
        h.bc = h.bc + bc
        h.windows = h.windows + 1

    def checked(self) -> bool:
        """Both halves hold a closed window: the estimate has met data one of its halves did not use."""
        return min(h.windows for h in self._halves) > 0

    def heading_deg(self, n_windows: int, s2: float, prior_info: F64, prior_b: F64, grads: F64) -> float:
        """The heading (deg, rms over the heading grid of :func:`heading_sd_deg`, ``grads``) that the two
        halves' own estimates give apart, halved: each half solved alone with the prior (information
        ``prior_info``, right-hand side ``prior_b``) at the noise scale ``s2`` (mgauss^2). Two independent
        halves of equal information differ by twice the whole estimate's standard deviation. A half with no
        closed window is the prior: a large spread, honestly. Recomputed only when a window closed since
        (``n_windows``: the halves change only then)."""
        if self._cache is not None and self._cache[0] == n_windows:
            return self._cache[1]
        est = []
        out = 0.0
        for h in self._halves:
            info, rhs, _ = common_schur(h.info, h.pc, h.cc, h.rhs, h.bc, h.zz)
            try:
                est.append(np.linalg.solve(info / s2 + prior_info, rhs / s2 + prior_b))
            except np.linalg.LinAlgError:
                break
        else:
            dp = est[0] - est[1]
            out = 0.5 * heading_sd_deg(grads, np.outer(dp, dp))
        self._cache = (n_windows, out)
        return out


class HeadingSigma:
    """The heading's gradients (rad per unit parameter) over eight headings, at the mean and at the largest
    delta^2 seen (:func:`heading_sd_deg` turns a covariance into the heading's standard deviation)."""

    def __init__(self, mode: InflightMode, k: int) -> None:
        """``k``: where the hard iron starts in the parameter vector."""
        self.mode: InflightMode = mode
        self._k = k
        self._cache: tuple[tuple[float, float, float, int], F64, F64] | None = None

    def grads(self, h_ned: F64, n: int, stats: SampleStats) -> F64:
        """(2, 8, n): at the mean and at the largest delta^2 seen (``stats``), for each of the eight
        headings, with the Earth field ``h_ned`` (NED, mgauss).

        The corrected field is ``u = (I + E)(y - d - theta x)`` (relative form; ``u = A^-1 (...)``,
        absolute), so ``du = dE u - dd - x dtheta`` and the heading moves by ``(u_x du_y - u_y du_x) /
        H^2``, i.e. by ``w . du`` with ``w = (-u_y, u_x, 0) / H^2``."""
        k = self._k
        mean_x0 = stats.mean_x0
        # all but theta's columns depend on the Earth field only: built once per field
        key = (float(h_ned[0]), float(h_ned[1]), float(h_ned[2]), n)
        cached = self._cache
        if cached is None or cached[0] != key:
            cached = self._cache = (key, *self._grads_field(h_ned, n))
        _, base, w = cached
        g = np.empty((2, 8, n))
        g[:] = base
        for i, x0 in enumerate((mean_x0, stats.x0_max)):  # only theta's columns depend on delta^2
            g[i, :, k + 3 : k + 6] = -x0 * w
        return g

    def _grads_field(self, h_ned: F64, n: int) -> tuple[F64, F64]:
        """:meth:`grads` but theta's columns (8, n), and ``w`` (8, 3)."""
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
            g[:, :N_SOFT] = np.einsum("pi,kij,pj->pk", w, SOFT_BASIS, u)
            # a yaw offset of the mount is neither seen by rotations nor corrected (its estimate stays 0):
            # it is the same in the corrected and the uncorrected heading
            g[:, N_SOFT - 1] = 0.0
        g[:, k : k + 3] = -w
        return g, w


def heading_sd_deg(grads: F64, cov: F64 | None = None, spread: F64 | None = None) -> float:
    """Heading standard deviation (deg) the parameters' joint covariance ``cov`` leaves
    on a level vehicle, rms over eight headings, at the mean and at the largest delta^2 seen (the larger of
    the two; ``grads``: :meth:`HeadingSigma.grads`); ``spread`` instead: the covariance ``outer(spread,
    spread)``.

    The joint covariance matters: in level yaw turns a compass tilted on its mount leaks the vertical
    field into a constant horizontal offset, exactly as a hard iron does, so either alone is poorly
    known while their sum, which is what the heading sees when level, is well known."""
    g = grads
    if spread is not None:
        var = np.square(g @ spread).sum(axis=1)
    else:
        assert cov is not None
        var = np.einsum("ipa,ipa->i", g @ cov, g)
    worst = max(0.0, float(var[0]) / 8.0)
    worst = max(worst, float(var[1]) / 8.0)
    return math.degrees(math.sqrt(worst))


def build_solution(
    mode: InflightMode, k: int, p: F64, cov: F64, s2: float, vif: float, grads: F64, n: int,
    spread: F64 | None = None,
) -> InflightSolution:  # fmt: skip
    """The solution at parameters ``p`` (``k``: where the hard iron starts); its sigmas from ``cov`` times
    the variance inflation ``vif``; ``spread``: another model's parameters minus these (the heading they
    give apart is a model uncertainty, HEADING_MODEL_SPREAD); ``n`` samples used."""
    cov = cov * vif
    model_deg = 0.0 if spread is None else heading_sd_deg(grads, None, spread)
    sd_deg = heading_sd_deg(grads, cov)
    if HEADING_MODEL_SPREAD:
        sd_deg = math.hypot(sd_deg, model_deg)
    if mode == "absolute":
        a = p[0:9].reshape(3, 3)
        try:
            l_mat = np.asarray(np.linalg.inv(a), dtype=np.float64)
        except np.linalg.LinAlgError:
            l_mat = np.eye(3)
    else:
        l_mat = _EYE3 + soft_iron_matrix(p[0:N_SOFT])
    d_raw = p[k : k + 3]
    th_raw = p[k + 3 : k + 6]
    mot_raw = p[k + 6 :].reshape(-1, 3)
    th_cov = cov[k + 3 : k + 6, k + 3 : k + 6]
    th_sd = np.sqrt(np.maximum((l_mat @ th_cov @ l_mat.T).diagonal(), 0.0))
    return InflightSolution(
        calib_l=l_mat,
        calib_d=l_mat @ d_raw,
        theta_mgauss=l_mat @ th_raw,
        motor_theta_mgauss=mot_raw @ l_mat.T,
        theta_sigma_mgauss=th_sd,
        heading_sigma_deg=sd_deg,
        residual_rms_mgauss=math.sqrt(s2),
        n=n,
        variance_inflation=vif,
        heading_model_deg=model_deg,
    )


def with_split(sol: InflightSolution, split: float) -> InflightSolution:
    """``sol`` with the split check's heading (SPLIT_CHECK) added in quadrature to its heading sigma."""
    # the fields written out (``dataclasses.replace`` costs 6 us a solution in introspection)
    return InflightSolution(
        calib_l=sol.calib_l, calib_d=sol.calib_d, theta_mgauss=sol.theta_mgauss,
        motor_theta_mgauss=sol.motor_theta_mgauss, theta_sigma_mgauss=sol.theta_sigma_mgauss,
        heading_sigma_deg=math.hypot(sol.heading_sigma_deg, split),
        residual_rms_mgauss=sol.residual_rms_mgauss, n=sol.n,
        variance_inflation=sol.variance_inflation, heading_model_deg=sol.heading_model_deg,
        heading_split_deg=split,
    )  # fmt: skip
