"""Stage 3, calibrate: the calibration of a compass, eqs. (1)-(3), applied as eq. (2) ``u = L v - d``.

Two ways to a calibration, the first that applies wins:

* a hand rotation with the motors off (the paper's DPI, eq. (3)): :class:`HandCalibration` collects
  (down vector, raw field) pairs at zero throttle, adopts the first linear fit the DPI module accepts and
  refits while the vehicle is turned; when the motors start it makes one final, refined fit in a worker
  thread, adopted exactly REFINE_ADOPT_AFTER samples later (so a live run and a replay adopt it at the
  same sample). The theta of eq. (11) then comes from the observer (:mod:`magcomp.service.theta`).
* in flight, jointly with theta (:mod:`magcomp.service.inflight_stage`, departure from the paper: no hand
  rotation needed); :class:`CalibrateStage` picks its rotation source and hands it each sample.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from concurrent.futures import Executor, Future
from dataclasses import dataclass
from typing import Any, Generic, NamedTuple, Protocol, TypeVar

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.config import Config
from magcomp.adapters.state_store import CompassState
from magcomp.core.autopilot_params import (
    calibrated_by_autopilot,
    external_compass,
    relative_rotation_source,
    yaw_reference,
)
from magcomp.core.dpi import field_error_dilution
from magcomp.core.inflight import InflightMode, InflightOutput
from magcomp.core.types import FLAG_CALIBRATED, FLAG_THETA_CONVERGED, STANDARD_GRAVITY_M_S2
from magcomp.service import estimators as est_core
from magcomp.service.align import CompassClock, ThrottleTrack
from magcomp.service.attitude import AttitudeStage
from magcomp.service.inflight_stage import InflightStage
from magcomp.service.record import Float3, MagRecord

log = logging.getLogger("magcomp.pipeline")

F64 = NDArray[np.float64]

#: at most this many (evenly strided) pairs go into the final (refined) DPI fit / an interim one
FIT_MAX_ROWS = 3000
INTERIM_FIT_MAX_ROWS = 1000
#: the refined calibration is adopted this many magnetometer samples after the motors start
REFINE_ADOPT_AFTER = 50
#: a hand rotation cut short (fewer pairs than ``[calibration] min_samples`` when the motors start or the
#: autopilot reboots) is still fitted when its pairs determine the calibration at least as well as one
#: sample is measured: :func:`magcomp.core.dpi.field_error_dilution` <= 1. Measured: a whole hand rotation
#: (833 pairs) 0.22; the hostile corpus's case 10 (492 pairs left by three damaged blocks) 0.40-0.41; the
#: two parts of a rotation split by a reboot at 13 s (tests/integration/test_fault_clock.py) 2.5 (300 pairs
#: before it: theta 15 mgauss off once fitted) and 3.5 (197 after it: 93 mgauss off)
MAX_SHORT_ROTATION_DILUTION = 1.0
#: attitude rows of the in-flight calibration are left out beyond this tilt (acrobatics, a crash)
MAX_TILT_RAD = math.radians(60.0)
COS_MAX_TILT = math.cos(MAX_TILT_RAD)
#: specific force this far from 1 g is an impact (the diagnosis's crash mask uses 2.5 g; a hover never
#: leaves 1 +- 0.5 g): the in-flight calibration takes no rows then
IMPACT_M_S2 = 1.5 * STANDARD_GRAVITY_M_S2


def apply_eq2(k: tuple[float, ...], vx: float, vy: float, vz: float) -> Float3:
    """Eq. (2), ``u = L v - d``, with L (row-major) and d as 12 floats (scalar twin of
    :func:`magcomp.core.dpi.apply_calibration`)."""
    return (
        k[0] * vx + k[1] * vy + k[2] * vz - k[9],
        k[3] * vx + k[4] * vy + k[5] * vz - k[10],
        k[6] * vx + k[7] * vy + k[8] * vz - k[11],
    )


class CalibrationCloud(NamedTuple):
    """The hand rotation's raw samples (n, 3) and the same after eq. (2), mgauss."""

    raw_mgauss: F64
    calibrated_mgauss: F64


#: attitude streams at least this slow (s between messages) get their samples matched to the field's time.
#: Measured (simulated ordinary flight, internal primary, worst of 3 seeds): at 1 Hz matching brings the
#: heading from 12.2 to 11.1 deg rms (oracle 10.9); at 10 and 50 Hz it changes nothing (1.59 -> 1.57,
#: 1.38 -> 1.42); on log171 (10 Hz DataFlash) it made compass 1 / 2 3.7 / 4.0 deg instead of 2.2 / 2.5 (an
#: 8 deg offset on the ground, cause not found). Staleness matters once it is comparable with the 0.3 s
#: pair baseline: applied from 4 Hz down. The threshold sits well between 10 Hz (0.1 s) and 4 Hz (0.25 s):
#: at 0.25 s the smoothed interval of a 4 Hz stream (ticks 0.24 / 0.26 s apart on a 50 Hz loop) fell on
#: either side of it, matching flipped on and off and 54 % of the samples took a stale or mislabelled
#: attitude (3.3 deg rms of yaw; theta 14.7-25.9 % -> 4.8-13.7 % at theta x6; docs/inflight.md, "4 Hz").
LATE_MATCH_MIN_INTERVAL_S = 0.15


#: the raw gyro's yaw goes with a field sample when the last IMU sample is at most this far from it (s):
#: the same RAW_IMU message on a telemetry link; within one 50 Hz IMU interval in a DataFlash log
GYRO_MATCH_S = 0.02
#: the raw gyro is integrated into a yaw only when it comes at least this often (s): a snapshot of the body
#: rate stands for its interval (10 Hz telemetry at most; 1-2 Hz would miss most of a turn)
GYRO_YAW_MAX_DT_S = 0.11


class RotationSource(NamedTuple):
    """Where the relative form's rotations come from: ``kind`` gyro | attitude | none, and the epoch of
    the gyro integral (a new epoch: no pair across it)."""

    kind: str
    epoch_s: float


NO_ROTATION = RotationSource("none", 0.0)


@dataclass(frozen=True)
class CalibrationSummary:
    source: str  # "learned", "stored", "identity"
    residual_rms_mgauss: float
    coverage: float
    n: int


@dataclass(frozen=True)
class PendingFit:
    """The refined fit running in the background, the sample count at which it is adopted, its pairs."""

    future: Future[est_core.LearnedCalibration | None]
    adopt_at: int
    n: int


def _starting_calibration(
    cfg: Config, stored: CompassState | None
) -> tuple[F64 | None, F64 | None, CalibrationSummary | None]:
    """L, d of eq. (2) and their summary to start from: the identity with ``[calibration] mode = none``, the
    stored ones unless the mode learns afresh, else none yet."""
    mode = cfg.calibration.mode
    if mode == "none":
        return np.eye(3), np.zeros(3), CalibrationSummary("identity", float("nan"), float("nan"), 0)
    if mode != "learn" and stored is not None and stored.calib_l is not None:
        info = stored.calib_info or {}
        summary = CalibrationSummary(
            "stored",
            float(info.get("residual_rms_mgauss", float("nan"))),
            float(info.get("coverage", float("nan"))),
            int(info.get("n", 0)),
        )
        return stored.calib_l, stored.calib_d, summary
    return None, None, None


class HandCalibration:
    """One compass's eq. (2) calibration: stored, identity, or learned from a motors-off hand rotation.
    ``on_adopt`` is called whenever a new calibration is adopted."""

    def __init__(
        self,
        cfg: Config,
        earth_ned: F64,
        stored: CompassState | None,
        fits: Executor,
        on_adopt: Callable[[], None],
    ) -> None:
        self.cfg = cfg
        self.earth_ned = earth_ned
        self._fits = fits
        self._on_adopt = on_adopt
        self.calib_l, self.calib_d, self.summary = _starting_calibration(cfg, stored)
        mode = cfg.calibration.mode
        # calibration data (down_b, raw field) at zero throttle
        n_max = cfg.calibration.max_samples
        self._down = np.empty((n_max, 3))
        self._field = np.empty((n_max, 3))
        self._n = 0
        self.n_fits = 0
        self._refine: PendingFit | None = None
        self._next_check = cfg.calibration.min_samples
        self._collecting = self.summary is None and mode in ("auto", "learn")
        self._coeffs: tuple[float, ...] = ()
        self._coeffs_of: tuple[object, object] = (None, None)

    def coeffs(self) -> tuple[float, ...] | None:
        """L (row-major) and d of eq. (2) as 12 floats for the per-sample path; None while uncalibrated."""
        cl, cd = self.calib_l, self.calib_d
        if cl is None or cd is None:
            return None
        if self._coeffs_of[0] is not cl or self._coeffs_of[1] is not cd:
            self._coeffs = (*np.ravel(cl).astype(float).tolist(), *np.ravel(cd).astype(float).tolist())
            self._coeffs_of = (cl, cd)
        return self._coeffs

    @property
    def calibrated(self) -> bool:
        return self.calib_l is not None

    @property
    def learned(self) -> bool:
        return self.summary is not None and self.summary.source == "learned"

    @property
    def n_collected(self) -> int:
        return self._n

    @property
    def collecting(self) -> bool:
        """True while (down, field) pairs are gathered: learning enabled, not frozen, room left."""
        return self._collecting and self._n < self._down.shape[0]

    def restart_collection(self) -> None:
        """Drop the calibration pairs collected so far (they belong to another boot)."""
        self._n = 0
        self._next_check = self.cfg.calibration.min_samples

    def fit_now(self) -> bool:
        """Fit (eq. (3)) on the pairs collected so far, the rotation having ended; True when the fit was
        adopted. Fewer than ``min_samples`` pairs only when they carry enough information
        (:data:`MAX_SHORT_ROTATION_DILUTION`): a count is no measure of a rotation cut short."""
        n = self._n
        if n == 0:
            return False
        if n < self.cfg.calibration.min_samples:
            dilution = field_error_dilution(self._down[:n], self._field[:n])
            if not dilution <= MAX_SHORT_ROTATION_DILUTION:
                return False
            log.info("hand rotation cut short at %d pairs: fitted (field error dilution %.2f)", n, dilution)
        return self._fit()

    def collect(self, down_b: Float3, field_raw: Float3, n_mag: int) -> bool:
        """Add one (down vector, raw field) pair at zero throttle and refit now and then (eq. (3)).

        The first (linear) fit that the DPI module accepts is adopted at once; later fits on more samples
        replace it while the vehicle is still being rotated by hand; when the motors start,
        :meth:`freeze` makes the final, refined fit. Returns True when a fit was adopted.
        """
        n = self._n
        self._down[n] = down_b
        self._field[n] = field_raw
        n += 1
        self._n = n
        if n == self._down.shape[0]:  # full: the final, refined fit follows
            self.freeze(n_mag)
            return False
        if n < self._next_check:
            return False
        self._next_check = n + self.cfg.calibration.check_every
        return self._fit()  # the linear eq. (3) solve while collecting: a few ms

    def freeze(self, n_mag: int) -> None:
        """The motors started after a calibration was learned (``n_mag``: samples seen so far): the
        hand-rotation phase is over. The final calibration is one refined fit on all the pairs collected;
        it runs on the ``fits`` executor (tens to hundreds of ms) and is adopted exactly
        ``REFINE_ADOPT_AFTER`` magnetometer samples later (waiting for it if need be)."""
        self._collecting = False
        if not self.learned and not (self._n < self.cfg.calibration.min_samples and self.fit_now()):
            return
        n = self._n
        stride = max(1, n // FIT_MAX_ROWS)
        down, field = self._down[:n:stride].copy(), self._field[:n:stride].copy()
        fut = self._fits.submit(est_core.calibrate, down, field, self.earth_ned, True)
        self._refine = PendingFit(fut, n_mag + REFINE_ADOPT_AFTER, n)

    @property
    def refine_pending(self) -> bool:
        """A refined calibration fit is running or waiting to be adopted."""
        return self._refine is not None

    def adopt_refined(self, n_mag: int, force: bool = False) -> bool:
        """Adopt the refined fit once its sample has come (``force``: now). True when adopted."""
        r = self._refine
        if r is None or (not force and n_mag < r.adopt_at):
            return False
        self._refine = None
        return self._adopt(r.future.result(), r.n)

    def _fit(self) -> bool:
        n = self._n
        stride = max(1, n // INTERIM_FIT_MAX_ROWS)  # bounds the time one fit takes on the live path
        res = est_core.calibrate(self._down[:n:stride], self._field[:n:stride], self.earth_ned, False)
        return self._adopt(res, n)

    def _adopt(self, res: est_core.LearnedCalibration | None, n: int) -> bool:
        if res is None:
            return False
        self.calib_l, self.calib_d = res.calib_l, res.calib_d
        self.summary = CalibrationSummary("learned", res.residual_rms_mgauss, res.coverage, n)
        self.n_fits += 1
        self._on_adopt()
        return True

    def cloud(self) -> CalibrationCloud:
        """The raw calibration samples and the same after eq. (2) (for the viewer)."""
        raw = self._field[: self._n]
        if self.calib_l is None or self.calib_d is None:
            return CalibrationCloud(raw, raw)
        return CalibrationCloud(raw, raw @ self.calib_l.T - self.calib_d)


class CompassHost(Protocol):
    """What the calibrate stage reads and writes of one compass (``service.compass.CompassCorrector``)."""

    mag_index: int
    calib: HandCalibration
    clock: CompassClock
    inflight: InflightStage | None
    rel_source: RotationSource
    stored_inflight: dict[str, Any] | None
    dirty: bool


H = TypeVar("H", bound=CompassHost)


class CalibrateStage(Generic[H]):
    """Applies each compass's calibration to its samples (eq. (2)) and keeps learning it: the hand
    rotation's pairs while the motors are off, the in-flight calibration's samples while they run.

    ``params``: the autopilot's parameters (a dict the pipeline keeps filling); ``earth_ned``: the Earth
    field (the pipeline replaces it at the first GNSS fix); ``save``: persists one compass's state now;
    ``text``: status lines."""

    def __init__(
        self,
        cfg: Config,
        attitude: AttitudeStage,
        throttle: ThrottleTrack,
        params: dict[str, float],
        earth_ned: F64,
        save: Callable[[H, float], None],
        text: Callable[[float, str, bool], None],
        outputs: bool = True,
    ) -> None:
        """``outputs`` False (a learn-only pass): the in-flight correction's field (eq. (2)) is not written
        into the records, which nothing there reads (the theta stage reads the field only of samples the
        in-flight calibration does not correct)."""
        self.cfg = cfg
        self._outputs = outputs
        self.attitude = attitude
        self.throttle = throttle
        self.params = params
        self.earth_ned = earth_ned
        self._save = save
        self._text = text
        self._at_rest = cfg.calibration.max_throttle_01
        self._inflight_on = cfg.observer.learn and cfg.inflight.enabled
        #: counts the parameters received (the pipeline increments it); each compass's stage was decided at
        #: the count in ``_decided``
        self.params_version = 0
        self._decided: dict[int, int] = {}
        #: per compass, what its parameters say at params_version: (version, external, rotation source)
        self._facts: dict[int, tuple[int, bool | None, str]] = {}

    def run(self, rec: MagRecord, c: H) -> None:
        """Fills ``rec.field_cal`` (eq. (2)), ``rec.calibrated`` and ``rec.inflight``."""
        cal = c.calib
        t = rec.t_s
        if cal.refine_pending and cal.adopt_refined(c.clock.n_mag):
            self.refined(c, t)
        if cal.collecting:
            self._collect(rec, c)
        k = cal.coeffs()
        vx, vy, vz = rec.raw
        if k is None and self._inflight_on and rec.have_throttle:
            out = self._inflight(rec, c)
            if out is not None:
                rec.flags |= FLAG_CALIBRATED | FLAG_THETA_CONVERGED if out.converged else FLAG_CALIBRATED
                rec.calibrated = True
                rec.inflight = out
                # eq. (2) with the in-flight L and d (its theta and bias come with it: service/theta.py)
                if self._outputs:
                    rec.field_cal = apply_eq2(out.coeffs, vx, vy, vz)
                return
            if c.inflight is not None:
                rec.shadow = c.inflight.candidate()
        if k is not None:
            rec.flags |= FLAG_CALIBRATED
            rec.calibrated = True
            rec.field_cal = apply_eq2(k, vx, vy, vz)
        else:
            rec.field_cal = rec.raw

    def _collect(self, rec: MagRecord, c: H) -> None:
        """The hand rotation: pairs at zero throttle; the motors starting ends it (eqs. (1)-(3))."""
        cal = c.calib
        if rec.have_throttle and rec.throttle_01 > self._at_rest:
            cal.freeze(c.clock.n_mag)
            return
        if rec.down is None or not rec.gyro_fresh or not cal.collect(rec.down, rec.raw, c.clock.n_mag):
            return
        assert cal.summary is not None
        rms = cal.summary.residual_rms_mgauss
        if cal.n_fits == 1:
            self._text(
                rec.t_s,
                f"compass {c.mag_index}: calibration learned from {cal.summary.n} samples "
                f"(eq. (3) residual {rms:.1f} mgauss); refining while the motors are off",
                False,
            )
        else:
            log.debug("compass %d: calibration refined from %d samples (residual %.1f mgauss)",
                      c.mag_index, cal.summary.n, rms)  # fmt: skip
        self._save(c, rec.t_s)

    def refined(self, c: H, t: float) -> None:
        """The refined fit was adopted at message time ``t``: saved and said."""
        s = c.calib.summary
        assert s is not None
        self._save(c, t)
        self._text(t, f"compass {c.mag_index}: motors on, calibration final ({s.n} samples, "
                      f"eq. (3) residual {s.residual_rms_mgauss:.1f} mgauss)", False)  # fmt: skip

    # ---------------------------------------------------------------------------------------- in flight

    def _reference(self, c: H) -> tuple[InflightMode, str, bool | None]:
        """(form, why, calibrated by the autopilot) of compass ``c`` from the parameters known now."""
        icfg = self.cfg.inflight
        mode: InflightMode
        if icfg.reference == "auto":
            mode, why = yaw_reference(self.params, c.mag_index)
        else:
            mode = "absolute" if icfg.reference == "absolute" else "relative"
            why = "set in the configuration ([inflight] reference)"
        return mode, why, calibrated_by_autopilot(self.params, c.mag_index)

    def _stage(self, c: H, t: float, again: str = "") -> InflightStage:
        """The in-flight calibration of compass ``c``, created at its first sample with the throttle known
        (``again``: re-created, and why)."""
        mode, why, cal = self._reference(c)
        norm = float(np.linalg.norm(self.earth_ned))
        st = InflightStage(c.mag_index, self.cfg.inflight, mode, why, cal, norm, c.stored_inflight)
        self._decided[c.mag_index] = self.params_version
        head = f"compass {c.mag_index}: {again}learning calibration and theta in flight"
        self._text(t, f"{head} ({mode} form: {why}); a motors-off hand rotation, if one comes, takes "
                      "precedence", False)  # fmt: skip
        return st

    def _redecide(self, c: H, t: float) -> None:
        """Parameters arrived since compass ``c``'s stage was created (a tlog's parameters often come
        seconds after the first samples, issue 23 item 5): when they change its form, why, or whether
        the autopilot calibrated it, the stage starts again with them (what it learned was learned against
        the wrong reference). Its rows before the parameters are lost: they come at the start, before
        the motors run, when it has hardly any."""
        self._decided[c.mag_index] = self.params_version
        old = c.inflight
        if old is None or self._reference(c) == (old.mode, old.why, old.calibrated_by_autopilot):
            return
        c.inflight = self._stage(c, t, "the autopilot's parameters arrived: re-")
        c.rel_source = NO_ROTATION


    def _inflight(self, rec: MagRecord, c: H) -> InflightOutput | None:
        """Feed the in-flight calibration of compass ``c`` and return its correction when it is usable."""
        t = rec.t_s
        if c.inflight is not None and self._decided.get(c.mag_index) != self.params_version:
            self._redecide(c, t)
        st = c.inflight
        if st is None:
            st = c.inflight = self._stage(c, t)
        if rec.reset:
            st.reset_pairs()
        thr = self.throttle.at(t)
        if thr is not None:
            r_abs, r_rel = self._rotations(c, st, t)
            if abs(self.attitude.accel_norm - STANDARD_GRAVITY_M_S2) > IMPACT_M_S2:
                r_abs = r_rel = None  # an impact (a crash, a hard landing): the field may be disturbed too
            # on a slow link the attitude and throttle of an instant arrive after its field, a whole interval
            # stale: the stage then matches them to the field's own time (docs/inflight.md, cause 5)
            r_t = thr_t = None
            att_dt = self.attitude.att_dt
            if att_dt is not None and att_dt >= LATE_MATCH_MIN_INTERVAL_S:
                gyro = st.mode == "relative" and c.rel_source.kind == "gyro"
                r_t = self.attitude.imu_t if gyro else self.attitude.att_t
                thr_t = self.throttle.t if self.throttle.t is not None and self.throttle.t < t else t
            # the raw gyro's yaw for the relative form, unless this compass is external: the autopilot's yaw
            # then follows a compass the currents hardly disturb (log171 compass 1 / 2 against compass 0:
            # 2.42 / 2.93 deg with the gyro's yaw for compass 0, 2.14 / 2.62 with the autopilot's)
            gyro_yaw = None
            if r_rel is not None and self._param_facts(c.mag_index)[1] is not True:
                gyro_yaw = self.attitude.gyro_yaw_at(t, GYRO_MATCH_S, GYRO_YAW_MAX_DT_S)
            st.feed(t, rec.raw, thr, self.throttle.motors, r_abs, self.earth_ned, r_rel,
                    r_t_s=r_t, throttle_t_s=thr_t, gyro_yaw=gyro_yaw)  # fmt: skip
            c.dirty = True
        return st.output(t, rec.raw, self.throttle.value, self.throttle.motors)

    def _param_facts(self, idx: int) -> tuple[int, bool | None, str]:
        """(params_version, external, rotation source) of compass ``idx``: what the parameters say, read
        again only when they change (per sample it was two dictionary reads and three calls)."""
        got = self._facts.get(idx)
        if got is None or got[0] != self.params_version:
            rot = self.cfg.inflight.rotation
            if rot == "auto":
                rot = relative_rotation_source(self.params, idx)[0]
            got = self._facts[idx] = (self.params_version, external_compass(self.params, idx), rot)
        return got

    def _rotations(self, c: H, st: InflightStage, t: float) -> tuple[F64 | None, F64 | None]:
        """(absolute attitude, relative-form rotation) for this sample, each None when it cannot be used."""
        att = self.attitude
        att_fresh = att.autopilot_fresh(t)
        r_abs = None
        motors_on_t = self.throttle.motors_on_t
        if st.mode == "absolute" and att_fresh and motors_on_t is not None:
            settled = t - motors_on_t >= self.cfg.inflight.absolute_settle_s
            level = abs(att.roll) < MAX_TILT_RAD and abs(att.pitch) < MAX_TILT_RAD
            if settled and level:
                r_abs = att.autopilot_dcm()
        if st.mode != "relative":
            return r_abs, None
        r_rel = None
        rot = self._param_facts(c.mag_index)[2]
        # the integrated gyro only while it is fast; the autopilot's attitude when it is too slow
        use_gyro = (rot == "gyro" and att.gyro_fast()) or not att_fresh
        if use_gyro and att.gyro_usable(t):
            r_rel = att.gyro_dcm()
            kind, epoch_s = "gyro", att.mahony_t0
        elif att_fresh:
            r_rel = att.autopilot_dcm()
            kind, epoch_s = "attitude", 0.0
        else:
            kind, epoch_s = NO_ROTATION
        old = c.rel_source  # (compared by its fields: a RotationSource is made only where it changes)
        if kind != old.kind or epoch_s != old.epoch_s:
            st.reset_pairs()
            c.rel_source = RotationSource(kind, epoch_s)
        if r_rel is not None and r_rel.item(2, 2) < COS_MAX_TILT:
            r_rel = None  # acrobatics or a crash: no pair across it
        return r_abs, r_rel
