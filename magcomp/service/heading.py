"""Stage 5, heading: eq. (24) on the corrected field, then the heading filter.

The heading is tilt-compensated (roll and pitch from the attitude stage; departure from the paper, whose
eq. (24) is for a level vehicle) and passes a gyro-aided complementary filter
(:class:`~magcomp.core.heading_filter.HeadingFilter`, departure from the paper: what its Table III measured
was an attitude estimator's yaw). The uncorrected heading (calibration only, no bias removed) goes the
same way, for comparison.
"""

from __future__ import annotations

import math
from itertools import chain

import numpy as np
from numpy.typing import NDArray

from magcomp.core.correction import Correction
from magcomp.core.heading import heading_from_trig_deg
from magcomp.core.heading_filter import FloatOrArray, HeadingFilter, turn_rate
from magcomp.core.hover_theta import (
    OFFSET_PRIOR_SD_MGAUSS,
    HoverGroups,
    HoverNormal,
    HoverTheta,
    grouped_jackknife,
    offset_changed,
)
from magcomp.core.inflight import InflightOutput
from magcomp.core.selfcheck import (
    LIVE_WINDOW_S,
    MIN_PER_WINDOW,
    MIN_WINDOWS,
    MOTORS_RUNNING_01,
    Estimate,
    RunningSelfCheck,
    SelfCheck,
    constant_change_rad,
    judge_estimate,
    judged,
    switch_on_offset_rad,
)
from magcomp.core.types import FLAG_CALIBRATED, FLAG_THETA_CONVERGED
from magcomp.service.calibrate import apply_eq2
from magcomp.service.record import Float3, MagRecord

F64 = NDArray[np.float64]
_DEG_PER_RAD = 180.0 / math.pi  # the factor of math.degrees

#: below this |cos(pitch)| the Euler yaw rate is undefined (pitch beyond +-75.5 deg): the filter restarts
MIN_COS_PITCH = 0.25


#: the live hover fit's forms, simplest first (core/hover_theta.py): theta alone, then with a change of the
#: autopilot's offsets; the first whose running self-check is on is published
HOVER_FORMS: tuple[float | None, ...] = (None, OFFSET_PRIOR_SD_MGAUSS)


class HoverShadow:
    """Theta against the autopilot's calibration, live (core/hover_theta.py, the two-pass replay's
    ``final_pass.hover_candidate``): the samples with the motors running go into the hover model's normal
    equations in blocks; each form is re-fitted whenever its running self-check closes a window and judged
    in the shadow, sample by sample, like the in-flight estimate; its heading has a filter of its own."""

    __slots__ = ("_anchor_sc", "_block", "_blocks", "_cors", "_fit_t", "_groups", "_normal", "_offset",
                 "_pending", "_solved", "checks", "deg", "filter", "fits", "on_form")  # fmt: skip

    def __init__(self, tau_s: float) -> None:
        self._normal = HoverNormal()
        #: the same normal equations per stretch of time (theta's sigma: :meth:`stated_fit`)
        self._groups = HoverGroups()
        self._fit_t = math.nan
        self._block: list[tuple[float, float, float, float, float, float, float]] = []
        #: the blocks :meth:`refit` closed whose sums are not taken yet, each with its latest time: taken, in
        #: their order, where the normal equations are next read (where the in-flight correction applies,
        #: the fits are never read: the sums were ~1.4 % of a 10 min ``--causal`` replay's CPU)
        self._blocks: list[tuple[list[tuple[float, float, float, float, float, float, float]], float]] = []
        self._pending = 0  # the rows of those blocks
        self.fits: list[HoverTheta | None] = [None] * len(HOVER_FORMS)
        #: the fits are those of the normal equations as they are (False: solved when next needed)
        self._solved = True
        #: per form, the sums (sin, cos) of the offsets' change's heading change over the samples
        self._anchor_sc = [[0.0, 0.0] for _ in HOVER_FORMS]
        #: the fits as core corrections, and which of them change the offsets
        self._cors: list[Correction | None] = [None] * len(HOVER_FORMS)
        self._offset = [False] * len(HOVER_FORMS)
        self.checks = [RunningSelfCheck() for _ in HOVER_FORMS]
        self.filter = HeadingFilter(tau_s)
        self.deg = math.nan
        #: the form published (None: none is on)
        self.on_form: int | None = None

    def refit(self, t_s: float) -> None:
        """The buffered samples (the latest at ``t_s``) go, as one block, into the normal equations and into
        those of their block of time (when next read: :attr:`normal`); every form is solved again when next
        needed (:meth:`_solve`; where the in-flight correction applies the forms are neither judged nor
        reported)."""
        if self._block:
            self._blocks.append((self._block, t_s))
            self._pending += len(self._block)
            self._block = []
            if self._pending > MAX_PENDING_HOVER_ROWS:  # a live daemon's memory stays bounded
                _ = self.normal
        self._solved = False

    @property
    def normal(self) -> HoverNormal:
        """The normal equations of every block :meth:`refit` closed (the blocks' sums taken in order)."""
        for block, t_s in self._blocks:  # (the rows' floats one by one: half np.asarray's time on tuples)
            a = np.fromiter(chain.from_iterable(block), float, HOVER_ROW * len(block)).reshape(-1, HOVER_ROW)
            part = HoverNormal()
            part.add(a[:, 0:3], a[:, 3], a[:, 4], a[:, 5], a[:, 6])
            self._normal.merge(part)
            self._groups.add(part, t_s)
        self._blocks = []
        self._pending = 0
        return self._normal

    def _solve(self) -> None:
        """Every form solved on the normal equations as the last :meth:`refit` left them (only it adds to
        them: the same fits as solved there and then)."""
        self._solved = True
        self.fits = [self.normal.fit(sd) for sd in HOVER_FORMS]
        self._cors = [None if f is None else f.correction() for f in self.fits]
        self._offset = [f is not None and offset_changed(f) for f in self.fits]

    def step(self, rec: MagRecord, own_field: Float3, psi_own: float, judged: bool, shadow: bool,
             rate: float, dt: float, turn_rad_s: float = 0.0) -> None:  # fmt: skip
        """One sample: ``own_field`` the field as the autopilot had it, ``psi_own`` its heading; ``judged``:
        the motors run and the tilt is within the check's bounds; ``shadow``: judge and filter the forms'
        headings (False where the in-flight correction applies: the samples are only accumulated); ``rate``,
        ``dt``, ``turn_rad_s``: the heading filter's propagation (:attr:`HeadingTrack.last_rate`)."""
        cr, sr, cp, sp = rec.tilt
        ok = judged and rec.ap_yaw == rec.ap_yaw
        if ok:
            roll, pitch = math.atan2(sr, cr), math.atan2(sp, cp)
            self._block.append((*own_field, roll, pitch, rec.ap_yaw, rec.throttle_01))
        refit = False
        if shadow:
            if not self._solved:
                self._solve()
            thr = rec.throttle_01
            fx, fy, fz = own_field
            ref, seg = (rec.gyro_yaw, rec.gyro_epoch) if rec.imu_fast else (rec.ap_yaw, 0.0)
            cands: list[float] = []
            for k, (cor, chk) in enumerate(zip(self._cors, self.checks, strict=True)):
                if cor is None:
                    cands.append(psi_own)
                    continue
                got = cor.apply(fx, fy, fz, thr)  # eqs. (2), (11)
                cand = heading_from_trig_deg(*got.corrected, cr, sr, cp, sp)  # eq. (24)
                if self._offset[k]:  # the offsets' change's own heading change, averaged (see published_deg)
                    b0, b1, b2 = got.bias
                    a = math.radians(cand - heading_from_trig_deg(fx - b0, fy - b1, fz - b2, cr, sr, cp, sp))
                    sc = self._anchor_sc[k]  # its mean over every sample so far: d's heading change turns
                    sc[0] += math.sin(a)  # with the yaw about a constant part, and only that goes
                    sc[1] += math.cos(a)
                cands.append(cand)
                if ok and ref == ref:
                    refit |= chk.add(rec.t_s, math.radians(psi_own), math.radians(cand), ref, seg, rec.ap_yaw)
            on_form = None  # the first form whose check is on (a loop: a generator costs ~1 us a sample)
            for k, c in enumerate(self.checks):
                if c.on and self._cors[k] is not None:
                    on_form = k
                    break
            self.on_form = on_form
            self.deg = self.filter.update(cands[self.on_form if self.on_form is not None else 0], rate, dt,
                                          turn_rad_s)  # fmt: skip
        elif self.filter.psi_deg is not None:  # (already reset: nothing to do, at every such sample)
            self.filter.reset()
        due = ok and len(self._block) >= MIN_HOVER_BLOCK and not rec.t_s - self._fit_t < LIVE_WINDOW_S
        if refit or due:
            self.refit(rec.t_s)
            self._fit_t = rec.t_s

    @property
    def fit(self) -> HoverTheta | None:
        """The published form's fit (None: none is published)."""
        if not self._solved:
            self._solve()
        return None if self.on_form is None else self.fits[self.on_form]

    def stated_fit(self) -> HoverTheta | None:
        """:attr:`fit` with theta's sigma the larger of its own and the jackknife's over the blocks of time
        (core/hover_theta.py :func:`~magcomp.core.hover_theta.grouped_jackknife`), for the summary."""
        fit = self.fit
        if fit is None or self.on_form is None:
            return fit
        normal = self.normal  # (the blocks' sums taken: the groups too)
        return grouped_jackknife(normal, self._groups, fit, HOVER_FORMS[self.on_form])

    def published_deg(self) -> float:
        """The published form's filtered heading, the constant heading change of an offsets' change taken out
        (core/hover_theta.py ``anchored``; theta's own change at the mean throttle is the correction), deg."""
        if not self._solved:
            self._solve()
        k = self.on_form
        if k is None or self._cors[k] is None or not self._offset[k]:
            return self.deg % 360.0
        sn, cs = self._anchor_sc[k]
        return (self.deg - math.degrees(math.atan2(sn, cs))) % 360.0


#: the samples a re-solve's constant change is measured on: one every RECENT_EVERY_S (s), the latest RECENT_N
#: (two minutes, the running check's RECENT_S)
RECENT_EVERY_S = 0.2
RECENT_N = 600
#: what is remembered of each: the field as received (3), the throttle, cos / sin of roll and pitch (4), the
#: autopilot's own heading, the time, the check's reference and its segment, the autopilot's yaw
RECENT_FIELDS = 13

#: the live hover model is solved again when a self-check window closes, or with this many new samples
#: with the motors running and a window's time (LIVE_WINDOW_S) since the last solve (before any fit, no check
#: has windows): more than twice its unknowns' count of 3-row samples
MIN_HOVER_BLOCK = 50
#: the most hover rows :meth:`HoverShadow.refit` keeps unsummed (its sums are taken where they are read, never
#: where the in-flight correction applies; a daemon flies for hours): ~10 min of a 50 Hz compass, ~3 MB of
#: 7-float rows. The sums are taken in the same order either way (bit for bit)
MAX_PENDING_HOVER_ROWS = 30_000
#: a hover sample's row in the block (:meth:`HoverShadow.step`): the field (3), roll, pitch, yaw, throttle
HOVER_ROW = 7


class HeadingTrack:
    """One compass's two heading filters (corrected, uncorrected) and their last outputs (deg)."""

    __slots__ = (
        "_holding",
        "_last_rate",
        "_recent",
        "_recent_a",
        "_recent_i",
        "_recent_n",
        "_recent_t",
        "_theta_anchored",
        "check",
        "corrected",
        "corrected_deg",
        "flown_d2",
        "flown_n",
        "gyro_epoch",
        "gyro_yaw",
        "hover",
        "hover_on",
        "own",
        "own_deg",
        "raw",
        "raw_deg",
        "self_check",
        "solution",
        "starts_published",
    )  # fmt: skip

    def __init__(self, tau_s: float, self_check: bool = True, hover: bool = True,
                 starts_published: bool = False) -> None:  # fmt: skip
        #: judge in-flight corrections before publishing them (``[output] self_check``)
        self.self_check = self_check
        #: learn theta against the autopilot's calibration live (``[inflight] enabled``)
        self.hover_on = hover
        self.corrected = HeadingFilter(tau_s)
        self.raw = HeadingFilter(tau_s)
        #: the autopilot's own field (as logged) through the same filter: what is published while the
        #: self-check has not found an in-flight correction better (the live form of the two-pass check)
        self.own = HeadingFilter(tau_s)
        self.own_deg = math.nan
        self.check: RunningSelfCheck | None = None
        #: theta against the autopilot's calibration, live (created with the first throttle-known sample)
        self.hover: HoverShadow | None = None
        self.corrected_deg = self.raw_deg = math.nan
        self._last_rate = (math.nan, 0.0, 0.0)
        self.gyro_yaw = math.nan
        self.gyro_epoch = -1.0
        #: an in-flight correction warm-started from a state learned on this very log (a two-pass replay's
        #: per-sample second pass) starts published; one from another flight's state does not
        self.starts_published = starts_published
        #: the in-flight estimate published last (L and d as 12 floats, theta): a new one moves the check's
        #: held offset by its constant part's change (RunningSelfCheck.shift)
        self.solution: Estimate | None = None
        #: the latest judged samples (field as received, throttle, cos / sin of roll and pitch, the
        #: autopilot's own heading), one every RECENT_EVERY_S over RECENT_N: where that change is measured.
        #: A ring of columns (row k: the k-th quantity), ``_recent_i`` the next column written, ``_recent_n``
        #: those held; ``_recent_a`` the held ones oldest first (None: taken again when next needed)
        self._recent = np.empty((RECENT_FIELDS, RECENT_N))
        self._recent_i = self._recent_n = 0
        self._recent_a: NDArray[np.float64] | None = None
        self._recent_t = -math.inf
        self._holding = False
        #: the held constant was taken with theta's bias out (:meth:`own_offset_rad`)
        self._theta_anchored = False
        #: the samples judged so far (:func:`count_flown`) and the sum of their throttle^2
        self.flown_n = 0
        self.flown_d2 = 0.0

    def remember(self, t_s: float, raw: Float3, throttle_01: float, tilt: tuple[float, ...],
                 psi_own_deg: float, ref_rad: float = math.nan, segment: float = 0.0,
                 ap_yaw_rad: float = math.nan) -> None:  # fmt: skip
        """One judged sample for :meth:`constant_change_rad`, :meth:`own_offset_rad` and :meth:`rejudge` (at
        most one every RECENT_EVERY_S): the field as received, the throttle, cos / sin of roll and pitch, the
        autopilot's own heading (deg), the check's reference (rad) and its segment, the autopilot's yaw
        (rad)."""
        if t_s - self._recent_t >= RECENT_EVERY_S or t_s < self._recent_t:
            self._recent_t = t_s
            i = self._recent_i
            self._recent[:, i] = (*raw, throttle_01, *tilt, psi_own_deg, t_s, ref_rad, segment, ap_yaw_rad)
            self._recent_i = (i + 1) % RECENT_N
            self._recent_n = min(self._recent_n + 1, RECENT_N)
            self._recent_a = None

    def add_flown(self, n: int, sum_throttle2: float) -> None:
        """``n`` more samples judged, the sum of their throttle^2 (:attr:`throttle2_flown`)."""
        self.flown_n += n
        self.flown_d2 += sum_throttle2

    @property
    def throttle2_flown(self) -> float:
        """The mean throttle^2 over the flight (:func:`count_flown`; NaN before any sample): theta times it is
        the bias eq. (11) puts on the field at the throttle flown."""
        return self.flown_d2 / self.flown_n if self.flown_n else math.nan

    def _remembered(self) -> NDArray[np.float64] | None:
        """The samples remembered, oldest first, as columns (RECENT_FIELDS, n) (None: none)."""
        a = self._recent_a
        if a is None and self._recent_n:
            r, i = self._recent, self._recent_i
            a = r[:, :i].copy() if self._recent_n < RECENT_N else np.concatenate((r[:, i:], r[:, :i]), axis=1)
            self._recent_a = a
        return a

    def own_offset_rad(self, estimate: Estimate) -> float:
        """The constant that puts ``estimate``'s heading on the autopilot's calibration over the samples
        remembered (rad; NaN: none): core/selfcheck.py :func:`~magcomp.core.selfcheck.switch_on_offset_rad`,
        theta's bias out where the throttle flown measures it (log171, against its external compass: the
        live corrected headings of compasses 1 and 2 were +12.8 and +8.5 deg off on average with the
        autopilot's own heading's constant, -4.4 and +1.4 with this one, the two-pass replay's -1.2 and
        -1.6)."""
        a = self._remembered()
        if a is None:
            return math.nan
        offset, self._theta_anchored = switch_on_offset_rad(a[0:3].T, a[3], a[4:8].T, a[8], estimate)
        return offset

    def rejudge(self, att_circular: bool) -> SelfCheck | None:
        """The estimate published last judged again on the samples remembered
        (:func:`~magcomp.core.selfcheck.judge_estimate`; None: no estimate or samples yet)."""
        a = self._remembered()
        sol = self.solution
        if a is None or sol is None or a.shape[1] < MIN_WINDOWS * MIN_PER_WINDOW:
            return None
        return judge_estimate(a[9], a[0:3].T, a[3], a[4:8].T, a[8], a[10], a[11], a[12], sol, att_circular)

    def constant_change_rad(self, old: Estimate, new: Estimate) -> float:
        """The corrected heading's change as a whole from estimate ``old`` to ``new`` over the samples
        remembered (core/selfcheck.py :func:`~magcomp.core.selfcheck.constant_change_rad`, theta's part out
        where the held constant has it out; NaN: none)."""
        a = self._remembered()
        if a is None:
            return math.nan
        return constant_change_rad(a[0:3].T, a[3], a[4:8].T, old, new, self._theta_anchored)

    def follow(self, sol: Estimate | None, chk: RunningSelfCheck) -> None:
        """The in-flight estimate judged at this sample (None: none); a new one (re-solved) while the check
        holds its offset moves that offset by its constant change (:meth:`constant_change_rad`)."""
        if sol is None:
            return
        last = self.solution
        holds = chk.holds  # neither shift nor hold changes it
        if holds and last is not None and last[0] is not sol[0]:
            change = self.constant_change_rad(last, sol)
            if change == change:  # not NaN: samples to measure it on
                chk.shift(change)
        if holds and not self._holding:  # switched on: the offset with this estimate on every sample
            chk.hold(self.own_offset_rad(sol))
        self._holding = holds
        self.solution = sol

    def reset(self) -> None:
        self.corrected.reset()
        self.raw.reset()
        self.own.reset()
        if self.hover is not None:
            self.hover.filter.reset()

    def step(
        self,
        psi: float,
        psi_raw: float,
        corrected: bool,
        restart: bool,
        rate: float,
        dt: float,
        gyro_yaw: float = math.nan,
        gyro_epoch: float = -1.0,
        imu_dt: float = math.nan,
        turn_rad_s: float = 0.0,
        bias_rad_s: float = math.nan,
        psi_own: float | None = None,
    ) -> None:
        """Both filters over one sample; the results in :attr:`corrected_deg` and :attr:`raw_deg`. ``psi`` /
        ``psi_raw``: eq. (24) of the corrected and the calibrated-only field; ``corrected``: the throttle is
        known (else the corrected heading is the uncorrected one); ``restart``: the filters start again from
        this sample (a gap, a stale gyro); ``rate``: the Euler yaw rate (:func:`yaw_rate`), ``dt`` the
        interval (0: none). ``gyro_yaw`` / ``gyro_epoch``: the gyro's yaw integrated at the IMU's rate; where
        the previous sample had one of the same epoch, the filter propagates with its change over the interval
        (the mean rate) rather than the latest IMU sample's rate times the interval, which at 2-4 Hz
        telemetry or ULog compass rates misses most of a turn. Only where the interval holds several IMU
        samples (``imu_dt``): where the gyro comes with the field (RAW_IMU), one sample per interval, its own
        rate is kept (the paper's pan: 1.66 deg max error that way, 2.97 with the trapezoid). ``psi_own``:
        the autopilot's own heading, through its filter with the same rate and interval (:attr:`own_deg`;
        None: not this track's). Used by the per-sample stage and by the two-pass replay's second pass."""
        prev_yaw, prev_epoch = self.gyro_yaw, self.gyro_epoch
        self.gyro_yaw, self.gyro_epoch = gyro_yaw, gyro_epoch
        if dt > 1.5 * imu_dt and prev_epoch == gyro_epoch and gyro_yaw - prev_yaw == gyro_yaw - prev_yaw:
            rate = (gyro_yaw - prev_yaw) / dt  # several IMU samples in the interval (NaN imu_dt: never)
        if restart:
            self.reset()
        if bias_rad_s == bias_rad_s:  # not NaN: the attitude filter's bias, where it can be trusted
            b = bias_rad_s * _DEG_PER_RAD
            self.raw.bias_deg_s = self.corrected.bias_deg_s = self.own.bias_deg_s = b
        raw = self.raw_deg = self.raw.update(psi_raw, rate, dt, turn_rad_s)
        self.corrected_deg = self.corrected.update(psi, rate, dt, turn_rad_s) if corrected else raw
        if psi_own is not None:
            self.own_deg = self.own.update(psi_own, rate, dt, turn_rad_s)
        self._last_rate = (rate, dt, turn_rad_s)

    @property
    def last_rate(self) -> tuple[float, float, float]:
        """The Euler yaw rate (rad/s), interval (s) and turn rate (rad/s, :func:`turn_rate`) the last
        :meth:`step` propagated with."""
        return self._last_rate


#: a body rate (rad/s) above which the vehicle is moving, not resting: five times the largest gyro bias seen
#: (0.07-0.3 deg/s on the development logs, the simulator's uncalibrated 0.57 deg/s: ~0.01 rad/s)
STILL_RATE_RAD_S = 0.05


def gyro_bias_rad_s(rec: MagRecord, raw_rate_rad_s: float) -> float:
    """The attitude filter's gyro bias as a yaw-rate bias (rad/s) where it can be trusted: with the motors
    off (no throttle, or the throttle below MOTORS_RUNNING_01), the vehicle at rest (its body rate below
    STILL_RATE_RAD_S) and the filter settled, the accelerometer reads gravity alone and the filter's bias
    is the gyro's; NaN elsewhere, where the heading filter learns its own: in flight the attitude filter
    learns thrust, drag and a turn's centripetal acceleration as bias (1.1-1.6 deg/s on log171 and 1.BIN,
    up to 0.9 deg/s of yaw rate in the simulator's banked turns), and a hand carrying the vehicle moves it
    (the paper's log: 1.96 deg max in its pan with the motors-off rule alone, 1.70 with rest)."""
    if not bias_trusted(rec.down is not None, rec.have_throttle, rec.throttle_01, rec.gyro_raw):
        return math.nan
    cr, sr, cp, _ = rec.tilt
    return raw_rate_rad_s - yaw_rate(rec.gyro[1], rec.gyro[2], cr, sr, cp)


def bias_trusted(
    settled: bool | NDArray[np.bool_],
    have_throttle: bool | NDArray[np.bool_],
    throttle_01: float | F64,
    gyro_raw: tuple[float, float, float] | tuple[F64, F64, F64],
) -> bool | NDArray[np.bool_]:
    """:func:`gyro_bias_rad_s`'s rule: the attitude filter settled, the motors off (no throttle, or the
    throttle not above MOTORS_RUNNING_01), the vehicle at rest (its raw body rate not above
    STILL_RATE_RAD_S). Python bools and floats (one sample), or arrays of a block of samples (element by
    element); ``^ True`` negates both a bool and a boolean array."""
    gx, gy, gz = gyro_raw
    motors_running = have_throttle & (throttle_01 > MOTORS_RUNNING_01)
    moving = gx * gx + gy * gy + gz * gz > STILL_RATE_RAD_S * STILL_RATE_RAD_S
    return settled & ((motors_running | moving) ^ True)


def filter_rates(rec: MagRecord) -> tuple[float, float, float]:
    """What the heading filters propagate with at this sample, from the raw gyro: the Euler yaw rate
    (:func:`yaw_rate`, rad/s), the turn rate (core/heading_filter.py :func:`turn_rate`, rad/s) and the
    attitude filter's bias where it can be trusted (:func:`gyro_bias_rad_s`; NaN elsewhere). The live stage
    takes them here; the two-pass replay's second pass takes the same numbers a block at a time
    (:func:`filter_rates_block`)."""
    gx, gy, gz = rec.gyro_raw
    cr, sr, cp, _ = rec.tilt
    rate = yaw_rate(gy, gz, cr, sr, cp)
    return rate, turn_rate(gx, gy, gz, cr * cp), gyro_bias_rad_s(rec, rate)


def filter_rates_block(
    gyro_raw: tuple[F64, F64, F64],
    gyro_yz: tuple[F64, F64],
    tilt: tuple[F64, F64, F64],
    settled: NDArray[np.bool_],
    have_throttle: NDArray[np.bool_],
    throttle_01: F64,
) -> tuple[F64, F64, F64]:
    """:func:`filter_rates` of a block of samples (the same numbers: the same operations, element by element)
    from their columns: the gyro as logged (x, y, z), the bias-corrected gyro's y and z, cos / sin of roll and
    cos of pitch, whether the attitude filter had settled (``MagRecord.down`` not None), the throttle."""
    gx, gy, gz = gyro_raw
    cr, sr, cp = tilt
    rate = yaw_rate(gy, gz, cr, sr, cp)
    trusted = bias_trusted(settled, have_throttle, throttle_01, gyro_raw)  # gyro_bias_rad_s's rule
    bias = np.where(trusted, rate - yaw_rate(gyro_yz[0], gyro_yz[1], cr, sr, cp), np.nan)
    return rate, turn_rate(gx, gy, gz, cr * cp), bias


def yaw_rate(gy: FloatOrArray, gz: FloatOrArray, cos_roll: FloatOrArray, sin_roll: FloatOrArray,
             cos_pitch: FloatOrArray) -> FloatOrArray:  # fmt: skip
    """Euler yaw rate from body rates (ZYX): ``(q sin(roll) + r cos(roll)) / cos(pitch)`` (NaN where
    ``|cos(pitch)| < MIN_COS_PITCH``); floats, or arrays of a block of samples."""
    undefined = abs(cos_pitch) < MIN_COS_PITCH  # abs() of an array is np.abs
    if not isinstance(cos_pitch, np.ndarray):
        return math.nan if undefined else _euler_yaw_rate(gy, gz, cos_roll, sin_roll, cos_pitch)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(undefined, np.nan, _euler_yaw_rate(gy, gz, cos_roll, sin_roll, cos_pitch))


def _euler_yaw_rate(gy: FloatOrArray, gz: FloatOrArray, cos_roll: FloatOrArray, sin_roll: FloatOrArray,
                    cos_pitch: FloatOrArray) -> FloatOrArray:  # fmt: skip
    """:func:`yaw_rate` where it is defined (ZYX Euler angles)."""
    return (gy * sin_roll + gz * cos_roll) / cos_pitch


def _shadow_heading_deg(rec: MagRecord) -> float | None:
    """Eq. (2), eq. (11) and eq. (24) with the in-flight solution not yet applied (``rec.shadow``)."""
    if rec.shadow is None or not rec.have_throttle:
        return None
    coeffs, theta = rec.shadow
    ux, uy, uz = apply_eq2(coeffs, *rec.raw)
    d2 = rec.throttle_01 * rec.throttle_01
    return heading_from_trig_deg(ux - theta[0] * d2, uy - theta[1] * d2, uz - theta[2] * d2, *rec.tilt)


def count_flown(rec: MagRecord, track: HeadingTrack) -> bool:
    """Whether the self-check judges this sample (the throttle known, the motors running, roll and pitch
    within MAX_TILT_COS); each such sample counts towards :attr:`HeadingTrack.throttle2_flown` (a two-pass
    replay's first pass, which has no heading stage, counts them from its sample log:
    service/final_pass.py :func:`~magcomp.service.final_pass.throttle2_flown`)."""
    cr, _, cp, _ = rec.tilt
    thr = rec.throttle_01
    if rec.have_throttle and judged(thr, cr, cp):
        track.add_flown(1, thr * thr)
        return True
    return False


def _start_check(track: HeadingTrack, inf: InflightOutput | None) -> RunningSelfCheck:
    """A compass's running self-check, at its first sample with a candidate: off until it beats the
    autopilot's own heading on this flight, also where the correction is carried over from the vehicle's
    saved state: the vehicle may have changed since, and the relative form's constant part settles again
    on the new flight (37-42 deg off for 5 s on a development log when a saved correction was published
    from the first window: test_warm_start_check.py); one learned from this very log by a two-pass
    replay's first pass starts published."""
    chk = RunningSelfCheck()
    chk.on = track.starts_published and inf is not None and inf.warm_started
    chk.rejudge = track.rejudge
    return chk


def heading_stage(rec: MagRecord, track: HeadingTrack) -> None:
    """Fills ``rec.heading_deg`` and ``rec.heading_raw_deg`` (deg, [0, 360)). Where the correction is the
    in-flight calibration (it replaces the autopilot's own), the published heading is the autopilot's own
    field through the same filter (its flags without FLAG_CALIBRATED) until the running self-check
    (:class:`~magcomp.core.selfcheck.RunningSelfCheck`) finds the corrected one better beyond the noise.
    In flight the estimate's constant part moves as it is re-solved (and in the relative form it cannot be
    known at all: the mount's yaw), which no window of the check sees: the published heading takes its
    constant part from the autopilot's calibration, theta's bias out where the throttle flown measures it,
    when it switches on (over the samples judged lately, with the current estimate:
    :meth:`HeadingTrack.own_offset_rad`) and holds it,
    moved at each re-solve by the estimate's own constant change over the samples judged lately
    (:meth:`HeadingTrack.constant_change_rad`), so that it neither jumps when the correction switches on
    nor drifts with the re-solves nor with the autopilot's own error. The two-pass replay, whose
    correction is fixed over the log, keeps its own. Theta against the autopilot's calibration is
    published only where no in-flight correction applies: where one applies but is not published (its
    check not on, or its own error possibly above the autopilot's:
    :meth:`~magcomp.core.selfcheck.RunningSelfCheck.publishes`), the autopilot's own heading is
    (publishing the hover theta there made two development compasses worse, docs/benchmarks.md)."""
    cr, sr, cp, sp = rec.tilt
    ux, uy, uz = rec.field_cal
    psi_raw = heading_from_trig_deg(ux, uy, uz, cr, sr, cp, sp)  # eq. (24)
    have_throttle = rec.have_throttle
    psi = heading_from_trig_deg(*rec.field_corrected, cr, sr, cp, sp) if have_throttle else psi_raw
    psi_own: float | None = None
    if track.self_check:
        vx, vy, vz = rec.raw
        onb = rec.sample.onboard_mgauss
        if onb is not None:  # the autopilot's own motor compensation, which the source removed, put back
            vx, vy, vz = vx + onb[0], vy + onb[1], vz + onb[2]
        psi_own = heading_from_trig_deg(vx, vy, vz, cr, sr, cp, sp)  # eq. (24) of the field as logged
    rate, turn, bias = filter_rates(rec)
    dt = 0.0 if rec.prev_t is None or rec.reset else rec.t_s - rec.prev_t
    # the own heading's filter at every sample: its state stays current
    track.step(psi, psi_raw, have_throttle, rec.reset or not rec.gyro_fresh, rate, dt, rec.gyro_yaw,
               rec.gyro_epoch, rec.imu_dt, turn, bias, psi_own)  # fmt: skip
    rec.heading_deg, rec.heading_raw_deg = track.corrected_deg, track.raw_deg
    if psi_own is None:
        return
    own = track.own_deg
    inf = rec.inflight
    calibrated = rec.calibrated
    if not calibrated:  # nothing of magcomp's applies: the autopilot's own heading
        rec.heading_deg = own
    judged = count_flown(rec, track)  # the throttle known, the motors running, the tilt within bounds
    hover = track.hover
    if have_throttle and track.hover_on and (inf is not None or not calibrated):
        if hover is None:
            hover = track.hover = HoverShadow(track.own.tau_s)
        rate, dt, turn = track.last_rate
        # judged only where it could be published: where the in-flight correction applies, published or
        # not, the hover theta is neither published (below) nor reported (``Pipeline._hover``); judging it
        # there cost ~5 us a sample, 0.4 s of a 10 min ``--causal`` replay
        hover.step(rec, (vx, vy, vz), psi_own, judged, inf is None, rate, dt, turn)
    chk = track.check
    cand = psi if inf is not None else _shadow_heading_deg(rec)
    if cand is not None and have_throttle:
        if chk is None:
            chk = track.check = _start_check(track, inf)
        if judged:
            t_s, ap_yaw = rec.t_s, rec.ap_yaw
            ref, seg = (rec.gyro_yaw, rec.gyro_epoch) if rec.imu_fast else (ap_yaw, 0.0)
            if ref == ref:  # not NaN
                chk.add(t_s, math.radians(psi_own), math.radians(cand), ref, seg, ap_yaw)
            track.remember(t_s, rec.raw, rec.throttle_01, rec.tilt, psi_own, ref, seg, ap_yaw)
    if chk is not None:
        track.follow((inf.coeffs, inf.theta_mgauss) if inf is not None else rec.shadow, chk)
    if inf is not None and chk is not None and chk.publishes(inf.heading_sigma_deg):
        rec.heading_deg = (track.corrected_deg + math.degrees(chk.offset_rad)) % 360.0  # see the doc
        return
    if inf is None and not calibrated and hover is not None and hover.on_form is not None:
        rec.heading_deg = hover.published_deg()  # theta against the autopilot's calibration
        rec.flags = (rec.flags | FLAG_CALIBRATED) & ~FLAG_THETA_CONVERGED
        return
    if cand is not None or chk is not None:
        rec.heading_deg = own
        rec.flags &= ~(FLAG_CALIBRATED | FLAG_THETA_CONVERGED)
