"""Theta against the autopilot's calibration: eq. (11) where the flight cannot determine a calibration.

A hover (or any flight with little rotation) does not determine a compass calibration: eq. (2)'s hard iron
d and the Earth field look alike unless the vehicle turns through a large angle. But theta is observable: the
throttle varies at near-constant attitude, and eq. (11)'s bias ``theta * throttle^2`` moves the field with it.
So here the calibration is the autopilot's own (L = I, d = 0 on the field as logged, the prior of issue 23
item 3) and theta is fitted alone, by linear least squares, with the Earth field:

    m_b(t) = R_nb(t)^T e_n + theta * throttle(t)^2 + noise          (eq. (11) with eq. (2) the identity)

R_nb from the autopilot's roll, pitch and yaw; e_n (3) and theta (3) are the six unknowns. A second form
adds a change d (3) of the autopilot's hard-iron offsets (``m_b - d``, eq. (2) with L = I), under a prior of
OFFSET_PRIOR_SD_MGAUSS: where the autopilot's calibration is off (a battery or payload moved since, a
calibration accepted at its fit limit), theta alone cannot take the heading error that turns with the yaw.
The second form moves the heading's constant part by what the flight cannot tell from the Earth field (a
hover hardly turns): :func:`anchored` gives the heading offset that takes d's constant heading change out
again (a rotation of the field about the body z axis would not do: with the vehicle tilted it mixes the
vertical field into the heading). Theta's constant change, its bias at the mean throttle, is a correction
and stays: anchoring the whole correction to the autopilot's mean heading put that bias back (simulated
ordinary flight, theta x6: the heading's constant error 4.0 -> 9.2-13.3 deg). Departure from
the paper's eqs. (12)-(15): no DPI calibration first, no observer; one batch solve. Where the autopilot's yaw
is fused from this compass it carries part of the bias; the throttle moves faster (seconds) than the
autopilot pulls its yaw to the compass (a minute or more, docs/real-flights.md), so the fit still sees
theta. Whether the result helps is left to the self-check (core/selfcheck.py), never assumed.

Pure numpy; fields in mgauss, angles in rad.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from magcomp.core.correction import Correction
from magcomp.core.heading import heading_from_trig_deg
from magcomp.core.rotations import dcms_from_quats, quats_from_euler

F64 = NDArray[np.float64]

#: prior sd (mgauss, per axis) of a change of the autopilot's hard-iron offsets since its calibration:
#: ArduPilot accepts a calibration whose sphere fit leaves up to COMPASS_CAL_FIT (16 mgauss by default) rms,
#: so its offsets are uncertain by a few times that, and a battery or payload moved since adds tens of mgauss.
#: 60 is 12 % of a 500 mgauss field; the development logs' result is the same for 40 and 100
#: (docs/real-flights.md)
OFFSET_PRIOR_SD_MGAUSS = 60.0
#: below this standard deviation of throttle^2 the bias hardly changes (a 0.05 swing around hover at 0.5 is
#: 0.05 of throttle^2): theta is not separable from the Earth field's constant part
MIN_THROTTLE2_STD = 0.01


@dataclass(frozen=True)
class HoverTheta:
    """theta (mgauss, compass frame), its 1-sigma (mgauss) and the residual rms (mgauss)."""

    theta_mgauss: F64
    theta_sigma_mgauss: F64
    residual_rms_mgauss: float
    n: int
    #: the change of the autopilot's hard-iron offsets (zeros in the theta-only form), mgauss
    offset_mgauss: F64 = field(default_factory=lambda: np.zeros(3))
    #: subtracted from the heading of the corrected field (rad): the constant heading change of the
    #: offsets' change taken out again (:func:`anchored`)
    anchor_rad: float = 0.0
    #: where the fit's yaw came from: "autopilot" (:class:`HoverNormal`) or "gyro" (:class:`GyroYawNormal`)
    yaw_source: str = "autopilot"
    #: the blocks of time of the jackknife that ``theta_sigma_mgauss`` also takes, per axis the larger
    #: (:func:`with_jackknife`; 0: none, the fit's own covariance alone, which takes the residuals as white)
    sigma_blocks: int = 0
    #: a block left out left too little to fit (theta rests on that stretch of the flight): the jackknife
    #: over the other blocks, and so the sigma stated, is a lower bound
    sigma_lower_bound: bool = False

    def correction(self) -> Correction:
        """The fit as a core correction (eq. (2) with L = I and d the offsets' change, eq. (11) with theta),
        applied where the throttle is known."""
        th = self.theta_mgauss.tolist()
        identity = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
        return Correction((*identity, *self.offset_mgauss.tolist()), (th[0], th[1], th[2]), source="hover",
                          needs_throttle=True)  # fmt: skip

    def corrected_mgauss(self, field_b_mgauss: F64, throttle_01: F64) -> F64:
        """``m_b - d - theta throttle^2`` per sample, (n, 3) mgauss (:meth:`correction`'s apply)."""
        m = np.asarray(field_b_mgauss, dtype=float)
        got = self.correction().apply(m[:, 0], m[:, 1], m[:, 2], np.asarray(throttle_01, dtype=float))
        return np.column_stack(got.corrected)


def anchored(
    fit: HoverTheta, field_b_mgauss: F64, throttle_01: F64, cos_roll: F64, sin_roll: F64, cos_pitch: F64,
    sin_pitch: F64,
) -> HoverTheta:
    """``fit`` with the anchor that removes the heading's constant change made by its offsets' change d alone
    (the circular mean over the samples of eq. (24) with d and theta removed minus eq. (24) with theta
    removed): the flight cannot tell d's constant part from the Earth field's. Theta's own constant change
    (its bias at the mean throttle) is what the correction is for and stays. Zero in the theta-only form."""
    if not offset_changed(fit):
        return replace(fit, anchor_rad=0.0)
    m = np.asarray(field_b_mgauss, dtype=float)
    got = fit.correction().apply(m[:, 0], m[:, 1], m[:, 2], np.asarray(throttle_01, dtype=float))
    u = (m[:, 0] - got.bias[0], m[:, 1] - got.bias[1], m[:, 2] - got.bias[2])  # theta removed, d kept
    trig = (cos_roll, sin_roll, cos_pitch, sin_pitch)
    d = np.radians(heading_from_trig_deg(*got.corrected, *trig) - heading_from_trig_deg(*u, *trig))
    d = d[np.isfinite(d)]
    if d.size == 0:
        return fit
    return replace(fit, anchor_rad=math.atan2(float(np.mean(np.sin(d))), float(np.mean(np.cos(d)))))


def offset_changed(fit: HoverTheta) -> bool:
    """The fit has the second form's change of the autopilot's offsets."""
    return bool(np.any(fit.offset_mgauss != 0.0))


def body_from_nav(roll_rad: F64, pitch_rad: F64, yaw_rad: F64) -> F64:
    """R_nb^T per sample, (n, 3, 3): NED to body FRD (ZYX Euler), from :mod:`magcomp.core.rotations`."""
    return np.asarray(dcms_from_quats(quats_from_euler(roll_rad, pitch_rad, yaw_rad)).transpose(0, 2, 1))


class _ThrottleSums:
    """The count of samples added and the sums of their throttle^2 and throttle^4 (how much eq. (11)'s bias
    varies over them: MIN_THROTTLE2_STD)."""

    __slots__ = ("_d2", "_d4", "n")

    def __init__(self) -> None:
        self.n = 0
        self._d2 = 0.0
        self._d4 = 0.0

    def _count(self, d2: F64) -> tuple[float, float]:
        """``d2`` (throttle^2 of the samples added) counted; returns its sum and its sum of squares."""
        sums = float(d2.sum()), float(d2 @ d2)
        self._d2 += sums[0]
        self._d4 += sums[1]
        self.n += int(d2.shape[0])
        return sums

    def throttle2_std(self) -> float:
        """Standard deviation of throttle^2 over the samples added."""
        if self.n == 0:
            return 0.0
        mean = self._d2 / self.n
        return math.sqrt(max(self._d4 / self.n - mean * mean, 0.0))


class HoverNormal(_ThrottleSums):
    """The normal equations of the module's model, unknowns x = (e_n, theta, d) (9), accumulated one block
    of samples at a time: the batch fit (:func:`fit_hover_theta`) adds a whole log at once, the live path
    (service/heading.py) blocks of samples as they come; both solve with :meth:`fit`. A sample's rows are
    ``A_i = [R_nb^T, throttle^2 I, I]`` (3 x 9), so ``sum A_i^T A_i`` needs only the sums of R_nb, of
    throttle^2 R_nb, of throttle^2 and throttle^4 and the count (R_nb R_nb^T = I)."""

    __slots__ = ("_ata", "_aty", "_yty")

    def __init__(self) -> None:
        super().__init__()
        self._ata = np.zeros((9, 9))
        self._aty = np.zeros(9)
        self._yty = 0.0

    def add(self, field_b_mgauss: F64, roll_rad: F64, pitch_rad: F64, yaw_rad: F64, throttle_01: F64) -> None:
        """A block of samples ((n, 3) field as the autopilot had it, attitude and throttle (n,)); samples
        with a non-finite value are left out."""
        m = np.asarray(field_b_mgauss, dtype=float).reshape(-1, 3)
        d2 = np.asarray(throttle_01, dtype=float) ** 2
        roll, pitch, yaw = (np.asarray(v, dtype=float) for v in (roll_rad, pitch_rad, yaw_rad))
        ok = np.isfinite(m).all(axis=1) & np.isfinite(d2) & np.isfinite(roll) & np.isfinite(pitch)
        ok &= np.isfinite(yaw)
        if not ok.any():
            return
        m, d2 = m[ok], d2[ok]
        r_nb = body_from_nav(roll[ok], pitch[ok], yaw[ok]).transpose(0, 2, 1)  # (n, 3, 3)
        k = int(ok.sum())
        s_r = r_nb.sum(axis=0)
        s_dr = np.einsum("n,nij->ij", d2, r_nb)
        s_d2, s_d4 = self._count(d2)
        eye = np.eye(3)
        n_ = self._ata
        n_[0:3, 0:3] += k * eye
        n_[0:3, 3:6] += s_dr
        n_[0:3, 6:9] += s_r
        n_[3:6, 0:3] += s_dr.T
        n_[6:9, 0:3] += s_r.T
        n_[3:6, 3:6] += s_d4 * eye
        n_[3:6, 6:9] += s_d2 * eye
        n_[6:9, 3:6] += s_d2 * eye
        n_[6:9, 6:9] += k * eye
        self._aty[0:3] += np.einsum("nij,nj->i", r_nb, m)
        self._aty[3:6] += d2 @ m
        self._aty[6:9] += m.sum(axis=0)
        self._yty += float(np.einsum("ni,ni->", m, m))

    def merge(self, other: HoverNormal, sign: int = 1) -> None:
        """``other``'s samples added to these (the sums are additive); ``sign`` -1: taken out."""
        self._ata += sign * other._ata
        self._aty += sign * other._aty
        self._yty += sign * other._yty
        self.n += sign * other.n
        self._d2 += sign * other._d2
        self._d4 += sign * other._d4

    def without(self, other: HoverNormal) -> HoverNormal:
        """These normal equations less ``other``'s samples (a part of them): the fit with them left out."""
        out = HoverNormal()
        out.merge(self)
        out.merge(other, -1)
        return out

    def fit(self, offset_sd_mgauss: float | None = None) -> HoverTheta | None:
        """The least-squares theta (see :func:`fit_hover_theta`); None where throttle^2 hardly varies (see
        MIN_THROTTLE2_STD) or there are fewer samples than twice the unknowns."""
        n = self.n
        if n < 12 or self.throttle2_std() < MIN_THROTTLE2_STD:
            return None
        return _theta_forms(self._ata, self._aty, self._yty, 3 * n, 3, n, offset_sd_mgauss, "autopilot")


#: the compass-free yaw's pieces (s): the gyro's integrated yaw (core/selfcheck.py) drifts with the part of
#: the gyro's bias the attitude filter has not taken out; within a piece the yaw's offset and a constant drift
#: are free (as the Earth field's horizontal part and its turn), so only the bias' change over a piece errs.
#: A MEMS gyro's bias after the filter's estimate changes by well under 0.01 deg/s in a minute (the filters'
#: own bias time constants are minutes): under 0.3 deg of yaw over a piece, against the degrees a motor bias
#: turns the heading
PIECE_S = 60.0
#: the unknowns shared by every piece: the Earth field's down component, theta, the offsets' change
_SHARED = 7


class GyroYawNormal(_ThrottleSums):
    """The module's model with the yaw from the gyro, not from the autopilot (whose yaw, fused from this
    compass, can follow the compass's error: on one development log at 0.045 /s, so a fit against it takes
    part of theta's bias for attitude). The yaw is the gyro's integral, known up to an offset and a drift, so
    per piece of PIECE_S (and per restart of the integral) the Earth field's horizontal part (2) and a linear
    change of it in time (2) are unknowns of their own:

        m_b(t) = R_nb(t)^T (e_p + (t - t_p) w_p) + theta * throttle(t)^2 + d + noise

    with e_p = (e_x,p, e_y,p, e_z) and w_p horizontal. A drift of the yaw turns e_p at a constant rate, which
    to first order is such a w_p (one unknown would do; the second also takes a slow change of the horizontal
    field's size). Each piece's four unknowns are eliminated from the normal equations when the piece closes
    (a Schur complement; exact for least squares, the pseudo-inverse where a piece has a single time), so the
    batch fit (a whole log) and the live fit (blocks as they come) solve the same equations. Departure from
    :class:`HoverNormal`: the Earth field's horizontal part is local to a piece, so theta is seen only through
    the field's change within each piece (the throttle's swings at near-constant attitude)."""

    __slots__ = ("_bs", "_key", "_loc", "_ns", "_t0", "_yty", "piece_s", "pieces")

    def __init__(self, piece_s: float = PIECE_S) -> None:
        super().__init__()
        self.piece_s = piece_s
        self.pieces = 0
        self._ns = np.zeros((_SHARED, _SHARED))  # the shared unknowns' normal matrix, closed pieces folded
        self._bs = np.zeros(_SHARED)
        self._yty = 0.0
        self._key: tuple[float, float] | None = None
        self._t0 = 0.0
        #: the open piece's sums: N_ll (4, 4), N_ls (4, 7), N_ss (7, 7), b_l (4), b_s (7), y'y, its samples
        self._loc = self._empty()

    @staticmethod
    def _empty() -> list[Any]:
        return [np.zeros((4, 4)), np.zeros((4, _SHARED)), np.zeros((_SHARED, _SHARED)), np.zeros(4),
                np.zeros(_SHARED), 0.0, 0]  # fmt: skip

    def add(self, field_b_mgauss: F64, roll_rad: F64, pitch_rad: F64, yaw_gyro_rad: F64, epoch: F64,
            t_s: F64, throttle_01: F64) -> None:  # fmt: skip
        """A block of samples in time order ((n, 3) field as the autopilot had it; roll, pitch, the gyro's
        integrated yaw and its restart count, time, throttle (n,)); non-finite samples are left out."""
        m = np.asarray(field_b_mgauss, dtype=float).reshape(-1, 3)
        given = (roll_rad, pitch_rad, yaw_gyro_rad, epoch, t_s, throttle_01)
        cols = [np.asarray(v, dtype=float) for v in given]
        ok = np.isfinite(m).all(axis=1)
        for c in cols:
            ok &= np.isfinite(c)
        if not ok.any():
            return
        roll, pitch, yaw, ep, t, thr = (c[ok] for c in cols)
        m = m[ok]
        slot = np.floor(t / self.piece_s)
        change = np.flatnonzero((np.diff(ep) != 0) | (np.diff(slot) != 0)) + 1
        for lo, hi in zip(np.r_[0, change], np.r_[change, t.size], strict=True):
            key = (float(ep[lo]), float(slot[lo]))
            if key != self._key:
                self._close()
                self._key, self._t0 = key, (key[1] + 0.5) * self.piece_s
            self._accumulate(m[lo:hi], roll[lo:hi], pitch[lo:hi], yaw[lo:hi], t[lo:hi], thr[lo:hi])

    def _accumulate(self, m: F64, roll: F64, pitch: F64, yaw: F64, t: F64, thr: F64) -> None:
        r_bn = body_from_nav(roll, pitch, yaw)  # (n, 3, 3): nav to body
        d2 = thr * thr
        tau = (t - self._t0)[:, None]
        k = m.shape[0]
        a_l = np.concatenate((r_bn[:, :, 0:2], r_bn[:, :, 0:2] * tau[:, :, None]), axis=2)  # (n, 3, 4)
        a_s = np.zeros((k, 3, _SHARED))
        a_s[:, :, 0] = r_bn[:, :, 2]
        a_s[:, :, 1:4] = np.eye(3)[None] * d2[:, None, None]
        a_s[:, :, 4:7] = np.eye(3)[None]
        loc = self._loc
        loc[0] += np.einsum("nij,nik->jk", a_l, a_l)
        loc[1] += np.einsum("nij,nik->jk", a_l, a_s)
        loc[2] += np.einsum("nij,nik->jk", a_s, a_s)
        loc[3] += np.einsum("nij,ni->j", a_l, m)
        loc[4] += np.einsum("nij,ni->j", a_s, m)
        loc[5] += float(np.einsum("ni,ni->", m, m))
        loc[6] += k
        self._count(d2)

    @staticmethod
    def _folded(loc: list[Any]) -> tuple[F64, F64, float]:
        """The open piece's contribution with its own unknowns eliminated: (N, b, y'y)."""
        n_ll, n_ls, n_ss, b_l, b_s, yty, _ = loc
        inv = np.linalg.pinv(n_ll)
        return n_ss - n_ls.T @ inv @ n_ls, b_s - n_ls.T @ inv @ b_l, yty - float(b_l @ inv @ b_l)

    def _close(self) -> None:
        if self._key is None or not self._loc[6]:
            return
        n_, b_, y_ = self._folded(self._loc)
        self._ns += n_
        self._bs += b_
        self._yty += y_
        self.pieces += 1
        self._loc = self._empty()

    def fit(self, offset_sd_mgauss: float | None = None) -> HoverTheta | None:
        """The least-squares theta, the open piece included (not closed: more samples may join it); None
        where throttle^2 hardly varies (MIN_THROTTLE2_STD) or there are fewer rows (3 a sample) than twice the
        unknowns, the pieces' own included."""
        n_, b_, y_ = self._ns.copy(), self._bs.copy(), self._yty
        pieces = self.pieces
        if self._loc[6]:
            fn, fb, fy = self._folded(self._loc)
            n_, b_, y_ = n_ + fn, b_ + fb, y_ + fy
            pieces += 1
        n = self.n
        local = 4 * pieces
        if 3 * n < 2 * (local + _SHARED) or self.throttle2_std() < MIN_THROTTLE2_STD:
            return None
        return _theta_forms(n_, b_, y_, 3 * n - local, 1, n, offset_sd_mgauss, "gyro")


def fit_hover_theta_gyro(field_b_mgauss: F64, roll_rad: F64, pitch_rad: F64, yaw_gyro_rad: F64, epoch: F64,
                         t_s: F64, throttle_01: F64, offset_sd_mgauss: float | None = None,
                         ) -> HoverTheta | None:  # fmt: skip
    """:class:`GyroYawNormal`'s fit over a whole log (samples in time order); see :func:`fit_hover_theta`."""
    acc = GyroYawNormal()
    acc.add(field_b_mgauss, roll_rad, pitch_rad, yaw_gyro_rad, epoch, t_s, throttle_01)
    return acc.fit(offset_sd_mgauss)


def _theta_forms(ata: F64, aty: F64, yty: float, dof_rows: int, n_e: int, n: int,
                 offset_sd_mgauss: float | None, yaw_source: str) -> HoverTheta:  # fmt: skip
    """The fit of either normal equations whose unknowns are the Earth field's shared components (``n_e``),
    theta (3) and the offsets' change d (3): the theta-only form (d left out), or with d under a prior of
    ``offset_sd_mgauss`` per axis, weighed by the theta-only residual's scale. ``dof_rows``: the data rows
    less the unknowns already eliminated."""
    k = n_e + 3
    x, s2, cov = _solve(ata[:k, :k], aty[:k], yty, dof_rows - k)
    if offset_sd_mgauss is None:
        sd = np.sqrt(np.maximum(np.diag(cov)[n_e:], 0.0))
        return HoverTheta(x[n_e:].copy(), sd, math.sqrt(s2), n, yaw_source=yaw_source)
    prior = np.zeros(ata.shape)
    prior[k:, k:] = np.eye(3) * (s2 / offset_sd_mgauss**2)
    xd, s2d, covd = _solve(ata + prior, aty, yty, dof_rows - k - 3, ata)
    sd = np.sqrt(np.maximum(np.diag(covd)[n_e:k], 0.0))
    return HoverTheta(xd[n_e:k].copy(), sd, math.sqrt(s2d), n, xd[k:k + 3].copy(), yaw_source=yaw_source)


def _solve(ata: F64, aty: F64, yty: float, dof: int, data_ata: F64 | None = None) -> tuple[F64, float, F64]:
    """(x, residual variance, covariance) of the normal equations ``ata x = aty``; the residual over the
    data rows only (``data_ata``: their part of ``ata`` where a prior was added)."""
    inv = np.linalg.pinv(ata)
    x = inv @ aty
    d = ata if data_ata is None else data_ata
    sse = max(yty - 2.0 * float(x @ aty) + float(x @ d @ x), 0.0)
    s2 = sse / max(dof, 1)
    return x, s2, np.asarray(s2 * inv, dtype=float)


def fit_hover_theta(
    field_b_mgauss: F64,
    roll_rad: F64,
    pitch_rad: F64,
    yaw_rad: F64,
    throttle_01: F64,
    offset_sd_mgauss: float | None = None,
) -> HoverTheta | None:
    """The least-squares theta of the module's model over a whole log (:class:`HoverNormal` with every
    sample); None where throttle^2 hardly varies (see MIN_THROTTLE2_STD) or there are fewer samples than
    twice the unknowns. With ``offset_sd_mgauss`` the second form: a change of the hard-iron offsets too,
    under that prior (weighed by the residual's scale of the theta-only fit)."""
    acc = HoverNormal()
    acc.add(field_b_mgauss, roll_rad, pitch_rad, yaw_rad, throttle_01)
    return acc.fit(offset_sd_mgauss)


#: the jackknife's blocks of time (s): long against the residual's correlation (on the development logs'
#: hover fits its lag-1 autocorrelation is 0.57-0.83 between samples, and the autopilot's yaw wanders 7-15 deg
#: over 30-120 s against the gyro's), short enough that a few minutes of hover give several
JACKKNIFE_BLOCK_S = 30.0
#: no block shorter than the self-check's window (core/selfcheck.py WINDOW_S, 10 s)
MIN_JACKKNIFE_BLOCK_S = 10.0
#: fewer blocks than this give a variance with too few degrees of freedom to replace the fit's own
MIN_JACKKNIFE_BLOCKS = 4
#: at most this many refits: the blocks lengthen on a long log
MAX_JACKKNIFE_BLOCKS = 12


def jackknife_count(covered_s: float) -> int | None:
    """How many blocks the jackknife takes for samples covering ``covered_s`` of time: one per
    JACKKNIFE_BLOCK_S, at least MIN_JACKKNIFE_BLOCKS and at most MAX_JACKKNIFE_BLOCKS; None where that many
    would be shorter than MIN_JACKKNIFE_BLOCK_S on average."""
    j = min(max(int(covered_s // JACKKNIFE_BLOCK_S), MIN_JACKKNIFE_BLOCKS), MAX_JACKKNIFE_BLOCKS)
    return None if covered_s < j * MIN_JACKKNIFE_BLOCK_S else j


def covered_s(t_s: F64) -> float:
    """The time samples in time order cover (s): their spacings, gaps longer than MIN_JACKKNIFE_BLOCK_S left
    out (the motors stopped, the vehicle out of the fit's bounds)."""
    dt = np.diff(np.asarray(t_s, dtype=float))
    return float(dt[(dt > 0.0) & (dt <= MIN_JACKKNIFE_BLOCK_S)].sum())


def jackknife_blocks(t_s: F64) -> NDArray[np.int64] | None:
    """A block index per sample for :func:`block_jackknife_sd` (samples in time order):
    :func:`jackknife_count` contiguous runs of equal sample counts over the time they cover
    (:func:`covered_s`); None where too short."""
    t = np.asarray(t_s, dtype=float)
    j = jackknife_count(covered_s(t)) if t.size >= 2 else None
    if j is None:
        return None
    return np.asarray(np.arange(t.size) * j // t.size, dtype=np.int64)


FitOnMask = Callable[[NDArray[np.bool_]], "HoverTheta | None"]


class Jackknife(NamedTuple):
    """The delete-one-block jackknife's sd of theta (mgauss, per axis), its blocks, and whether every refit
    succeeded (else the sd is over the others only: a lower bound)."""

    sd: F64
    blocks: int
    complete: bool


def block_jackknife_sd(blocks: NDArray[np.int64], fit_without: FitOnMask) -> Jackknife | None:
    """theta's standard deviation (mgauss, per axis) by the delete-one-block jackknife: theta refitted with
    each block of time left out (``fit_without(mask of the samples kept)``; :func:`jackknife_sd`).
    Residuals correlated in time (a yaw reference that wanders, a field that changes along the path) make the
    fit's own covariance, which takes them as white, too small; blocks long against that correlation carry it
    into the spread of the refits."""
    return jackknife_sd([fit_without(blocks != b) for b in np.unique(blocks)])


def jackknife_sd(fits_without: list[HoverTheta | None]) -> Jackknife | None:
    """sd = sqrt((J - 1) / J * sum of the squared deviations of the refits' theta from their mean), from the
    refits with each block left out. A refit that fails (None: the block left out held the throttle's
    change) is not counted and marks the result incomplete: theta rests on that block, which the others
    cannot measure. None below MIN_JACKKNIFE_BLOCKS refits."""
    thetas = [f.theta_mgauss for f in fits_without if f is not None]
    j = len(thetas)
    if j < MIN_JACKKNIFE_BLOCKS:
        return None
    th = np.asarray(thetas, dtype=float)
    sd = np.sqrt((j - 1) / j * ((th - th.mean(axis=0)) ** 2).sum(axis=0))
    return Jackknife(sd, j, j == len(fits_without))


def with_jackknife(fit: HoverTheta, got: Jackknife | None) -> HoverTheta:
    """``fit`` with theta's sigma the larger, per axis, of its own and the jackknife's ``got``."""
    if got is None:
        return fit
    sd = np.maximum(fit.theta_sigma_mgauss, got.sd)
    return replace(fit, theta_sigma_mgauss=sd, sigma_blocks=got.blocks, sigma_lower_bound=not got.complete)


#: the live fit's groups of normal equations (one per MIN_JACKKNIFE_BLOCK_S) are merged in adjacent pairs
#: beyond this many, so that a long flight keeps a bounded memory (each is ~1 kB)
MAX_LIVE_GROUPS = 72


class HoverGroups:
    """The live fit's normal equations also kept per stretch of about MIN_JACKKNIFE_BLOCK_S
    (service/heading.py HoverShadow), with the time each covers (:func:`covered_s`'s rule, sample block by
    block): what :func:`grouped_jackknife` leaves out one block at a time."""

    __slots__ = ("_last_t", "_start_t", "groups", "seconds")

    def __init__(self) -> None:
        self.groups: list[HoverNormal] = []
        self.seconds: list[float] = []
        self._start_t = -math.inf
        self._last_t = math.nan

    def add(self, part: HoverNormal, t_s: float) -> None:
        """A block of samples' normal equations, its latest sample at ``t_s``."""
        step = t_s - self._last_t
        self._last_t = t_s
        if not t_s - self._start_t < MIN_JACKKNIFE_BLOCK_S:
            if len(self.groups) >= MAX_LIVE_GROUPS:
                self._halve()
            self.groups.append(HoverNormal())
            self.seconds.append(0.0)
            self._start_t = t_s
        self.groups[-1].merge(part)
        if 0.0 < step <= MIN_JACKKNIFE_BLOCK_S:
            self.seconds[-1] += step

    def _halve(self) -> None:
        groups, seconds = self.groups, self.seconds
        for i in range(0, len(groups) - 1, 2):
            groups[i].merge(groups[i + 1])
            seconds[i] += seconds[i + 1]
        self.groups, self.seconds = groups[::2], seconds[::2]


def grouped_jackknife(total: HoverNormal, groups: HoverGroups, fit: HoverTheta,
                      offset_sd_mgauss: float | None) -> HoverTheta:  # fmt: skip
    """:func:`with_block_sigma` on normal equations kept per stretch of time (the live fit's ``groups``,
    whose sum is ``total``): :func:`jackknife_count` blocks for the time they cover, adjacent groups merged
    into runs of about equal sample counts, each block left out by subtraction."""
    j = jackknife_count(sum(groups.seconds))
    if j is None or len(groups.groups) < j:
        return fit
    counts = np.cumsum([g.n for g in groups.groups])
    cuts = np.searchsorted(counts, np.arange(1, j) * counts[-1] / j, side="left") + 1
    merged: list[HoverNormal] = []
    for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, len(groups.groups)], strict=True):
        g = HoverNormal()
        for part in groups.groups[int(lo):int(hi)]:
            g.merge(part)
        merged.append(g)
    return with_jackknife(fit, jackknife_sd([total.without(g).fit(offset_sd_mgauss) for g in merged if g.n]))


def with_block_sigma(fit: HoverTheta, t_s: F64, fit_on: FitOnMask) -> HoverTheta:
    """``fit`` with theta's sigma the larger, per axis, of its own and :func:`block_jackknife_sd`'s
    (``fit_on``: the same form fitted on a mask of the samples ``t_s``); unchanged where the span holds too
    few blocks. The blocks are counted over the samples the form fits (``t_s``: their times; ``fit_on``
    takes a mask of them). Departure from the paper, whose eq. (15) covariance takes the noise as white: on
    the development logs' hover fits the jackknife's sd is 1-45x the white one (docs/real-flights.md)."""
    blocks = jackknife_blocks(t_s)
    return with_jackknife(fit, None if blocks is None else block_jackknife_sd(blocks, fit_on))
