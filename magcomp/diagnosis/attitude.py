"""Compass-free attitude for the forward model: gyro-propagated rotation with tilt from a reference.

Why not the log's own attitude: ArduPilot's and PX4's ATTITUDE yaw is fused from the very compass we are
diagnosing, so a throttle-driven bias leaks into the yaw, and a forward model driven by that yaw would
absorb part of the bias it is meant to expose. Roll and pitch, by contrast, come from the gyro and the
accelerometer (gravity), not the compass.

So the rotation ``R_nb`` used here is the strap-down integral of the gyro, eq. (18) ``R_dot = R [omega]_x``,
with a Mahony-style complementary correction (proportional + integral, ref. [23]) that pulls only the
*tilt* toward a compass-free "down" reference: the log's roll and pitch when it has an attitude, otherwise
the accelerometer. When the log also has the GNSS velocity, the reference may be the accelerometer minus the
GNSS acceleration (:mod:`magcomp.diagnosis.gps_tilt`): a GPS-aided autopilot that removes that acceleration
with its compass-steered yaw leans its roll and pitch with the very bias diagnosed whenever the vehicle
accelerates. It is used only where the log's own data show that lean exceeding the GNSS reference's own error
(on the simulator's autopilot, not on any development log: docs/diagnosis.md). The heading is then pure gyro
integration: it is free of the compass, drifts only with the gyro bias about the vertical, and that drift
is a fitted nuisance parameter of the forward model (:mod:`magcomp.diagnosis.model`). Departure from the
paper: the paper feeds the accelerometer to the Mahony filter and uses the full estimated attitude; here the
filter never sees the compass.

Symbols: ``q_nb`` body FRD -> NED (w, x, y, z); ``down_b`` unit down vector in body axes (third row of R_nb).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magcomp.core.rotations import (
    dcm_from_euler,
    dcm_from_quat,
    dcms_from_quats,
    down_b_from_quat,
    euler_from_dcms,
    quat_from_dcm,
)
from magcomp.diagnosis.gps_tilt import aligned_gyro_rotation, gps_tilt_reference

F64 = NDArray[np.float64]


STATIONARY_RATE_RAD_S = 0.05

#: Slowest gyro the strap-down integral is trusted at. A multirotor's attitude loop moves the vehicle at up
#: to ~5 Hz; sampling the rate below twice that aliases rotation the integral then never sees, and the
#: trapezoid's commutation error grows as (omega dt)^2. 20 Hz keeps a factor of 2 over Nyquist. Below it
#: (telemetry logs with ~1 Hz RAW_IMU) the autopilot's attitude, estimated on board at the full IMU rate,
#: is the better source.
MIN_GYRO_HZ = 20.0


@dataclass(frozen=True)
class TiltFilterParams:
    """Gains of the tilt-only complementary filter.

    kp_rad_s: proportional gain on the tilt error (rad/s per rad); ki_rad_s2: gyro-bias integral gain;
    passes: runs over the log, each starting from the gyro bias the previous one ended with (a log is
    short compared with the integral's time constant, so the second pass removes most of the start-up drift).
    """

    kp_rad_s: float = 5.0
    ki_rad_s2: float = 0.3
    passes: int = 2


def down_b_from_euler(roll_rad: F64, pitch_rad: F64) -> F64:
    """Unit down vector in body axes from roll/pitch, shape (n, 3): yaw-free third row of ``R_nb``."""
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    return np.column_stack([-sp, cp * sr, cp * cr])


def _interp_rows(t_new: F64, t: F64, x: F64) -> F64:
    out = np.empty((t_new.shape[0], x.shape[1]))
    for j in range(x.shape[1]):
        out[:, j] = np.interp(t_new, t, x[:, j])
    return out


def propagate_attitude(
    imu_t_s: F64,
    gyro_b_rad_s: F64,
    ref_t_s: F64,
    ref_down_b: F64,
    q0_nb: F64,
    p: TiltFilterParams | None = None,
) -> F64:
    """Integrate the gyro (eq. (18)) from ``q0_nb``, correcting tilt toward ``ref_down_b``.

    Parameters
    ----------
    imu_t_s : (n,) s, sorted. gyro_b_rad_s : (n, 3) rad/s, body FRD.
    ref_t_s, ref_down_b : (m,), (m, 3) reference down vector in body axes (unit), interpolated to IMU times.
    q0_nb : (4,) initial attitude.

    Returns
    -------
    (n, 4) quaternions q_nb at the IMU times.
    """
    return _propagate((imu_t_s, gyro_b_rad_s), (ref_t_s, ref_down_b), q0_nb, p)[0]


def _propagate(
    imu: tuple[F64, F64],
    reference: tuple[F64, F64],
    q0_nb: F64,
    p: TiltFilterParams | None = None,
    bias0: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> tuple[F64, tuple[float, float, float]]:
    """:func:`propagate_attitude` with ``imu`` = (t, gyro) and ``reference`` = (t, down) paired, starting
    from the gyro bias ``bias0``; also returns the final bias."""
    p = p or TiltFilterParams()
    imu_t_s, gyro_b_rad_s = imu
    n = imu_t_s.shape[0]
    ref = _interp_rows(imu_t_s, *reference)
    ref /= np.maximum(np.linalg.norm(ref, axis=1, keepdims=True), 1e-9)
    out = np.empty((n, 4))
    bias = bias0
    for _ in range(max(1, p.passes)):
        bias = _tilt_pass(imu_t_s, gyro_b_rad_s, ref, q0_nb, p, bias, out)
    return out, bias


_ROW_BLOCK = 1 << 16


def _tilt_pass(
    imu_t_s: F64,
    gyro_b_rad_s: F64,
    ref: F64,
    q0_nb: F64,
    p: TiltFilterParams,
    bias0: tuple[float, float, float],
    out: F64,
) -> tuple[float, float, float]:
    """One pass of the filter, writing ``out`` (n, 4); returns the final gyro-bias estimate (rad/s)."""
    n = imu_t_s.shape[0]
    w, x, y, z = (float(v) for v in q0_nb)
    bx, by, bz = bias0
    dts = np.diff(imu_t_s, prepend=imu_t_s[0])
    med = float(np.median(dts[1:])) if n > 1 else 0.02
    kp, ki = p.kp_rad_s, p.ki_rad_s2
    # the gyro and reference rows as Python floats a block at a time (with the row before the block): as lists
    # of the whole log they took ~300 bytes a row, 0.2 GB for 4 h at 50 Hz (issue 12)
    for a in range(0, n, _ROW_BLOCK):
        lo = max(a - 1, 0)
        # flat lists (x, y, z, x, y, z, ...): a list of floats, not one list object per row
        g = gyro_b_rad_s[lo : a + _ROW_BLOCK].ravel().tolist()
        r = ref[lo : a + _ROW_BLOCK].ravel().tolist()
        dt_block = dts[a : a + _ROW_BLOCK].tolist()
        q_block: list[tuple[float, float, float, float]] = []  # the block's rows of ``out``, set at once
        append = q_block.append
        # the rows before the first of the block (row k - 1; row 0 for the log's first sample)
        j0 = 3 * (a - lo - 1) if a > 0 else 0
        gpx, gpy, gpz = g[j0], g[j0 + 1], g[j0 + 2]
        rx, ry, rz = r[j0], r[j0 + 1], r[j0 + 2]
        j = 3 * (a - lo)  # row k in g and r
        for dt in dt_block:
            if not 0.0 < dt < 10.0 * med:
                dt = 0.0 if j == 0 else med
            dx, dy, dz = down_b_from_quat((w, x, y, z))  # estimated down in body axes
            # (rx, ry, rz): the reference at t_{k-1}, which the state still stands for
            # tilt error e = d_est x d_ref (rotation that takes the estimate to the reference)
            ex = dy * rz - dz * ry
            ey = dz * rx - dx * rz
            ez = dx * ry - dy * rx
            bx += ki * ex * dt
            by += ki * ey * dt
            bz += ki * ez * dt
            # trapezoid: the mean rate over (t_{k-1}, t_k], whichever end of the interval a sample stands for
            gkx, gky, gkz = g[j], g[j + 1], g[j + 2]
            ox = 0.5 * (gkx + gpx) - bx - kp * ex
            oy = 0.5 * (gky + gpy) - by - kp * ey
            oz = 0.5 * (gkz + gpz) - bz - kp * ez
            gpx, gpy, gpz = gkx, gky, gkz
            rx, ry, rz = r[j], r[j + 1], r[j + 2]
            j += 3
            # q <- q * exp(omega dt / 2), eq. (18) in closed form
            ang = math.sqrt(ox * ox + oy * oy + oz * oz) * dt
            if ang > 1e-12:
                s = math.sin(ang / 2.0) / (ang / dt)
                c = math.cos(ang / 2.0)
                qx, qy, qz = ox * s, oy * s, oz * s
                w, x, y, z = (
                    w * c - x * qx - y * qy - z * qz,
                    w * qx + x * c + y * qz - z * qy,
                    w * qy - x * qz + y * c + z * qx,
                    w * qz + x * qy - y * qx + z * c,
                )
                nq = math.sqrt(w * w + x * x + y * y + z * z)
                w, x, y, z = w / nq, x / nq, y / nq, z / nq
            append((w, x, y, z))
        out[a : a + len(q_block)] = q_block
    return bx, by, bz


def quats_at(t_new: F64, t: F64, q: F64) -> F64:
    """Quaternions at ``t_new`` by component-wise linear interpolation (sign-continuous) + renormalisation."""
    qc = q.copy()
    flip = np.sum(qc[1:] * qc[:-1], axis=1) < 0.0
    sign = np.cumprod(np.where(np.concatenate([[False], flip]), -1.0, 1.0))
    qc *= sign[:, None]
    out = _interp_rows(t_new, t, qc)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def dcms_from_euler(att_rad: F64) -> F64:
    """(n, 3) roll, pitch, yaw -> (n, 3, 3) R_nb."""
    return np.stack([dcm_from_euler(float(a[0]), float(a[1]), float(a[2])) for a in att_rad])


@dataclass(frozen=True)
class AttitudeTrack:
    """Rotation used by the forward model at the compass sample times.

    r_nb: (n, 3, 3); source: 'gyro+tilt(gps)', 'gyro+tilt(attitude)', 'gyro+tilt(accelerometer)' or
    'autopilot';
    note: one sentence for the JSON ``evidence`` and the report.
    """

    r_nb: F64
    source: str
    note: str


def attitude_track(
    t_s: F64,
    imu_t_s: F64,
    gyro_b_rad_s: F64,
    accel_b_m_s2: F64,
    att_t_s: F64,
    att_rad: F64,
) -> AttitudeTrack:
    """Choose and build the rotation for the forward model at times ``t_s`` (see module docstring)."""
    return attitude_source(imu_t_s, gyro_b_rad_s, accel_b_m_s2, att_t_s, att_rad).at(t_s)


@dataclass(frozen=True)
class AttitudeSource:
    """The rotation of a log before it is taken at a compass's sample times: which source, and for the gyro
    the filtered integral at the IMU times. Built once per log (:func:`attitude_source`): the choice and the
    integral depend on the log's IMU and attitude only, not on the compass or its latency, and the integral
    is most of the cost of :func:`attitude_track` (a Python loop over every IMU sample, twice)."""

    source: str
    note: str
    #: stationary / none: the one rotation (3, 3)
    r0_nb: F64 | None = None
    #: gyro: the IMU times (n,) and the quaternions q_nb there (n, 4)
    imu_t_s: F64 | None = None
    q_nb: F64 | None = None
    #: autopilot: its attitude's times (m,) and roll, pitch, yaw (m, 3)
    att_t_s: F64 | None = None
    att_rad: F64 | None = None
    #: the GNSS tilt reference's verdict on this log (used or why not, with its figures); "" without GNSS
    gnss_note: str = ""

    def at(self, t_s: F64) -> AttitudeTrack:
        """The rotation at the times ``t_s`` (n,) as an :class:`AttitudeTrack`."""
        if self.q_nb is not None and self.imu_t_s is not None:
            r = dcms_from_quats(quats_at(t_s, self.imu_t_s, self.q_nb))
        elif self.att_t_s is not None and self.att_rad is not None:
            att_t, att_rad = self.att_t_s, self.att_rad
            att = np.column_stack([np.interp(t_s, att_t, np.unwrap(att_rad[:, j])) for j in range(3)])
            r = dcms_from_euler(att)
        else:
            assert self.r0_nb is not None
            r = np.repeat(self.r0_nb[None], t_s.shape[0], axis=0)
        return AttitudeTrack(r, self.source, self.note)


GPS_TILT = (
    "the accelerometer minus the GNSS acceleration (rotated with the gyro heading, not the compass-steered "
    "one of the autopilot)"
)


def _gps_pass(
    imu_t_s: F64,
    gyro_b_rad_s: F64,
    accel_b_m_s2: F64,
    q_nb: F64,
    bias: tuple[float, float, float],
    log_down: tuple[F64, F64],
    att: tuple[F64, F64],
    gps: tuple[F64, F64],
    mask: NDArray[np.bool_] | None,
) -> tuple[F64 | None, str]:
    """The tilt filter's pass toward the GNSS reference (:func:`.gps_tilt.gps_tilt_reference`) after the
    first pass ``q_nb`` (toward the log's tilt ``log_down`` = (t, (m, 3) down)), with the log's attitude
    ``att`` = (t, (m, 3) roll/pitch/yaw) and the GNSS ``gps`` = (t, (k, 3) NED velocity): the new quaternions
    and a clause for the note, or (None, why it is not used)."""
    r_gyro = aligned_gyro_rotation(imu_t_s, q_nb, att[0], att[1][:, 2], mask)
    log_yaw = np.interp(imu_t_s, att[0], np.unwrap(att[1][:, 2]))
    down = _interp_rows(imu_t_s, *log_down)
    got = gps_tilt_reference(imu_t_s, accel_b_m_s2, r_gyro, *gps, down, log_yaw, mask)
    if got.down_b is None:
        return None, f"not toward the GNSS velocity: {got.note}"
    q0 = q_nb[0]
    q, _ = _propagate((imu_t_s, gyro_b_rad_s), (imu_t_s, got.down_b), q0, TiltFilterParams(passes=1), bias)
    return q, f"{GPS_TILT} on {got.fresh:.0%} of the log ({got.note})"


def _stationary_source(gyro_b_rad_s: F64, att_rad: F64 | None) -> AttitudeSource | None:
    """The one rotation of a vehicle that does not rotate (tilt: the log's mean roll and pitch when it has an
    attitude), or None when the gyro shows rotation. Asked of a gyro at any rate: one logged too slowly to be
    integrated (below MIN_GYRO_HZ) still shows that nothing turns, and the fallback, the autopilot's yaw,
    follows its disturbed compass (measured: 24 deg of yaw on held-out bench logs with the gyro at 16.7 Hz,
    which the calibration's gate then took for rotation)."""
    dev = np.linalg.norm(gyro_b_rad_s - np.median(gyro_b_rad_s, axis=0), axis=1)
    if float(np.percentile(dev, 99)) < STATIONARY_RATE_RAD_S:
        if att_rad is not None:
            d = down_b_from_euler(att_rad[:, 0], att_rad[:, 1]).mean(axis=0)
            roll0 = math.atan2(float(d[1]), float(d[2]))
            pitch0 = -math.asin(float(np.clip(d[0] / np.linalg.norm(d), -1.0, 1.0)))
        else:
            roll0 = pitch0 = 0.0
        return AttitudeSource(
            "stationary",
            "the vehicle does not rotate (gyro within "
            f"{STATIONARY_RATE_RAD_S} rad/s of its median): the Earth field is constant in body axes, as "
            "in the paper's offline fit (eqs. (14a), (15)); the calibration is neither "
            "needed nor observable",
            r0_nb=dcm_from_euler(roll0, pitch0, 0.0),
        )
    return None


def _tilt_reference(imu_t_s: F64, accel_b_m_s2: F64, att_t_s: F64 | None,
                    att_rad: F64) -> tuple[F64, F64, F64, str, str]:  # fmt: skip
    """The down direction the gyro's tilt is pulled toward, its times, the initial attitude, the source's name
    and its words: the log's roll and pitch where there is an attitude (``att_t_s`` not None), else the
    accelerometer's gravity direction."""
    if att_t_s is not None:
        ref = down_b_from_euler(att_rad[:, 0], att_rad[:, 1])
        d0 = _interp_rows(imu_t_s[:1], att_t_s, ref)[0]
        roll0 = math.atan2(float(d0[1]), float(d0[2]))
        pitch0 = -math.asin(float(np.clip(d0[0] / np.linalg.norm(d0), -1.0, 1.0)))
        q0 = quat_from_dcm(dcm_from_euler(roll0, pitch0, float(att_rad[0, 2])))
        return att_t_s, ref, q0, "gyro+tilt(attitude)", "the log's roll and pitch"
    a = accel_b_m_s2
    ref = -a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-9)
    d = ref[0]
    roll0 = math.atan2(float(d[1]), float(d[2]))
    pitch0 = -math.asin(float(np.clip(d[0], -1.0, 1.0)))
    q0 = quat_from_dcm(dcm_from_euler(roll0, pitch0, 0.0))
    return imu_t_s, ref, q0, "gyro+tilt(accelerometer)", "the accelerometer's gravity direction"


def attitude_source(
    imu_t_s: F64,
    gyro_b_rad_s: F64,
    accel_b_m_s2: F64,
    att_t_s: F64,
    att_rad: F64,
    gps_t_s: F64 | None = None,
    gps_vel_ned_m_s: F64 | None = None,
    gps_mask: NDArray[np.bool_] | None = None,
    min_gyro_hz: float = MIN_GYRO_HZ,
) -> AttitudeSource:
    """Choose the rotation for the forward model and integrate the gyro when it is the source (module
    docstring); :meth:`AttitudeSource.at` takes it at a compass's times. GNSS velocity ``gps_t_s`` (k,),
    ``gps_vel_ned_m_s`` (k, 3) m/s, usable where ``gps_mask`` (n,) allows: :func:`_gps_pass`.
    ``min_gyro_hz``: the slowest gyro integrated (default MIN_GYRO_HZ; 0 for the slow gyro's integral that
    :mod:`magcomp.diagnosis.slow_gyro` puts to the compass)."""
    has_gyro = imu_t_s.shape[0] >= 10 and np.all(np.isfinite(gyro_b_rad_s))
    has_att = att_t_s.shape[0] >= 2
    slow_gyro = ""
    if has_gyro:
        # before the rate test: a gyro too slow to integrate still shows that nothing rotates
        stationary = _stationary_source(gyro_b_rad_s, att_rad if has_att else None)
        if stationary is not None:
            return stationary
        dt = float(np.median(np.diff(imu_t_s)))
        gyro_hz = 1.0 / dt if dt > 0 else 0.0
        if gyro_hz < min_gyro_hz and has_att:
            has_gyro = False
            slow_gyro = (
                f"the gyro is logged at {gyro_hz:.1f} Hz (< {min_gyro_hz:.0f} Hz: its integral misses "
                "rotation), so "
            )
    if has_gyro:
        att_times = att_t_s if has_att else None
        ref_t, ref, q0, src, tilt = _tilt_reference(imu_t_s, accel_b_m_s2, att_times, att_rad)
        q, bias = _propagate((imu_t_s, gyro_b_rad_s), (ref_t, ref), q0)
        gnss_note = ""
        if has_att and gps_t_s is not None and gps_vel_ned_m_s is not None and gps_t_s.shape[0]:
            args = (q, bias, (ref_t, ref), (att_t_s, att_rad), (gps_t_s, gps_vel_ned_m_s), gps_mask)
            q_gps, why = _gps_pass(imu_t_s, gyro_b_rad_s, accel_b_m_s2, *args)
            if q_gps is not None:
                q, src, tilt = q_gps, "gyro+tilt(gps)", f"{why}, else {tilt}"
                gnss_note = f"tilt pulled toward {why}"
            else:
                tilt, gnss_note = f"{tilt} ({why})", f"tilt from the log's roll and pitch, {why}"
        note = (
            "rotation from the gyro (eq. (18)) with tilt pulled toward "
            f"{tilt}; heading is gyro-only (no compass), its drift is a fitted nuisance term, "
            "because the autopilot's yaw is fused from the disturbed compass"
        )
        return AttitudeSource(src, note, imu_t_s=imu_t_s, q_nb=q, gnss_note=gnss_note)
    if has_att:
        return AttitudeSource(
            "autopilot",
            (slow_gyro or "no gyro in the log: ")
            + "rotation from the autopilot's attitude (estimated on board at the full IMU rate), whose "
            "yaw is fused from a compass: if that is this compass, the heading-axis part of its bias is "
            "partly hidden from this residual",
            att_t_s=att_t_s,
            att_rad=att_rad,
        )
    return AttitudeSource(
        "none",
        "no gyro and no attitude: the vehicle is assumed not to rotate",
        r0_nb=dcm_from_quat(np.array([1.0, 0.0, 0.0, 0.0])),
    )


def with_yaw_reference(r_nb: F64, yaw_ref_rad: F64) -> F64:
    """``r_nb`` (n, 3, 3) with its yaw replaced by ``yaw_ref_rad`` (n,), roll and pitch kept."""
    e = euler_from_dcms(r_nb)
    e[:, 2] = yaw_ref_rad
    return dcms_from_euler(e)
