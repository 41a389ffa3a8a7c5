"""The in-flight calibration stage of one compass: the stateful shell around :mod:`magcomp.core.inflight`.

It decides, sample by sample, which rows go into the estimator (absolute rows from the autopilot's
attitude, relative rows from the rotation between two samples), at what rate, and whether the estimate is
good enough to be applied; it keeps the time spent in each state for the summary. No I/O.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.config import InflightConfig
from magcomp.core.inflight import (
    NUISANCE_PRIOR_RAD_S,
    VIF_BATCH_S,
    InflightEstimator,
    InflightMode,
    InflightParams,
    InflightSolution,
    WindowFieldRows,
    absolute_rows,
    reference_yaw_error_rows,
    regressors,
    relative_rows,
    rotation_error_rows,
    window_field_rows,
    window_nuisance_cols,
)
from magcomp.core.linalg3 import cross, vec3
from magcomp.core.rotations import so3_exp, so3_log
from magcomp.core.types import EARTH_MAX_MGAUSS, EARTH_MIN_MGAUSS, STANDARD_GRAVITY_M_S2

if TYPE_CHECKING:
    from magcomp.service.attitude import GyroYaw

F64 = NDArray[np.float64]

#: the longest interval (s) over which two samples form a relative pair: the rotation between them comes
#: from integrated gyro or the autopilot's attitude, whose yaw drift over this time is well under 1 deg
MAX_PAIR_S = 2.5
#: the relative form pairs a sample with the newest one at least this much older. Longer baselines carry
#: more rotation and throttle change per pair (above the noise of two samples), but a compass-to-IMU
#: misalignment of a few degrees errs in proportion to the rotation between the pair. Measured (compass 1
#: / 2 vs compass 0 on log171, two-pass; simulated ordinary flight at 50 Hz, internal primary compass):
#: 0 s (consecutive, 0.1 s): 2.34 / 2.63 deg, sim never confident (heading sigma 7.8 deg); 0.3 s: 2.26 /
#: 2.50 deg, sim 1.9 deg rms vs 3.9 uncorrected; 0.5 s: 2.66 / 2.90; 1 s: 3.22 / 3.44 (all measured before
#: the relative form's soft-iron term, which brought 0.3 s to 2.19 / 2.43).
PAIR_BASELINE_S = 0.3
#: the correction is applied once its heading uncertainty is below half the heading change it makes (a
#: 2-sigma test that the correction is real) or below ``heading_ok_deg``
APPLY_Z = 2.0
#: never applied while the heading uncertainty is above this, whatever heading change the correction makes:
#: the uncertainty atan(err / h) is a linearisation, meaningful only while the error stays well inside the
#: horizontal field (err <= h / 2, atan(0.5) = 26.6 deg); above it a correction that turns the heading by
#: 150 deg would "justify" itself with a 75 deg uncertainty (seen on a 23 s log with 8 deg of yaw)
MAX_APPLY_HEADING_SIGMA_DEG = math.degrees(math.atan(0.5))
#: the relative form adds one field-norm row per sample (InflightEstimator.add_norm)
NORM_ROWS = False
#: the relative form's rows are written against each ROTATION_WINDOW_S window's own Earth field
#: (``window_field_rows``: the horizontal field free per window, the vertical one common to the flight)
#: instead of 0.3 s pairs (docs/inflight.md, "window-field rows")
WINDOW_FIELD_ROWS = True
#: the window-field rows take samples with the motors running only (a disarmed log gives none: said so)
WINDOW_ROWS_MOTORS_ONLY = True
#: the window-field rows take the yaw from the raw gyro (integrated about the vertical of the autopilot's
#: GPS-aided tilt) instead of the autopilot's yaw, which follows the disturbed compass, whenever a raw gyro
#: yaw comes with the field sample
GYRO_YAW = True
#: with the gyro's yaw, a window's Earth field and yaw rate (the gyro's bias about the vertical) are taken
#: as constant over this long (s): the gyro's own drift is its bias, not a compass correction
GYRO_WINDOW_S = 10.0
#: prior standard deviation (rad) of the rotation source's tilt error, one per window (window-field rows):
#: the rows compare the field's vertical part across windows, so a tilt error of the autopilot's GPS-aided
#: attitude (a few tenths of a degree; the simulator's 0.49 deg rms) is a model error of |h| x tilt (4 mgauss
#: at 0.5 deg), comparable to theta x delta^2 itself
TILT_PRIOR_RAD = math.radians(0.5)
#: the window-field rows with the gyro's yaw model the autopilot's tilt error that its compass-driven yaw
#: error makes in accelerated flight (``_ap_yaw_tilt``; docs/inflight.md, "The autopilot's yaw error tilts
#: it"). Off: it removes most of theta's noise-free bias (10 Hz seed 2: 9.9 -> 4.0 %) but the heading gets
#: worse on held-out seeds (10 Hz seed 4 two-pass 1.64 -> 2.57 deg): the per-window nuisance lies along the
#: specific force, i.e. the compass's misalignment about z in a coordinated turn, and no psi good enough to
#: drop it was found (docs/inflight.md, fifth pass). Needs ``attitude.TRACK_ACCEL_H`` on too. What is kept
#: instead: TILT_CONDITION (the model's theta, the ordinary calibration conditioned on it)
AP_YAW_TILT = False
#: the tilt model in a second estimator of its own (``est_tilt``: the same samples, its rows with the tilt
#: removed and its per-window nuisance) whose theta the published solution takes, the other parameters
#: from the ordinary estimator conditioned on that theta (``InflightEstimator.theta_from``; docs/inflight.md,
#: seventh pass). Measured, seeds 0-5 at 10 / 50 Hz: theta's worst error 14.5 -> 8.6 % (theta x1), the
#: heading within 0.05 deg of the ordinary estimate's. Needs ``attitude.TRACK_ACCEL_H``; AP_YAW_TILT off
TILT_CONDITION = True
#: the tilt model's estimator is re-solved at every this many solutions of the published one (every
#: SOLVE_PERIOD_S): theta moves little in a second, and solving both every 0.1 s cost 55 % more CPU on a 50 Hz
#: replay (now 17 %); the final state and the stored one always take its latest theta
TILT_SOLVE_EVERY = 10
#: prior standard deviation (rad) of the gyro yaw's error that the line fit of the windows' field directions
#: leaves, one per window (the tilt-from-yaw nuisance): a single window's field direction scatters by 2-7 deg
#: about the gyro frame's true error (noise-free 10 Hz seed 2: it takes up hard-iron errors in windows with
#: little rotation)
AP_YAW_PRIOR_RAD = math.radians(5.0)
#: take the autopilot's yaw minus the gyro's at the ATTITUDE's own time (``GyroYaw.att_lead_rad``)
AP_YAW_ATT_LEAD = True
#: carry the tilt-from-yaw nuisance per window (AP_YAW_PRIOR_RAD) with AP_YAW_TILT
AP_YAW_NUISANCE = True
#: the relative form's 2 s windows (the autopilot's yaw) write their rows' yaw-rate and tilt columns again
#: about the window's final field estimate when it closes (``_relinearise_window``), on slow links only
#: (the attitude matched to the field's time: 6.7 Hz and slower, 2-13 samples per window). Measured
#: (docs/inflight.md, sixth pass): theta x6 2 / 4 Hz worst theta error 14.5 -> 11.3 % / 13.7 -> 12.0 %;
#: on log171 (10 Hz, not a slow link) it moved compass 1 / 2 from 1.65 / 1.96 to 1.67 / 1.98 deg
RELINEARISE_WINDOW = True
#: prior standard deviation (mgauss) of a window's horizontal Earth field in the window-field rows: any
#: Earth field (under 700 mgauss anywhere), i.e. free
WINDOW_FIELD_PRIOR_MGAUSS = 1000.0
#: the relative form is applied only once the heading has covered this span (deg; as the diagnosis's gate)
MIN_RELATIVE_YAW_SPAN_DEG = 90.0
#: the corrected field's strength must be an Earth field's: Earth's surface range (core.types) widened by the
#: +-35 % a compass calibration within tolerance can leave (the diagnosis's gate, ``max_scale_error``). A
#: compass stuck at one value learns a hard iron equal to its reading and corrects to ~0 mgauss: its heading
#: is then noise, whatever the statistical sigma says.
CORRECTED_FIELD_RANGE_MGAUSS = (0.65 * EARTH_MIN_MGAUSS, 1.35 * EARTH_MAX_MGAUSS)
#: the relative form's rotation-source yaw-rate error (InflightEstimator.add) is taken as constant over
#: windows this long (s). The error is the autopilot's compass-driven yaw correction, which varies on the
#: time constant of that correction (2 s for a complementary filter with a 0.5/s yaw gain, longer for an
#: EKF): a window no longer than that. Measured (simulated ordinary flight, 50 Hz, seed 0: heading rms vs
#: an oracle of 0.84 deg): no nuisance 1.61, 2 s 0.97, 5 s 1.36; log171 compass 1 / 2: 1.73 / 2.05 (none),
#: 1.98 / 2.30 (2 s), 1.70 / 2.03 (5 s).
ROTATION_WINDOW_S = 2.0
#: the absolute form's reference yaw (an external compass's, or GPS yaw) has errors of its own that vary as
#: the vehicle turns (an external compass's residual hard iron: ~2 deg per 10 mgauss). One yaw error per
#: ROTATION_WINDOW_S window is a nuisance of the absolute form, with this prior (rad): a calibrated
#: compass's heading accuracy. Measured: simulated external primary (50 Hz, seed 0) 2.21 -> 0.70 deg rms
#: (oracle 0.58); log171 compass 1 / 2 against compass 0: 1.98 / 2.30 -> 2.19 / 2.55 (a prior of 0.02 rad
#: 2.29 / 2.80 with the unscaled ridge; none: the absolute form follows compass 0's yaw exactly).
REFERENCE_YAW_PRIOR_RAD = 0.035
#: the estimate is re-solved at most this often (s of message time)
SOLVE_PERIOD_S = 0.1
#: states a compass spends time in (summary)
STATES = ("corrected", "learning", "uncorrected")


@dataclass(frozen=True, slots=True)
class InflightOutput:
    """What the pipeline applies: L and d of eq. (2) as 12 floats, theta and the bias at this sample."""

    coeffs: tuple[float, ...]
    theta_mgauss: tuple[float, float, float]
    bias_mgauss: tuple[float, float, float]
    converged: bool
    #: started from a stored state (a previous flight's correction): the self-check starts it published
    warm_started: bool = False
    #: the relative form: the heading's constant part (the mount's yaw) is not observable
    relative: bool = False
    #: the estimate's own heading uncertainty (deg, 1 sigma)
    heading_sigma_deg: float = 0.0


class InflightStage:
    """Per-compass in-flight calibration (see :mod:`magcomp.core.inflight`)."""

    def __init__(
        self,
        mag_index: int,
        cfg: InflightConfig,
        mode: InflightMode,
        why: str,
        calibrated: bool | None,
        field_norm_mgauss: float,
        warm: dict[str, object] | None = None,
    ) -> None:
        """``warm``: a stored in-flight state (form, n_motors, mean, sd) to start from; used only when its
        form is this compass's form (else the autopilot's calibration is the prior, as on a first run)."""
        self.mag_index = mag_index
        self.cfg = cfg
        self.mode: InflightMode = mode
        self.why = why
        self.calibrated_by_autopilot = calibrated
        cal = calibrated is True
        self.params = InflightParams(
            sigma_a=cfg.sigma_a_calibrated if cal else cfg.sigma_a_uncalibrated,
            sigma_d_mgauss=cfg.sigma_d_calibrated_mgauss if cal else cfg.sigma_d_uncalibrated_mgauss,
            sigma_theta_mgauss=cfg.sigma_theta_mgauss,
            heading_ok_deg=cfg.heading_ok_deg,
            heading_converged_deg=cfg.heading_converged_deg,
        )
        self.field_norm_mgauss = field_norm_mgauss
        self.est: InflightEstimator | None = None
        #: the tilt model's own estimator (TILT_CONDITION), fed the same samples
        self.est_tilt: InflightEstimator | None = None
        self.n_motors = -1  # decided at the first sample
        self._period = 1.0 / cfg.max_rate_hz
        self._last_fed: float | None = None
        self._prev: tuple[float, F64, F64, F64] | None = None  # t, R_nb, field, regressors
        self._hist: deque[tuple[float, F64, F64, F64]] = deque()  # recent samples (relative pairs)
        self._win_field: F64 | None = None
        self._win_field_tilt: F64 | None = None
        # RELINEARISE_WINDOW: the open window's key and its used rows (rows, z, field cols, R_nb, tau, common)
        self._rl_key: tuple[int, int] | None = None
        self._slow_link = False  # the attitude is matched to the field's time (a link of 6.7 Hz or slower)
        self._rl_rows: list[tuple[F64, F64, F64, F64, float, F64 | None]] = []
        # the compass-free yaw (GYRO_YAW): in use, the gyro chain's epoch, its offset to the autopilot's yaw
        self._gy_on = False
        self._gy_epoch = -1
        self._gy_offset = 0.0  # the last window-field estimate (NED of the rotation source)
        self._init_tilt_model()
        self._epoch = 0  # counts rotation-source restarts (a nuisance window never spans one)
        # samples waiting for the rotation source to pass their time, and its recent (time, R_nb) samples
        self._pending: deque[tuple[float, F64, tuple[float, ...] | None, F64 | None, GyroYaw | None]] = (
            deque()
        )
        self._att_hist: deque[tuple[float, F64]] = deque()
        self._thr_hist: deque[tuple[float, float]] = deque()
        self.applied = False
        self.solution: InflightSolution | None = None
        self.time_s = dict.fromkeys(STATES, 0.0)
        self._last_t: float | None = None
        self.first_applied_t: float | None = None
        #: the corrected field's strength at the last decision not to apply (mgauss), for why_not()
        self.corrected_field_mgauss: float | None = None
        self.n_rows = 0
        #: samples with an attitude that the window-field rows left out because the motors were off
        self.n_motors_off = 0
        self.yaw_min = math.inf
        self.yaw_max = -math.inf
        self._yaw_prev: float | None = None
        self._yaw_unwrapped = 0.0
        self._solved_t: float | None = None
        self._coeffs: tuple[float, ...] = ()
        self._theta3 = (0.0, 0.0, 0.0)
        self.warm_started = False
        self._warm: tuple[F64, F64] | None = None
        self._warm_start(warm, mode, field_norm_mgauss)

    def _init_tilt_model(self) -> None:
        """State of the tilt-from-yaw model (AP_YAW_TILT, off by default; docs/inflight.md)."""
        # AP_YAW_TILT: the autopilot's yaw minus the gyro's (rad), the horizontal acceleration in the gyro
        # yaw's frame (m/s^2), and the window whose start that yaw difference is taken against
        self._ap_yaw_dev = 0.0
        self._accel_h = (0.0, 0.0)
        # the line fit of the gyro frame's yaw error over the closed windows of one chain: sums of 1, t, t^2,
        # f, t f (AP_YAW_TILT), its epoch, and the window being filled
        self._fit = np.zeros(5)
        self._fit_epoch = -1
        self._ap_key: tuple[int, int] | None = None

    def _warm_start(
        self, warm: dict[str, object] | None, mode: InflightMode, field_norm_mgauss: float
    ) -> None:
        """Start from a stored in-flight state when its form is this compass's (``__init__``)."""
        if warm is not None and warm.get("form") == mode:
            self.n_motors = int(warm["n_motors"])  # type: ignore[call-overload]
            self._warm = (
                np.asarray(warm["mean"], dtype=float),
                np.asarray(warm["sd"], dtype=float),
            )
            self.est = InflightEstimator(
                mode, self.n_motors, self.params, field_norm_mgauss, self._warm, TILT_SOLVE_EVERY
            )
            self._new_tilt_estimator()
            if self.est.prior.mean.shape == self._warm[0].shape and np.array_equal(
                self.est.prior.mean, self._warm[0]
            ):
                self.warm_started = True
                # applied from the first sample only if the run it comes from had found it good enough
                self.applied = bool(warm.get("applied", False))
            else:
                self.est, self.n_motors, self._warm = None, -1, None
                self.est_tilt = None

    def _new_tilt_estimator(self) -> None:
        """The tilt model's own estimator (TILT_CONDITION, relative form), its theta the published one's."""
        assert self.est is not None
        self.est_tilt = None
        if TILT_CONDITION and not AP_YAW_TILT and self.mode == "relative" and WINDOW_FIELD_ROWS and GYRO_YAW:
            self.est_tilt = InflightEstimator(
                self.mode, self.n_motors, self.params, self.field_norm_mgauss, self._warm
            )
        # the published estimate takes the tilt model's theta from the first sample it applies to (a raw
        # gyro's yaw: ``_window_row``)

    # ------------------------------------------------------------------------------------------ feeding

    def reset_pairs(self) -> None:
        """A gap, a clock reset or a change of rotation source: the next sample starts a new pair."""
        self._prev = None
        self._pending.clear()
        self._att_hist.clear()
        self._thr_hist.clear()

    def restart(self, field_norm_mgauss: float) -> None:
        """The Earth field changed (a GPS fix after the configured fallback): absolute rows made against
        the old field are dropped."""
        self.field_norm_mgauss = field_norm_mgauss
        if self.mode == "absolute" and not self.warm_started:
            self.est = None
            self.solution = None
            self.applied = False
        self._prev = None

    def _track_yaw(self, r_nb: F64) -> None:
        yaw = math.atan2(float(r_nb[1, 0]), float(r_nb[0, 0]))
        if self._yaw_prev is not None:
            self._yaw_unwrapped += (yaw - self._yaw_prev + math.pi) % (2.0 * math.pi) - math.pi
        self._yaw_prev = yaw
        self.yaw_min = min(self.yaw_min, self._yaw_unwrapped)
        self.yaw_max = max(self.yaw_max, self._yaw_unwrapped)

    def feed(
        self,
        t_s: float,
        field_mgauss: F64 | tuple[float, float, float],
        throttle_01: float,
        motors_01: tuple[float, ...],
        r_abs_nb: F64 | None,
        field_ref_n_mgauss: F64 | None,
        r_rel_nb: F64 | None,
        r_t_s: float | None = None,
        throttle_t_s: float | None = None,
        gyro_yaw: GyroYaw | None = None,
    ) -> None:
        """One magnetometer sample (field as received, mgauss) with its throttle and motor outputs.

        r_abs_nb: the trusted attitude (absolute form) or None when it cannot be used now;
        field_ref_n_mgauss: the Earth field (NED) for it. r_rel_nb: the rotation-source attitude for the
        relative form (gyro-integrated or the autopilot's), None when there is none. r_t_s, throttle_t_s:
        the times of that attitude and of that throttle (None: this sample's time); when either is older
        than the field, the sample waits for the next ones and gets both interpolated to its time: on a
        telemetry link ATTITUDE and the throttle of an instant often arrive after the RAW_IMU of that
        instant, so the latest ones are a whole message interval old (1 s at 1 Hz; docs/inflight.md).
        gyro_yaw: the raw gyro's yaw at this sample (``AttitudeStage.gyro_yaw_at``) for the relative form's
        compass-free yaw (GYRO_YAW; None: the rotation source's own yaw).
        """
        if self._last_fed is not None and t_s - self._last_fed < 0.9 * self._period and t_s > self._last_fed:
            return
        if self.n_motors < 0:
            use = self.cfg.per_motor == "auto" and 2 <= len(motors_01) <= 8
            self.n_motors = len(motors_01) if use else 0
        if self.est is None:
            self.est = InflightEstimator(
                self.mode, self.n_motors, self.params, self.field_norm_mgauss, self._warm, TILT_SOLVE_EVERY
            )
            self._new_tilt_estimator()
        if field_ref_n_mgauss is not None:
            self.est.set_earth_field(np.asarray(field_ref_n_mgauss, dtype=float))
            if self.est_tilt is not None:
                self.est_tilt.set_earth_field(self.est.field_ned_mgauss)
        mot = motors_01 if self.n_motors > 0 and len(motors_01) == self.n_motors else None
        if self.n_motors > 0 and mot is None:
            return  # the motor set changed: these regressors would not match
        self._last_fed = t_s
        y = np.asarray(field_mgauss, dtype=float)
        r_nb = r_abs_nb if self.mode == "absolute" else r_rel_nb
        if r_nb is None or (self.mode == "absolute" and field_ref_n_mgauss is None):
            if self.mode == "relative":
                self.reset_pairs()
            return
        self._slow_link = r_t_s is not None
        late_r = r_t_s is not None and r_t_s < t_s
        late_thr = throttle_t_s is not None and throttle_t_s < t_s
        if not (late_r or late_thr or self._pending):
            if self.mode == "relative" and WINDOW_FIELD_ROWS and GYRO_YAW:
                r_nb = self._gyro_yaw(r_nb, gyro_yaw)
            self._use(t_s, y, regressors(throttle_01, mot), r_nb, field_ref_n_mgauss)
            return
        att, thr = self._att_hist, self._thr_hist
        t_r = t_s if r_t_s is None else r_t_s
        t_thr = t_s if throttle_t_s is None else throttle_t_s
        if not att or t_r > att[-1][0]:
            att.append((t_r, r_nb))
        if not thr or t_thr > thr[-1][0]:
            thr.append((t_thr, throttle_01))
        for h in (att, thr):
            while len(h) > 2 and h[1][0] < t_s - 2.0 * MAX_PAIR_S:
                h.popleft()
        self._pending.append((t_s, y, mot, field_ref_n_mgauss, gyro_yaw))
        self._drain_pending()

    def _drain_pending(self) -> None:
        """Use every waiting sample whose time the attitude and the throttle have both passed."""
        att, thr = self._att_hist, self._thr_hist
        while self._pending:
            tp, yp, mot, ref, gy = self._pending[0]
            reached = min(att[-1][0], thr[-1][0])
            if tp > reached and tp - reached <= MAX_PAIR_S:
                return  # wait for the next ones
            self._pending.popleft()
            if tp > reached:
                continue  # a source stopped: this one will not be matched
            r_at = _interpolate_rotation(att, tp)
            thr_at = _interpolate_scalar(thr, tp)
            if r_at is not None and thr_at is not None:
                if self.mode == "relative" and WINDOW_FIELD_ROWS and GYRO_YAW:
                    # the gyro's yaw came with the field (the same RAW_IMU): the attitude now matches its time
                    r_at = self._gyro_yaw(r_at, gy, matched=True)
                self._use(tp, yp, regressors(thr_at, mot), r_at, ref)

    def _use(self, t_s: float, y: F64, x: F64, r_nb: F64, field_ref_n_mgauss: F64 | None) -> None:
        """One sample with its attitude and regressors at its own time: absolute rows, or a relative pair."""
        assert self.est is not None
        if self.mode == "absolute":
            assert field_ref_n_mgauss is not None
            self._track_yaw(r_nb)
            rows, z = absolute_rows(r_nb.T @ field_ref_n_mgauss, y, x)
            # the reference's own yaw error (its compass's calibration): one value per window, prior 2 deg
            cols = reference_yaw_error_rows(r_nb, field_ref_n_mgauss)
            key = (self._epoch, math.floor(t_s / ROTATION_WINDOW_S))
            self.est.add(rows, z, float(x[0]), cols, key, prior_sd=REFERENCE_YAW_PRIOR_RAD)
            self.n_rows += 1
            return
        if WINDOW_FIELD_ROWS:
            if x[0] > 0.0 or not WINDOW_ROWS_MOTORS_ONLY:
                self._window_row(t_s, r_nb, y, x)
            else:
                self.n_motors_off += 1
            return
        if NORM_ROWS and self.applied:
            self.est.add_norm(y, x)
        self._pair(t_s, r_nb, y, x)

    def _gyro_yaw(self, r_nb: F64, gyro_yaw: GyroYaw | None, matched: bool = False) -> F64:
        """The autopilot's attitude with its yaw replaced by the raw gyro's (``AttitudeStage``: the Euler yaw
        rate from the raw gyro and the autopilot's roll and pitch, integrated at the IMU's rate), offset to
        the autopilot's yaw where its chain starts. The autopilot's yaw follows the compass being corrected;
        the gyro's does not, and drifts only by its bias: a yaw rate per GYRO_WINDOW_S window (the
        window-field rows' nuisance). Without a gyro yaw, ``R_nb`` as it is (the 2 s windows)."""
        if gyro_yaw is None:
            if self._gy_on:
                self._gy_on = False
                self._prev = None  # a new window sequence
            return r_nb
        epoch, yaw_g = gyro_yaw.epoch, gyro_yaw.yaw_rad
        yaw_ap = math.atan2(float(r_nb[1, 0]), float(r_nb[0, 0]))
        if not self._gy_on or epoch != self._gy_epoch:
            self._gy_on, self._gy_epoch = True, epoch
            self._gy_offset = yaw_ap - yaw_g
            self._prev = None  # a window never spans a restart of the chain
        a = yaw_g + self._gy_offset - yaw_ap
        c, s = math.cos(a), math.sin(a)
        # the autopilot's yaw minus this one (AP_YAW_TILT), and the acceleration in this yaw's frame
        a_att = a + gyro_yaw.att_lead_rad if AP_YAW_ATT_LEAD and not matched else a
        self._ap_yaw_dev = -((a_att + math.pi) % (2.0 * math.pi) - math.pi)
        an, ae = gyro_yaw.accel_h_m_s2
        co, so = math.cos(self._gy_offset), math.sin(self._gy_offset)
        self._accel_h = (co * an - so * ae, so * an + co * ae)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ r_nb

    def _window_row(self, t_s: float, r_nb: F64, y: F64, x: F64) -> None:
        """One sample against its window's Earth field (``window_field_rows``), with the window's
        horizontal field and the rotation source's yaw rate as the window's nuisance; with TILT_CONDITION
        the same sample into the tilt model's estimator too."""
        assert self.est is not None
        self._track_yaw(r_nb)
        if self._prev is None:  # reset_pairs(): a window never spans a rotation-source restart
            self._epoch += 1
        self._prev = (t_s, r_nb, y, x)
        w_s = GYRO_WINDOW_S if self._gy_on else ROTATION_WINDOW_S
        win = math.floor(t_s / w_s)
        tau = t_s - (win + 0.5) * w_s
        key = (self._epoch, win)
        relin = RELINEARISE_WINDOW and not self._gy_on and self._slow_link
        if relin and key != self._rl_key:
            self._relinearise_window()
            self._rl_key = key
        gated = self.est.n_gated
        self._win_field, w = self._add_window_row(
            self.est, self._win_field, t_s, key, tau, r_nb, y, x, AP_YAW_TILT, relin
        )
        # the tilt model's estimator takes the samples with a raw gyro's yaw (a compass marked external never
        # has one: no cost) that the ordinary one's gate passed (the same glitches). Only those: its windows
        # carry one more nuisance column, and a window never mixes the two
        if self._gy_on and self.est_tilt is not None:
            self.est.condition_theta_on(self.est_tilt)
        if self._gy_on and self.est_tilt is not None and self.est.n_gated == gated:
            self._win_field_tilt, _ = self._add_window_row(
                self.est_tilt, self._win_field_tilt, t_s, key, tau, r_nb, y, x, True, False, w
            )
        self.n_rows += 1

    def _add_window_row(
        self,
        est: InflightEstimator,
        win_field: F64 | None,
        t_s: float,
        key: tuple[int, int],
        tau: float,
        r_nb: F64,
        y: F64,
        x: F64,
        tilt_model: bool,
        relin: bool,
        like: WindowFieldRows | None = None,
    ) -> tuple[F64 | None, WindowFieldRows]:
        """One sample's window-field rows into ``est`` (the tilt model's when ``tilt_model``); returns the
        window field the yaw-rate column was written about (kept for the next window's first samples) and
        the rows (``like``: this sample's rows for the other estimator, whose columns but the soft-iron
        ones they share)."""
        w = window_field_rows(r_nb, y, x, est.uncalibrated(y, x), like)
        batch_windows = max(1, round(VIF_BATCH_S / (GYRO_WINDOW_S if self._gy_on else ROTATION_WINDOW_S)))
        # the yaw-rate column about the window's own field (its horizontal part as estimated so far: an
        # autopilot yaw following a compass 15 deg off puts it 15 deg from the WMM's)
        e_w = est.window_nuisance(key)
        if e_w is not None:
            win_field = np.array([e_w[0], e_w[1], est.common_estimate])
        h_w = est.field_ned_mgauss if win_field is None else win_field
        ap_yaw = tilt_model and self._gy_on and AP_YAW_NUISANCE
        z = w.z
        if tilt_model and self._gy_on:
            psi, vh = self._ap_yaw_tilt(est, t_s, key, h_w)
            # the tilt's column R^T (v x h) last: the window's yaw rate tilts it too (its column takes it
            # times tau); the right-hand side with the tilt removed; with AP_YAW_NUISANCE the column stays,
            # for what the line fit leaves of the gyro yaw's error, one per window
            nuis = window_nuisance_cols(r_nb, h_w, tau, TILT_PRIOR_RAD > 0.0, vh)
            z = z - psi * nuis[:, -1]
            if not AP_YAW_NUISANCE:
                nuis = nuis[:, :-1]
        else:
            nuis = window_nuisance_cols(r_nb, h_w, tau, TILT_PRIOR_RAD > 0.0)
        gated = est.n_gated
        est.add(w.rows, z, float(x[0]), nuis, key, w.common, gate=est is not self.est_tilt,
                prior_sd=_window_prior_sd(ap_yaw), batch_windows=batch_windows)  # fmt: skip
        if relin and est.n_gated == gated:
            self._rl_rows.append((w.rows, z, w.field_cols, r_nb, tau, w.common))
        return win_field, w

    def _relinearise_window(self) -> None:
        """The window closing: its rows' yaw-rate and tilt columns written again about the window's final
        field estimate (RELINEARISE_WINDOW). Each row's column was written about the field as estimated when
        it came, from the window's first samples only (4-8 of them at 2-4 Hz): a direction error there gives
        the rate column a share along the field, which then takes up throttle-driven changes of the field's
        size (docs/inflight.md, sixth pass)."""
        assert self.est is not None
        rows, self._rl_rows = self._rl_rows, []
        if not rows or self._rl_key is None:
            return
        e_w = self.est.window_nuisance(self._rl_key)
        if e_w is None:
            return
        h_fin = np.array([e_w[0], e_w[1], self.est.common_estimate])
        self.est.refill_open_window(
            [
                (r, z, window_nuisance_cols(rn, h_fin, tau, TILT_PRIOR_RAD > 0.0), com)
                for r, z, _fc, rn, tau, com in rows
            ]
        )

    def _ap_yaw_tilt(
        self, est: InflightEstimator, t_s: float, key: tuple[int, int], h_w: F64
    ) -> tuple[float, tuple[float, float, float]]:
        """The autopilot's tilt error that its own yaw error makes (AP_YAW_TILT). It subtracts the GPS
        acceleration ``a`` from the specific force with its own yaw, so a yaw error ``psi`` leaves a
        horizontal ``-psi a`` that it takes for gravity: its tilt is off by the rotation ``-psi a / g`` (NED,
        horizontal; along ``a``, not across it: its attitude error is a rotation by ``psi`` about the
        specific force, the one direction its accelerometer cannot see). ``psi`` = the autopilot's yaw minus
        the gyro's (known) + the gyro yaw's own error, which the windows' fields show: their direction
        against the WMM's, a straight line in time over the gyro chain (its bias) fitted to the closed
        windows (``_frame_at``). Returns ``psi`` and ``v x h`` (NED, ``v = -a / g``): the tilt's column per
        radian of yaw error is R^T (v x h) (``window_nuisance_cols``), the right-hand side has ``psi`` times
        it removed. ``est``: the estimator the rows go to (its windows' fields)."""
        if key != self._ap_key:
            if self._ap_key is not None:
                self._frame_close(est, self._ap_key)
            self._ap_key = key
        psi = (self._ap_yaw_dev + self._frame_at(est, t_s, h_w) + math.pi) % (2.0 * math.pi) - math.pi
        v1, v2 = -self._accel_h[0] / STANDARD_GRAVITY_M_S2, -self._accel_h[1] / STANDARD_GRAVITY_M_S2
        return psi, cross((v1, v2, 0.0), vec3(h_w))

    @staticmethod
    def _frame_of(est: InflightEstimator, h: F64) -> float:
        ref = est.field_ned_mgauss
        return math.atan2(float(h[1]), float(h[0])) - math.atan2(float(ref[1]), float(ref[0]))

    def _frame_close(self, est: InflightEstimator, key: tuple[int, int]) -> None:
        """A window closed: its field direction joins the line fit of the gyro frame's error."""
        e_w = est.window_nuisance(key)
        if e_w is None or key[0] != self._fit_epoch:
            if key[0] != self._fit_epoch:
                self._fit_epoch, self._fit = key[0], np.zeros(5)
            if e_w is None:
                return
        t = (key[1] + 0.5) * GYRO_WINDOW_S
        f = self._frame_of(est, np.asarray(e_w[:2]))
        if self._fit[0] > 0.0:  # unwrap against the line so far
            f = self._fit_value(t) + (f - self._fit_value(t) + math.pi) % (2.0 * math.pi) - math.pi
        self._fit += np.array([1.0, t, t * t, f, t * f])

    def _fit_value(self, t: float) -> float:
        n, st, stt, sf, stf = self._fit
        den = n * stt - st * st
        if n < 3 or abs(den) < 1e-9:
            return float(sf / n)
        b = (n * stf - st * sf) / den
        return float((sf - b * st) / n + b * t)

    def _frame_at(self, est: InflightEstimator, t_s: float, h_w: F64) -> float:
        if self._fit[0] < 3 or self._ap_key is None or self._ap_key[0] != self._fit_epoch:
            return self._frame_of(est, h_w)
        return self._fit_value(t_s)

    def _pair(self, t_s: float, r_rel_nb: F64, y: F64, x: F64) -> None:
        """Pair this sample (rotation-source attitude ``r_rel_nb`` at its time) with an older one."""
        self._track_yaw(r_rel_nb)
        hist = self._hist
        if self._prev is None:  # reset_pairs() was called: nothing before this sample pairs with it
            hist.clear()
            self._epoch += 1
        self._prev = (t_s, r_rel_nb, y, x)
        while hist and t_s - hist[0][0] > MAX_PAIR_S:
            hist.popleft()
        prev = None
        while len(hist) > 1 and t_s - hist[1][0] >= PAIR_BASELINE_S:
            hist.popleft()  # the newest sample at least PAIR_BASELINE_S old is the partner
        if hist and 0.0 < t_s - hist[0][0] <= MAX_PAIR_S:
            prev = hist[0]
        hist.append(self._prev)
        if prev is not None:
            self._add_pair(prev, t_s, r_rel_nb, y, x)

    def _add_pair(self, prev: tuple[float, F64, F64, F64], t_s: float, r_nb: F64, y: F64, x: F64) -> None:
        assert self.est is not None
        q_b1b0 = r_nb.T @ prev[1]
        v0, v1 = self.est.uncalibrated(prev[2], prev[3]), self.est.uncalibrated(y, x)
        rows, z = relative_rows(q_b1b0, prev[2], y, prev[3], x, v0, v1)
        # the rotation-source's yaw-rate error about the Earth's vertical (R_nb^T e_3 in body axes), one
        # value per window
        nuis = rotation_error_rows(q_b1b0, v0, t_s - prev[0]) @ r_nb[2, :].reshape(3, 1)
        self.est.add(rows, z, float(x[0]), nuis, (self._epoch, math.floor(t_s / ROTATION_WINDOW_S)))
        self.n_rows += 1

    # ---------------------------------------------------------------------------------------- applying

    def candidate(self) -> tuple[tuple[float, ...], tuple[float, float, float]] | None:
        """The latest solution's L, d (12 floats) and theta while it is not applied (None: no solution yet,
        or applied): what the self-check judges in the shadow before the stage applies it."""
        if self.applied or self.solution is None or not self._coeffs:
            return None
        return self._coeffs, self._theta3

    def output(
        self,
        t_s: float,
        field_mgauss: tuple[float, float, float],
        throttle_01: float,
        motors_01: tuple[float, ...],
    ) -> InflightOutput | None:
        """The correction for this sample, or None while the estimate is not good enough to apply."""
        est = self.est
        state = "uncorrected"
        out: InflightOutput | None = None
        if est is not None and (est.n >= 10 or self.warm_started):
            # re-solved at most every SOLVE_PERIOD_S of message time (a few 30x30 factorisations), whatever
            # the magnetometer rate; the rows are accumulated at every sample
            sol = self.solution
            if sol is None or self._solved_t is None or not 0.0 <= t_s - self._solved_t < SOLVE_PERIOD_S:
                sol = est.solve()
                self.solution = sol
                self._solved_t = t_s
                # the floats the per-sample path needs, once per solution
                self._coeffs = (*np.ravel(sol.calib_l).tolist(), *np.ravel(sol.calib_d).tolist())
                th = sol.theta_mgauss.tolist()
                self._theta3 = (th[0], th[1], th[2])
            state = "learning"
            mot = motors_01 if self.n_motors > 0 and len(motors_01) == self.n_motors else None
            d2 = throttle_01 * throttle_01
            t0, t1, t2 = self._theta3
            bias3 = (t0 * d2, t1 * d2, t2 * d2)  # eq. (11)
            if mot is not None:
                x = regressors(throttle_01, mot)
                b = sol.theta_mgauss * x[0] + sol.motor_theta_mgauss.T @ x[1:]
                bias3 = (float(b[0]), float(b[1]), float(b[2]))
            if not self.applied:
                bias = np.asarray(bias3)
                y = np.asarray(field_mgauss, dtype=float)
                corrected = sol.calib_l @ y - sol.calib_d - bias
                change = _horizontal_angle_deg(corrected, y)
                sig = sol.heading_sigma_deg
                if self.mode == "absolute":  # the split-half term reported, not decided on (log171's causal)
                    sig = math.sqrt(max(sig * sig - sol.heading_split_deg**2, 0.0))
                ok = sig < max(self.params.heading_ok_deg, change / APPLY_Z)
                # the relative form tells the hard iron from the Earth field only by rotation: below a
                # quarter turn its statistical sigma hides the misalignment and gyro errors it cannot model
                # (the diagnosis's gate uses the same span)
                turned = self.mode == "absolute" or self.yaw_span_deg >= MIN_RELATIVE_YAW_SPAN_DEG
                strength = math.sqrt(float(corrected @ corrected))
                self.corrected_field_mgauss = strength
                lo, hi = CORRECTED_FIELD_RANGE_MGAUSS
                earthly = lo <= strength <= hi
                if ok and turned and earthly and sig < MAX_APPLY_HEADING_SIGMA_DEG and self.sigma_checked:
                    self.applied = True
                    self.first_applied_t = t_s
            if self.applied:
                state = "corrected"
                out = InflightOutput(
                    coeffs=self._coeffs,
                    theta_mgauss=self._theta3,
                    bias_mgauss=bias3,
                    converged=sol.heading_sigma_deg < self.params.heading_converged_deg,
                    warm_started=self.warm_started,
                    relative=self.mode == "relative",
                    heading_sigma_deg=sol.heading_sigma_deg,
                )
        self.account(t_s, state)
        return out

    def account(self, t_s: float, state: str) -> None:
        """The time since the previous sample (up to 5 s) spent in ``state`` (one of STATES)."""
        if self._last_t is not None and 0.0 < t_s - self._last_t <= 5.0:
            self.time_s[state] += t_s - self._last_t
        self._last_t = t_s

    def final_state(self) -> str:
        """The state of a sample with the final estimate held fixed (the two-pass replay's second pass)."""
        if self.est is not None:
            self.est.sync_theta_from()  # the final estimate takes the tilt model's final theta
        if self.applied and self.solution is not None:
            return "corrected"
        est = self.est
        return "learning" if est is not None and (est.n >= 10 or self.warm_started) else "uncorrected"

    def restart_accounts(self) -> None:
        """Time in each state counted again from zero (the second pass of a two-pass replay)."""
        self.time_s = dict.fromkeys(STATES, 0.0)
        self._last_t = None

    def state(self) -> dict[str, object] | None:
        """What the state store keeps to start the next run from (None before any estimate)."""
        if self.est is None or (self.est.n == 0 and not self.warm_started):
            return None
        self.est.sync_theta_from()
        mean, sd = self.est.state()
        return {
            "form": self.mode,
            "n_motors": self.n_motors,
            "mean": mean.tolist(),
            "sd": sd.tolist(),
            "applied": self.applied,
        }

    @property
    def sigma_checked(self) -> bool:
        """The heading sigma has been checked on data the estimate's other half did not use (both halves of
        ``InflightEstimator.split_heading_deg`` hold data): before that, a bias that leaves no residual
        (a short flight's, docs/inflight.md "Short flights") cannot show in it. A run started from a stored
        state was checked by the run that stored it."""
        return self.warm_started or (self.est is not None and self.est.split_checked)

    @property
    def yaw_span_deg(self) -> float:
        """Heading span covered by the samples used so far (deg, unwrapped)."""
        return math.degrees(self.yaw_max - self.yaw_min) if self.yaw_max > self.yaw_min else 0.0

    # ----------------------------------------------------------------------------------------- summary

    def why_not(self) -> str:
        """Why the estimate is not applied (for the summary), from what the data held."""
        est = self.est
        if est is None or (self.n_rows == 0 and not self.warm_started):
            if self.mode == "absolute":
                return "no usable attitude with the motors running (absolute form)"
            if self.n_motors_off > 0:
                return "the motors never ran (the relative form learns from samples with the motors running)"
            return "no rotation source (no gyro or attitude stream) for the relative form"
        if est.n < 10 and not self.warm_started:
            return f"too few usable samples ({est.n})"
        span = math.degrees(self.yaw_max - self.yaw_min) if self.yaw_max > self.yaw_min else 0.0
        parts = []
        # std(delta^2) below 0.02: theta's sigma ~ noise / (std sqrt(N)) stays above ~8 mgauss even with 1000
        # samples of 5 mgauss noise, a tenth of Table II's theta: nothing to claim
        if est.throttle2_std < 0.02:
            parts.append(f"throttle^2 hardly varies (std {est.throttle2_std:.3f})")
        if span < MIN_RELATIVE_YAW_SPAN_DEG:
            parts.append(f"yaw span only {span:.0f} deg")
        if not self.sigma_checked:
            parts.append(
                f"not yet checked on a second stretch of data (halves alternate every {VIF_BATCH_S:.0f} s)"
            )
        strength = self.corrected_field_mgauss
        lo, hi = CORRECTED_FIELD_RANGE_MGAUSS
        if strength is not None and not lo <= strength <= hi:
            parts.append(
                f"the corrected field is {strength:.0f} mgauss, outside Earth's {EARTH_MIN_MGAUSS:.0f}-"
                f"{EARTH_MAX_MGAUSS:.0f} widened by +-35 % (a stuck or dead compass?)"
            )
        sol = self.solution
        if sol is not None:
            parts.append(f"heading uncertainty {sol.heading_sigma_deg:.1f} deg")
        return "not observable: " + ", ".join(parts)

    def summary(self) -> dict[str, object]:
        sol = self.solution
        est = self.est
        span = math.degrees(self.yaw_max - self.yaw_min) if self.yaw_max > self.yaw_min else 0.0
        return {
            "form": self.mode,
            "form_why": self.why,
            # a compass mounted rotated about body z: the relative form cannot see it (its yaw reference is
            # this compass; the rotation looks like a declination error), so it is in neither the heading
            # nor its sigma; the absolute form sees it against the reference's yaw (docs/inflight.md, tenth
            # pass)
            "mount_yaw_observable": self.mode != "relative",
            "calibrated_by_autopilot": self.calibrated_by_autopilot,
            "applied": self.applied,
            "started_from_stored_state": self.warm_started,
            "applied_from_t_s": self.first_applied_t,
            "corrected_field_mgauss": self.corrected_field_mgauss,
            "why_not_applied": None if self.applied else self.why_not(),
            "samples_used": 0 if est is None else est.n,
            "samples_gated": 0 if est is None else est.n_gated,
            "per_motor": self.n_motors > 0,
            "throttle2_std": 0.0 if est is None else est.throttle2_std,
            "yaw_span_deg": span,
            "theta_sigma_mgauss": None if sol is None else sol.theta_sigma_mgauss.tolist(),
            "heading_sigma_deg": None if sol is None else sol.heading_sigma_deg,
            "heading_model_deg": None if sol is None else sol.heading_model_deg,
            "heading_split_deg": None if sol is None else sol.heading_split_deg,
            "residual_rms_mgauss": None if sol is None else sol.residual_rms_mgauss,
            "variance_inflation": None if sol is None else sol.variance_inflation,
            "motor_theta_mgauss": None
            if sol is None or self.n_motors == 0
            else sol.motor_theta_mgauss.tolist(),
            "time_s": dict(self.time_s),
        }


_PRIOR_SD_CACHE: dict[tuple[float, ...], F64] = {}


def _window_prior_sd(ap_yaw: bool) -> F64:
    """The window-field rows' nuisance prior standard deviations: the window's horizontal field, its yaw
    rate, with TILT_PRIOR_RAD its tilt about north and east, with ``ap_yaw`` the tilt-from-yaw nuisance
    (AP_YAW_PRIOR_RAD). One read-only array per set of values (built once, not per row)."""
    sd: tuple[float, ...] = (WINDOW_FIELD_PRIOR_MGAUSS, WINDOW_FIELD_PRIOR_MGAUSS, NUISANCE_PRIOR_RAD_S)
    if TILT_PRIOR_RAD > 0.0:
        sd += (TILT_PRIOR_RAD, TILT_PRIOR_RAD)
    if ap_yaw:
        sd += (AP_YAW_PRIOR_RAD,)
    arr = _PRIOR_SD_CACHE.get(sd)
    if arr is None:
        arr = _PRIOR_SD_CACHE[sd] = np.array(sd)
        arr.flags.writeable = False
    return arr


def _interpolate_rotation(att: deque[tuple[float, F64]], t_s: float) -> F64 | None:
    """R_nb at ``t_s`` on the geodesic between the source samples around it (None: outside them, or they
    are more than MAX_PAIR_S apart)."""
    if att and att[-1][0] == t_s:
        return att[-1][1]
    for (t1, r1), (t0, r0) in itertools.pairwise(reversed(att)):  # newest first: the match is near the end
        if t0 <= t_s <= t1:
            if t1 - t0 > MAX_PAIR_S:
                return None
            if t1 == t0:
                return r1
            step = so3_log(r0.T @ r1) * ((t_s - t0) / (t1 - t0))
            return np.asarray(r0 @ so3_exp(step), dtype=np.float64)
    return None


def _interpolate_scalar(hist: deque[tuple[float, float]], t_s: float) -> float | None:
    """The value at ``t_s``, linear between the samples around it (None: outside them, or they are more
    than MAX_PAIR_S apart)."""
    if hist and hist[-1][0] == t_s:
        return hist[-1][1]
    for (t1, v1), (t0, v0) in itertools.pairwise(reversed(hist)):
        if t0 <= t_s <= t1:
            if t1 - t0 > MAX_PAIR_S:
                return None
            return v1 if t1 == t0 else v0 + (v1 - v0) * (t_s - t0) / (t1 - t0)
    return None


def _horizontal_angle_deg(a: F64, b: F64) -> float:
    """Angle between the body-horizontal parts of two field vectors (deg): the heading change a correction
    makes when the vehicle is level (an upper bound's worth of its effect elsewhere)."""
    ang = math.atan2(float(a[1]), float(a[0])) - math.atan2(float(b[1]), float(b[0]))
    return abs(math.degrees((ang + math.pi) % (2.0 * math.pi) - math.pi))
