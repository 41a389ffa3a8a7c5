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
from magcomp.service import estimators as est_core
from magcomp.service.record import MagRecord

#: below this |cos(pitch)| the Euler yaw rate is undefined (pitch beyond +-75.5 deg): the filter restarts
MIN_COS_PITCH = 0.25


class HeadingTrack:
    """One compass's two heading filters (corrected, uncorrected) and their last outputs (deg)."""

    __slots__ = ("corrected", "corrected_deg", "gyro_epoch", "gyro_yaw", "raw", "raw_deg")

    def __init__(self, tau_s: float) -> None:
        self.corrected = est_core.HeadingFilter(tau_s)
        self.raw = est_core.HeadingFilter(tau_s)
        self.corrected_deg = self.raw_deg = math.nan
        self.gyro_yaw = math.nan
        self.gyro_epoch = -1.0

    def reset(self) -> None:
        self.corrected.reset()
        self.raw.reset()

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
    ) -> None:
        """Both filters over one sample; the results in :attr:`corrected_deg` and :attr:`raw_deg`. ``psi`` /
        ``psi_raw``: eq. (24) of the corrected and the calibrated-only field; ``corrected``: the throttle is
        known (else the corrected heading is the uncorrected one); ``restart``: the filters start again from
        this sample (a gap, a stale gyro); ``rate``: the Euler yaw rate (:func:`yaw_rate`), ``dt`` the
        interval (0: none). ``gyro_yaw`` / ``gyro_epoch``: the gyro's yaw integrated at the IMU's rate; where
        the previous sample had one of the same epoch, the filter propagates with its change over the interval
        (the mean rate) rather than the latest IMU sample's rate times the interval, which at 2-4 Hz
        telemetry or ULog compass rates misses most of a turn. Used by the per-sample stage and by the
        two-pass replay's second pass."""
        prev_yaw, prev_epoch = self.gyro_yaw, self.gyro_epoch
        self.gyro_yaw, self.gyro_epoch = gyro_yaw, gyro_epoch
        if dt > 0.0 and prev_epoch == gyro_epoch and gyro_yaw - prev_yaw == gyro_yaw - prev_yaw:  # not NaN
            rate = (gyro_yaw - prev_yaw) / dt
        if restart:
            self.reset()
        raw = self.raw_deg = self.raw.update(psi_raw, rate, dt)
        self.corrected_deg = self.corrected.update(psi, rate, dt) if corrected else raw


def yaw_rate(gy: float, gz: float, cos_roll: float, sin_roll: float, cos_pitch: float) -> float:
    """Euler yaw rate from body rates (ZYX): ``(q sin(roll) + r cos(roll)) / cos(pitch)``."""
    return math.nan if abs(cos_pitch) < MIN_COS_PITCH else (gy * sin_roll + gz * cos_roll) / cos_pitch


def heading_stage(rec: MagRecord, track: HeadingTrack) -> None:
    """Fills ``rec.heading_deg`` and ``rec.heading_raw_deg`` (deg, [0, 360))."""
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
               rec.gyro_epoch)  # fmt: skip
    rec.heading_deg, rec.heading_raw_deg = track.corrected_deg, track.raw_deg
