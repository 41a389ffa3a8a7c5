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
* the candidate: the field corrected by the model the diagnosis reports: the extended fit's calibration and
  bias (eqs. (1)-(2), (11) and the named effects) where the compass is observable, else theta with the
  autopilot's calibration as prior (the field minus theta throttle^2).

So that the parameters the diagnosis suggests are judged on the data in hand, as the replay judges its own
correction. Pure: arrays in, a verdict out; no I/O.
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


def _reference(log: LogData, t_s: F64) -> tuple[F64, F64, bool] | None:
    """(reference yaw, its segment, from the gyro) at ``t_s`` (rad): the gyro's integral where the IMU is
    logged at 10 Hz or faster, else the autopilot's yaw; None without an attitude."""
    att = log.attitude_rad
    if len(att) < 10:
        return None
    roll, pitch, yaw = att.values[:, 0], att.values[:, 1], np.unwrap(att.values[:, 2])
    gt, gyro = log.imu_t_s, log.gyro_rad_s
    if gt.size > 10 and float(np.median(np.diff(gt))) <= selfcheck.MAX_GYRO_DT_S:
        r = np.interp(gt, att.t_s, roll)
        p = np.interp(gt, att.t_s, pitch)
        g_yaw, seg = selfcheck.integrate_yaw_rad(gt, selfcheck.euler_yaw_rate_rad_s(gyro, r, p))
        return np.interp(t_s, gt, g_yaw), np.interp(t_s, gt, seg).round(), True
    return np.interp(t_s, att.t_s, yaw), np.zeros(t_s.shape[0]), False


def heading_check(c: CompassDiagnosis, log: LogData) -> selfcheck.SelfCheck | None:
    """The self-check of the heading corrected by ``c``'s model against the field as logged (module doc);
    None where there is nothing to judge (no attitude, no model with theta, the motors never running)."""
    data = c.data
    if c.observable:
        cand = compass_yaw_rad(data, c.extended)
    elif c.prior_theta is not None:
        thr2 = data.throttle_01**2
        m = data.field_mgauss - np.outer(thr2, c.prior_theta.theta_mgauss)
        roll, pitch, _ = euler_from_dcms(data.r_nb).T
        trig = (np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch))
        cand = np.radians(heading_from_trig_deg(m[:, 0], m[:, 1], m[:, 2], *trig))
    else:
        return None
    roll, pitch, _ = euler_from_dcms(data.r_nb).T
    trig = (np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch))
    y = data.field_mgauss
    base = np.radians(heading_from_trig_deg(y[:, 0], y[:, 1], y[:, 2], *trig))
    ref = _reference(log, data.t_s)
    if ref is None:
        return None
    ref_yaw, seg, _ = ref
    keep = (data.throttle_01 > selfcheck.MOTORS_RUNNING_01) & (trig[0] > selfcheck.MAX_TILT_COS)
    keep &= (trig[2] > selfcheck.MAX_TILT_COS) & np.isfinite(ref_yaw) & np.isfinite(cand) & np.isfinite(base)
    if np.count_nonzero(keep) < selfcheck.MIN_PER_WINDOW * selfcheck.MIN_WINDOWS:
        return None
    t = data.t_s[keep]
    att = log.attitude_rad
    ap_yaw = np.interp(t, att.t_s, np.unwrap(att.values[:, 2]))
    ids = selfcheck.window_ids(t, seg[keep])
    return selfcheck.compare(base[keep], cand[keep], ref_yaw[keep], ids, ap_yaw)
