"""The in-flight calibration stage of one compass: the stateful shell around :mod:`magcomp.core.inflight`.

It decides, sample by sample, which samples go to the estimator and when (the rate limit, the motor set,
the attitude source, waiting for a late attitude or throttle), re-solves it at most every ``solve_period_s``
of its configuration, and keeps the time spent in each state for the summary. The rows, the yaw frame, the
late matching and the apply decision are core's (:mod:`magcomp.core.inflight.feed`, ``.yawframe``,
``.matching``, ``.apply``). No I/O.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.config import InflightConfig
from magcomp.core.inflight import (
    VIF_BATCH_S,
    InflightEstimator,
    InflightMode,
    InflightParams,
    InflightSolution,
    regressor_values,
)
from magcomp.core.inflight.apply import (
    CORRECTED_FIELD_RANGE_MGAUSS,
    MIN_RELATIVE_YAW_SPAN_DEG,
    InflightOutput,
    YawSpan,
    apply_decision,
    bias_at,
)
from magcomp.core.inflight.feed import (
    FeedSwitches,
    WindowRowFeed,
    add_absolute_row,
)
from magcomp.core.inflight.matching import LateMatcher
from magcomp.core.inflight.yawframe import GyroYaw, GyroYawFrame, YawTurn
from magcomp.core.types import EARTH_MAX_MGAUSS, EARTH_MIN_MGAUSS

F64 = NDArray[np.float64]

#: the first pass of a two-pass replay re-solves the estimate at most this often (s of message time; the
#: live stages: ``InflightConfig.solve_period_s``, 0.5 s). Only its final estimate is published; what the
#: solutions in between steer (the rows' linearisation point, the gate, the window-field rows' blocks: the
#: samples between two solutions) moved the simulated ordinary flight's and log171's headings by under 1 %
#: and none of the corpus's two-pass figures; the ordinary flight's two-pass replay took 6.3 s of CPU
#: re-solving every 0.1 s, 3.7 s every 1 s. Every 3 s (3.4 s of CPU) rows linearised at older estimates
#: leave correlated residuals: log171 compass 0's heading sigma 0.92 -> 1.55 deg (docs/benchmarks.md)
LEARN_SOLVE_PERIOD_S = 1.0
#: and the tilt model's every this often (10 solutions: what it has been since the first pass re-solves once a
#: second; the live stages: ``InflightConfig.tilt_solve_period_s``, 1 s)
LEARN_TILT_SOLVE_PERIOD_S = 10.0


def learn_config(cfg: InflightConfig) -> InflightConfig:
    """The in-flight settings of a two-pass replay's first pass: re-solved no more often than
    LEARN_SOLVE_PERIOD_S, the tilt model no more often than LEARN_TILT_SOLVE_PERIOD_S."""
    return replace(cfg, solve_period_s=max(cfg.solve_period_s, LEARN_SOLVE_PERIOD_S),
                   tilt_solve_period_s=max(cfg.tilt_solve_period_s, LEARN_TILT_SOLVE_PERIOD_S))  # fmt: skip


_new_output = tuple.__new__

#: states a compass spends time in (summary)
STATES = ("corrected", "learning", "uncorrected")

#: what a sample waiting for its attitude and throttle carries: field, motor outputs, Earth field, gyro yaw
Field3 = F64 | tuple[float, float, float]
_Waiting = tuple[Field3, tuple[float, ...] | None, F64 | None, GyroYaw | None]


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
        switches: FeedSwitches | None = None,
    ) -> None:
        """``warm``: a stored in-flight state (form, n_motors, mean, sd) to start from; used only when its
        form is this compass's form (else the autopilot's calibration is the prior, as on a first run).
        ``switches``: which rows a sample becomes (default: :class:`FeedSwitches`' defaults)."""
        self.mag_index = mag_index
        self.cfg = cfg
        self.mode: InflightMode = mode
        self.why = why
        self.calibrated_by_autopilot = calibrated
        self.switches = switches or FeedSwitches()
        self._relative = mode == "relative"
        # the relative form's compass-free yaw (FeedSwitches.gyro_yaw), its rows with the motors running only
        self._gyro_on = self._relative and self.switches.gyro_yaw
        self._motors_only = self.switches.window_rows_motors_only
        cal = calibrated is True
        self.params = InflightParams(
            sigma_a=cfg.sigma_a_calibrated if cal else cfg.sigma_a_uncalibrated,
            sigma_d_mgauss=cfg.sigma_d_calibrated_mgauss if cal else cfg.sigma_d_uncalibrated_mgauss,
            sigma_theta_mgauss=cfg.sigma_theta_mgauss,
            heading_ok_deg=cfg.heading_ok_deg,
            heading_converged_deg=cfg.heading_converged_deg,
        )
        self.field_norm_mgauss = field_norm_mgauss
        self._est: InflightEstimator | None = None
        #: the tilt model's own estimator (FeedSwitches.tilt_condition), fed the same samples
        self.est_tilt: InflightEstimator | None = None
        self._rows: WindowRowFeed | None = None  # the relative form's window-field rows into both
        self.n_motors = -1  # decided at the first sample
        self._min_gap = 0.9 * (1.0 / cfg.max_rate_hz)  # a sample closer than this to the last one fed: out
        self._solve_period = cfg.solve_period_s
        #: the tilt model's estimator is re-solved at every this many solutions of the published one
        self._tilt_every = max(1, round(cfg.tilt_solve_period_s / cfg.solve_period_s))
        self._earth_given: object = None  # the Earth field last handed to the estimators (feed)
        self._last_fed: float | None = None
        #: a window sequence is running (False: the next sample starts one; a window never spans a gap)
        self._continuing = False
        self._slow_link = False  # the attitude is matched to the field's time (a link of 6.7 Hz or slower)
        # the compass-free yaw (FeedSwitches.gyro_yaw)
        self._frame = GyroYawFrame(self.switches.ap_yaw_att_lead)
        self._epoch = 0  # counts rotation-source restarts (a nuisance window never spans one)
        # samples waiting for the rotation source and the throttle to pass their time
        self._matcher: LateMatcher[_Waiting] = LateMatcher()
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
        self._span = YawSpan()
        self._solved_t: float | None = None
        self._coeffs: tuple[float, ...] = ()
        self._theta3 = (0.0, 0.0, 0.0)
        self.warm_started = False
        self._warm: tuple[F64, F64] | None = None
        self._warm_start(warm, mode, field_norm_mgauss)

    @property
    def est(self) -> InflightEstimator | None:
        """The estimator, with the samples held for the window-field rows in it (:meth:`flush`): whoever
        reads it sees every sample fed so far."""
        self.flush()
        return self._est

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
            self._new_estimators()
            assert self._est is not None
            if self._est.prior.mean.shape == self._warm[0].shape and np.array_equal(
                self._est.prior.mean, self._warm[0]
            ):
                self.warm_started = True
                # applied from the first sample only if the run it comes from had found it good enough
                self.applied = bool(warm.get("applied", False))
            else:
                self._est, self.n_motors, self._warm = None, -1, None
                self.est_tilt = self._rows = None

    def _new_estimators(self) -> None:
        """The estimator, and in the relative form the tilt model's (its theta the published one's) and the
        window-field rows that feed both."""
        self.est_tilt = None
        if self.mode == "relative" and self.switches.tilt_model:
            # rows only with a raw gyro's yaw: the published theta is its own until then
            self.est_tilt = InflightEstimator(
                self.mode, self.n_motors, self.params, self.field_norm_mgauss, self._warm
            )
        self._est = InflightEstimator(self.mode, self.n_motors, self.params, self.field_norm_mgauss,
                                      self._warm, self.est_tilt, self._tilt_every)  # fmt: skip
        self._earth_given = None  # the new estimators take the Earth field at the next sample
        relative = self.mode == "relative"
        self._rows = WindowRowFeed(self._est, self.est_tilt, self.switches) if relative else None

    # ------------------------------------------------------------------------------------------ feeding

    def reset_pairs(self) -> None:
        """A gap, a clock reset or a change of rotation source: the next sample starts a new window."""
        self._continuing = False
        self._matcher.clear()

    def restart(self, field_norm_mgauss: float) -> None:
        """The Earth field changed (a GPS fix after the configured fallback): absolute rows made against
        the old field are dropped."""
        self.field_norm_mgauss = field_norm_mgauss
        if self.mode == "absolute" and not self.warm_started:
            self._est = None
            self.solution = None
            self.applied = False
        self._continuing = False

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
        than the field, the sample waits for the next ones and gets both interpolated to its time
        (:class:`~magcomp.core.inflight.matching.LateMatcher`). gyro_yaw: the raw gyro's yaw at this sample
        (``AttitudeStage.gyro_yaw_at``) for the relative form's compass-free yaw (None: the rotation
        source's own yaw).
        """
        last = self._last_fed
        if last is not None and t_s - last < self._min_gap and t_s > last:
            return
        n_motors = self.n_motors
        if n_motors < 0:
            use = self.cfg.per_motor == "auto" and 2 <= len(motors_01) <= 8
            n_motors = self.n_motors = len(motors_01) if use else 0
        est = self._est
        if est is None:
            self._new_estimators()
            est = self._est
        assert est is not None
        if field_ref_n_mgauss is not None and field_ref_n_mgauss is not self._earth_given:
            # the pipeline hands the same read-only array until the Earth field changes
            self._earth_given = field_ref_n_mgauss
            est.set_earth_field(np.asarray(field_ref_n_mgauss, dtype=float))
            if self.est_tilt is not None:
                self.est_tilt.set_earth_field(est.field_ned_mgauss)
        mot = None
        if n_motors > 0:
            if len(motors_01) != n_motors:
                return  # the motor set changed: these regressors would not match
            mot = motors_01
        self._last_fed = t_s
        y = field_mgauss  # as it came: an array is made a block of samples at a time (core.inflight.feed)
        relative = self._relative
        r_nb = r_rel_nb if relative else r_abs_nb
        if r_nb is None or (not relative and field_ref_n_mgauss is None):
            if relative:
                self.reset_pairs()
            return
        self._slow_link = r_t_s is not None
        late_r = r_t_s is not None and r_t_s < t_s
        late_thr = throttle_t_s is not None and throttle_t_s < t_s
        gyro = self._gyro_on
        if not (late_r or late_thr or self._matcher.waiting):
            x = regressor_values(throttle_01, mot)
            if relative:
                self._relative_row(t_s, y, x, r_nb, gyro_yaw)
            else:
                self._use(t_s, y, x, r_nb, field_ref_n_mgauss)
            return
        t_r = t_s if r_t_s is None else r_t_s
        t_thr = t_s if throttle_t_s is None else throttle_t_s
        waiting = (y, mot, field_ref_n_mgauss, gyro_yaw)
        for tp, (yp, mp, ref, gy), r_at, thr_at in self._matcher.push(
            t_s, waiting, r_nb, t_r, throttle_01, t_thr
        ):
            # the gyro's yaw came with the field (the same RAW_IMU): the attitude now matches its time
            turn = self._gyro_yaw(r_at, gy, matched=True) if gyro else None
            self._use(tp, yp, regressor_values(thr_at, mp), r_at, ref, turn)

    def _relative_row(
        self, t_s: float, y: Field3, x: tuple[float, ...], r_nb: F64, gyro_yaw: GyroYaw | None
    ) -> None:
        """:meth:`_use` of the relative form for a sample at its own time."""
        self._window_or_off(t_s, r_nb, y, x, self._gyro_yaw(r_nb, gyro_yaw) if self._gyro_on else None)

    def _gyro_yaw(self, r_nb: F64, gyro_yaw: GyroYaw | None, matched: bool = False) -> YawTurn | None:
        """The yaw turn that gives ``r_nb`` the raw gyro's yaw (:class:`~magcomp.core.inflight.yawframe.
        GyroYawFrame`; None: no gyro yaw); a new window sequence when the gyro yaw stops or its chain
        restarts."""
        turn, restart = self._frame.turn(r_nb, gyro_yaw, matched)
        if restart:
            self._continuing = False
        return turn

    def _use(
        self,
        t_s: float,
        y: Field3,
        x: tuple[float, ...],
        r_nb: F64,
        field_ref_n_mgauss: F64 | None,
        turn: YawTurn | None = None,
    ) -> None:
        """One sample with its attitude and regressors at its own time: absolute rows, or window-field
        rows (``turn``: the yaw turn the attitude takes first, the gyro's yaw)."""
        assert self._est is not None
        if self.mode == "absolute":
            assert field_ref_n_mgauss is not None
            self._span.track(r_nb)
            add_absolute_row(self._est, t_s, self._epoch, r_nb, field_ref_n_mgauss, y, x)
            self.n_rows += 1
            return
        self._window_or_off(t_s, r_nb, y, x, turn)

    def _window_or_off(
        self, t_s: float, r_nb: F64, y: Field3, x: tuple[float, ...], turn: YawTurn | None
    ) -> None:
        """A window-field row, or with the motors off (``window_rows_motors_only``) only counted."""
        if x[0] > 0.0 or not self._motors_only:
            self._window_row(t_s, r_nb, y, x, turn)
        else:
            self.n_motors_off += 1

    def _window_row(
        self, t_s: float, r_nb: F64, y: Field3, x: tuple[float, ...], turn: YawTurn | None
    ) -> None:
        """One sample against its window's Earth field (``core.inflight.feed.WindowRowFeed``)."""
        assert self._rows is not None
        self._span.track(r_nb, turn)
        if not self._continuing:  # reset_pairs(): a window never spans a rotation-source restart
            self._epoch += 1
        self._continuing = True
        self._rows.add(t_s, self._epoch, r_nb, y, x, self._frame, self._slow_link, turn)
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
        est = self._est
        state = "uncorrected"
        out: InflightOutput | None = None
        sol = self.solution
        solved_t = self._solved_t
        due = sol is None or solved_t is None or not 0.0 <= t_s - solved_t < self._solve_period
        if due:
            self.flush()
        if est is not None and (est.n >= 10 or self.warm_started):
            # re-solved at most every solve_period_s of message time (a few 30x30 factorisations), whatever
            # the magnetometer rate; the rows go in as a block before each solution (WindowRowFeed)
            if due or sol is None:
                sol = est.solve()
                self.solution = sol
                self._solved_t = t_s
                # the floats the per-sample path needs, once per solution
                self._coeffs = (*np.ravel(sol.calib_l).tolist(), *np.ravel(sol.calib_d).tolist())
                th = sol.theta_mgauss.tolist()
                self._theta3 = (th[0], th[1], th[2])
            state = "learning"
            n_motors = self.n_motors
            mot = motors_01 if n_motors > 0 and len(motors_01) == n_motors else None
            bias3 = bias_at(sol, self._theta3, throttle_01, mot)
            if not self.applied:
                ok, self.corrected_field_mgauss = apply_decision(
                    sol, self.mode, field_mgauss, bias3, self.params.heading_ok_deg, self.yaw_span_deg,
                    self.sigma_checked,
                )  # fmt: skip
                if ok:
                    self.applied = True
                    self.first_applied_t = t_s
            if self.applied:
                state = "corrected"
                sig = sol.heading_sigma_deg
                # coeffs, theta, bias, converged, warm started, relative form, sigma (tuple.__new__: the named
                # tuple's own constructor without its keyword handling, ~0.3 us a sample less)
                out = _new_output(InflightOutput, (self._coeffs, self._theta3, bias3,
                                                   sig < self.params.heading_converged_deg, self.warm_started,
                                                   self._relative, sig))  # fmt: skip
        self.account(t_s, state)
        return out

    def flush(self) -> None:
        """The samples held for the window-field rows into the estimators (before a solution, or whatever
        reads them)."""
        if self._rows is not None and self._rows.pending:
            self._rows.flush()

    def account(self, t_s: float, state: str) -> None:
        """The time since the previous sample (up to 5 s) spent in ``state`` (one of STATES)."""
        if self._last_t is not None and 0.0 < t_s - self._last_t <= 5.0:
            self.time_s[state] += t_s - self._last_t
        self._last_t = t_s

    def final_state(self) -> str:
        """The state of a sample with the final estimate held fixed (the two-pass replay's second pass)."""
        self.flush()
        if self._est is not None:
            self._est.sync_theta_from()  # the final estimate takes the tilt model's final theta
        if self.applied and self.solution is not None:
            return "corrected"
        est = self._est
        return "learning" if est is not None and (est.n >= 10 or self.warm_started) else "uncorrected"

    def restart_accounts(self) -> None:
        """Time in each state counted again from zero (the second pass of a two-pass replay)."""
        self.time_s = dict.fromkeys(STATES, 0.0)
        self._last_t = None

    def state(self) -> dict[str, object] | None:
        """What the state store keeps to start the next run from (None before any estimate)."""
        self.flush()
        if self._est is None or (self._est.n == 0 and not self.warm_started):
            return None
        self._est.sync_theta_from()
        mean, sd = self._est.state()
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
        the estimator's split check hold data): before that, a bias that leaves no residual
        (a short flight's, docs/inflight.md "Short flights") cannot show in it. A run started from a stored
        state was checked by the run that stored it."""
        return self.warm_started or (self._est is not None and self._est.split_checked)

    @property
    def yaw_span_deg(self) -> float:
        """Heading span covered by the samples used so far (deg, unwrapped)."""
        return self._span.span_deg

    # ----------------------------------------------------------------------------------------- summary

    def why_not(self) -> str:
        """Why the estimate is not applied (for the summary), from what the data held."""
        est = self._est
        if est is None or (self.n_rows == 0 and not self.warm_started):
            if self.mode == "absolute":
                return "no usable attitude with the motors running (absolute form)"
            if self.n_motors_off > 0:
                return "the motors never ran (the relative form learns from samples with the motors running)"
            return "no rotation source (no gyro or attitude stream) for the relative form"
        if est.n < 10 and not self.warm_started:
            return f"too few usable samples ({est.n})"
        span = self._span.span_deg
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
        self.flush()
        sol = self.solution
        est = self._est
        span = self._span.span_deg
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
