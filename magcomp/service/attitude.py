"""Stage 2, attitude: the primary IMU through the attitude filter (Mahony, sec. II-A), the autopilot's
ATTITUDE, and what a magnetometer sample takes from them.

The gyro and attitude of a magnetometer sample are those of the latest IMU sample (in ArduPilot's RAW_IMU
both share one message, so they are exact). The DPI calibration takes the filter's down vector once it
has settled (MAHONY_SETTLE_S); the heading's roll and pitch come from the autopilot's ATTITUDE while it
streams (``[input] attitude = "auto"``), else from the filter. The gyro integrated alone (no accelerometer
or compass correction) is the relative rotation the in-flight calibration pairs samples with.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.config import Config
from magcomp.core.inflight.yawframe import GyroYaw
from magcomp.core.mahony import mahony_init
from magcomp.core.rotations import (
    dcm_from_euler,
    dcm_from_quat,
    euler_tilt_step,
    euler_yaw_rate_coefs,
    quat_step_body_rate,
    roll_pitch_from_down,
)
from magcomp.core.selfcheck import MAX_GYRO_DT_S
from magcomp.core.types import FLAG_INPUTS_STALE, FLAG_SATURATED, STANDARD_GRAVITY_M_S2, AttitudeSample
from magcomp.service.align import (
    PITCH_MAX_RAD,
    ROLL_MAX_RAD,
    TIME_OK,
    TIME_SKIP,
    YAW_MAX_RAD,
    Counts,
    check_time,
)
from magcomp.service.estimators import mahony_params
from magcomp.service.fastpath import FastMahony
from magcomp.service.record import LEVEL, Float3, MagRecord, Tilt

F64 = NDArray[np.float64]

#: seconds of IMU data the attitude filter gets before its down vector feeds the calibration
MAHONY_SETTLE_S = 2.0
#: the IMU is "fast" (its gyro can be integrated between magnetometer samples) below this interval
FAST_IMU_DT_S = 0.05
#: Input gate on the gyro (issue 12: a short gyro glitch must not move a converged theta). A body-rate
#: change between two IMU samples larger than GYRO_JUMP_FLOOR_RAD_S + MAX_ANGULAR_ACCEL_RAD_S2 * dt is not
#: physical for the vehicles we serve: the largest step in the 8 simulated scenarios is 0.1 rad/s per 20 ms,
#: and on the measured log171 (228 s of flight, 50 Hz) none exceeds 3 rad/s before the crash (all 28
#: larger steps are in the crash). A saturated (clipped) or jumping gyro makes the gyro and the attitude
#: untrusted until GYRO_HOLDOFF_S after the last bad sample: the observer gets nothing (its filters restart
#: after), headings carry FLAG_SATURATED, and the attitude filter restarts from the accelerometer.
GYRO_JUMP_FLOOR_RAD_S = 3.0
MAX_ANGULAR_ACCEL_RAD_S2 = 400.0
GYRO_HOLDOFF_S = 0.5
#: beyond any accelerometer's full scale (m/s^2, ~204 g: high-g accelerometers read +-200 g, flight IMUs
#: +-16 to +-32 g): a sample beyond it is a damaged record, not a measurement, and is dropped (counted
#: ``implausible``). One such value in the horizontal-acceleration low-pass (ACCEL_LP_S) stays in it for
#: minutes and overflowed the in-flight rows built from it (a DataFlash log with flipped bytes: 8e35 m/s^2,
#: every compass "corrected" with a NaN calibration)
ACCEL_MAX_M_S2 = 2000.0
#: time constant (s) of the low-pass on the horizontal kinematic acceleration that comes with the gyro's
#: yaw: a GPS-aided autopilot corrects its tilt with the acceleration that GPS velocity confirms, over about
#: a second (the simulator's complementary filter: 1 / kp_tilt = 1 s); it also keeps the motors' vibration
#: (tens of Hz) out
ACCEL_LP_S = 1.0
#: track that acceleration (for the tilt model: ``core.inflight.feed.FeedSwitches``)
TRACK_ACCEL_H = True

#: a named tuple made from its values without its constructor's argument handling (~0.2 us less a record;
#: the per-sample records below)
_new_tuple = tuple.__new__


class AttitudeView(NamedTuple):
    """What the magnetometer path needs of the attitude (derived once per IMU or ATTITUDE sample)."""

    down: Float3 | None  # the settled down vector in body axes, None while not settled
    tilt: Tilt


class AttitudeStage:
    """The attitude state shared by every compass of one vehicle."""

    def __init__(self, cfg: Config, counts: Counts) -> None:
        self.counts = counts
        self._mahony_p = mahony_params(cfg)
        self._stale_s = cfg.input.stale_s
        self._reset_s = cfg.input.time_reset_s
        self._gyro_sat = cfg.input.gyro_saturation_rad_s
        self._dt_max = cfg.observer.dt_max_s
        self._use_mahony = cfg.input.attitude in ("mahony", "auto")
        # auto: the heading's roll and pitch from the autopilot's ATTITUDE while it streams (its estimator
        # compensates flight accelerations with GPS; a gyro+accelerometer filter tilts by several degrees in
        # accelerated flight, and with a 60-70 deg inclination each degree of tilt is 2-3 deg of heading);
        # the DPI down vector always from the own Mahony filter (sec. II-A)
        self._auto = cfg.input.attitude == "auto"
        self.mahony: FastMahony | None = None
        self.mahony_t0 = 0.0
        self.imu_t: float | None = None
        self.imu_dt: float | None = None
        #: bias-corrected body rate of the latest IMU sample, rad/s
        self.gyro: Float3 = (0.0, 0.0, 0.0)
        self.gyro_raw: Float3 = (0.0, 0.0, 0.0)
        # the gyro gate (GYRO_HOLDOFF_S): raw rate and time of the previous IMU sample, end of the bad spell
        self._gyro_raw: Float3 | None = None
        self._gyro_raw_t = -math.inf
        self.gyro_bad_until = -math.inf
        self.restart = False  # the next IMU sample restarts the filter (after a gyro gate or a reboot)
        self.accel_norm = STANDARD_GRAVITY_M_S2
        # the bias-corrected gyro integrated alone: the rotation between two magnetometer samples for the
        # relative form, free of anything a compass disturbs
        self.qg: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
        # the autopilot's ATTITUDE
        self.att_t: float | None = None
        self.att_dt: float | None = None  # its usual interval (s)
        self.roll = 0.0
        self.pitch = 0.0
        self.yaw = 0.0
        self._view: AttitudeView | None = None
        # the raw gyro's yaw (Euler yaw rate with the autopilot's roll and pitch, trapezoid, no bias removed):
        # a heading no compass steers, for the in-flight calibration (gyro_yaw_at); its chain restarts with
        # the filter (a new epoch)
        self.gyro_yaw_rad = 0.0
        self.gyro_yaw_epoch = 0
        #: the same integral of the raw gyro with the heading's roll and pitch: what the heading filter
        #: propagates with and the self-check's reference (service/heading.py), same epochs. Not the attitude
        #: filter's bias-corrected gyro: in flight a multicopter's accelerometer measures thrust and drag, not
        #: gravity, and the filter's bias adaptation learns that as a gyro bias (about z: log171 1.1 deg/s,
        #: peterbarker 1.BIN 1.6, where the raw gyro's yaw drifts from the autopilot's by 0.07-0.11 and
        #: 0.1-0.3 deg/s); the autopilot logs its gyro with its own calibration applied
        self.heading_yaw_rad = 0.0
        self._heading_rate_prev = 0.0
        #: (sin roll, cos roll) / cos pitch of the latest attitude view (the autopilot's or the filter's, as
        #: the headings use it): the coefficients of that integral
        self._heading_coef = (0.0, 1.0)
        self._yaw_coef = (0.0, 1.0)  # (sin roll, cos roll) / cos pitch of the latest ATTITUDE
        self._ap_trig: Tilt | None = LEVEL  # cos / sin of its roll and pitch (None: not yet taken)
        #: the latest ATTITUDE's roll and pitch carried to the current IMU sample by the gyro: the heading
        #: integral's coefficients between two ATTITUDE messages (held, they lag a fast roll by up to one
        #: interval: luk8426 log_66 lost 33 deg of yaw in a 0.5 s, 300 deg/s manoeuvre at 27 Hz ATTITUDE)
        self._ap_tilt: tuple[float, float] | None = None
        self._ap_tilt_t = 0.0  # the time it is at
        self._yaw_rate_prev = 0.0
        #: the horizontal kinematic acceleration in the gyro chain's yaw frame (north, east; m/s^2),
        #: low-passed (ACCEL_LP_S): what a GPS-aided autopilot subtracts from the specific force with its own
        #: yaw, so an error of that yaw tilts its attitude by yaw error x acceleration / g (docs/inflight.md)
        self.accel_h: tuple[float, float] = (0.0, 0.0)
        #: tracked only once someone asks for the gyro's yaw (gyro_yaw_at: the in-flight relative form), so a
        #: log without in-flight calibration (a hand rotation) does not pay for it
        self._accel_wanted = False
        #: the last DCMs built (autopilot_dcm, gyro_dcm) with what they were built from
        self._att_dcm: tuple[tuple[float, float, float], F64] | None = None
        self._gyro_dcm: tuple[tuple[float, float, float, float], F64] | None = None

    # ------------------------------------------------------------------------------------------ inputs

    def on_attitude(self, s: AttitudeSample) -> None:
        if not (math.isfinite(s.roll_rad) and math.isfinite(s.pitch_rad) and math.isfinite(s.t_s)):
            self.counts["non_finite"] += 1
            return
        if abs(s.roll_rad) > ROLL_MAX_RAD or abs(s.pitch_rad) > PITCH_MAX_RAD:
            # no Euler attitude has these angles: a damaged record (a flipped bit, a garbage message),
            # which tilt-compensated into every heading until the next one (up to 12 deg off, unflagged)
            self.counts["implausible"] += 1
            return
        if check_time(self.att_t, s.t_s, self._reset_s, self.counts, allow_equal=True) == TIME_SKIP:
            return
        if self.att_t is not None and 0.0 < s.t_s - self.att_t < 10.0:
            dt = s.t_s - self.att_t
            self.att_dt = dt if self.att_dt is None else self.att_dt + 0.05 * (dt - self.att_dt)
        self.att_t = s.t_s
        self.roll, self.pitch = s.roll_rad, s.pitch_rad
        self._yaw_coef = euler_yaw_rate_coefs(s.roll_rad, s.pitch_rad)
        self._ap_trig = None
        self._ap_tilt, self._ap_tilt_t = (s.roll_rad, s.pitch_rad), s.t_s
        if self._auto or not self._use_mahony:  # the view takes this roll and pitch (while it is fresh):
            self._heading_coef = self._yaw_coef  # the integral follows them now, not at the next view
        self.yaw = s.yaw_rad if math.isfinite(s.yaw_rad) and abs(s.yaw_rad) <= YAW_MAX_RAD else self.yaw
        self._view = None

    def on_imu(self, t: float, gx: float, gy: float, gz: float, ax: float, ay: float, az: float) -> bool:
        """A sample of the primary IMU: body rate (rad/s) and specific force (m/s^2). True when a bad gyro
        spell starts (the caller resets the observers' filters)."""
        self.counts["imu"] += 1
        # (the sum is finite only where every term is; a finite sum that overflows is tested term by term)
        if not math.isfinite(t + gx + gy + gz + ax + ay + az) and not all(
            map(math.isfinite, (t, gx, gy, gz, ax, ay, az))
        ):
            self.counts["non_finite"] += 1
            return False
        accel_norm = math.sqrt(ax * ax + ay * ay + az * az)
        if accel_norm > ACCEL_MAX_M_S2:  # no accelerometer reads this: a damaged record (e.g. a flipped
            self.counts["implausible"] += 1  # exponent bit in a DataFlash log), kept out of the low-pass
            return False
        self.accel_norm = accel_norm
        lim = self._gyro_sat
        saturated = abs(gx) >= lim or abs(gy) >= lim or abs(gz) >= lim
        raw, raw_t = self._gyro_raw, self._gyro_raw_t
        jump = False
        if not saturated:
            if raw is not None and t > raw_t:
                step = max(abs(gx - raw[0]), abs(gy - raw[1]), abs(gz - raw[2]))
                jump = step > GYRO_JUMP_FLOOR_RAD_S + MAX_ANGULAR_ACCEL_RAD_S2 * (t - raw_t)
            self._gyro_raw, self._gyro_raw_t = (gx, gy, gz), t
        if saturated or jump:
            self.counts["saturated" if saturated else "gyro_jumps"] += 1
            return self._gate_gyro(t)
        if t <= self.gyro_bad_until:
            self.counts["gyro_gated"] += 1
            return False
        prev_t = self.imu_t
        verdict = check_time(prev_t, t, self._reset_s, self.counts)
        if verdict == TIME_SKIP:
            return False
        m = self.mahony
        self._view = None
        self.imu_dt = None if prev_t is None or verdict != TIME_OK else t - prev_t
        restart, self.restart = self.restart, False
        if (
            m is not None
            and prev_t is not None
            and verdict == TIME_OK
            and not restart
            and t - prev_t <= self._dt_max
        ):
            self.imu_t = t
            m.update(gx, gy, gz, ax, ay, az, t - prev_t)
            att_t = self.att_t  # the view's roll and pitch are the filter's: the integral follows them now
            b = m.b
            self.gyro = (gx - b[0], gy - b[1], gz - b[2])
            self.gyro_raw = (gx, gy, gz)
            if self._use_mahony and (not self._auto or att_t is None or abs(t - att_t) > self._stale_s):
                self._heading_coef = euler_yaw_rate_coefs(*roll_pitch_from_down(m.down_b()))
            elif self._ap_tilt is not None:  # the autopilot's roll and pitch, carried to this sample
                if t > self._ap_tilt_t:
                    self._ap_tilt = euler_tilt_step(*self._ap_tilt, gx, gy, gz, t - self._ap_tilt_t)
                    self._ap_tilt_t = t
                self._heading_coef = euler_yaw_rate_coefs(*self._ap_tilt)
            self.qg = quat_step_body_rate(self.qg, self.gyro, t - prev_t)
            rate = self._yaw_coef[0] * gy + self._yaw_coef[1] * gz
            self.gyro_yaw_rad += 0.5 * (rate + self._yaw_rate_prev) * (t - prev_t)
            self._yaw_rate_prev = rate
            rate_c = self._heading_coef[0] * gy + self._heading_coef[1] * gz
            self.heading_yaw_rad += 0.5 * (rate_c + self._heading_rate_prev) * (t - prev_t)
            self._heading_rate_prev = rate_c
            if self._accel_wanted:
                self._track_accel(ax, ay, az, t - prev_t)
            return False
        self._restart_filter(t, gx, gy, gz, ax, ay, az)
        return False

    def _track_accel(self, ax: float, ay: float, az: float, dt: float) -> None:
        """Low-pass the horizontal kinematic acceleration ``R f + g e_3`` (FRD / NED; R from the autopilot's
        roll and pitch and the gyro chain's yaw) with ACCEL_LP_S."""
        cr, sr, cp, sp = self._autopilot_tilt()
        sy, cy = math.sin(self.gyro_yaw_rad), math.cos(self.gyro_yaw_rad)
        # the first two rows of Rz(yaw) Ry(pitch) Rx(roll) applied to f (gravity has no horizontal part)
        fx = cp * ax + sp * sr * ay + sp * cr * az
        fy = cr * ay - sr * az
        an, ae = cy * fx - sy * fy, sy * fx + cy * fy
        k = min(1.0, dt / ACCEL_LP_S)
        n0, e0 = self.accel_h
        self.accel_h = (n0 + k * (an - n0), e0 + k * (ae - e0))

    def _restart_filter(
        self, t: float, gx: float, gy: float, gz: float, ax: float, ay: float, az: float
    ) -> None:
        """First sample, a gap or a clock reset: the rotation since the last sample is unknown, so the tilt
        restarts from the accelerometer (gyro bias kept) and must settle again before the calibration
        uses it."""
        try:
            fresh = mahony_init(np.array((ax, ay, az)))
        except ValueError:
            self.counts["non_finite"] += 1
            return
        m = self.mahony
        bias = np.array(m.b) if m is not None else fresh.gyro_bias_b_rad_s
        self.mahony = FastMahony(self._mahony_p, fresh.q_nb, bias)
        self.mahony_t0 = t
        self.qg = (1.0, 0.0, 0.0, 0.0)  # the gyro integral restarts (a new epoch: no pair across it)
        self.gyro_yaw_epoch += 1
        self._yaw_rate_prev = self._yaw_coef[0] * gy + self._yaw_coef[1] * gz
        self.imu_t = t
        self.gyro = (gx - float(bias[0]), gy - float(bias[1]), gz - float(bias[2]))
        self.gyro_raw = (gx, gy, gz)
        self._heading_rate_prev = self._heading_coef[0] * gy + self._heading_coef[1] * gz

    def _gate_gyro(self, t: float) -> bool:
        """A saturated or jumping gyro sample at ``t``: gyro and attitude untrusted until GYRO_HOLDOFF_S
        after it. True at the start of a bad spell."""
        starts = t > self.gyro_bad_until or not math.isfinite(self.gyro_bad_until)
        self.gyro_bad_until = max(self.gyro_bad_until, t + GYRO_HOLDOFF_S)
        self.restart = True  # the rotation during the spell is unknown: the tilt restarts
        self._view = None
        return starts

    def on_reboot(self) -> None:
        self.restart = True
        self._view = None

    # ------------------------------------------------------------------------------------------ outputs

    def view(self) -> AttitudeView:
        """The DPI reference down vector (None when no settled estimate) and cos/sin of roll and pitch;
        derived once per IMU (or ATTITUDE) sample, shared by the compasses."""
        a = self._view
        if a is not None:
            return a
        down: Float3 | None = None
        # the autopilot's roll and pitch (taken once per ATTITUDE), unless the filter's are used
        tilt: Tilt | None = None
        coef = self._yaw_coef
        if self.mahony is not None and self._use_mahony:
            d = self.mahony.down_b()  # the down vector in body axes (sec. II-A); roll/pitch of ZYX Euler
            att_t, imu_t = self.att_t, self.imu_t
            fresh = att_t is not None and imu_t is not None and abs(imu_t - att_t) <= self._stale_s
            if not (self._auto and fresh):
                roll, pitch = roll_pitch_from_down(d)
                tilt = _new_tuple(Tilt, (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)))
                coef = euler_yaw_rate_coefs(roll, pitch)
            if self.imu_t is not None and self.imu_t - self.mahony_t0 >= MAHONY_SETTLE_S:
                down = d
        a = _new_tuple(AttitudeView, (down, self._autopilot_tilt() if tilt is None else tilt))
        self._view = a
        self._heading_coef = coef
        return a

    def _autopilot_tilt(self) -> Tilt:
        """cos / sin of the latest ATTITUDE's roll and pitch (computed once per ATTITUDE)."""
        got = self._ap_trig
        if got is None:
            roll, pitch = self.roll, self.pitch
            got = self._ap_trig = Tilt(math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch))
        return got

    def stamp(self, rec: MagRecord) -> None:
        """The attitude and gyro of a magnetometer sample: those of the latest IMU sample."""
        view = self._view
        rec.down, rec.tilt = view if view is not None else self.view()
        t = rec.t_s
        rec.gyro = self.gyro
        rec.gyro_raw = self.gyro_raw
        rec.gyro_yaw, rec.gyro_epoch = self.heading_yaw_rad, float(self.gyro_yaw_epoch)
        rec.ap_yaw = self.yaw if self.att_t is not None else math.nan
        imu_dt, imu_t = self.imu_dt, self.imu_t
        rec.imu_fast = imu_dt is not None and imu_dt <= MAX_GYRO_DT_S
        rec.imu_dt = math.nan if imu_dt is None else imu_dt
        fresh = imu_t is not None and abs(t - imu_t) <= self._stale_s
        if t <= self.gyro_bad_until:  # the gyro gate: no observer, no calibration
            fresh = False
            rec.flags |= FLAG_SATURATED
        elif self.restart or not fresh:  # (restart: after a gyro gate or a reboot)
            fresh = False
            rec.flags |= FLAG_INPUTS_STALE
        rec.gyro_fresh = fresh

    # ------------------------------------------------------------- rotations for the in-flight calibration

    def autopilot_fresh(self, t: float) -> bool:
        """The autopilot's attitude is fresh at ``t``: within stale_s, or within one and a half of its own
        interval (1-2 Hz telemetry)."""
        att_dt = self.att_dt
        stale_s = self._stale_s if att_dt is None else max(self._stale_s, 1.5 * att_dt)
        return self.att_t is not None and abs(t - self.att_t) <= stale_s

    def autopilot_dcm(self) -> F64:
        """R_nb of the autopilot's ATTITUDE (read-only: built once per attitude, shared by the compasses and
        the two forms: ATTITUDE comes at half the magnetometer's rate or slower)."""
        key = (self.roll, self.pitch, self.yaw)
        cached = self._att_dcm
        if cached is None or cached[0] != key:
            r = dcm_from_euler(*key)
            r.flags.writeable = False
            cached = self._att_dcm = (key, r)
        return cached[1]

    def gyro_usable(self, t: float) -> bool:
        """The integrated gyro is a usable rotation source at ``t``: fast, fresh and running."""
        fast = self.imu_dt is not None and self.imu_dt <= FAST_IMU_DT_S
        fresh = self.imu_t is not None and abs(t - self.imu_t) <= self._stale_s
        return fast and fresh and self.mahony is not None

    def gyro_yaw_at(self, t: float, tol_s: float, max_dt_s: float) -> GyroYaw | None:
        """(epoch, raw gyro yaw in rad) when the last IMU sample is within ``tol_s`` of ``t``, the IMU comes
        at least every ``max_dt_s`` and the gyro is not gated, else None."""
        self._accel_wanted = TRACK_ACCEL_H
        imu_t, imu_dt, att_t = self.imu_t, self.imu_dt, self.att_t
        if imu_t is None or abs(t - imu_t) > tol_s or t <= self.gyro_bad_until or self.restart:
            return None
        if imu_dt is None or imu_dt > max_dt_s:
            return None
        lead = 0.0
        if att_t is not None and abs(att_t - imu_t) <= 0.5:
            lead = self._yaw_rate_prev * (att_t - imu_t)
        return _new_tuple(GyroYaw, (self.gyro_yaw_epoch, self.gyro_yaw_rad, self.accel_h, lead))

    def gyro_fast(self) -> bool:
        return self.imu_dt is not None and self.imu_dt <= FAST_IMU_DT_S

    def gyro_dcm(self) -> F64:
        """R of the gyro integrated alone since :attr:`mahony_t0` (read-only: built once per IMU sample)."""
        q = self.qg
        cached = self._gyro_dcm
        if cached is None or cached[0] is not q:
            r = dcm_from_quat(q)
            r.flags.writeable = False
            cached = self._gyro_dcm = (q, r)
        return cached[1]
