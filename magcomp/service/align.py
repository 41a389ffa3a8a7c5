"""Stage 1, align: input gates, message-time checks and the throttle at a magnetometer sample.

Every ``dt`` comes from the messages' own timestamps (never arrival time). A sample that goes back in
time a little is skipped; one that goes back by more than ``[input] time_reset_s`` is a clock reset
(filters restart). A gap (an interval above GAP_FACTOR times the compass's usual one) restarts the filters
too; a shorter interval with samples missing in it (``core.observer.samples_missing``) only makes the observer
skip it (``MagRecord.obs_skip``). The throttle is aligned two ways (see :mod:`magcomp.service.pipeline`):
the latest one for the published heading, and the one interpolated at the sample's own time for the
observer (:meth:`ThrottleTrack.at`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from magcomp.adapters.config import Config
from magcomp.core.observer import samples_missing
from magcomp.core.types import FLAG_INPUTS_STALE, FLAG_NO_THROTTLE, LogData, MagSample, Series, ThrottleSample
from magcomp.service.record import Float3, MagRecord

#: a magnetometer interval above this many times the compass's usual interval (and above [observer]
#: dt_max_s) is a gap: counted, flagged and the observer reset. A 1 Hz telemetry magnetometer is not a
#: gap on every sample.
GAP_FACTOR = 5.0
#: message-time seconds without any throttle sample before the "no throttle" warning
NO_THROTTLE_WARN_S = 2.0
#: Input gate on the magnetometer: a change of any axis between two samples of one compass larger than
#: this is not a field the vehicle can see (rotation at the gyro's full range and a full throttle step
#: included): the largest step in the 8 simulated scenarios is 88 mgauss, on log171 before its crash
#: 230 mgauss. Such a sample (a corrupt value) and the one after it are dropped (counts["mag_jumps"]).
MAG_JUMP_MGAUSS = 500.0
#: Euler angles no attitude has (roll and yaw in [-pi, pi] or yaw in [0, 2 pi], pitch in [-pi/2, pi/2]),
#: with a margin for rounding: an attitude sample beyond them is damaged (counts["implausible"])
ANGLE_MARGIN_RAD = 1e-3
ROLL_MAX_RAD = math.pi + ANGLE_MARGIN_RAD
PITCH_MAX_RAD = math.pi / 2 + ANGLE_MARGIN_RAD
YAW_MAX_RAD = 2 * math.pi + ANGLE_MARGIN_RAD


def gate_log_inputs(log: LogData, saturation_mgauss: float) -> dict[str, int]:
    """The magnetometer and attitude columns of a whole log (``fit``, ``diagnose``) through the gates the
    pipeline applies to a replay (:meth:`AlignStage.admit` / :meth:`AlignStage.begin`,
    ``AttitudeStage.on_attitude``): saturated, non-finite and jump
    magnetometer samples and impossible attitudes dropped in place; returns what was dropped
    (``saturated``, ``mag_jumps``, ``implausible``)."""
    from magcomp.core.plausible import mag_outliers

    out = {"saturated": 0, "mag_jumps": 0, "implausible": 0}
    for index, series in list(log.mag.items()):
        if len(series) == 0:
            continue
        saturated, jump = mag_outliers(series.values, saturation_mgauss, MAG_JUMP_MGAUSS)
        bad = saturated | jump
        if bad.any():
            out["saturated"] += int(saturated.sum())
            out["mag_jumps"] += int(jump.sum())
            log.mag[index] = Series(series.t_s[~bad], series.values[~bad])
    att = log.attitude_rad
    if len(att) and att.values.ndim == 2 and att.values.shape[1] >= 2:
        with np.errstate(invalid="ignore"):
            ok = (np.abs(att.values[:, 0]) <= ROLL_MAX_RAD) & (np.abs(att.values[:, 1]) <= PITCH_MAX_RAD)
        if not ok.all():
            out["implausible"] += int((~ok).sum())
            log.attitude_rad = Series(att.t_s[ok], att.values[ok])
    return out


#: verdicts of :func:`check_time`
TIME_OK, TIME_SKIP, TIME_RESET = 0, 1, 2

Counts = dict[str, int]
TextSink = Callable[[float, str, bool], None]


def check_time(
    last: float | None, t: float, reset_s: float, counts: Counts, allow_equal: bool = False
) -> int:
    """TIME_OK: fine; TIME_SKIP: time went backwards a little; TIME_RESET: backwards by more than
    ``reset_s`` (a clock reset). Counts the last two."""
    if last is None or t > last or (allow_equal and t == last):
        return TIME_OK
    if last - t > reset_s:
        counts["clock_resets"] += 1
        return TIME_RESET
    counts["time_backwards"] += 1
    return TIME_SKIP


@dataclass(slots=True)
class CompassClock:
    """The align stage's memory of one compass."""

    last_t: float | None = None
    #: the previous raw field (the jump gate)
    prev_raw: Float3 | None = None
    #: usual magnetometer interval (s)
    dt_nominal: float | None = None
    #: magnetometer samples accepted (the clock of the refined-fit adoption)
    n_mag: int = 0


class ThrottleTrack:
    """The last two throttle samples (and the motor outputs of the last), on message time."""

    def __init__(self, cfg: Config, counts: Counts) -> None:
        self.counts = counts
        self.enabled = cfg.input.throttle_source != "none"
        self._reset_s = cfg.input.time_reset_s
        self._max_jump = cfg.observer.max_throttle_jump_01
        self._at_rest = cfg.calibration.max_throttle_01
        self.t: float | None = None
        self.value = 0.0
        self.prev_t: float | None = None
        self.prev = 0.0
        self.motors: tuple[float, ...] = ()
        #: message time the throttle rose above the calibration's at-rest limit (None: at rest)
        self.motors_on_t: float | None = None

    def on_sample(self, s: ThrottleSample) -> bool:
        """Take one throttle sample; False when it was not used (disabled, not finite, out of order)."""
        if not self.enabled:
            return False
        thr = s.throttle_01
        if not math.isfinite(thr) or not math.isfinite(s.t_s):
            self.counts["non_finite"] += 1
            return False
        if check_time(self.t, s.t_s, self._reset_s, self.counts, allow_equal=True) == TIME_SKIP:
            return False
        self.prev_t, self.prev = self.t, self.value
        self.t = s.t_s
        self.value = min(max(thr, 0.0), 1.0)
        self.motors = s.motors_01
        if self.value > self._at_rest:
            if self.motors_on_t is None:
                self.motors_on_t = s.t_s
        else:
            self.motors_on_t = None
        return True

    def forget(self) -> None:
        """The autopilot rebooted: no interpolation across the boots."""
        self.t = self.prev_t = None

    def at(self, t: float) -> float | None:
        """Throttle at message time ``t``: linear between the two samples around it, else the nearest.
        None when ``t`` lies strictly between two throttle samples that differ by more than
        ``[observer] max_throttle_jump_01`` (a step whose instant the throttle stream does not resolve)."""
        t1, pt = self.t, self.prev_t
        if t1 is None or t >= t1 or pt is None or pt >= t1:
            return self.value
        if t <= pt:
            return self.prev
        thr1, thr0 = self.value, self.prev
        if abs(thr1 - thr0) > self._max_jump:
            return None
        return thr0 + (t - pt) / (t1 - pt) * (thr1 - thr0)


class AlignStage:
    """Gates a magnetometer sample, checks its time against its compass's clock and attaches the
    throttle: the start of a :class:`MagRecord`."""

    def __init__(self, cfg: Config, counts: Counts, text: TextSink) -> None:
        self.counts = counts
        self._text = text
        self.throttle = ThrottleTrack(cfg, counts)
        self._compasses = set(cfg.input.compasses)
        self._mag_sat = cfg.input.saturation_mgauss
        self._stale_s = cfg.input.stale_s
        self._reset_s = cfg.input.time_reset_s
        self._dt_min = cfg.observer.dt_min_s
        self._dt_max = cfg.observer.dt_max_s
        self._first_mag_t: float | None = None
        self._warned_no_throttle = False

    def admit(self, mag_index: int, t: float, vx: float, vy: float, vz: float) -> bool:
        """Counts the sample; False for a compass not configured, a non-finite or a saturated sample."""
        self.counts["mag"] += 1
        if self._compasses and mag_index not in self._compasses:
            return False
        if not (math.isfinite(t) and math.isfinite(vx) and math.isfinite(vy) and math.isfinite(vz)):
            self.counts["non_finite"] += 1
            return False
        lim = self._mag_sat
        if abs(vx) >= lim or abs(vy) >= lim or abs(vz) >= lim:
            self.counts["saturated"] += 1
            return False
        return True

    def begin(self, s: MagSample, vx: float, vy: float, vz: float, clock: CompassClock) -> MagRecord | None:
        """The record of an admitted sample, or None when the jump gate or the time check drops it."""
        t = s.t_s
        pv = clock.prev_raw
        clock.prev_raw = (vx, vy, vz)
        lim = MAG_JUMP_MGAUSS  # (admitted samples are finite: the largest step above it, as max() took it)
        if pv is not None and (abs(vx - pv[0]) > lim or abs(vy - pv[1]) > lim or abs(vz - pv[2]) > lim):
            self.counts["mag_jumps"] += 1
            return None
        prev_t = clock.last_t
        verdict = check_time(prev_t, t, self._reset_s, self.counts)
        if verdict == TIME_SKIP:
            return None
        clock.n_mag += 1
        clock.last_t = t
        if self._first_mag_t is None or verdict == TIME_RESET:
            self._first_mag_t = t
        reset = obs_reset = verdict == TIME_RESET or prev_t is None  # filters restart
        obs_skip = False
        if not reset:
            assert prev_t is not None
            dt = t - prev_t
            nominal = clock.dt_nominal
            # the first interval (up to 10 s) sets the compass's usual one
            gap_s = 10.0 if nominal is None else GAP_FACTOR * nominal
            if not gap_s > self._dt_max:  # max(dt_max, gap_s), as max() picks
                gap_s = self._dt_max
            if dt > gap_s:
                self.counts["gaps"] += 1
                reset = obs_reset = True
            else:
                obs_reset = dt < self._dt_min or dt > self._dt_max
                # samples missing in the interval: the observer steps only between consecutive samples
                obs_skip = not obs_reset and samples_missing(dt, nominal)
                obs_reset = obs_reset or obs_skip
                clock.dt_nominal = dt if nominal is None else nominal + 0.05 * (dt - nominal)
        thr, thr_t = self.throttle.value, self.throttle.t
        flags = 0
        if thr_t is None:
            thr = 0.0
            flags = FLAG_NO_THROTTLE
            self._no_throttle(t)
        elif t - thr_t > self._stale_s:
            flags = FLAG_INPUTS_STALE
        return MagRecord(
            s, t, s.mag_index, (vx, vy, vz), prev_t, reset, obs_reset, thr, thr_t is not None, flags, obs_skip
        )

    def _no_throttle(self, t: float) -> None:
        self.counts["no_throttle"] += 1
        if self._warned_no_throttle:
            return
        first = self._first_mag_t if self._first_mag_t is not None else t
        if not self.throttle.enabled or t - first >= NO_THROTTLE_WARN_S:
            self._warned_no_throttle = True
            why = ("disabled in the configuration" if not self.throttle.enabled
                   else "no throttle samples, or motor outputs without pulse widths")  # fmt: skip
            self._text(t, f"no throttle source ({why}): headings are published uncorrected", True)
