"""Does the diagnosis's model help the heading on this log? The self-check against the gyro of the replay
(:mod:`magcomp.core.selfcheck`), applied to the heading the diagnosis's fitted model gives.

A real log has no heading truth, so :mod:`magcomp.diagnosis.heading` omits heading errors unless another
compass far from the wires serves as the reference. The gyro is a reference no compass steers on short time
scales: the yaw integrated from the logged gyro with the autopilot's roll and pitch, its mean removed in each
10 s window (:func:`magcomp.core.selfcheck.compare`; the autopilot's yaw on the same windows where the gyro is
logged below 10 Hz). Compared per compass, over the samples with the motors running and the tilt within 60
deg, on the same samples and the same tilt:

* the baseline: the field as logged (the autopilot's calibration applied; an onboard motor compensation, which
  the diagnosis reads out of the field, taken out), tilt-compensated (eq. (24));
* the candidate: the same field with the motor term the diagnosis reports removed, ``theta throttle^2``
  (eq. (11); the extended fit's theta where the compass is observable, else theta with the autopilot's
  calibration as prior): what the compensation parameters it writes (ArduPilot COMPASS_MOT*, PX4
  CAL_MAGn_xCOMP) do on top of the autopilot's own calibration.

So that the parameters the diagnosis suggests are judged on the data in hand, as the replay judges its own
correction; ``diagnose --params-out`` leaves out a compass whose theta makes the heading worse. Pure:
arrays in, a verdict out; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcomp.core import selfcheck
from magcomp.core.heading import heading_from_trig_deg
from magcomp.core.rotations import euler_from_dcms
from magcomp.core.types import LogData
from magcomp.core.yaw_follow import YawFollow
from magcomp.diagnosis.export import CompassDiagnosis
from magcomp.diagnosis.heading import compass_yaw_rad
from magcomp.diagnosis.inputs import finite_series
from magcomp.diagnosis.model import F64

#: "helps" also asks for a gain a pilot sees: the rms against the gyro down to this fraction or below (the
#: real-flight benchmark's "better": down 10 % or more); a gain beyond the noise but smaller is no clear gain
MATERIAL_GAIN = 0.9


def verdict(chk: selfcheck.SelfCheck) -> tuple[str, str]:
    """("helps" | "no clear gain" | "makes it worse", why) of a check."""
    if chk.worse:
        return "makes it worse", chk.reason
    if chk.applies and chk.candidate_gyro_deg <= MATERIAL_GAIN * chk.baseline_gyro_deg:
        return "helps", chk.reason
    if chk.applies:
        return "no clear gain", f"better beyond the noise but by less than {100 * (1 - MATERIAL_GAIN):.0f} %"
    return "no clear gain", chk.reason


@dataclass(frozen=True)
class References:
    """What every compass of a log is judged against, computed once per log: the windowed reference (the
    gyro's integral where the IMU is logged at 10 Hz or faster, else the autopilot's yaw) and the autopilot's
    unwrapped yaw, at their own times (rad), and whether that yaw is a second reference."""

    ref_t_s: F64
    ref_yaw_rad: F64
    ref_segment: F64
    att_t_s: F64
    ap_yaw_rad: F64
    ap_yaw_second: bool


def references(log: LogData, yaw_follow: YawFollow | None) -> References | None:
    """The log's references; ``yaw_follow``: how fast the autopilot's yaw follows its primary compass (the
    diagnosis's; None, not measured, keeps that yaw as a second reference): the replay's rule
    (core/selfcheck.py :func:`~magcomp.core.selfcheck.att_is_circular`: the gain 2 sigma above 1 / WINDOW_S,
    a real EKF's 0.01-0.05 /s far below, the simulator's complementary filter's ~0.5 /s above) decides
    whether it is a second reference. None without an attitude."""
    att = finite_series(log.attitude_rad)  # a damaged record's NaN would end an unwrapped yaw
    if len(att) < 10:
        return None
    roll, pitch, yaw = att.values[:, 0], att.values[:, 1], np.unwrap(att.values[:, 2])
    second = not selfcheck.att_is_circular(yaw_follow)
    gt = log.imu_t_s
    if gt.size > 10 and float(np.median(np.diff(gt))) <= selfcheck.MAX_GYRO_DT_S:
        rate = selfcheck.euler_yaw_rate_rad_s(log.gyro_rad_s, np.interp(gt, att.t_s, roll),
                                              np.interp(gt, att.t_s, pitch))  # fmt: skip
        g_yaw, seg = selfcheck.integrate_yaw_rad(gt, rate)
        return References(gt, g_yaw, seg, att.t_s, yaw, second)
    return References(att.t_s, yaw, np.zeros(att.t_s.shape[0]), att.t_s, yaw, second)


def heading_check(c: CompassDiagnosis, refs: References) -> selfcheck.SelfCheck | None:
    """The self-check of the heading with ``c``'s theta removed against the field as logged (module doc);
    None where there is nothing to judge (no theta, the motors never running)."""
    if c.observable:
        theta = c.extended.theta_mgauss
    elif c.prior_theta is not None:
        theta = c.prior_theta.theta_mgauss
    else:
        return None
    trig = _trig(c)
    m = c.data.field_mgauss - np.outer(c.data.throttle_01**2, theta)  # eq. (11)
    cand = np.radians(heading_from_trig_deg(m[:, 0], m[:, 1], m[:, 2], *trig))  # eq. (24)
    return _judge(c, refs, cand, trig)


def model_check(c: CompassDiagnosis, refs: References) -> selfcheck.SelfCheck | None:
    """The same check of the heading the diagnosis's whole model gives (its calibration, eqs. (1)-(2), and
    its bias: :func:`magcomp.diagnosis.heading.compass_yaw_rad`), where the compass is observable: what
    calibrating the compass again would add to the compensation parameters. None elsewhere."""
    if not c.observable:
        return None
    return _judge(c, refs, compass_yaw_rad(c.data, c.extended), _trig(c))


def _trig(c: CompassDiagnosis) -> tuple[F64, F64, F64, F64]:
    """cos / sin of roll and pitch of the diagnosis's compass-free attitude at ``c``'s samples."""
    roll, pitch, _ = euler_from_dcms(c.data.r_nb).T
    return np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)


def _judge(c: CompassDiagnosis, refs: References, cand: F64, trig: tuple[F64, F64, F64, F64]
           ) -> selfcheck.SelfCheck | None:  # fmt: skip
    """:func:`magcomp.core.selfcheck.compare` of ``cand`` (rad, at ``c``'s samples) against the field as
    logged, on the samples with the motors running and the tilt within 60 deg."""
    data = c.data
    y = data.field_mgauss
    base = np.radians(heading_from_trig_deg(y[:, 0], y[:, 1], y[:, 2], *trig))  # eq. (24)
    ref_yaw = np.interp(data.t_s, refs.ref_t_s, refs.ref_yaw_rad)
    keep = (data.throttle_01 > selfcheck.MOTORS_RUNNING_01) & (trig[0] > selfcheck.MAX_TILT_COS)
    keep &= (trig[2] > selfcheck.MAX_TILT_COS) & np.isfinite(ref_yaw) & np.isfinite(cand) & np.isfinite(base)
    if np.count_nonzero(keep) < selfcheck.MIN_PER_WINDOW * selfcheck.MIN_WINDOWS:
        return None
    t = data.t_s[keep]
    seg = np.interp(t, refs.ref_t_s, refs.ref_segment).round()
    ap_yaw = np.interp(t, refs.att_t_s, refs.ap_yaw_rad) if refs.ap_yaw_second else None
    return selfcheck.compare(base[keep], cand[keep], ref_yaw[keep], selfcheck.window_ids(t, seg), ap_yaw)
