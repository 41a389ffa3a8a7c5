"""The open nuisance window of the in-flight estimator: the sums of its rows and the algebra that eliminates
its nuisance (a Schur complement) when it closes.

A nuisance window holds the rows whose nuisance columns (the rotation source's rate and tilt errors, the
window's horizontal Earth field, the reference's yaw error) share one value. Its rows are summed as one Gram
matrix of their augmented columns ``[rows | common | z | nuisance]`` (:func:`~magcomp.core.inflight.rows.
augmented`); the nuisance has a weak prior (``prior_sd``, at the residual scale ``s_ref`` of the last
solution) so that a window without the information to fix it stays solvable. No I/O.
"""

from __future__ import annotations

import numpy as np

from magcomp.core.inflight.base import F64, NUISANCE_PRIOR_RAD_S, lapack

#: the open window's contribution with its nuisance eliminated (:meth:`OpenWindow.schur`): (info, rhs, z'z)
#: of the parameters and (parameters x common, common x common, common rhs) of the common unknown
WindowSchur = tuple[F64, F64, float, F64, float, float]


class OpenWindow:
    """The rows of the open nuisance window (``key``: any hashable, None while no window is open), summed."""

    def __init__(self, n: int, prior_sd: float | F64 = NUISANCE_PRIOR_RAD_S) -> None:
        """``n`` parameters; ``prior_sd``: the nuisance's prior standard deviation (its units: rad/s for a
        rotation-rate error), one value for every column or one per column."""
        self.key: object = None
        self.n_params = n
        #: the nuisance's prior standard deviation (the rows' owner sets it with the rows it adds)
        self.prior_sd: float | F64 = prior_sd
        self.n_rows = 0
        self.blocks(n, 0)
        self._ridge_cache: tuple[tuple[float, tuple[float, ...]], F64] | None = None
        self._coef_cache: tuple[tuple[F64, float, int], F64] | None = None
        self._sd_key_cache: tuple[F64 | float, int, tuple[float, ...]] | None = None
        self._open_cache: tuple[tuple[int, bool, tuple[float, ...]], tuple[F64, F64]] | None = None

    def blocks(self, n: int, k: int) -> None:
        """The open window's sums for ``k`` nuisance columns, zero: the Gram matrix ``sum A'A`` and the sum
        ``sum A`` of its samples' augmented rows ``A = [rows | common | z | nuisance]`` (3, n + 2 + k), one
        matrix product per sample; the blocks the window's algebra reads are views of them."""
        m = n + 2 + k
        self.gram = np.zeros((m, m))
        self.sums = np.zeros((3, m))
        self._views(n)

    def _views(self, n: int) -> None:
        """The views of the open window's sums that its algebra reads (``blocks``)."""
        g, sa = self.gram, self.sums
        m = g.shape[0]
        c, z, e = n, n + 1, slice(n + 2, m)
        self.pp, self.pe, self.ee = g[:n, :n], g[:n, e], g[e, e]
        #: the Gram matrix's nuisance rows ``[W_ep | w_ec | w_be | H_ee]`` (the nuisance's right-hand side)
        self.erows = g[n + 2 :]
        #: H_ee was seen to hold a nonzero entry since the sums were last cleared: its diagonal (sums of
        #: squares) only grows until then, so it stays so (``nuisance`` need not look again)
        self.ee_seen = False
        self.bp, self.be, self.pc, self.ec = g[:n, z], g[e, z], g[:n, c], g[e, c]
        self.srows, self.sn, self.scom, self.sz = sa[:, :n], sa[:, e], sa[:, c], sa[:, z]

    def __setstate__(self, state: dict[str, object]) -> None:
        """Unpickled (an in-flight stage copied through pickle, e.g. to another process): the window's
        views made again. Pickle copies a view as an array of its own, so the views would no
        longer follow the window's sums: a row added after the round trip would go into ``gram`` while
        ``ee`` and the others kept their old values."""
        self.__dict__.update(state)
        self._views(self.n_params)

    def zz_cc_bc(self) -> tuple[float, float, float]:
        """The raw (nuisance not eliminated) z'z, common x common and common x z of the open window."""
        n = self.n_params
        g = self.gram
        return float(g[n + 1, n + 1]), float(g[n, n]), float(g[n, n + 1])

    def prior_key(self, k: int) -> tuple[float, ...]:
        """The nuisance prior's standard deviations as k numbers (a cache key); the same read-only array as
        the last call's is not read again."""
        sd = self.prior_sd
        cached = self._sd_key_cache
        if cached is not None and cached[0] is sd and cached[1] == k:
            return cached[2]
        if isinstance(sd, np.ndarray) and sd.shape == (k,) and sd.dtype == np.float64:
            arr: F64 = sd
        else:
            arr = np.broadcast_to(np.asarray(sd, dtype=float), (k,))
        out = tuple(arr.tolist())
        if isinstance(sd, np.ndarray) and not sd.flags.writeable:
            self._sd_key_cache = (sd, k, out)
        return out

    def hee(self, s_ref: float, sd: tuple[float, ...]) -> F64:
        """The open window's nuisance information H_ee with its prior ``diag((s_ref / sd)^2)`` (the data rows
        are not divided by s), the prior built once per residual scale and prior."""
        key = (s_ref, sd)
        if self._ridge_cache is None or self._ridge_cache[0] != key:
            self._ridge_cache = (key, np.diag((s_ref / np.asarray(sd)) ** 2))
        return self.ee + self._ridge_cache[1]

    def solve(self, s_ref: float) -> F64 | None:
        """``H_ee^-1 [W_ep | w_ec | w_be]`` of the open window (H_ee with the nuisance's prior; None when
        it is singular): what its Schur complement and its residual sum both need."""
        n = self.n_params
        hee = self.hee(s_ref, self.prior_key(self.ee.shape[0]))
        _, x, info = lapack().dposv(hee, self.gram[n + 2 :, : n + 2])
        return None if info != 0 else np.asarray(x, dtype=np.float64)

    def schur(self, x: F64 | None) -> WindowSchur:
        """The open window's contribution with its nuisance eliminated: the Schur complement ``G_rr - G_re
        H_ee^-1 G_er`` of its Gram matrix, ``r`` = [parameters, common, z]; ``x``: :meth:`solve` (None:
        singular, the window's blocks as they are)."""
        n = self.n_params
        if x is None:
            zz, cc, bc = self.zz_cc_bc()
            return self.pp, self.bp, zz, self.pc, cc, bc
        g = self.gram
        sc = g[: n + 2, : n + 2] - g[n + 2 :, : n + 2].T @ x
        zz, cc, bc = float(sc[n + 1, n + 1]), float(sc[n, n]), float(sc[n, n + 1])
        return sc[:n, :n], sc[:n, n + 1], zz, sc[:n, n], cc, bc

    def add_block(self, aug: F64, n: int) -> None:
        """N samples' augmented columns ``aug`` (N, 3, n + 2 + k: ``rows.augmented`` stacked) into the open
        window (``n`` parameters)."""
        k = aug.shape[2] - n - 2
        if self.ee.shape[0] != k:  # a new nuisance size: the nuisance's sums start again
            g, sa = self.gram, self.sums
            self.n_params = n
            self.blocks(n, k)
            self.gram[: n + 2, : n + 2] = g[: n + 2, : n + 2]
            self.sums[:, : n + 2] = sa[:, : n + 2]
        if aug.shape[0] == 1:
            a = aug[0]
            self.gram += a.T @ a
            self.sums += a
        else:
            a = aug.reshape(-1, aug.shape[2])
            self.gram += a.T @ a
            self.sums += aug.sum(axis=0)
        self.n_rows += aug.shape[0]

    def residual_sums(self, x: F64 | None) -> tuple[F64, F64, F64, int] | None:
        """The window's residual sum as ``c - M p - g c0`` (the nuisance at its least-squares value e = H^-1
        (b_e - W_ep p - w_ec c): the sum over the window of z - rows p - common c - N e), and its number of
        rows; None without rows or a solution ``x`` (:meth:`solve`). The sums are cleared."""
        n = self.n_params
        out = None
        if self.n_rows > 0 and self.sn.shape[1] == self.ee.shape[0] and x is not None:
            out = (
                self.sz - self.sn @ x[:, n + 1],
                self.srows - self.sn @ x[:, :n],
                self.scom - self.sn @ x[:, n],
                self.n_rows,
            )
        for a in (self.sz, self.srows, self.sn, self.scom):
            a[...] = 0.0
        self.n_rows = 0
        return out

    def nuisance(self, rev: int, with_common: bool, p: F64, c: float, s_ref: float) -> tuple[F64, F64] | None:
        """The open window's nuisance estimate at parameters ``p`` (and common unknown ``c`` with
        ``with_common``) and its information H_ee (None when the window has no rows with nuisance columns
        yet, or H_ee is singular), cached against ``rev`` (the owner's revision: it changes with every
        input)."""
        k = self.ee.shape[0]
        # the stage asks twice per row with nothing changed in between (window_nuisance, then add): the
        # second answer is the first (same inputs, same numbers)
        key = (rev, with_common, self.prior_key(k))
        cached = self._open_cache
        if cached is not None and cached[0] == key:
            return cached[1]
        if self.n_rows == 0 or not (self.ee_seen or self.ee_nonzero()):
            return None
        hee = self.hee(s_ref, key[2])
        # b_e = w_be - W_pe' p - w_ec c as one product with the window's Gram rows of the nuisance (their
        # nuisance block times 0): [W_ep | w_ec | w_be | H_ee] [-p, -c, 1, 0]
        b_e = self.erows @ self._b_e_coef(k, p, c if with_common else 0.0)
        # LAPACK's Cholesky solve directly (numpy's solve costs 6x more in checks for a 5x5)
        _, e_hat, info = lapack().dposv(hee, b_e)
        if info != 0:
            return None
        out = np.asarray(e_hat, dtype=np.float64), hee
        self._open_cache = (key, out)
        return out

    def ee_nonzero(self) -> bool:
        """H_ee has a nonzero entry (remembered until the sums are cleared: :meth:`clear`)."""
        self.ee_seen = bool(self.ee.any())
        return self.ee_seen

    def clear(self) -> None:
        """The window's sums zero (its key and row count as they are)."""
        self.gram[...] = 0.0
        self.ee_seen = False

    def _b_e_coef(self, k: int, p: F64, c: float) -> F64:
        """``[-p, -c, 1, 0_k]``: the window Gram's nuisance rows times it are the nuisance's right-hand side.
        Built once per solution (the parameters change only there)."""
        key = (p, c, k)
        cached = self._coef_cache
        if cached is not None and cached[0][0] is key[0] and cached[0][1:] == key[1:]:
            return cached[1]
        n = p.shape[0]
        coef = np.zeros(n + 2 + k)
        coef[:n] = -p
        coef[n] = -c
        coef[n + 1] = 1.0
        self._coef_cache = (key, coef)
        return coef
