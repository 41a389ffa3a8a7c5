"""Stage 5, heading: eq. (24) on the corrected field, then the heading filter.

The heading is tilt-compensated (roll and pitch from the attitude stage; departure from the paper, whose
eq. (24) is for a level vehicle) and passes a gyro-aided complementary filter
(:class:`~magcomp.service.estimators.HeadingFilter`, departure from the paper: what its Table III measured
was an attitude estimator's yaw). The uncorrected heading (calibration only, no bias removed) goes the
same way, for comparison.
"""

from __future__ import annotations

import math

from magcomp.core.heading import heading_from_trig_deg
from magcomp.core.inflight import InflightOutput
from magcomp.core.selfcheck import RunningSelfCheck
from magcomp.core.types import FLAG_CALIBRATED, FLAG_THETA_CONVERGED
from magcomp.service import estimators as est_core
from magcomp.service.calibrate import apply_eq2
from magcomp.service.record import MagRecord

#: the throttle (0..1) above which the motors count as running for the self-check (service/final_pass.py)
MOTORS_RUNNING_01 = 0.05
#: beyond 60 deg of roll or pitch the tilt-compensated heading is dominated by the tilt's own error
MAX_TILT_COS = 0.5
#: below this |cos(pitch)| the Euler yaw rate is undefined (pitch beyond +-75.5 deg): the filter restarts
MIN_COS_PITCH = 0.25


class HeadingTrack:
    """One compass's two heading filters (corrected, uncorrected) and their last outputs (deg)."""

    __slots__ = (
        "_last_rate",
        "check",
        "corrected",
        "corrected_deg",
        "gyro_epoch",
        "gyro_yaw",
        "own",
        "own_deg",
        "raw",
        "raw_deg",
        "self_check",
    )  # fmt: skip

    def __init__(self, tau_s: float, self_check: bool = True) -> None:
        #: judge in-flight corrections before publishing them (``[output] self_check``)
        self.self_check = self_check
        self.corrected = est_core.HeadingFilter(tau_s)
        self.raw = est_core.HeadingFilter(tau_s)
        #: the autopilot's own field (as logged) through the same filter: what is published while the
        #: self-check has not found an in-flight correction better (the live form of the two-pass check)
        self.own = est_core.HeadingFilter(tau_s)
        self.own_deg = math.nan
        self.check: RunningSelfCheck | None = None
        self.corrected_deg = self.raw_deg = math.nan
        self._last_rate = (math.nan, 0.0)
        self.gyro_yaw = math.nan
        self.gyro_epoch = -1.0

    def reset(self) -> None:
        self.corrected.reset()
        self.raw.reset()
        self.own.reset()

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
        rate is kept (the paper's pan: 1.66 deg max error that way, 2.97 with the trapezoid). Used by the
        per-sample stage and by the two-pass replay's second pass."""
        prev_yaw, prev_epoch = self.gyro_yaw, self.gyro_epoch
        self.gyro_yaw, self.gyro_epoch = gyro_yaw, gyro_epoch
        if dt > 1.5 * imu_dt and prev_epoch == gyro_epoch and gyro_yaw - prev_yaw == gyro_yaw - prev_yaw:
            rate = (gyro_yaw - prev_yaw) / dt  # several IMU samples in the interval (NaN imu_dt: never)
        if restart:
            self.reset()
        raw = self.raw_deg = self.raw.update(psi_raw, rate, dt)
        self.corrected_deg = self.corrected.update(psi, rate, dt) if corrected else raw
        self._last_rate = (rate, dt)

    def step_own(self, psi_own: float) -> float:
        """The autopilot's own heading through its filter, with the rate and interval of the last
        :meth:`step` (call right after it)."""
        rate, dt = self._last_rate
        self.own_deg = self.own.update(psi_own, rate, dt)
        return self.own_deg


def yaw_rate(gy: float, gz: float, cos_roll: float, sin_roll: float, cos_pitch: float) -> float:
    """Euler yaw rate from body rates (ZYX): ``(q sin(roll) + r cos(roll)) / cos(pitch)``."""
    return math.nan if abs(cos_pitch) < MIN_COS_PITCH else (gy * sin_roll + gz * cos_roll) / cos_pitch


def _shadow_heading_deg(rec: MagRecord) -> float | None:
    """Eq. (2), eq. (11) and eq. (24) with the in-flight solution not yet applied (``rec.shadow``)."""
    if rec.shadow is None or not rec.have_throttle:
        return None
    coeffs, theta = rec.shadow
    ux, uy, uz = apply_eq2(coeffs, *rec.raw)
    d2 = rec.throttle_01 * rec.throttle_01
    return heading_from_trig_deg(ux - theta[0] * d2, uy - theta[1] * d2, uz - theta[2] * d2, rec.cos_roll,
                                 rec.sin_roll, rec.cos_pitch, rec.sin_pitch)  # fmt: skip


def _within_baseline(out: InflightOutput, chk: RunningSelfCheck) -> bool:
    """The estimate's own heading uncertainty is below the error measured of the autopilot's own heading
    (against its yaw, else the gyro): a correction that may itself be off by more than what it corrects
    cannot be shown to help, whatever a few windows say."""
    v = chk.verdict
    if v is None:
        return False
    base = v.baseline_att_deg if v.baseline_att_deg == v.baseline_att_deg else v.baseline_gyro_deg
    return out.heading_sigma_deg <= base


def heading_stage(rec: MagRecord, track: HeadingTrack) -> None:
    """Fills ``rec.heading_deg`` and ``rec.heading_raw_deg`` (deg, [0, 360)). Where the correction is the
    in-flight calibration (it replaces the autopilot's own), the published heading is the autopilot's own
    field through the same filter (its flags without FLAG_CALIBRATED) until the running self-check
    (:class:`~magcomp.core.selfcheck.RunningSelfCheck`) finds the corrected one better beyond the noise. In
    flight the estimate's constant part moves as it is re-solved (and in the relative form it cannot be known
    at all: the mount's yaw), which no window of the check sees: the published heading takes its constant
    part from the autopilot's own over the check's latest windows (their circular mean difference), so that
    it neither jumps when the correction switches on or off nor drifts with the re-solves. The two-pass
    replay, whose correction is fixed over the log, keeps its own."""
    cr, sr, cp, sp = rec.cos_roll, rec.sin_roll, rec.cos_pitch, rec.sin_pitch
    ux, uy, uz = rec.field_cal
    psi_raw = heading_from_trig_deg(ux, uy, uz, cr, sr, cp, sp)  # eq. (24)
    if rec.have_throttle:
        cx, cy, cz = rec.field_corrected
        psi = heading_from_trig_deg(cx, cy, cz, cr, sr, cp, sp)
    else:
        psi = psi_raw
    _, gy, gz = rec.gyro
    track.step(psi, psi_raw, rec.have_throttle, rec.reset or not rec.gyro_fresh, yaw_rate(gy, gz, cr, sr, cp),
               0.0 if rec.prev_t is None or rec.reset else rec.t_s - rec.prev_t, rec.gyro_yaw,
               rec.gyro_epoch, rec.imu_dt)  # fmt: skip
    rec.heading_deg, rec.heading_raw_deg = track.corrected_deg, track.raw_deg
    if not track.self_check:
        return
    vx, vy, vz = rec.raw
    onb = rec.sample.onboard_mgauss
    if onb is not None:  # the autopilot's own motor compensation, which the source removed, put back
        vx, vy, vz = vx + onb[0], vy + onb[1], vz + onb[2]
    psi_own = heading_from_trig_deg(vx, vy, vz, cr, sr, cp, sp)  # eq. (24) of the field as logged
    own = track.step_own(psi_own)  # every sample: the filter's state stays current
    if not rec.calibrated:  # nothing of magcomp's applies: the autopilot's own heading
        rec.heading_deg = own
    chk = track.check
    cand = psi if rec.inflight is not None else _shadow_heading_deg(rec)
    if cand is None and chk is None:
        return
    if cand is not None and rec.have_throttle:
        if chk is None:
            chk = track.check = RunningSelfCheck()
            chk.on = rec.inflight is not None and rec.inflight.warm_started  # judged on its own flight
        if rec.throttle_01 > MOTORS_RUNNING_01 and cr > MAX_TILT_COS and cp > MAX_TILT_COS:
            ref, seg = (rec.gyro_yaw, rec.gyro_epoch) if rec.imu_fast else (rec.ap_yaw, 0.0)
            if ref == ref:  # not NaN
                chk.add(rec.t_s, math.radians(psi_own), math.radians(cand), ref, seg, rec.ap_yaw)
    if rec.inflight is None or chk is None or not chk.on or not _within_baseline(rec.inflight, chk):
        rec.heading_deg = own
        rec.flags &= ~(FLAG_CALIBRATED | FLAG_THETA_CONVERGED)
    else:  # the constant part is the autopilot's own (see the doc)
        rec.heading_deg = (track.corrected_deg + math.degrees(chk.offset_rad)) % 360.0
