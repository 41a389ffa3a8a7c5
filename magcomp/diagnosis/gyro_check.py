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

import numpy as np

from magcomp.core import selfcheck
from magcomp.core.heading import heading_from_trig_deg
from magcomp.core.rotations import euler_from_dcms
from magcomp.core.types import LogData
from magcomp.diagnosis.export import CompassDiagnosis
from magcomp.diagnosis.heading import compass_yaw_rad
from magcomp.diagnosis.model import F64
from magcomp.diagnosis.yaw_follow import yaw_follow_gain

#: the autopilot's yaw is no second reference where it follows the compass it fuses this fast or faster
#: (1/s): within the check's own window (WINDOW_S) it then carries that compass's throttle-driven error (a
#: complementary filter's ~0.5 /s), and the other compasses' errors follow the same throttle; a real EKF's
#: pull of 0.01-0.05 /s leaves it an independent reference over the window (diagnosis's yaw-follow note
#: measures the rate)
CIRCULAR_FOLLOW_PER_S = 1.0 / selfcheck.WINDOW_S
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


def _reference(log: LogData, t_s: F64) -> tuple[F64, F64, bool] | None:
    """(reference yaw, its segment, from the gyro) at ``t_s`` (rad): the gyro's integral where the IMU is
    logged at 10 Hz or faster, else the autopilot's yaw; None without an attitude."""
    att_t, att_v = _finite_attitude(log)
    if att_t.size < 10:
        return None
    roll, pitch, yaw = att_v[:, 0], att_v[:, 1], np.unwrap(att_v[:, 2])
    gt, gyro = log.imu_t_s, log.gyro_rad_s
    if gt.size > 10 and float(np.median(np.diff(gt))) <= selfcheck.MAX_GYRO_DT_S:
        r = np.interp(gt, att_t, roll)
        p = np.interp(gt, att_t, pitch)
        g_yaw, seg = selfcheck.integrate_yaw_rad(gt, selfcheck.euler_yaw_rate_rad_s(gyro, r, p))
        return np.interp(t_s, gt, g_yaw), np.interp(t_s, gt, seg).round(), True
    return np.interp(t_s, att_t, yaw), np.zeros(t_s.shape[0]), False


def _finite_attitude(log: LogData) -> tuple[F64, F64]:
    """The autopilot's attitude rows that are finite (a damaged record's NaN would end an unwrapped yaw)."""
    att = log.attitude_rad
    v = np.asarray(att.values, dtype=float).reshape(-1, 3)
    ok = np.isfinite(v).all(axis=1) & np.isfinite(np.asarray(att.t_s, dtype=float))
    return np.asarray(att.t_s, dtype=float)[ok], v[ok]


def heading_check(c: CompassDiagnosis, log: LogData, primary: int) -> selfcheck.SelfCheck | None:
    """The self-check of the heading with ``c``'s theta removed against the field as logged (module doc);
    ``primary``: the compass the autopilot fuses (whose pull on its yaw decides whether that yaw is a second
    reference). None where there is nothing to judge (no attitude, no theta, the motors never running)."""
    data = c.data
    if c.observable:
        theta = c.extended.theta_mgauss
    elif c.prior_theta is not None:
        theta = c.prior_theta.theta_mgauss
    else:
        return None
    roll, pitch, _ = euler_from_dcms(data.r_nb).T
    trig = (np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch))
    m = data.field_mgauss - np.outer(data.throttle_01**2, theta)  # eq. (11)
    cand = np.radians(heading_from_trig_deg(m[:, 0], m[:, 1], m[:, 2], *trig))  # eq. (24)
    return _judge(c, log, primary, cand)


def model_check(c: CompassDiagnosis, log: LogData, primary: int) -> selfcheck.SelfCheck | None:
    """The same check of the heading the diagnosis's whole model gives (its calibration, eqs. (1)-(2), and
    its bias: :func:`magcomp.diagnosis.heading.compass_yaw_rad`), where the compass is observable: what
    calibrating the compass again would add to the compensation parameters. None elsewhere."""
    if not c.observable:
        return None
    return _judge(c, log, primary, compass_yaw_rad(c.data, c.extended))


def _judge(c: CompassDiagnosis, log: LogData, primary: int, cand: F64) -> selfcheck.SelfCheck | None:
    """:func:`magcomp.core.selfcheck.compare` of ``cand`` (rad, at ``c``'s samples) against the field as
    logged, on the samples with the motors running and the tilt within 60 deg."""
    data = c.data
    roll, pitch, _ = euler_from_dcms(data.r_nb).T
    trig = (np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch))
    y = data.field_mgauss
    base = np.radians(heading_from_trig_deg(y[:, 0], y[:, 1], y[:, 2], *trig))  # eq. (24)
    ref = _reference(log, data.t_s)
    if ref is None:
        return None
    ref_yaw, seg, _ = ref
    keep = (data.throttle_01 > selfcheck.MOTORS_RUNNING_01) & (trig[0] > selfcheck.MAX_TILT_COS)
    keep &= (trig[2] > selfcheck.MAX_TILT_COS) & np.isfinite(ref_yaw) & np.isfinite(cand) & np.isfinite(base)
    if np.count_nonzero(keep) < selfcheck.MIN_PER_WINDOW * selfcheck.MIN_WINDOWS:
        return None
    t = data.t_s[keep]
    att_t, att_v = _finite_attitude(log)
    ap_yaw = np.interp(t, att_t, np.unwrap(att_v[:, 2]))
    ids = selfcheck.window_ids(t, seg[keep])
    follows = _follow_rate_per_s(log, primary, t) if primary in log.mag else float("nan")
    second = ap_yaw if not follows >= CIRCULAR_FOLLOW_PER_S else None  # NaN (not measured): kept
    return selfcheck.compare(base[keep], cand[keep], ref_yaw[keep], ids, second)


def _follow_rate_per_s(log: LogData, index: int, t_s: F64) -> float:
    """How fast the autopilot's yaw follows compass ``index`` over the judged samples' span (1/s; NaN where
    it cannot be measured)."""
    mag, att = log.mag[index], log.attitude_rad
    try:
        fit = yaw_follow_gain(att.t_s, att.values, log.imu_t_s, log.gyro_rad_s, mag.t_s, mag.values,
                              t_start_s=float(t_s[0]), t_end_s=float(t_s[-1]))  # fmt: skip
    except (np.linalg.LinAlgError, ValueError):
        return float("nan")
    return float("nan") if fit is None else float(fit.gain_per_s)
