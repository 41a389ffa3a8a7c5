"""The recursive solver of the in-flight problem for one compass: rows in one at a time (or a window's
worth), the MAP estimate and its uncertainty out. A thin facade over its parts: the accumulator of the
rows (:mod:`~magcomp.core.inflight.accumulate`), the innovation gate (:mod:`~magcomp.core.inflight.gate`),
the solution (:mod:`~magcomp.core.inflight.solve`) and its uncertainty
(:mod:`~magcomp.core.inflight.uncertainty`). No I/O; the state is numpy arrays."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from magcomp.core.inflight.accumulate import Accumulator
from magcomp.core.inflight.base import (
    F64,
    NUISANCE_PRIOR_RAD_S,
    SPLIT_CHECK,
    WARM_INFLATE,
    InflightMode,
    InflightParams,
    InflightSolution,
    identity,
    lapack,
)
from magcomp.core.inflight.gate import innovation_gated, innovation_gated_block
from magcomp.core.inflight.rows import ROW_ENTRY_MAX, augmented, bounded, norm_row
from magcomp.core.inflight.solve import GaussianPrior, condition_on_theta, map_estimate
from magcomp.core.inflight.uncertainty import HeadingSigma, build_solution, with_split


class InflightEstimator:
    """Recursive least squares in information form for one compass.

    ``add`` accumulates ``rows^T rows / s^2`` and ``rows^T z / s^2``; ``solve`` returns the MAP estimate
    under the Gaussian prior. The residual scale ``s`` is estimated from the residuals at the estimate
    (floor :attr:`InflightParams.noise_floor_mgauss`), so the covariance is in real units.
    """

    def __init__(
        self,
        mode: InflightMode,
        n_motors: int,
        p: InflightParams | None = None,
        field_norm_mgauss: float = 500.0,
        warm: tuple[F64, F64] | None = None,
        theta_from: InflightEstimator | None = None,
        theta_solve_every: int = 1,
    ) -> None:
        """``warm``: (mean, standard deviation) of every parameter from an earlier run (the state store),
        used as the prior instead of the autopilot's calibration. ``theta_from``: another estimator of the
        same parameters from other rows whose theta the published solution takes once it has rows, the rest
        conditioned on it (this one's own estimate stays the linearisation point and the gate's); it is
        re-solved at every ``theta_solve_every`` solutions of this one (its cost: a second set of normal
        equations solved), and whenever :meth:`sync_theta_from` asks."""
        self.mode: InflightMode = mode
        #: the Earth field (NED, mgauss) for the heading uncertainty (:meth:`set_earth_field`). Default: the
        #: norm at 60 deg of inclination
        self.field_ned_mgauss: F64 = field_norm_mgauss * np.array([0.5, 0.0, math.sqrt(0.75)])
        self.n_motors = n_motors
        self.p = p or InflightParams()
        self.prior = GaussianPrior(mode, n_motors, self.p, warm)
        self._k = self.prior.k
        n = self.prior.mean.shape[0]
        self.acc = Accumulator(n, self.p.noise_floor_mgauss, NUISANCE_PRIOR_RAD_S)
        self._heading = HeadingSigma(mode, self._k)
        self._theta: F64 = self.prior.mean.copy()
        self._cov: F64 | None = np.asarray(np.linalg.inv(self.prior.info), dtype=np.float64)
        self.n_gated = 0
        #: rows left out as not finite (:meth:`add`, :meth:`add_norm`)
        self.n_nonfinite = 0
        self._solution: InflightSolution | None = None
        self._dirty = True
        #: the unknown common to the flight at the last solution (mgauss; 0 before any)
        self.common_estimate = 0.0
        #: uncalibrated(): theta's d and Theta views, with one regressor their six floats
        self._unc_cache: tuple[F64, F64, F64, tuple[float, ...] | None] | None = None
        self._theta_from = theta_from
        self._theta_every = theta_solve_every
        #: the published (conditioned) mean and covariance (inflated) when a theta is taken
        self._pub: tuple[F64, F64] | None = None
        #: the variance inflation at the last solution (another estimator taking this one's theta reads it)
        self._vif = 1.0
        self._n_refresh = 0
        self._sync = False

    @property
    def n(self) -> int:
        """The number of samples used."""
        return self.acc.stats.n

    @property
    def throttle2_std(self) -> float:
        """Standard deviation of delta^2 over the samples used: the throttle excitation theta needs."""
        return self.acc.stats.throttle2_std

    @property
    def split_checked(self) -> bool:
        """Both halves of the split check hold a closed window: the estimate has met data one of its halves
        did not use (SPLIT_CHECK, relative form; always True with the check off or the absolute form)."""
        return not SPLIT_CHECK or self.mode != "relative" or self.acc.halves.checked()

    def set_earth_field(self, field_ned_mgauss: F64) -> None:
        """The Earth field (NED, mgauss: the WMM's at the vehicle) of the heading uncertainty."""
        self.field_ned_mgauss = field_ned_mgauss

    def add(
        self,
        rows: F64,
        z: F64,
        x0: float,
        nuisance: F64 | None = None,
        window: object = None,
        common: F64 | None = None,
        gate: bool = True,
        prior_sd: float | F64 | None = None,
        batch_windows: int | None = None,
    ) -> float:
        """Add one sample's rows; returns its a-priori residual norm (mgauss) against the current estimate
        (NaN with ``gate`` False: the caller has judged the sample, e.g. with another estimator's gate).

        ``nuisance`` (3, k): columns of an error held constant over ``window`` (any hashable key; a new key
        closes the previous window), estimated with the window's rows and eliminated (Schur complement) so
        that what it can explain informs nothing else. The relative form's rotations carry such slowly
        varying errors: a gyro bias the attitude filter mis-estimates in accelerated flight, the
        autopilot's compass-driven yaw correction (docs/inflight.md). ``prior_sd``: the nuisance's prior
        standard deviation from this row on (its units: rad/s for a rotation-rate error; one value for
        every column or one per column; None: as before, at first NUISANCE_PRIOR_RAD_S);
        ``batch_windows``: nuisance windows per residual batch from this row on (None: as before, at first
        15).

        Innovation gate (:func:`~magcomp.core.inflight.gate.innovation_gated`): a sample whose residual is
        implausible under the predictive covariance is counted in :attr:`n_gated` and not used.

        ``common`` (3,): the column of the one unknown common to the whole flight (window-field rows: the
        vertical Earth field), eliminated when solving; only with a ``nuisance`` window."""
        acc = self.acc
        if prior_sd is not None:
            acc.window.prior_sd = prior_sd
        if batch_windows is not None:
            acc.batch_windows = batch_windows
        # with a nuisance window, its augmented columns are built here and checked at once (one reduction,
        # not four), then summed as they are
        aug = None if nuisance is None else augmented(rows, z, nuisance, common)
        if aug is not None:
            ok = bounded(aug)
        else:
            ok = bounded(rows) and bounded(z) and (common is None or bounded(common))
        if not ok:
            # a NaN, an infinity or a value whose square products overflow (a damaged record upstream):
            # left out. In the normal equations it would make every later solution NaN (LAPACK's
            # Cholesky does not report a NaN matrix as a failure) or its heading sigma 0
            self.n_nonfinite += 1
            return math.nan
        if not gate:
            acc.take(rows, z, x0, nuisance, window, common, aug)
            self._dirty = True
            return math.nan
        r = z - rows @ self._theta  # a new array: the subtractions below go into it
        if common is not None:
            r -= common * self.common_estimate
        h_ee = None
        if nuisance is not None:
            e_hat, h_ee = acc.nuisance_estimate(
                nuisance, r, window, common is not None, self._theta, self.common_estimate
            )
            r -= nuisance @ e_hat
        rn2 = float(r @ r)
        if innovation_gated(r, rn2, rows, nuisance, h_ee, self._cov, self._solution, self.p):
            self.n_gated += 1
            return math.sqrt(rn2)
        acc.take(rows, z, x0, nuisance, window, common, aug)
        self._dirty = True
        return math.sqrt(rn2)

    def add_block(
        self,
        rows: F64,
        z: F64,
        x0: F64,
        nuisance: F64,
        window: object,
        common: F64,
        gate: bool = True,
        prior_sd: float | F64 | None = None,
        batch_windows: int | None = None,
    ) -> NDArray[np.bool_]:
        """N samples' rows (N, 3, n), right-hand sides (N, 3), delta^2 ``x0`` (N,), nuisance columns (N, 3,
        k) and common columns (N, 3), all of nuisance window ``window``, as :meth:`add` takes one sample's
        (the same arguments with a leading axis N); returns which samples were used (N,).

        The gate (``gate``) judges every sample against the last solution and the open window's nuisance
        estimate as they were before the block (:meth:`add` moves the latter with each row): a block is a
        few rows between two solutions. A block that opens its window is not gated: one row's nuisance
        fitted to that row alone (what :meth:`add` does there) leaves it no residual."""
        acc = self.acc
        if prior_sd is not None:
            acc.window.prior_sd = prior_sd
        if batch_windows is not None:
            acc.batch_windows = batch_windows
        aug = np.concatenate((rows, common[:, :, None], z[:, :, None], nuisance), axis=2)
        use = np.abs(aug).max(axis=(1, 2)) <= ROW_ENTRY_MAX  # as bounded(): a NaN compares False
        n_bad = use.shape[0] - int(np.count_nonzero(use))
        self.n_nonfinite += n_bad
        w = acc.window
        if gate and window == w.key and w.ee.shape[0] == nuisance.shape[2] and self._solution is not None:
            out = w.nuisance(acc.rev, True, self._theta, self.common_estimate, acc.s_ref)
            if out is not None:
                e_hat, h_ee = out
                r = z - rows @ self._theta - common * self.common_estimate - nuisance @ e_hat
                gated = innovation_gated_block(r, rows, nuisance, h_ee, self._cov, self._solution, self.p)
                gated &= use
                self.n_gated += int(np.count_nonzero(gated))
                use &= ~gated
        if n_bad or not use.all():
            aug, x0 = aug[use], x0[use]
        if aug.shape[0] > 0:
            acc.take_block(aug, x0, window)
            self._dirty = True
        return use

    def window_nuisance(self, window: object) -> F64 | None:
        """The open window's nuisance estimate at the current parameters when ``window`` is the open one
        and has rows (window-field rows: its horizontal Earth field first), else None."""
        return self.acc.window_nuisance(window, self._theta, self.common_estimate)

    def add_norm(self, y_mgauss: F64, x: F64) -> None:
        """One field-norm row (relative form, :func:`~magcomp.core.inflight.rows.norm_row`), linearised at
        the current estimate.

        The differenced pairs see theta only through the throttle change within a pair (0.3 s); the norm
        of the calibrated field is the Earth field's whatever the attitude, so every throttle change, however
        slow (a climb, forward flight), tells theta's component along the field. A common unknown ``c``
        rather than the WMM's |h|: the relative form has no common scale (a traceless E) and a WMM norm is
        off by a few % locally; eliminating ``c`` keeps only the norm's variation."""
        if not (bounded(y_mgauss) and bounded(x)):  # as in add
            self.n_nonfinite += 1
            return
        row = norm_row(self._theta, self._k, y_mgauss, x)
        if row is None:
            return
        self.acc.add_norm(*row)
        self._dirty = True

    def refill_open_window(self, samples: list[tuple[F64, F64, F64, F64 | None]]) -> None:
        """Replace the open window's rows by ``samples`` (rows, z, nuisance, common): the same samples with
        their nuisance columns written again (relinearised at the window's final estimate). Sample counts
        and throttle statistics stay as they were; nothing happens without an open window."""
        if self.acc.refill(samples):
            self._dirty = True

    def _refresh(self) -> None:
        """Re-solve the normal equations (called by :meth:`solve`; cheap, n <= 30)."""
        acc = self.acc
        # nothing the open window's Schur complement depends on changes here (only theta does): computed
        # once for the refresh
        ws = acc.window_schur()
        eff = acc.eq.effective(ws)
        info, rhs, _ = eff
        # two rounds: the noise scale weighs data against the prior, and is itself the residual at the
        # estimate (the first round's scale comes from the previous estimate)
        for _ in range(2):
            got = map_estimate(info, rhs, acc.sigma_at(self._theta, eff) ** 2, self.prior)
            if got is None:
                return
            cho, theta = got
            self._theta = theta
            acc.rev += 1
        self.common_estimate = acc.common_value(theta, ws)
        s2 = acc.sigma_at(self._theta, eff) ** 2
        # lam^-1 from its factor (LAPACK's dpotri is as fast single-threaded, but 100x slower under
        # OpenBLAS threads on a small matrix)
        cov, fail = lapack().dpotrs(cho, identity(cho.shape[0]))
        if fail != 0:
            return
        self._cov = cov  # white: the gate's predictive covariance
        vif = self._vif = acc.vif_at(theta, self.common_estimate, cov, s2)
        self._pub = None
        self._n_refresh += 1
        other = self._theta_from
        if other is not None and other.n > 0:
            if self._sync or other._solution is None or self._n_refresh % max(1, self._theta_every) == 0:
                other.solve()
            self._sync = False
            p_o, c_w = other._theta, other._cov
            if c_w is not None and p_o.shape == theta.shape:
                th = slice(self._k + 3, self._k + 6)
                # theta's covariance at the other's last solution, with its variance inflation there
                c_o = c_w[th, th] * other._vif
                self._pub = condition_on_theta(theta, cov * vif, self._k, p_o, c_o)
        grads = self._heading.grads(self.field_ned_mgauss, theta.shape[0], acc.stats)
        if self._pub is not None and other is not None:
            # the two models' own estimates apart (L, d, theta and the motors' thetas; departure from the
            # paper: its observer has one model, and its heading sigma no model uncertainty)
            dp = other._theta - theta
            sol = build_solution(
                self.mode, self._k, self._pub[0], self._pub[1] / vif, s2, vif, grads, self.n, dp
            )
        else:
            sol = build_solution(self.mode, self._k, theta, cov, s2, vif, grads, self.n)
        if SPLIT_CHECK and acc.n_windows > 0:
            # the halves change only when a window closes: recomputed then (the noise scale and the
            # throttle statistics of that moment), not at every solution (+17 % CPU on log171's replay)
            split = acc.halves.heading_deg(acc.n_windows, s2, self.prior.info, self.prior.rhs(), grads)
            sol = with_split(sol, split)
        self._solution = sol
        acc.s_ref = sol.residual_rms_mgauss
        acc.rev += 1
        self._dirty = False

    def sync_theta_from(self) -> None:
        """The next solution takes the theta source's latest theta (``theta_from``), whatever
        ``theta_solve_every`` says (the final state of a log, the state stored for a later run)."""
        src = self._theta_from
        if src is not None and src.n > 0 and src._dirty:  # a source without rows gives no theta
            self._sync = True
            self._dirty = True

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
        if self._cov is not None:
            cov = self._cov * self.acc.vif_at(self._theta, self.common_estimate, self._cov)
        else:
            cov = np.asarray(np.linalg.inv(self.prior.info), dtype=np.float64)
        mean = self._theta
        if self._pub is not None:  # conditioned on another estimator's theta: what was published
            mean, cov = self._pub
        sd = np.sqrt(np.maximum(np.diag(cov), 0.0)) * inflate
        floor = 0.1 / np.sqrt(np.diag(self.prior.info))
        return mean.copy(), np.minimum(np.maximum(sd, floor), np.maximum(self.prior.sd_max, floor))

    def uncalibrated(self, y_mgauss: F64, x: F64) -> F64:
        """``y - d - sum theta_r x_r`` at the current estimate (raw frame, before L): the linearisation
        point of the relative form's soft-iron columns; of one sample (fields (3,), regressors (n_r,)) or
        of N (fields (N, 3), regressors (N, n_r): (N, 3))."""
        k = self._k
        p = self._theta
        th = p[k + 3 :].reshape(-1, 3)
        return np.asarray(y_mgauss - p[k : k + 3] - x[..., : th.shape[0]] @ th, dtype=np.float64)
