"""One pipeline for live links and replays: typed samples in, one :class:`HeadingEstimate` per magnetometer
sample out.

    samples (message time) -> alignment -> attitude (Mahony, sec. II-A) -> calibration (DPI, eqs. (1)-(3))
    -> 5 Hz low-pass (sec. II-D) -> theta observer (eq. (20)) -> bias (eq. (11)) -> heading (eq. (24))

:class:`Pipeline` is the imperative shell around the pure core states (PX4's module/lib split): it keeps
the current states and the last timestamps, computes every ``dt`` from the messages' own timestamps (never
arrival time), checks it, and decides resets. Live runs and replays call the same :meth:`Pipeline.process`
with the same sample order, so a replay at any speed gives the live answer by construction.

Alignment, on message time. The gyro and attitude of a magnetometer sample are those of the latest IMU
sample (in ArduPilot's RAW_IMU both share one message, so they are exact). The throttle differs by use:

* the published heading uses the latest throttle received (causal, no added latency; after a throttle
  step, up to one throttle period late: SERVO_OUTPUT_RAW comes at 25 Hz);
* the observer gets the throttle *interpolated at the sample's own time*: each sample waits in a short
  per-compass queue until the throttle after it has arrived (or ``stale_s`` passed). A sample between
  two throttle messages that straddle a jump is left out and the observer re-anchors after it (the
  instant of the step is unknown). The result does not depend on the order in which a link delivers
  the messages of one instant; with the latest throttle instead, theta came out 8-15 % off on
  simulated flights (docs/benchmarks.md).

The 5 Hz low-pass of sec. II-D goes where the observer module says: on the regression (``y`` and
``Phi`` alike) in the default form, so it adds no bias. Departure from the paper: the published heading
passes a gyro-aided complementary filter (:class:`~magcomp.service.estimators.HeadingFilter`).

Bad input never stops the pipeline: non-finite or saturated samples, time running backwards, gaps and
clock resets are skipped or absorbed and counted in :attr:`Pipeline.counts`.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.config import Config
from magcomp.adapters.mavlink_source import WireImuSample, WireMagSample
from magcomp.adapters.state_store import CompassState, StateStore
from magcomp.core.inflight import calibrated_by_autopilot, relative_rotation_source, yaw_reference
from magcomp.core.mahony import MahonyParams, mahony_init
from magcomp.core.rotations import dcm_from_euler, dcm_from_quat, quat_step_body_rate
from magcomp.core.types import (
    FLAG_CALIBRATED,
    FLAG_INPUTS_STALE,
    FLAG_NO_THROTTLE,
    FLAG_OBSERVER_RESET,
    FLAG_SATURATED,
    FLAG_THETA_CONVERGED,
    FLAG_Z_UNOBSERVABLE,
    STANDARD_GRAVITY_M_S2,
    AttitudeSample,
    ClockResetSample,
    HeadingEstimate,
    HeartbeatSample,
    ImuSample,
    MagSample,
    ParamSample,
    PositionSample,
    PowerSample,
    Sample,
    TemperatureSample,
    ThrottleSample,
    TimeSample,
)
from magcomp.geomag import earth_field_ned_mgauss
from magcomp.service import estimators as est_core
from magcomp.service.console import json_safe
from magcomp.service.fastpath import FastMahony
from magcomp.service.inflight_stage import InflightOutput, InflightStage

log = logging.getLogger("magcomp.pipeline")

F64 = NDArray[np.float64]

#: seconds of IMU data the attitude filter gets before its down vector feeds the calibration
MAHONY_SETTLE_S = 2.0
#: a magnetometer interval above this many times the compass's usual interval (and above [observer]
#: dt_max_s) is a gap: counted, flagged and the observer reset. A 1 Hz telemetry magnetometer is not a
#: gap on every sample.
GAP_FACTOR = 5.0
#: the IMU is "fast" (its gyro can be integrated between magnetometer samples) below this interval
FAST_IMU_DT_S = 0.05
#: attitude rows of the in-flight calibration are left out beyond this tilt (acrobatics, a crash)
MAX_TILT_RAD = math.radians(60.0)
COS_MAX_TILT = math.cos(MAX_TILT_RAD)
#: specific force this far from 1 g is an impact (the diagnosis's crash mask uses 2.5 g; a hover never
#: leaves 1 +- 0.5 g): the in-flight calibration takes no rows then
IMPACT_M_S2 = 1.5 * STANDARD_GRAVITY_M_S2
#: message-time seconds without any throttle sample before the "no throttle" warning
NO_THROTTLE_WARN_S = 2.0
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
#: Input gate on the magnetometer: a change of any axis between two samples of one compass larger than
#: this is not a field the vehicle can see (rotation at the gyro's full range and a full throttle step
#: included): the largest step in the 8 simulated scenarios is 88 mgauss, on log171 before its crash
#: 230 mgauss. Such a sample (a corrupt value) and the one after it are dropped (counts["mag_jumps"]).
MAG_JUMP_MGAUSS = 500.0
#: at most this many (evenly strided) pairs go into the final (refined) DPI fit / an interim one
FIT_MAX_ROWS = 3000
INTERIM_FIT_MAX_ROWS = 1000
#: the refined calibration is adopted this many magnetometer samples after the motors start
REFINE_ADOPT_AFTER = 50

_EXECUTOR: ThreadPoolExecutor | None = None

#: what the magnetometer path needs of the attitude: the settled down vector (or None), cos/sin of roll,
#: cos/sin of pitch
_Attitude = tuple[tuple[float, float, float] | None, float, float, float, float]


_STATE_WRITER: ThreadPoolExecutor | None = None


def _state_writer() -> ThreadPoolExecutor:
    """One background thread for state writes (in submission order)."""
    global _STATE_WRITER
    if _STATE_WRITER is None:
        _STATE_WRITER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="magcomp-state")
    return _STATE_WRITER


def _worker() -> ThreadPoolExecutor:
    """One background thread for the refined calibration fits (created on first use)."""
    global _EXECUTOR
    if _EXECUTOR is None:
        _EXECUTOR = ThreadPoolExecutor(max_workers=1, thread_name_prefix="magcomp-calibration")
    return _EXECUTOR


@dataclass(frozen=True)
class CalibrationSummary:
    source: str  # "learned", "stored", "identity"
    residual_rms_mgauss: float
    coverage: float
    n: int


class CompassCorrector:
    """The online corrector of one compass: calibration, low-pass, observer, heading (mutable shell)."""

    def __init__(
        self,
        mag_index: int,
        cfg: Config,
        earth_field_ned_mgauss: F64,
        stored: CompassState | None,
    ) -> None:
        self.mag_index = mag_index
        self.cfg = cfg
        self.earth_ned = earth_field_ned_mgauss
        self.calib_l: F64 | None = None
        self.calib_d: F64 | None = None
        self.calibration: CalibrationSummary | None = None
        mode = cfg.calibration.mode
        if mode == "none":
            self.calib_l, self.calib_d = np.eye(3), np.zeros(3)
            self.calibration = CalibrationSummary("identity", float("nan"), float("nan"), 0)
        elif mode != "learn" and stored is not None and stored.calib_l is not None:
            self.calib_l, self.calib_d = stored.calib_l, stored.calib_d
            info = stored.calib_info or {}
            self.calibration = CalibrationSummary(
                "stored",
                float(info.get("residual_rms_mgauss", float("nan"))),
                float(info.get("coverage", float("nan"))),
                int(info.get("n", 0)),
            )
        # an in-flight calibration from an earlier run (or an earlier pass over the same log)
        self.stored_inflight = stored.inflight if (stored is not None and mode != "learn") else None
        theta0 = stored.theta_mgauss if (stored is not None and mode != "learn") else np.zeros(3)
        self.theta_est = est_core.ThetaEstimator(cfg, theta0)
        # observer inputs waiting for the throttle at their time: (t_s, gyro, calibrated field);
        # (t_s, None, None) is a reset marker
        self.queue: deque[tuple[float, Any, Any]] = deque()
        self.obs_last_t: float | None = None
        self.last_info: est_core.ThetaStepInfo | None = None
        self.hdg_filter = est_core.HeadingFilter(cfg.output.heading_tau_s)
        self.hdg_raw_filter = est_core.HeadingFilter(cfg.output.heading_tau_s)
        # calibration data (down_b, raw field) at zero throttle
        n_max = cfg.calibration.max_samples
        self._cal_down = np.empty((n_max, 3))
        self._cal_field = np.empty((n_max, 3))
        self._cal_n = 0
        self.n_cal_fits = 0
        self.n_mag = 0  # magnetometer samples seen (the clock of the refined-fit adoption)
        self._refine: tuple[Future[est_core.LearnedCalibration | None], int, int] | None = None
        self._cal_next_check = cfg.calibration.min_samples
        self._collecting = self.calibration is None and mode in ("auto", "learn")
        self.last_t: float | None = None
        self.prev_raw: tuple[float, float, float] | None = None  # the previous raw field (the jump gate)
        self.n_out = 0
        self.out_t = -math.inf
        self.last_saved_t: float | None = None
        self.dirty = False
        self._coeffs: tuple[float, ...] = ()
        self._coeffs_of: tuple[object, object] = (None, None)
        # in-flight calibration jointly with theta (no hand rotation): created at the first sample
        self.inflight: InflightStage | None = None
        self.dt_nominal: float | None = None  # usual magnetometer interval (s)
        self.time_s = {"corrected": 0.0, "uncorrected": 0.0}
        self.rel_source: tuple[str, float] = ("none", 0.0)

    def calib_coeffs(self) -> tuple[float, ...] | None:
        """L (row-major) and d of eq. (2) as 12 floats for the per-sample path; None while uncalibrated."""
        cl, cd = self.calib_l, self.calib_d
        if cl is None or cd is None:
            return None
        if self._coeffs_of[0] is not cl or self._coeffs_of[1] is not cd:
            self._coeffs = (*np.ravel(cl).astype(float).tolist(), *np.ravel(cd).astype(float).tolist())
            self._coeffs_of = (cl, cd)
        return self._coeffs

    def queue_reset(self) -> None:
        """Reset the observer's filters (theta kept) once the samples queued before now are through."""
        self.queue.append((self.last_t if self.last_t is not None else 0.0, None, None))

    @property
    def calibrated(self) -> bool:
        return self.calib_l is not None

    @property
    def n_collected(self) -> int:
        return self._cal_n

    def fit_now(self) -> bool:
        """Fit (eq. (3)) on the pairs collected so far; True when the fit was adopted."""
        return self._cal_n > 0 and self._fit(refine=False)

    def restart_collection(self) -> None:
        """Drop the calibration pairs collected so far (they belong to another boot)."""
        self._cal_n = 0
        self._cal_next_check = self.cfg.calibration.min_samples

    @property
    def collecting(self) -> bool:
        """True while (down, field) pairs are gathered: learning enabled, not frozen, room left."""
        return self._collecting and self._cal_n < self._cal_down.shape[0]

    def freeze_calibration(self) -> None:
        """The motors started after a calibration was learned: the hand-rotation phase is over. The
        final calibration is one refined fit on all the pairs collected; it runs in a worker thread
        (tens to hundreds of ms) and is adopted exactly ``REFINE_ADOPT_AFTER`` magnetometer samples
        later (waiting for it if need be), so a live run and a replay adopt it at the same sample."""
        self._collecting = False
        if self.calibration is None or self.calibration.source != "learned":
            return
        n = self._cal_n
        stride = max(1, n // FIT_MAX_ROWS)
        down, field = self._cal_down[:n:stride].copy(), self._cal_field[:n:stride].copy()
        self._refine = (
            _worker().submit(est_core.calibrate, down, field, self.earth_ned, True),
            self.n_mag + REFINE_ADOPT_AFTER,
            n,
        )

    @property
    def refine_pending(self) -> bool:
        """A refined calibration fit is running or waiting to be adopted."""
        return self._refine is not None

    def adopt_refined(self, force: bool = False) -> bool:
        """Adopt the refined fit once its sample has come (``force``: now). True when adopted."""
        if self._refine is None or (not force and self.n_mag < self._refine[1]):
            return False
        future, _, n = self._refine
        self._refine = None
        return self._adopt(future.result(), n)

    def _fit(self, refine: bool) -> bool:
        n = self._cal_n
        stride = max(1, n // INTERIM_FIT_MAX_ROWS)  # bounds the time one fit takes on the live path
        res = est_core.calibrate(
            self._cal_down[:n:stride], self._cal_field[:n:stride], self.earth_ned, refine
        )
        return self._adopt(res, n)

    def _adopt(self, res: est_core.LearnedCalibration | None, n: int) -> bool:
        if res is None:
            return False
        self.calib_l, self.calib_d = res.calib_l, res.calib_d
        self.calibration = CalibrationSummary("learned", res.residual_rms_mgauss, res.coverage, n)
        self.n_cal_fits += 1
        self.queue_reset()
        self.dirty = True
        return True

    def collect_calibration(
        self, down_b: F64 | tuple[float, float, float], field_raw: F64 | tuple[float, float, float]
    ) -> bool:
        """Add one (down vector, raw field) pair at zero throttle and refit now and then (eq. (3)).

        The first (linear) fit that the DPI module accepts is adopted at once; later fits on more samples
        replace it while the vehicle is still being rotated by hand; when the motors start,
        :meth:`freeze_calibration` makes the final, refined fit. Returns True when a fit was adopted.
        """
        n = self._cal_n
        self._cal_down[n] = down_b
        self._cal_field[n] = field_raw
        n += 1
        self._cal_n = n
        if n == self._cal_down.shape[0]:  # full: the final, refined fit follows
            self.freeze_calibration()
            return False
        if n < self._cal_next_check:
            return False
        self._cal_next_check = n + self.cfg.calibration.check_every
        return self._fit(refine=False)  # the linear eq. (3) solve while collecting: a few ms

    def calibration_cloud(self) -> tuple[F64, F64]:
        """The raw calibration samples and the same after eq. (2) (for the viewer)."""
        raw = self._cal_field[: self._cal_n]
        if self.calib_l is None or self.calib_d is None:
            return raw, raw
        return raw, raw @ self.calib_l.T - self.calib_d

    def to_state(self, system_id: int, t_s: float) -> CompassState:
        info = None
        if self.calibration is not None and self.calibration.source != "identity":
            info = {
                "residual_rms_mgauss": self.calibration.residual_rms_mgauss,
                "coverage": self.calibration.coverage,
                "n": float(self.calibration.n),
            }
        keep = self.calibration is not None and self.calibration.source != "identity"
        inflight = self.inflight.state() if self.inflight is not None else self.stored_inflight
        theta = np.asarray(self.theta_est.theta_mgauss, dtype=float)
        if self.calibration is None and self.inflight is not None and self.inflight.solution is not None:
            theta = np.asarray(self.inflight.solution.theta_mgauss, dtype=float)
        return CompassState(
            system_id=system_id,
            mag_index=self.mag_index,
            calib_l=self.calib_l if keep else None,
            calib_d=self.calib_d if keep else None,
            theta_mgauss=theta,
            t_s=t_s,
            calib_info=info,
            inflight=inflight,
        )


class Pipeline:
    """Samples in (any order of types, message-time stamped), heading estimates out.

    ``store``: a :class:`StateStore` to load calibration and theta from at the first magnetometer sample
    of each compass and to save them to (on calibration, every ``state.save_interval_s`` of message time
    and on :meth:`close`). ``system_id``: the vehicle; None -> taken from the first HEARTBEAT, else 1.
    ``on_text``: status lines (calibration learned, resets, warnings) with their message time.
    """

    def __init__(
        self,
        cfg: Config,
        *,
        store: StateStore | None = None,
        system_id: int | None = None,
        on_text: Callable[[float, str], None] | None = None,
    ) -> None:
        self.cfg = cfg
        self.store = store
        self.system_id = system_id
        self._on_text = on_text
        self.counts: dict[str, int] = {
            "samples": 0,
            "mag": 0,
            "imu": 0,
            "estimates": 0,
            "non_finite": 0,
            "saturated": 0,
            "gyro_jumps": 0,
            "mag_jumps": 0,
            "gyro_gated": 0,
            "time_backwards": 0,
            "clock_resets": 0,
            "reboots": 0,
            "gaps": 0,
            "observer_resets": 0,
            "throttle_jumps": 0,
            "no_throttle": 0,
        }
        self.warnings: list[str] = []
        self.correctors: dict[int, CompassCorrector] = {}
        self._earth_ned = est_core.earth_field(cfg)
        self._mahony_p = MahonyParams(
            kp=cfg.mahony.kp,
            ki=cfg.mahony.ki,
            accel_gate_frac=cfg.mahony.accel_gate_m_s2 / 9.80665,
        )
        self._mahony: FastMahony | None = None
        self._mahony_t0 = 0.0
        self._imu_t: float | None = None
        self._gyro = [0.0, 0.0, 0.0]  # bias-corrected body rate of the latest IMU sample, rad/s
        # the gyro gate (GYRO_HOLDOFF_S): raw rate and time of the previous IMU sample, end of the bad spell
        self._gyro_raw: tuple[float, float, float] | None = None
        self._gyro_raw_t = -math.inf
        self._gyro_bad_until = -math.inf
        self._imu_restart = False
        self._boot_offset_s = 0.0  # t_s - the autopilot's own clock (changes at each reboot)
        self._att_t: float | None = None
        self._att_roll = 0.0
        self._att_pitch = 0.0
        self._thr_t: float | None = None
        self._thr = 0.0
        self._thr_prev_t: float | None = None
        self._thr_prev = 0.0
        self._use_throttle = cfg.input.throttle_source != "none"
        self._learn = cfg.observer.learn
        self._max_jump = cfg.observer.max_throttle_jump_01
        self._first_mag_t: float | None = None
        self._warned_no_throttle = False
        self._out_period = 1.0 / cfg.output.rate_hz if cfg.output.rate_hz > 0 else 0.0
        self._compasses = set(cfg.input.compasses)
        self._pending_saves: list[Future[None]] = []
        # configuration read once (the per-sample path below runs ~100k times a minute of log)
        self._stale_s = cfg.input.stale_s
        self._mag_sat = cfg.input.saturation_mgauss
        self._gyro_sat = cfg.input.gyro_saturation_rad_s
        self._dt_min = cfg.observer.dt_min_s
        self._dt_max = cfg.observer.dt_max_s
        self._save_interval_s = cfg.state.save_interval_s
        self._att_mahony = cfg.input.attitude in ("mahony", "auto")
        # auto: the heading's roll and pitch from the autopilot's ATTITUDE while it streams (its estimator
        # compensates flight accelerations with GPS; a gyro+accelerometer filter tilts by several degrees in
        # accelerated flight, and with a 60-70 deg inclination each degree of tilt is 2-3 deg of heading);
        # the DPI down vector always from the own Mahony filter (sec. II-A)
        self._att_auto = cfg.input.attitude == "auto"
        # attitude of the latest IMU / ATTITUDE sample, derived once for every compass (see _attitude)
        self._att_cache: _Attitude | None = None
        # the numbers of the last published estimate (see last_estimate)
        self._last: tuple[Any, ...] | None = None
        # in-flight calibration inputs: parameters, yaw, motor outputs, position
        self._params: dict[str, float] = {}
        self._att_yaw = 0.0
        self._motors: tuple[float, ...] = ()
        self._motors_on_t: float | None = None
        self._imu_dt: float | None = None
        self._att_dt: float | None = None  # the autopilot attitude's usual interval (s)
        self._accel_norm = STANDARD_GRAVITY_M_S2
        # the bias-corrected gyro integrated alone (no accelerometer or compass correction): the rotation
        # between two magnetometer samples for the relative form, free of anything a compass disturbs
        self._qg: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
        loc = cfg.location
        self._location = (loc.lat_deg, loc.lon_deg, loc.alt_m, loc.decimal_year)
        self._location_source = "config"
        self._gps_year: float | None = None

    # ------------------------------------------------------------------------------------------ helpers

    def _text(self, t_s: float, msg: str, warning: bool = False) -> None:
        if warning:
            self.warnings.append(msg)
            log.warning(msg)
        else:
            log.info(msg)
        if self._on_text is not None:
            self._on_text(t_s, msg)

    def _check_time(self, last: float | None, t: float, allow_equal: bool = False) -> int:
        """0: fine; 1: skip (time went backwards a little); 2: clock reset (backwards by a lot)."""
        if last is None or t > last or (allow_equal and t == last):
            return 0
        if last - t > self.cfg.input.time_reset_s:
            self.counts["clock_resets"] += 1
            return 2
        self.counts["time_backwards"] += 1
        return 1

    # --------------------------------------------------------------------------------------- dispatcher

    def process(self, sample: Sample) -> HeadingEstimate | None:
        """Feed one sample; returns the heading estimate for a magnetometer sample, else None."""
        return self.last_estimate() if self.feed(sample) else None

    def feed(self, sample: Sample) -> bool:
        """:meth:`process` without building the estimate: True when one was published; it is then
        :meth:`last_estimate` (for consumers that only count, or need only some estimates)."""
        self.counts["samples"] += 1
        kind = type(sample)
        # samples decoded by the MAVLink source carry their vectors as floats (no arrays built or read);
        # type(sample) spelt out so that mypy narrows it
        if type(sample) is WireMagSample:
            vx, vy, vz = sample.field_xyz
            return self._on_mag(sample, vx, vy, vz)
        if type(sample) is WireImuSample:
            if sample.imu_index == 0:  # the attitude comes from the primary IMU
                self._on_imu(sample.t_s, *sample.gyro_xyz, *sample.accel_xyz)
        elif kind is TemperatureSample or kind is PowerSample:  # not used here (one per IMU message)
            pass
        elif kind is ThrottleSample:
            self._on_throttle(sample)  # type: ignore[arg-type]
        elif kind is AttitudeSample:
            self._on_attitude(sample)  # type: ignore[arg-type]
        elif isinstance(sample, MagSample):
            v = sample.field_b_mgauss
            return self._on_mag(sample, float(v[0]), float(v[1]), float(v[2]))
        elif isinstance(sample, ImuSample):
            if sample.imu_index == 0:
                g, a = sample.gyro_b_rad_s, sample.accel_b_m_s2
                self._on_imu(sample.t_s, float(g[0]), float(g[1]), float(g[2]),
                             float(a[0]), float(a[1]), float(a[2]))  # fmt: skip
        elif kind is ClockResetSample:
            self._on_reboot(sample)  # type: ignore[arg-type]
        elif kind is HeartbeatSample and self.system_id is None:
            self.system_id = int(sample.system_id)  # type: ignore[union-attr]
        elif kind is ParamSample:
            self._params[sample.name] = float(sample.value)  # type: ignore[union-attr]
        elif kind is PositionSample:
            self._on_position(sample)  # type: ignore[arg-type]
        elif kind is TimeSample:
            yr = float(sample.decimal_year)  # type: ignore[union-attr]
            if math.isfinite(yr) and 2010.0 <= yr < 2030.0:
                self._gps_year = yr
        return False

    def last_estimate(self) -> HeadingEstimate:
        """The estimate of the last magnetometer sample for which :meth:`feed` returned True."""
        if self._last is None:
            raise ValueError("no estimate published yet")
        t, idx, heading, heading_raw, theta, bias, thr, flags, sample, corrected, info = self._last
        return HeadingEstimate(
            t_s=t,
            mag_index=idx,
            heading_deg=heading,
            heading_raw_deg=heading_raw,
            theta_mgauss=np.array(theta, dtype=float),
            bias_mgauss=np.array(bias, dtype=float),
            throttle_01=thr,
            flags=flags,
            field_raw_mgauss=sample.field_b_mgauss,
            field_cal_mgauss=np.array(corrected, dtype=float),
            residual_norm_mgauss=float("nan") if info is None else info.residual_norm_mgauss,
            excitation=float("nan") if info is None else info.excitation,
            t_boot_s=t - self._boot_offset_s,
        )

    def _on_throttle(self, s: ThrottleSample) -> None:
        if not self._use_throttle:
            return
        thr = s.throttle_01
        if not math.isfinite(thr) or not math.isfinite(s.t_s):
            self.counts["non_finite"] += 1
            return
        if self._check_time(self._thr_t, s.t_s, allow_equal=True) == 1:
            return
        self._thr_prev_t, self._thr_prev = self._thr_t, self._thr
        self._thr_t = s.t_s
        self._thr = min(max(thr, 0.0), 1.0)
        self._motors = s.motors_01
        if self._thr > self.cfg.calibration.max_throttle_01:
            if self._motors_on_t is None:
                self._motors_on_t = s.t_s
        else:
            self._motors_on_t = None
        for c in self.correctors.values():
            if c.queue:
                self._drain(c, s.t_s)

    def _throttle_at(self, t: float) -> float | None:
        """Throttle at message time ``t``: linear between the two samples around it, else the nearest.
        None when ``t`` lies strictly between two throttle samples that differ by more than
        ``[observer] max_throttle_jump_01`` (a step whose instant the throttle stream does not resolve)."""
        t1, pt = self._thr_t, self._thr_prev_t
        if t1 is None or t >= t1 or pt is None or pt >= t1:
            return self._thr
        if t <= pt:
            return self._thr_prev
        thr1, thr0 = self._thr, self._thr_prev
        if abs(thr1 - thr0) > self._max_jump:
            return None
        return thr0 + (t - pt) / (t1 - pt) * (thr1 - thr0)

    def _drain(self, c: CompassCorrector, t_now: float) -> None:
        """Feed the observer every queued sample whose throttle is known now (the throttle stream has
        reached its time), or that has waited longer than ``stale_s`` (then: the latest throttle)."""
        q = c.queue
        t_thr = self._thr_t
        stale = self._stale_s
        est = c.theta_est
        while q:
            t, omega, u = q[0]
            if u is None:  # a reset marker
                q.popleft()
                est.reset_filters()
                c.obs_last_t = None
                continue
            if t_thr is None or (t > t_thr and t_now - t <= stale):
                return
            q.popleft()
            thr = self._throttle_at(t)
            if thr is None:
                # the throttle jumped between the two throttle samples around this one: its value at
                # this instant is unknown, so this sample is not used and the observer re-anchors on
                # the next one whose throttle is known
                self.counts["throttle_jumps"] += 1
                est.reset_filters()
                c.obs_last_t = None
                continue
            last = c.obs_last_t
            c.obs_last_t = t
            c.last_info = est.step(omega, u, thr, 0.0 if last is None else t - last)
            c.dirty = True

    def _on_attitude(self, s: AttitudeSample) -> None:
        if not (math.isfinite(s.roll_rad) and math.isfinite(s.pitch_rad) and math.isfinite(s.t_s)):
            self.counts["non_finite"] += 1
            return
        if self._check_time(self._att_t, s.t_s, allow_equal=True) == 1:
            return
        if self._att_t is not None and 0.0 < s.t_s - self._att_t < 10.0:
            dt = s.t_s - self._att_t
            self._att_dt = dt if self._att_dt is None else self._att_dt + 0.05 * (dt - self._att_dt)
        self._att_t = s.t_s
        self._att_roll, self._att_pitch = s.roll_rad, s.pitch_rad
        self._att_yaw = s.yaw_rad if math.isfinite(s.yaw_rad) else self._att_yaw
        self._att_cache = None

    def _on_imu(self, t: float, gx: float, gy: float, gz: float, ax: float, ay: float, az: float) -> None:
        """A sample of the primary IMU: body rate (rad/s) and specific force (m/s^2)."""
        self.counts["imu"] += 1
        if not all(map(math.isfinite, (t, gx, gy, gz, ax, ay, az))):
            self.counts["non_finite"] += 1
            return
        self._accel_norm = math.sqrt(ax * ax + ay * ay + az * az)
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
            self._gate_gyro(t)
            return
        if t <= self._gyro_bad_until:
            self.counts["gyro_gated"] += 1
            return
        prev_t = self._imu_t
        verdict = 0 if prev_t is None or t > prev_t else self._check_time(prev_t, t)
        if verdict == 1:
            return
        m = self._mahony
        self._att_cache = None
        self._imu_dt = None if prev_t is None or verdict != 0 else t - prev_t
        restart, self._imu_restart = self._imu_restart, False
        if (m is not None and prev_t is not None and verdict == 0 and not restart
                and t - prev_t <= self._dt_max):  # fmt: skip
            self._imu_t = t
            m.update(gx, gy, gz, ax, ay, az, t - prev_t)
            b = m.b
            self._gyro = [gx - b[0], gy - b[1], gz - b[2]]
            self._qg = quat_step_body_rate(self._qg, self._gyro, t - prev_t)
            return
        # first sample, a gap or a clock reset: the rotation since the last sample is unknown, so the
        # tilt restarts from the accelerometer (gyro bias kept) and must settle again before the
        # calibration uses it
        try:
            fresh = mahony_init(np.array((ax, ay, az)))
        except ValueError:
            self.counts["non_finite"] += 1
            return
        bias = np.array(m.b) if m is not None else fresh.gyro_bias_b_rad_s
        self._mahony = FastMahony(self._mahony_p, fresh.q_nb, bias)
        self._mahony_t0 = t
        self._qg = (1.0, 0.0, 0.0, 0.0)  # the gyro integral restarts (a new epoch: no pair across it)
        self._imu_t = t
        self._gyro = [gx - float(bias[0]), gy - float(bias[1]), gz - float(bias[2])]

    def _on_reboot(self, s: ClockResetSample) -> None:
        """The autopilot rebooted (issue 12): data of two boots never meet in one calibration or one
        filter. A calibration window with a learned calibration ends here (its final fit uses this
        boot's pairs only); one without drops the old boot's pairs and starts again. The observers'
        filters, the heading filters, the attitude and the throttle history restart (theta kept)."""
        self.counts["reboots"] += 1
        self._boot_offset_s = s.offset_s
        self._imu_restart = True
        self._att_cache = None
        self._thr_t = self._thr_prev_t = None
        for c in self.correctors.values():
            if c.collecting:
                learned = c.calibration is not None and c.calibration.source == "learned"
                if not learned and c.n_collected >= self.cfg.calibration.min_samples:
                    learned = c.fit_now()  # the old boot's pairs on their own, if the DPI fit accepts them
                if learned:
                    c.freeze_calibration()
                else:
                    c.restart_collection()
            c.queue_reset()
            self.counts["observer_resets"] += 1
            c.hdg_filter.reset()
            c.hdg_raw_filter.reset()
        self._text(s.t_s, "autopilot rebooted (its clock restarted): calibration window closed, filters "
                          "restarted", warning=self.counts["reboots"] == 1)  # fmt: skip

    def _gate_gyro(self, t: float) -> None:
        """A saturated or jumping gyro sample at ``t``: gyro and attitude untrusted until GYRO_HOLDOFF_S
        after it; at the start of a bad spell the observers' filters are reset (theta kept)."""
        if t > self._gyro_bad_until or not math.isfinite(self._gyro_bad_until):
            for c in self.correctors.values():
                c.queue_reset()
            self.counts["observer_resets"] += len(self.correctors)
        self._gyro_bad_until = max(self._gyro_bad_until, t + GYRO_HOLDOFF_S)
        self._imu_restart = True  # the rotation during the spell is unknown: the tilt restarts
        self._att_cache = None

    # ----------------------------------------------------------------------------------- magnetometer

    def _corrector(self, idx: int) -> CompassCorrector:
        c = self.correctors.get(idx)
        if c is None:
            sysid = self.system_id if self.system_id is not None else 1
            if self.system_id is None:
                self.system_id = sysid
            stored = self.store.load(sysid, idx) if self.store is not None else None
            if self.store is not None:
                for w in self.store.warnings:
                    if w not in self.warnings:
                        self.warnings.append(w)
            c = CompassCorrector(idx, self.cfg, self._earth_ned, stored)
            self.correctors[idx] = c
        return c

    def _attitude(self) -> _Attitude:
        """The DPI reference down vector (None when no settled estimate) and cos/sin of roll and pitch;
        derived once per IMU (or ATTITUDE) sample, shared by the compasses."""
        a = self._att_cache
        if a is not None:
            return a
        down: tuple[float, float, float] | None = None
        if self._mahony is not None and self._att_mahony:
            w, x, y, z = self._mahony.q
            # third row of R_nb = down vector in body axes (sec. II-A); roll/pitch of ZYX Euler
            d = (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))
            roll = math.atan2(d[1], d[2])
            pitch = -math.asin(max(-1.0, min(1.0, d[0])))
            att_t, imu_t = self._att_t, self._imu_t
            fresh = att_t is not None and imu_t is not None and abs(imu_t - att_t) <= self._stale_s
            if self._att_auto and fresh:
                roll, pitch = self._att_roll, self._att_pitch
            if self._imu_t is not None and self._imu_t - self._mahony_t0 >= MAHONY_SETTLE_S:
                down = d
        else:
            roll, pitch = self._att_roll, self._att_pitch
        a = (down, math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch))
        self._att_cache = a
        return a

    def _on_mag(self, s: MagSample, vx: float, vy: float, vz: float) -> bool:
        """A magnetometer sample, whose field (mgauss) the caller has read as floats."""
        self.counts["mag"] += 1
        idx = s.mag_index
        if self._compasses and idx not in self._compasses:
            return False
        t = s.t_s
        if not (math.isfinite(t) and math.isfinite(vx) and math.isfinite(vy) and math.isfinite(vz)):
            self.counts["non_finite"] += 1
            return False
        lim = self._mag_sat
        if abs(vx) >= lim or abs(vy) >= lim or abs(vz) >= lim:
            self.counts["saturated"] += 1
            return False
        c = self.correctors.get(idx) or self._corrector(idx)
        pv = c.prev_raw
        c.prev_raw = (vx, vy, vz)
        if pv is not None and max(abs(vx - pv[0]), abs(vy - pv[1]), abs(vz - pv[2])) > MAG_JUMP_MGAUSS:
            self.counts["mag_jumps"] += 1
            return False
        prev_t = c.last_t
        verdict = 0 if prev_t is None or t > prev_t else self._check_time(prev_t, t)
        if verdict == 1:
            return False
        c.n_mag += 1
        if c.refine_pending and c.adopt_refined():
            self._refined_text(c, t)
        flags = 0
        c.last_t = t
        if self._first_mag_t is None or verdict == 2:
            self._first_mag_t = t
        reset = False  # a gap or a clock reset: filters restart
        obs_reset = False  # the observer's discrete step cannot span this interval
        if verdict == 2 or prev_t is None:
            reset = obs_reset = True
        else:
            dt = t - prev_t
            nominal = c.dt_nominal
            # the first interval (up to 10 s) sets the compass's usual one
            gap_s = max(self._dt_max, 10.0 if nominal is None else GAP_FACTOR * nominal)
            if dt > gap_s:
                self.counts["gaps"] += 1
                reset = obs_reset = True
            else:
                c.dt_nominal = dt if nominal is None else nominal + 0.05 * (dt - nominal)
                if dt < self._dt_min or dt > self._dt_max:
                    obs_reset = True
        # ---- throttle
        thr = 0.0
        thr_t = self._thr_t
        have_thr = thr_t is not None
        if thr_t is not None:
            thr = self._thr
            if t - thr_t > self._stale_s:
                flags |= FLAG_INPUTS_STALE
        else:
            flags |= FLAG_NO_THROTTLE
            self.counts["no_throttle"] += 1
            if not self._warned_no_throttle and (
                not self._use_throttle or t - self._first_mag_t >= NO_THROTTLE_WARN_S
            ):
                self._warned_no_throttle = True
                why = ("disabled in the configuration" if not self._use_throttle
                       else "no throttle samples, or motor outputs without pulse widths")  # fmt: skip
                self._text(t, f"no throttle source ({why}): headings are published uncorrected", warning=True)
        # ---- attitude and gyro
        down, cr, sr, cp, sp = self._attitude()
        gyro_fresh = self._imu_t is not None and abs(t - self._imu_t) <= self._stale_s
        if t <= self._gyro_bad_until:  # the gyro gate: no observer, no calibration
            gyro_fresh = False
            flags |= FLAG_SATURATED
        elif self._imu_restart or not gyro_fresh:  # (restart: after a gyro gate or a reboot)
            gyro_fresh = False
            flags |= FLAG_INPUTS_STALE
        # ---- calibration, eqs. (1)-(3)
        if c.collecting:
            at_rest = not have_thr or thr <= self.cfg.calibration.max_throttle_01
            if not at_rest:
                c.freeze_calibration()
            elif down is not None and gyro_fresh and c.collect_calibration(down, (vx, vy, vz)):
                assert c.calibration is not None
                rms = c.calibration.residual_rms_mgauss
                if c.n_cal_fits == 1:
                    self._text(t, f"compass {idx}: calibration learned from {c.calibration.n} samples "
                                  f"(eq. (3) residual {rms:.1f} mgauss); refining while the motors are off")
                else:
                    log.debug("compass %d: calibration refined from %d samples (residual %.1f mgauss)",
                              idx, c.calibration.n, rms)
                self._save(c, t)
        k = c.calib_coeffs()
        info: est_core.ThetaStepInfo | None = None
        inflight: InflightOutput | None = None
        if k is None and self._learn and self.cfg.inflight.enabled and have_thr:
            inflight = self._inflight_step(c, t, vx, vy, vz, reset)
        bias_inflight: tuple[float, float, float] | None = None
        if inflight is not None:
            flags |= FLAG_CALIBRATED
            if inflight.converged:
                flags |= FLAG_THETA_CONVERGED
            k = inflight.coeffs
            # eq. (2) with the in-flight L and d; the bias of eq. (11) (+ per-motor terms) from the same fit
            ux = k[0] * vx + k[1] * vy + k[2] * vz - k[9]
            uy = k[3] * vx + k[4] * vy + k[5] * vz - k[10]
            uz = k[6] * vx + k[7] * vy + k[8] * vz - k[11]
            th0, th1, th2 = inflight.theta_mgauss
            bias_inflight = inflight.bias_mgauss
        elif k is not None:
            flags |= FLAG_CALIBRATED
            # eq. (2): u = L v - d
            ux = k[0] * vx + k[1] * vy + k[2] * vz - k[9]
            uy = k[3] * vx + k[4] * vy + k[5] * vz - k[10]
            uz = k[6] * vx + k[7] * vy + k[8] * vz - k[11]
            # ---- low-pass + observer, eqs. (19)-(20), fed in time order with the throttle interpolated
            # at the sample's own time (queued until the throttle after it is known)
            if obs_reset:
                c.queue_reset()
                self.counts["observer_resets"] += 1
                flags |= FLAG_OBSERVER_RESET
            elif self._learn and have_thr and gyro_fresh:
                c.queue.append((t, self._gyro, (ux, uy, uz)))
            self._drain(c, t)
            info = c.last_info
            if info is not None:
                if info.z_unobservable:
                    flags |= FLAG_Z_UNOBSERVABLE
                if info.saturated:
                    flags |= FLAG_SATURATED
            if c.theta_est.converged:
                flags |= FLAG_THETA_CONVERGED
            th0, th1, th2 = c.theta_est.theta_values()
        else:
            ux, uy, uz = vx, vy, vz
            th0 = th1 = th2 = 0.0
        # eq. (11): bias = theta throttle^2, removed from the calibrated field
        d2 = thr * thr
        if bias_inflight is not None:
            bx, by, bz = bias_inflight
        else:
            bx, by, bz = (th0 * d2, th1 * d2, th2 * d2) if have_thr else (0.0, 0.0, 0.0)
        state = "corrected" if flags & FLAG_CALIBRATED and have_thr else "uncorrected"
        if prev_t is not None and not reset:
            c.time_s[state] += t - prev_t
        cx, cy, cz = ux - bx, uy - by, uz - bz
        psi_raw = est_core.heading_from_trig(ux, uy, uz, cr, sr, cp, sp)
        psi = est_core.heading_from_trig(cx, cy, cz, cr, sr, cp, sp) if have_thr else psi_raw
        if reset or not gyro_fresh:
            c.hdg_filter.reset()
            c.hdg_raw_filter.reset()
        # Euler yaw rate from body rates (ZYX), as est_core.yaw_rate_rad_s
        _, gy, gz = self._gyro
        yaw_rate = math.nan if abs(cp) < 0.25 else (gy * sr + gz * cr) / cp
        dt_h = 0.0 if prev_t is None or reset else t - prev_t
        heading_raw = c.hdg_raw_filter.update(psi_raw, yaw_rate, dt_h)
        heading = c.hdg_filter.update(psi, yaw_rate, dt_h) if have_thr else heading_raw
        # ---- state persistence on message time
        if c.dirty and (c.last_saved_t is None or t - c.last_saved_t >= self._save_interval_s):
            self._save(c, t)
        # ---- output decimation on message time
        if self._out_period > 0.0:
            if c.n_out > 0 and prev_t is not None and t - c.out_t < self._out_period and not reset:
                return False
            c.out_t = t
        c.n_out += 1
        self.counts["estimates"] += 1
        # the estimate itself is built by last_estimate(), only when someone asks for it
        self._last = (t, idx, heading, heading_raw, (th0, th1, th2), (bx, by, bz), thr, flags, s,
                      (cx, cy, cz), info)  # fmt: skip
        return True

    # ------------------------------------------------------------------------------ in-flight calibration

    def _on_position(self, s: PositionSample) -> None:
        """The first trusted GNSS fix sets the Earth field (WMM at the vehicle, at the log's date)."""
        if self._location_source == "gps" or not s.fix_ok:
            return
        lat, lon, alt = s.lat_deg, s.lon_deg, s.alt_m
        finite = math.isfinite(lat) and math.isfinite(lon)
        if not (finite and -90.0 <= lat <= 90.0 and -180.0 <= lon <= 360.0):
            self.counts["non_finite"] += 1
            return
        if lat == 0.0 and lon == 0.0:  # "no position" as some autopilots send it
            return
        year = s.decimal_year if math.isfinite(s.decimal_year) else self._gps_year
        if year is None or not (2010.0 <= year < 2030.0):
            year = self._location[3]
        alt = alt if math.isfinite(alt) and -1000.0 < alt < 20000.0 else 0.0
        try:
            field = earth_field_ned_mgauss(lat, lon, alt, year)
        except Exception:  # an out-of-range date or place: keep the configured field
            return
        self._location = (lat, lon, alt, year)
        self._location_source = "gps"
        self._earth_ned = field
        norm = float(np.linalg.norm(field))
        for c in self.correctors.values():
            c.earth_ned = field
            if c.inflight is not None:
                c.inflight.restart(norm)
        self._text(s.t_s, f"Earth field from the GPS position ({lat:.4f}, {lon:.4f}, {year:.1f}): "
                          f"{norm:.0f} mgauss, WMM")

    def _inflight_step(
        self, c: CompassCorrector, t: float, vx: float, vy: float, vz: float, reset: bool
    ) -> InflightOutput | None:
        """Feed the in-flight calibration of compass ``c`` and return its correction when it is usable."""
        st = c.inflight
        if st is None:
            icfg = self.cfg.inflight
            if icfg.reference == "auto":
                mode, why = yaw_reference(self._params, c.mag_index)
            else:
                mode = "absolute" if icfg.reference == "absolute" else "relative"
                why = "set in the configuration ([inflight] reference)"
            cal = calibrated_by_autopilot(self._params, c.mag_index)
            st = InflightStage(
                c.mag_index, icfg, mode, why, cal, float(np.linalg.norm(self._earth_ned)), c.stored_inflight
            )
            c.inflight = st
            self._text(t, f"compass {c.mag_index}: learning calibration and theta in flight ({mode} form: "
                          f"{why}); a motors-off hand rotation, if one comes, takes precedence")
        if reset:
            st.reset_pairs()
        thr = self._throttle_at(t)
        if thr is not None:
            # fresh: within stale_s, or within one and a half of its own interval (1-2 Hz telemetry)
            att_dt = self._att_dt
            att_stale_s = self._stale_s if att_dt is None else max(self._stale_s, 1.5 * att_dt)
            att_fresh = self._att_t is not None and abs(t - self._att_t) <= att_stale_s
            r_abs = None
            if st.mode == "absolute" and att_fresh and self._motors_on_t is not None:
                settled = t - self._motors_on_t >= self.cfg.inflight.absolute_settle_s
                level = abs(self._att_roll) < MAX_TILT_RAD and abs(self._att_pitch) < MAX_TILT_RAD
                if settled and level:
                    r_abs = dcm_from_euler(self._att_roll, self._att_pitch, self._att_yaw)
            r_rel = None
            if st.mode == "relative":
                fast_imu = self._imu_dt is not None and self._imu_dt <= FAST_IMU_DT_S
                gyro_fresh = self._imu_t is not None and abs(t - self._imu_t) <= self._stale_s
                src: tuple[str, float]
                rot = self.cfg.inflight.rotation
                if rot == "auto":
                    rot = relative_rotation_source(self._params, c.mag_index)[0]
                # the integrated gyro only while it is fast; the autopilot's attitude when it is too slow
                use_gyro = (rot == "gyro" and fast_imu) or not att_fresh
                if use_gyro and fast_imu and gyro_fresh and self._mahony is not None:
                    r_rel = dcm_from_quat(np.asarray(self._qg, dtype=float))
                    src = ("gyro", self._mahony_t0)
                elif att_fresh:
                    r_rel = dcm_from_euler(self._att_roll, self._att_pitch, self._att_yaw)
                    src = ("attitude", 0.0)
                else:
                    src = ("none", 0.0)
                if src != c.rel_source:
                    st.reset_pairs()
                    c.rel_source = src
                if r_rel is not None and float(r_rel[2, 2]) < COS_MAX_TILT:
                    r_rel = None  # acrobatics or a crash: no pair across it
            if abs(self._accel_norm - STANDARD_GRAVITY_M_S2) > IMPACT_M_S2:
                r_abs = r_rel = None  # an impact (a crash, a hard landing): the field may be disturbed too
            st.feed(t, np.array((vx, vy, vz)), thr, self._motors, r_abs, self._earth_ned, r_rel)
            c.dirty = True
        return st.output(t, (vx, vy, vz), self._thr, self._motors)

    def _refined_text(self, c: CompassCorrector, t: float) -> None:
        assert c.calibration is not None
        self._save(c, t)
        self._text(t, f"compass {c.mag_index}: motors on, calibration final ({c.calibration.n} samples, "
                      f"eq. (3) residual {c.calibration.residual_rms_mgauss:.1f} mgauss)")

    # ------------------------------------------------------------------------------------------ state

    def _save(self, c: CompassCorrector, t_s: float) -> None:
        """Write the compass's state in the background (two fsyncs can take tens of ms on some disks);
        one writer thread keeps the writes in order, :meth:`close` waits for them."""
        c.last_saved_t = t_s
        c.dirty = False
        if self.store is None:
            return
        state = c.to_state(self.system_id if self.system_id is not None else 1, t_s)
        self._pending_saves = [f for f in self._pending_saves if not f.done()]
        self._pending_saves.append(_state_writer().submit(self._write_state, state, t_s))

    def _write_state(self, state: CompassState, t_s: float) -> None:
        assert self.store is not None
        try:
            self.store.save(state)
        except OSError as exc:
            msg = f"cannot write state for compass {state.mag_index}: {exc.strerror}"
            self.warnings.append(msg)
            log.warning(msg)

    def close(self) -> None:
        """Feed what is still queued, save every compass's state and wait for the writes."""
        for c in self.correctors.values():
            if c.adopt_refined(force=True) and c.last_t is not None:
                self._refined_text(c, c.last_t)
            if c.queue:
                self._drain(c, math.inf)
            if c.last_t is not None:
                self._save(c, c.last_t)
        for f in self._pending_saves:
            f.result()
        self._pending_saves = []

    def summary(self) -> dict[str, object]:
        """Plain values for JSON: counts, warnings, where the Earth field came from, and per compass its
        calibration, theta, whether its headings are corrected and, when not, why (strictly valid JSON:
        no NaN)."""
        compasses = []
        for idx, c in sorted(self.correctors.items()):
            cal = c.calibration
            st = c.inflight
            theta = np.asarray(c.theta_est.theta_mgauss, dtype=float).tolist()
            converged = bool(c.theta_est.converged)
            calibrated = c.calibrated
            calib_doc: dict[str, object] | None = None
            if cal is not None:
                calib_doc = {
                    "source": cal.source,
                    "residual_rms_mgauss": cal.residual_rms_mgauss,
                    "coverage": cal.coverage,
                    "n": cal.n,
                    "L": None if c.calib_l is None else np.asarray(c.calib_l).tolist(),
                    "d_mgauss": None if c.calib_d is None else np.asarray(c.calib_d).tolist(),
                }
            elif st is not None and st.solution is not None and st.applied:
                sol = st.solution
                calibrated = True
                theta = sol.theta_mgauss.tolist()
                converged = sol.heading_sigma_deg < st.params.heading_converged_deg
                calib_doc = {
                    "source": "in-flight",
                    "residual_rms_mgauss": sol.residual_rms_mgauss,
                    "n": sol.n,
                    "L": sol.calib_l.tolist(),
                    "d_mgauss": sol.calib_d.tolist(),
                }
            status, why = self._status(c)
            compasses.append(
                {
                    "index": idx,
                    "calibrated": calibrated,
                    "calibration": calib_doc,
                    "theta_mgauss": theta,
                    "theta_converged": converged,
                    "estimates": c.n_out,
                    "status": status,
                    "why": why,
                    "time_s": dict(c.time_s),
                    "inflight": None if st is None else {**st.summary(), "rotation": c.rel_source[0]},
                }
            )
        lat, lon, alt, year = self._location
        return json_safe(
            {
                "system_id": self.system_id,
                "counts": dict(self.counts),
                "warnings": list(self.warnings),
                "earth_field": {
                    "source": self._location_source,
                    "lat_deg": lat,
                    "lon_deg": lon,
                    "alt_m": alt,
                    "decimal_year": year,
                    "ned_mgauss": np.asarray(self._earth_ned, dtype=float).tolist(),
                },
                "compasses": compasses,
            }
        )

    def _status(self, c: CompassCorrector) -> tuple[str, str]:
        """(corrected | uncorrected, why) for the summary: one phrase a user can act on."""
        if self._thr_t is None:
            why = "disabled in the configuration" if not self._use_throttle else "none in the input"
            return "uncorrected", f"no throttle source ({why})"
        if c.calibration is not None:
            return "corrected", f"calibration {c.calibration.source}, theta by the observer of eq. (20)"
        st = c.inflight
        if st is not None and st.applied:
            return "corrected", f"calibration and theta learned in flight ({st.mode} form)"
        if st is not None:
            return "uncorrected", st.why_not()
        if not self._learn:
            return "uncorrected", "no calibration and learning disabled ([observer] learn = false)"
        if not self.cfg.inflight.enabled:
            return "uncorrected", "no hand-rotation calibration and in-flight calibration disabled"
        return "uncorrected", "no samples with the throttle known"
