"""The accumulator of the in-flight estimator: where every used row goes (the normal equations, the open
nuisance window, the residual batches, the split halves, the sample statistics) and what the solver reads
from them (the effective normal equations, the residual scale, the variance inflation). No I/O."""

from __future__ import annotations

import math

import numpy as np

from magcomp.core.inflight.base import F64, NUISANCE_PRIOR_RAD_S, VIF_MIN_BATCHES
from magcomp.core.inflight.rows import augmented
from magcomp.core.inflight.solve import NormalEquations
from magcomp.core.inflight.uncertainty import ResidualBatches, SampleStats, SplitHalves
from magcomp.core.inflight.window import OpenWindow, WindowSchur

Effective = tuple[F64, F64, float]


class Accumulator:
    """The rows of one estimator, summed (unit weight). ``s_ref``: the residual scale of the last solution
    (the owner sets it; the noise floor, at least 10 mgauss, before one), at which the open window's
    nuisance prior is weighed; ``rev`` changes whenever the rows or the solution change (caches key on
    it)."""

    def __init__(
        self, n: int, noise_floor_mgauss: float, prior_sd: float | F64 = NUISANCE_PRIOR_RAD_S
    ) -> None:
        self.eq = NormalEquations(n)
        self.window = OpenWindow(n, prior_sd)
        self.batches = ResidualBatches(n)
        self.halves = SplitHalves(n)
        self.stats = SampleStats()
        self.n_windows = 0
        #: nuisance windows per residual batch (VIF_BATCH_S over the rows' window length; set with the rows)
        self.batch_windows = 15
        self.floor = noise_floor_mgauss
        self.s_ref = max(noise_floor_mgauss, 10.0)
        self.rev = 0
        self._eff_cache: tuple[tuple[int, float, tuple[float, ...]], Effective] | None = None

    def take(self, rows: F64, z: F64, x0: float, nuisance: F64 | None, key: object, common: F64 | None,
             aug: F64 | None = None) -> None:  # fmt: skip
        """One used sample's rows (``x0``: its delta^2) into the normal equations or, with ``nuisance``
        columns, into the nuisance window ``key`` (a new key closes the open window)."""
        self._accumulate(rows, z, nuisance, key, common, aug)
        self.stats.add(x0)

    def _accumulate(self, rows: F64, z: F64, nuisance: F64 | None, key: object, common: F64 | None,
                    aug: F64 | None = None) -> None:  # fmt: skip
        self.rev += 1
        if nuisance is None:
            self.eq.add_rows(rows, z)
        else:
            if key != self.window.key:
                self._close_window()
                self.window.key = key
            a = augmented(rows, z, nuisance, common) if aug is None else aug
            self.window.add_block(a[None], rows.shape[1])

    def _close_window(self) -> None:
        """The open window's rows with its nuisance eliminated into the normal equations, its residual sum
        into the open residual batch, its Schur complement into its split half."""
        w = self.window
        if w.key is None:
            return
        self.rev += 1
        x = w.solve(self.s_ref)
        self.batches.add_window(w.residual_sums(x), self.batch_windows)
        ws = w.schur(x)
        self.halves.add(self.n_windows, self.batch_windows, ws)
        self.eq.add_window(ws)
        self.n_windows += 1
        w.clear()
        w.key = None

    def take_block(self, aug: F64, x0: F64, key: object) -> None:
        """N used samples' augmented columns ``aug`` (N, 3, n + 2 + k) of nuisance window ``key`` (a new key
        closes the open window) and their delta^2 ``x0`` (N,)."""
        self.rev += 1
        if key != self.window.key:
            self._close_window()
            self.window.key = key
        self.window.add_block(aug, self.eq.info.shape[0])
        self.stats.add_block(x0)

    def refill(self, samples: list[tuple[F64, F64, F64, F64 | None]]) -> bool:
        """Replace the open window's rows by ``samples`` (rows, z, nuisance, common); sample counts and
        throttle statistics stay as they were. False (nothing done) without an open window."""
        w = self.window
        if w.key is None:
            return False
        self.rev += 1
        w.clear()
        w.sums[...] = 0.0
        w.n_rows = 0
        for rows, z, nuisance, common in samples:
            self._accumulate(rows, z, nuisance, w.key, common)
        return True

    def add_norm(self, g: F64, z: float, c: float) -> None:
        """One field-norm row (``rows.norm_row``)."""
        self.eq.add_norm(g, z, c)
        self.rev += 1

    def window_schur(self) -> WindowSchur | None:
        """The open window's contribution with its nuisance eliminated (None: no window open)."""
        w = self.window
        return None if w.key is None else w.schur(w.solve(self.s_ref))

    def effective_now(self) -> Effective:
        """The effective normal equations (``NormalEquations.effective``, the open window included) at the
        current state, kept until something they read changes (the rows, the solution: ``rev``; the residual
        scale and the nuisance prior of the open window's H_ee)."""
        w = self.window
        key = (self.rev, self.s_ref, w.prior_key(w.ee.shape[0]))
        cached = self._eff_cache
        if cached is not None and cached[0] == key:
            return cached[1]
        eff = self.eq.effective(self.window_schur())
        self._eff_cache = (key, eff)
        return eff

    def common_value(self, p: F64, ws: WindowSchur | None) -> float:
        """The common unknown's value at ``p`` (``ws``: the open window's :meth:`window_schur`)."""
        w = self.window
        use = w.key is not None and w.zz_cc_bc()[1] > 0.0
        return self.eq.common_value(p, ws if use else None)

    def sigma_at(self, p: F64, eff: Effective | None = None) -> float:
        """Residual standard deviation per component at parameters ``p`` (floored): the least-squares
        residual sum of squares from the information form, ``z'z - 2 p'b + p'Ip``, over its degrees of
        freedom (``eff``: the effective normal equations when known). A running mean of a-priori residuals
        would keep the large residuals of the first samples, when the estimate was still the prior, and
        overstate the noise tenfold."""
        w = self.window
        n = self.stats.n
        n_common = 1 if self.eq.common_cc + w.zz_cc_bc()[1] > 0.0 else 0
        n_dof = 3 * n + self.eq.n_norm - self.eq.info.shape[0] - w.ee.shape[0] * self.n_windows - n_common
        if n < 10 or n_dof < 10:
            return max(self.floor, 10.0)
        info, rhs, zz = self.effective_now() if eff is None else eff
        rss = zz - 2.0 * float(p @ rhs) + float(p @ info @ p)
        return max(self.floor, math.sqrt(max(rss, 0.0) / n_dof))

    def vif_at(self, p: F64, c0: float, cov: F64 | None, s2: float | None = None) -> float:
        """The variance inflation (``ResidualBatches``) at parameters ``p`` and common unknown ``c0`` (1
        until VIF_MIN_BATCHES batches are in); ``s2``: the residual scale squared when known."""
        if self.batches.count < VIF_MIN_BATCHES:
            return 1.0
        if s2 is None:
            s2 = self.sigma_at(p) ** 2  # per component, at the estimate
        return self.batches.inflation(p, c0, cov, s2)

    def nuisance_estimate(self, nuisance: F64, r: F64, key: object, with_common: bool, p: F64,
                          c: float) -> tuple[F64, F64 | None]:  # fmt: skip
        """A row's nuisance at the current parameters ``p`` (common unknown ``c``) and its unit-weight
        information ``H_ee`` (so that the gate judges what the nuisance cannot explain, with its
        uncertainty: a window-field row's residual is the whole Earth field before it, and a window's yaw
        rate is poorly known from its first samples). The open window's own estimate when the row (a
        priori residual ``r``) belongs to it; else the least-squares value for this row alone (information
        None: the residual is then what no nuisance value explains)."""
        w = self.window
        if key == w.key and w.ee.shape[0] == nuisance.shape[1]:
            out = w.nuisance(self.rev, with_common, p, c, self.s_ref)
            if out is not None:
                return out
        return np.asarray(np.linalg.lstsq(nuisance, r, rcond=None)[0], dtype=np.float64), None

    def window_nuisance(self, key: object, p: F64, c: float) -> F64 | None:
        """The open window's nuisance estimate at ``p`` (common unknown ``c``) when ``key`` is the open one
        and has rows, else None."""
        w = self.window
        k = w.ee.shape[0]
        if key != w.key or k == 0:
            return None
        out = w.nuisance(self.rev, True, p, c, self.s_ref)
        if out is None:  # no rows with nuisance columns (or singular: what the last row alone gives, 0)
            return None if w.n_rows == 0 or not w.ee_nonzero() else np.zeros(k)
        return out[0]
