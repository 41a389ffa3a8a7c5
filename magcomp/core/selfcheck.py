"""The self-check against the gyro: is a corrected heading more consistent than the autopilot's own?

Not in the paper (departure): the paper judges its correction against a motion-capture truth (Table III).
A real flight has no truth, but it has two references that no compass steers on short time scales:

* **gyro**: the yaw integrated from the gyro with the autopilot's roll and pitch (the Euler yaw rate
  ``(q sin(roll) + r cos(roll)) / cos(pitch)``). A gyro's rate bias is ~constant over seconds, so over a
  window of ``window_s`` (10 s) its integral is a constant plus a ramp of a fraction of a degree: the
  window's mean is removed and what stays of (heading - gyro yaw) is the compass's own error on time scales
  shorter than the window (the throttle-driven bias moves with every climb and turn, on those scales).
  Where the gyro comes slower than 10 Hz (1-4 Hz telemetry) its integral is poor; the autopilot's own yaw
  on the same windows takes its place (:func:`reference_yaw_rad` callers decide).
* **att**: the autopilot's fused yaw over the whole flight, its constant offset (declination, mounting)
  removed. Partly circular where that yaw comes from the compass judged.

:func:`compare` judges a candidate heading (magcomp's corrected one) against a baseline (the autopilot's
own field, tilt-compensated) on the same samples: per window the mean squared residual of each, and the
paired difference of the windows (a paired test: the windows are the independent units; a 10 s window
holds many correlated samples; the log of the ratio of their mean squares, so that the gain is judged
window by window rather than by the few windows of violent manoeuvre). The candidate *applies* only where
it is no worse than the baseline against either reference and its gain is beyond the noise (the mean over
at least ``MIN_WINDOWS`` windows above zero by the Student-t bound :func:`t_critical`) against the gyro, or
against the autopilot's yaw (where that yaw is fused from the compass judged it favours the baseline, so a
gain against it is conservative evidence). Everything else keeps the
baseline: never worse than what the autopilot already had.

Pure numpy; angles in rad unless the name says deg; times in s.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import NDArray

from magcomp.core.correction import IDENTITY_COEFFS, Correction, Float3
from magcomp.core.heading import heading_from_trig_deg
from magcomp.core.yaw_follow import YawFollow, fit_follow_gain, follows_within, window_follow_terms

F64 = NDArray[np.float64]

#: window over which a gyro's integral is a constant plus a small ramp (s). A rate bias b leaves a ramp of
#: rms b * W / sqrt(12) about the window's mean: 0.17 deg for 1e-3 rad/s (a MEMS gyro after the autopilot's
#: start-up calibration), 3.3 deg for an uncalibrated 0.02 rad/s. Shorter windows keep less of the compass's
#: error (a climb lasts seconds), longer ones more of the gyro's drift. The same 10 s as the issue's metric.
WINDOW_S = 10.0
#: a window needs this many samples for its mean to be removed with something left
MIN_PER_WINDOW = 3
#: a paired test needs an estimate of the spread between windows: at least this many windows (2 degrees of
#: freedom; with so few the Student-t bound below asks for a gain of 6 standard errors)
MIN_WINDOWS = 3
#: one-sided confidence the gain must reach: the mean paired gain over n windows must exceed the Student-t
#: quantile with n - 1 degrees of freedom in standard errors (2.0 for many windows: ~2.3 % false apply)
P_APPLY = 0.977
#: the large-sample limit of that bound (standard errors)
Z_APPLY = 2.0
#: the running check judges the correction on its latest windows only (2 min): while learning in flight the
#: correction changes with each re-solve, and the windows of an earlier, worse estimate say nothing of it
RECENT_S = 120.0
#: the running check's window (s): half the batch's, so that a live correction is judged on twice the
#: windows in the same time (its gyro ramp is half as large; the compass's errors of a climb or a turn last
#: seconds, within it)
LIVE_WINDOW_S = 5.0
#: floor on a window's mean square (rad^2): (0.5 deg)^2. A compass resolves ~1-2 mgauss of a ~200 mgauss
#: horizontal field (0.3-0.6 deg); below that two headings are the same measurement
FLOOR_RAD2 = math.radians(0.5) ** 2
#: the gyro is integrated where its samples come at least this often (s); slower (below 10 Hz), the
#: autopilot's yaw is the windowed reference. A 10 Hz stream's intervals jitter by tens of ms around 0.1 s,
#: so the cut is at one and a half of its intervals: a reference that flipped sample by sample would close
#: a window at each flip
MAX_GYRO_DT_S = 0.15
#: gaps in the gyro longer than this (s) restart its integral (a new window starts there)
MAX_GYRO_GAP_S = 0.5


#: the throttle (0..1) above which the motors count as running for the check: the corrected heading differs
#: from the autopilot's only through the bias theta * throttle^2, and an idle motor's few percent leave
#: nothing to judge
MOTORS_RUNNING_01 = 0.05
#: the check takes samples within 60 deg of roll and pitch (their cosines above this): beyond, the
#: tilt-compensated heading is dominated by the tilt's own error
MAX_TILT_COS = 0.5

def judged(throttle_01: F64 | float, cos_roll: F64 | float,
           cos_pitch: F64 | float) -> NDArray[np.bool_] | bool:  # fmt: skip
    """The samples the self-check judges (floats or arrays): the motors running (MOTORS_RUNNING_01), roll and
    pitch within MAX_TILT_COS; where the throttle is known."""
    return (throttle_01 > MOTORS_RUNNING_01) & (cos_roll > MAX_TILT_COS) & (cos_pitch > MAX_TILT_COS)


#: the largest relative increase of the rms against the autopilot's yaw still "no worse" (att_tolerance_deg)
MAX_ATT_WORSE_FRACTION = 0.1
#: the windows (s) on which the autopilot's yaw-follow gain is measured (core/yaw_follow.py): short against
#: the time constants that matter here (a window's WINDOW_S), long against a 10 Hz stream's interval
FOLLOW_WINDOW_S = 2.0


#: :func:`t_critical` for n = 2..T_CRITICAL_MAX_N windows from :data:`T_CRITICAL` (a 10 s window's check
#: over 21 min of motors running; the running check's at most 24), beyond it from scipy
T_CRITICAL_MAX_N = 128
#: the exact floats ``scipy.special.stdtrit(n - 1, P_APPLY)`` returns for n = 2..T_CRITICAL_MAX_N (printed by
#: benchmarks/t_critical_table.py; tests/unit/test_selfcheck.py compares each with scipy): importing
#: scipy.special costs 0.15-0.2 s of CPU in a fresh process, more than a replay's self-check itself
# fmt: off
T_CRITICAL = (
    13.815466337604004, 4.500100127941269, 3.2922555549226358, 2.8584802650736783, 2.639569873841992,
    2.508442332098139, 2.4213634988589128, 2.359417921489817, 2.3131330782239394, 2.2772533909124135,
    2.2486331753630813, 2.2252762475318146, 2.2058556172446533, 2.189455134588239, 2.1754221109277125,
    2.1632790698019573, 2.1526687093276093, 2.143318366605739, 2.135016377612688, 2.1275959355755325,
    2.120923814029617, 2.114892326918354, 2.109413491759891, 2.104414722704815, 2.0998356054534675,
    2.0956254498673665, 2.0917414100296607, 2.0881470240283115, 2.0848110680964798, 2.0817066489173204,
    2.078810478293018, 2.07610228883081, 2.0735643596735165, 2.071181128838005, 2.0689388742595987,
    2.0668254497471215, 2.0648300651299123, 2.062943102203982, 2.0611559598576172, 2.059460923119409,
    2.0578510519267272, 2.0563200862353774, 2.054862364737059, 2.0534727549614584, 2.052146592945404,
    2.0508796309756816, 2.0496679921726737, 2.04850813089253, 2.0473967980964702, 2.0463310109752912,
    2.0453080262313996, 2.04432531651473, 2.043380549586647, 2.042471569850375, 2.041596381940265,
    2.040753136107018, 2.0399401151737266, 2.0391557228692303, 2.038398473372064, 2.037666981920963,
    2.0369599563671223, 2.0362761895598385, 2.035614552471166, 2.034973987977268, 2.0343535052244115,
    2.033752174516494, 2.033169122668628, 2.0326035287779707, 2.0320546203687133, 2.031521669873207,
    2.031003991415489, 2.030500937867347, 2.0300118981503386, 2.029536294760138, 2.0290735814921135,
    2.028623241349319, 2.02818478461605, 2.0277577470818833, 2.02734168840266, 2.0269361905862464,
    2.0265408565921352, 2.026155309035023, 2.0257791889834715, 2.0254121548456063, 2.0250538813345957,
    2.024704058507317, 2.024362390870243, 2.0240285965471254, 2.023702406503559, 2.0233835638239244,
    2.0230718230366507, 2.0227669494840486, 2.0224687187333386, 2.0221769160257526, 2.0218913357608694,
    2.021611781013588, 2.0213380630813553, 2.0210700010594476, 2.020807421442316, 2.020550157749135,
    2.020298050171866, 2.020050945244266, 2.0198086955304015, 2.0195711593313526, 2.019338200408855,
    2.019109687724777, 2.0188854951953594, 2.0186655014592736, 2.0184495896585783, 2.018237647231759,
    2.018029565718083, 2.0178252405725363, 2.0176245709907064, 2.017427459742965, 2.0172338130174094,
    2.0170435402709948, 2.0168565540883963, 2.016672770048108, 2.0164921065953734, 2.0163144849215233,
    2.016139828849364, 2.015968064724255, 2.0157991213105535, 2.015632929693117, 2.0154694231835824,
    2.0153085372311477, 2.0151502093376124,
)
# fmt: on


@functools.lru_cache(maxsize=256)
def t_critical(n_windows: int) -> float:
    """The gain (standard errors) that ``n_windows`` paired windows must reach: the P_APPLY quantile of
    Student's t with n - 1 degrees of freedom (inf below 2 windows); scipy's own values (:data:`T_CRITICAL`)
    up to T_CRITICAL_MAX_N windows."""
    if n_windows < 2:
        return math.inf
    if n_windows <= T_CRITICAL_MAX_N:
        return T_CRITICAL[n_windows - 2]
    # scipy.special (scipy.stats would load scipy.optimize), imported at the first call beyond the table
    from scipy.special import stdtrit

    return float(stdtrit(n_windows - 1, P_APPLY))


def att_tolerance_deg(att_deg: float, n_windows: int) -> float:
    """How much larger an rms against the autopilot's yaw may come out and still be "no worse": its own
    sampling error over ``n_windows`` independent windows (an rms of n values scatters by 1/sqrt(2 n) of
    itself), not below the compass's resolution (FLOOR_RAD2's 0.5 deg), and never above a tenth of it (with
    few windows that sampling error is a third of the rms and more: a heading 30 % further from the
    autopilot's yaw is worse, whatever the window count). Where the autopilot's yaw is fused from the compass
    judged it holds part of the baseline's error, so a better candidate can come out slightly further from
    it."""
    floor = math.sqrt(FLOOR_RAD2) * 180.0 / math.pi
    return max(floor, min(att_deg / math.sqrt(2.0 * max(n_windows, 1)), MAX_ATT_WORSE_FRACTION * att_deg))


def rms_upper_deg(rms_deg: float, n_windows: int) -> float:
    """The one-sided P_APPLY upper bound of an rms measured over ``n_windows`` independent windows: an rms
    of n values scatters by 1/sqrt(2 n) of itself (as :func:`att_tolerance_deg`), taken t_critical(n)
    times (with 3 windows 2.8 times the rms, with 10 1.5 times)."""
    return rms_deg * (1.0 + t_critical(n_windows) / math.sqrt(2.0 * max(n_windows, 1)))


Estimate = tuple[tuple[float, ...], tuple[float, float, float]]


def corrected_headings_deg(raw_mgauss: F64, throttle_01: F64, tilt: F64,
                           estimates: Sequence[Estimate]) -> list[F64]:  # fmt: skip
    """The heading (deg) each of ``estimates`` gives the same samples (the field as received (n, 3), the
    throttle (n,), cos / sin of roll and pitch (n, 4)): its L and d of eq. (2) as 12 floats and its theta,
    applied as :class:`~magcomp.core.correction.Correction` applies them (eqs. (2), (11); per-motor terms,
    which sum to about zero over the motors, left out), then eq. (24) of the corrected field. All the
    estimates at once: one correction whose coefficients are columns (one row per estimate), so that each
    sample gets a float correction's arithmetic and each operation is one numpy call for all of them."""
    r = np.asarray(raw_mgauss, dtype=float)
    c = np.asarray(tilt, dtype=float)
    thr = np.asarray(throttle_01, dtype=float)
    vx, vy, vz = r[:, 0], r[:, 1], r[:, 2]
    cr, sr, cp, sp = c[:, 0], c[:, 1], c[:, 2], c[:, 3]
    coeffs = np.array([e[0] for e in estimates], dtype=float).T[:, :, None]  # (12, m, 1)
    theta = np.array([e[1] for e in estimates], dtype=float).T[:, :, None]  # (3, m, 1)
    columns = Correction(cast("tuple[float, ...]", tuple(coeffs)), cast("Float3", tuple(theta)))
    mx, my, mz = columns.apply(vx, vy, vz, thr).corrected
    return list(heading_from_trig_deg(mx, my, mz, cr, sr, cp, sp))  # eq. (24), one row per estimate


def circular_mean_rad(a_rad: F64) -> float:
    """The circular mean of angles (rad); NaN when empty."""
    a = np.asarray(a_rad, dtype=float)
    n = a.size
    if n == 0:
        return math.nan
    return math.atan2(float(np.sin(a).sum()) / n, float(np.cos(a).sum()) / n)  # the means, as np.mean


def mean_change_rad(psi_old_deg: F64, psi_new_deg: F64) -> float:
    """The circular mean (rad) of ``psi_new_deg - psi_old_deg``, headings of the same samples (deg)."""
    return circular_mean_rad(np.radians(psi_new_deg - psi_old_deg))


#: the published constant takes theta's bias out (:func:`switch_on_offset_rad`) where the throttle^2 flown
#: lately spans at least 1 / MAX_BIAS_EXTRAPOLATION of its distance from zero (5th to 95th percentile):
#: theta is measured by how the field moves with the throttle^2 flown, and its bias at that throttle is then
#: read off within twice that span of the zero-throttle calibration
MAX_BIAS_EXTRAPOLATION = 2.0


def theta_bias_measured(throttle_01: F64) -> bool:
    """The throttle flown measures theta's bias at that throttle (MAX_BIAS_EXTRAPOLATION), rather than
    extrapolating it to zero throttle from a narrow span (a hover)."""
    d2 = np.asarray(throttle_01, dtype=float) ** 2
    lo, hi = np.percentile(d2, (5.0, 95.0))
    return bool(lo <= MAX_BIAS_EXTRAPOLATION * (hi - lo))


def switch_on_offset_rad(raw_mgauss: F64, throttle_01: F64, tilt: F64, own_deg: F64,
                         estimate: Estimate) -> tuple[float, bool]:  # fmt: skip
    """The constant (rad) that puts ``estimate``'s heading on the autopilot's calibration over the samples
    (the field as received, the throttle, cos / sin of roll and pitch, the autopilot's own heading
    ``own_deg``), and whether it has theta's bias out: the circular mean of (the field as received with the
    estimate's theta removed, eq. (11), then eq. (24)) - the estimate's heading, where
    :func:`theta_bias_measured`; else of the autopilot's own heading - the estimate's (theta's bias at the
    throttle flown in it). The relative form cannot know the constant (declination, the mount's yaw); the
    autopilot's own heading's holds eq. (11)'s bias at the throttle flown, the error the correction removes
    (docs/real-flights.md)."""
    if not theta_bias_measured(throttle_01):
        (psi,) = corrected_headings_deg(raw_mgauss, throttle_01, tilt, (estimate,))
        return mean_change_rad(psi, own_deg), False
    psi, anchor = corrected_headings_deg(raw_mgauss, throttle_01, tilt,
                                         (estimate, (IDENTITY_COEFFS, estimate[1])))  # fmt: skip
    return mean_change_rad(psi, anchor), True


def constant_change_rad(raw_mgauss: F64, throttle_01: F64, tilt: F64, old: Estimate, new: Estimate,
                        theta_out: bool = False) -> float:  # fmt: skip
    """How much a new estimate moves the corrected heading as a whole (rad): the circular mean over the
    samples of the heading with ``new`` minus the heading with ``old`` (:func:`corrected_headings_deg`);
    ``theta_out``: less that of their thetas alone (the held constant has theta's bias out, and a new
    theta's bias at the throttle flown is a correction, not a constant to hold away). Taken over the
    samples flown lately rather than over every heading: what is constant for this flight (a change of the
    hard iron at the headings flown) is what the published heading must not jump by. NaN without samples."""
    if np.asarray(raw_mgauss).shape[0] == 0:
        return math.nan
    ests = (old, new, (IDENTITY_COEFFS, old[1]), (IDENTITY_COEFFS, new[1])) if theta_out else (old, new)
    psi = corrected_headings_deg(raw_mgauss, throttle_01, tilt, ests)
    whole = mean_change_rad(psi[0], psi[1])
    return whole - mean_change_rad(psi[2], psi[3]) if theta_out else whole


def wrap_rad(a: F64) -> F64:
    """Angles wrapped to [-pi, pi)."""
    return np.asarray((np.asarray(a, dtype=float) + math.pi) % (2.0 * math.pi) - math.pi, dtype=float)


def euler_yaw_rate_rad_s(gyro_b_rad_s: F64, roll_rad: F64, pitch_rad: F64) -> F64:
    """ZYX Euler yaw rate ``(q sin(roll) + r cos(roll)) / cos(pitch)`` per sample (NaN where |cos(pitch)| <
    0.25: the Euler yaw is not defined near +-90 deg of pitch)."""
    g = np.asarray(gyro_b_rad_s, dtype=float)
    cp = np.cos(pitch_rad)
    rate = (g[:, 1] * np.sin(roll_rad) + g[:, 2] * np.cos(roll_rad)) / np.where(np.abs(cp) < 0.25, np.nan, cp)
    return np.asarray(rate, dtype=float)


def integrate_yaw_rad(t_s: F64, rate_rad_s: F64, max_gap_s: float = MAX_GYRO_GAP_S) -> tuple[F64, F64]:
    """Trapezoid integral of a yaw rate; returns (yaw_rad, segment) where ``segment`` counts the restarts
    (a gap over ``max_gap_s`` or a non-finite rate): yaws of two segments are not comparable."""
    t = np.asarray(t_s, dtype=float)
    r = np.asarray(rate_rad_s, dtype=float)
    n = t.shape[0]
    if n == 0:
        return np.zeros(0), np.zeros(0)
    dt = np.diff(t)
    ok_r = np.isfinite(r)
    step_ok = (dt > 0) & (dt <= max_gap_s) & ok_r[1:] & ok_r[:-1]
    inc = np.where(step_ok, 0.5 * (np.nan_to_num(r[1:]) + np.nan_to_num(r[:-1])) * dt, 0.0)
    seg = np.concatenate(([0.0], np.cumsum(~step_ok))).astype(float)
    return np.concatenate(([0.0], np.cumsum(inc))), seg


def window_ids(t_s: F64, segment: F64 | None = None, window_s: float = WINDOW_S) -> NDArray[np.int64]:
    """An id per sample: one per ``window_s`` of time and per segment of the reference (a restart of the
    gyro's integral starts a new window)."""
    t = np.asarray(t_s, dtype=float)
    if t.size == 0:
        return np.zeros(0, dtype=np.int64)
    w = np.floor((t - t[0]) / window_s).astype(np.int64)
    if segment is None:
        return w
    seg = np.asarray(segment, dtype=np.int64)
    key = w * (int(seg.max()) + 1 if seg.size else 1) + seg
    _, ids = np.unique(key, return_inverse=True)
    return np.asarray(ids, dtype=np.int64)


def window_mse(err_rad: F64, ids: NDArray[np.int64], min_per_window: int = MIN_PER_WINDOW) -> tuple[F64, F64]:
    """Per window: (n, mean squared residual after the window's circular mean is removed, rad^2). Windows
    with fewer than ``min_per_window`` samples are left out."""
    e = wrap_rad(err_rad)
    if e.size == 0:
        return np.zeros(0), np.zeros(0)
    nw = int(ids.max()) + 1
    n = np.bincount(ids, minlength=nw).astype(float)
    c = np.bincount(ids, np.cos(e), minlength=nw)
    s = np.bincount(ids, np.sin(e), minlength=nw)
    mean = np.arctan2(s, c)
    res = wrap_rad(e - mean[ids])
    ss = np.bincount(ids, res * res, minlength=nw)
    keep = n >= min_per_window
    return n[keep], ss[keep] / n[keep]


def window_ms_about_mean(err_rad: F64, ids: NDArray[np.int64]) -> F64:
    """Per window (ids 0..k-1, all kept): the mean square of the residual about the circular mean of *all*
    samples (rad^2): what :func:`offset_removed_rms_deg` sums, window by window."""
    e = wrap_rad(err_rad)
    if e.size == 0:
        return np.zeros(0)
    m = math.atan2(float(np.mean(np.sin(e))), float(np.mean(np.cos(e))))
    r = wrap_rad(e - m)
    nw = int(ids.max()) + 1
    n = np.bincount(ids, minlength=nw).astype(float)
    ss = np.bincount(ids, r * r, minlength=nw)
    return np.asarray(ss / np.maximum(n, 1.0), dtype=float)


def paired_z(mse_b: F64, mse_c: F64) -> float:
    """The mean over windows of log((mse_b + floor) / (mse_c + floor)) in standard errors: > 0 where the
    candidate's windows are the quieter ones. Scale-free, so a few windows of violent manoeuvre do not
    outweigh the rest; each mean square floored at the compass's resolution (FLOOR_RAD2)."""
    nw = int(mse_b.size)
    if nw < 2:
        return math.nan
    d = np.log((mse_b + FLOOR_RAD2) / (mse_c + FLOOR_RAD2))
    mean = float(np.mean(d))
    se = float(np.std(d, ddof=1)) / math.sqrt(nw)
    return mean / se if se > 0 else (math.inf if mean > 0 else -math.inf if mean < 0 else 0.0)


def offset_removed_rms_deg(err_rad: F64) -> float:
    """rms (deg) of wrapped angle differences after their circular mean is removed; NaN when empty."""
    e = wrap_rad(err_rad)
    if e.size == 0:
        return math.nan
    m = math.atan2(float(np.mean(np.sin(e))), float(np.mean(np.cos(e))))
    r = wrap_rad(e - m)
    return math.degrees(math.sqrt(float(np.mean(r * r))))


def windowed_rms_deg(err_rad: F64, ids: NDArray[np.int64]) -> float:
    """rms (deg) of the residuals with each window's circular mean removed (the gyro metric)."""
    n, mse = window_mse(err_rad, ids)
    if n.size == 0:
        return math.nan
    return math.degrees(math.sqrt(float(np.sum(n * mse) / np.sum(n))))


@dataclass(frozen=True)
class SelfCheck:
    """The verdict of :func:`compare` (degrees; NaN where not measurable)."""

    baseline_gyro_deg: float
    candidate_gyro_deg: float
    baseline_att_deg: float
    candidate_att_deg: float
    #: windows compared and the paired gain in standard errors (NaN: fewer than MIN_WINDOWS)
    n_windows: int
    z: float
    applies: bool
    reason: str
    #: worse than the baseline (less consistent with the gyro, or further from the autopilot's yaw than its
    #: tolerance): what switches a running correction off again; "not better beyond the noise" does not
    worse: bool = False
    #: the autopilot's yaw follows the compass judged within a window (:func:`att_is_circular`): the rms
    #: against it is reported, not used
    att_circular: bool = False

    @property
    def att_used(self) -> bool:
        """The rms against the autopilot's yaw was measured and is a reference (not :attr:`att_circular`)."""
        return self.baseline_att_deg == self.baseline_att_deg and not self.att_circular

    def describe(self) -> str:
        """One line for the console: "heading vs gyro: 6.2 -> 2.5 deg (z 4.1, 23 windows)"."""
        g = f"heading vs gyro: {self.baseline_gyro_deg:.1f} -> {self.candidate_gyro_deg:.1f} deg"
        if math.isfinite(self.z):
            g += f" (gain {self.z:.1f} sigma over {self.n_windows} windows)"
        if math.isfinite(self.baseline_att_deg) and math.isfinite(self.candidate_att_deg):
            g += f"; vs autopilot yaw {self.baseline_att_deg:.1f} -> {self.candidate_att_deg:.1f} deg"
            if self.att_circular:
                g += " (not used: that yaw follows this compass within seconds)"
        return g


def compare(
    baseline_rad: F64,
    candidate_rad: F64,
    reference_rad: F64,
    ids: NDArray[np.int64],
    autopilot_yaw_rad: F64 | None = None,
    att_circular: bool = False,
) -> SelfCheck:
    """Judge ``candidate_rad`` against ``baseline_rad`` (headings of the same samples) with the windowed
    reference (gyro yaw, or the autopilot's yaw where the gyro is slow; ``ids`` from :func:`window_ids`)
    and, where given, the autopilot's yaw over the whole flight. The candidate applies where it is no worse
    than the baseline against either reference and better beyond the noise (the paired window gain beyond
    :func:`t_critical`) against either. Where the autopilot's yaw is fused from this compass it carries the
    baseline's own error and favours it: a candidate that agrees better with it all the same is better."""
    b = np.asarray(baseline_rad, dtype=float)
    c = np.asarray(candidate_rad, dtype=float)
    ref = np.asarray(reference_rad, dtype=float)
    ok = np.isfinite(b) & np.isfinite(c) & np.isfinite(ref)
    ap = None if autopilot_yaw_rad is None else np.asarray(autopilot_yaw_rad, dtype=float)
    if ap is not None:
        ok &= np.isfinite(ap)
    b, c, ref, ids_ok = b[ok], c[ok], ref[ok], ids[ok]
    if ids_ok.size:
        _, ids_ok = np.unique(ids_ok, return_inverse=True)
    n_b, mse_b = window_mse(b - ref, ids_ok)
    _, mse_c = window_mse(c - ref, ids_ok)
    att_b = att_c = z_att = math.nan
    if ap is not None and b.size:
        ap_ok = ap[ok]
        att_b, att_c = offset_removed_rms_deg(b - ap_ok), offset_removed_rms_deg(c - ap_ok)
        z_att = paired_z(window_ms_about_mean(b - ap_ok, ids_ok), window_ms_about_mean(c - ap_ok, ids_ok))
    return decide(n_b, mse_b, mse_c, att_b, att_c, z_att, att_circular)


def judge_estimate(t_s: F64, raw_mgauss: F64, throttle_01: F64, tilt: F64, own_deg: F64, reference_rad: F64,
                   segment: F64, autopilot_yaw_rad: F64, estimate: Estimate, att_circular: bool,
                   window_s: float = LIVE_WINDOW_S) -> SelfCheck:  # fmt: skip
    """:func:`compare` of ``estimate``'s heading (:func:`corrected_headings_deg`) with the autopilot's own
    (``own_deg``) on samples already judged: the field as received (n, 3), the throttle, cos / sin of roll and
    pitch (n, 4), the windowed reference and its segment, the autopilot's yaw (NaN where not known: then
    not used), windows of ``window_s``. The estimate was solved on these samples among others, as the
    two-pass replay's check judges the whole log's estimate on the whole log; the running check judges
    each window with the estimate solved before it, which keeps a correction that was poor early in the
    flight off long after it has become good (the simulated ordinary flight, x1, 10 Hz, seed 0: on for good
    119 s after take-off by its windows, 44 s judged again; tests/integration/test_live_switch_on.py)."""
    (psi,) = corrected_headings_deg(raw_mgauss, throttle_01, tilt, (estimate,))
    ap = np.asarray(autopilot_yaw_rad, dtype=float)
    ids = window_ids(t_s, segment, window_s)
    return compare(np.radians(own_deg), np.radians(psi), reference_rad, ids,
                   ap if np.isfinite(ap).all() else None, att_circular)  # fmt: skip


def autopilot_follows(t_s: F64, baseline_rad: F64, autopilot_yaw_rad: F64, gyro_yaw_rad: F64,
                      segment: F64) -> YawFollow | None:  # fmt: skip
    """How fast the autopilot's yaw follows the baseline (the compass's heading as the autopilot has it),
    measured on the check's own samples (core/yaw_follow.py, FOLLOW_WINDOW_S windows within the gyro's
    segments); None where it cannot be measured."""
    t = np.asarray(t_s, dtype=float)
    ok = np.isfinite(t) & np.isfinite(baseline_rad) & np.isfinite(autopilot_yaw_rad)
    ok &= np.isfinite(gyro_yaw_rad)
    if int(ok.sum()) < 3:
        return None
    ids = window_ids(t[ok], np.asarray(segment, dtype=float)[ok], FOLLOW_WINDOW_S)
    rates, offs = window_follow_terms(t[ok], np.asarray(baseline_rad)[ok], np.asarray(autopilot_yaw_rad)[ok],
                                      np.asarray(gyro_yaw_rad)[ok], ids)  # fmt: skip
    return fit_follow_gain(rates, offs)


def att_is_circular(follow: YawFollow | None) -> bool:
    """The autopilot's yaw follows the compass judged with a time constant shorter than the check's window
    (WINDOW_S): it then holds that compass's error on every time scale the windows do not see already, and
    a candidate that removes the error moves away from it (the simulator's complementary filter, 0.5 /s); a
    real EKF's 0.01-0.05 /s leaves it a reference over tens of seconds."""
    return follows_within(follow, WINDOW_S)


def decide(n_w: F64, mse_b: F64, mse_c: F64, att_b: float, att_c: float, z_att: float,
           att_circular: bool = False) -> SelfCheck:  # fmt: skip
    """The rule of :func:`compare` on its window statistics: per window the samples and the mean squared
    residuals against the windowed reference (rad^2), the rms against the autopilot's yaw (deg) and the paired
    gain against it in standard errors (NaN: that yaw is not independent evidence). ``att_circular``: that
    yaw follows the compass judged (:func:`att_is_circular`): neither a veto nor a gain."""
    tot = float(np.sum(n_w))
    gyro_b = math.degrees(math.sqrt(float(np.sum(n_w * mse_b)) / tot)) if n_w.size else math.nan
    gyro_c = math.degrees(math.sqrt(float(np.sum(n_w * mse_c)) / tot)) if n_w.size else math.nan
    nw = int(n_w.size)
    if nw < MIN_WINDOWS:
        why = f"only {nw} usable windows with the motors running"
        return SelfCheck(gyro_b, gyro_c, att_b, att_c, nw, math.nan, False, why, att_circular=att_circular)
    if att_circular:
        z_att = math.nan
    z = paired_z(mse_b, mse_c)
    crit = t_critical(nw)
    if gyro_c > gyro_b:
        why = f"less consistent with the gyro than the autopilot's own ({gyro_b:.1f} -> {gyro_c:.1f} deg)"
        return SelfCheck(gyro_b, gyro_c, att_b, att_c, nw, z, False, why, True, att_circular)
    if not att_circular and math.isfinite(att_c) and att_c > att_b + att_tolerance_deg(att_b, nw):
        why = f"in less agreement with the autopilot's yaw than its own ({att_b:.1f} -> {att_c:.1f} deg)"
        return SelfCheck(gyro_b, gyro_c, att_b, att_c, nw, z, False, why, worse=True)
    if not (z >= crit or z_att >= crit):
        why = (
            f"not better than the autopilot's own heading beyond the noise (against the gyro "
            f"{gyro_b:.1f} -> {gyro_c:.1f} deg, {z:+.1f} sigma"
            + (f"; against its yaw {att_b:.1f} -> {att_c:.1f} deg, {z_att:+.1f} sigma)"
               if math.isfinite(z_att) else ")")
        )
        return SelfCheck(gyro_b, gyro_c, att_b, att_c, nw, z, False, why, att_circular=att_circular)
    return SelfCheck(gyro_b, gyro_c, att_b, att_c, nw, max(z, z_att) if math.isfinite(z_att) else z, True,
                     "better than the autopilot's own heading", att_circular=att_circular)  # fmt: skip


class RunningSelfCheck:
    """:func:`compare` sample by sample (the live daemon, ``replay --causal``): samples are added as they
    come, a window closes every ``window_s`` (or where the reference's segment changes) and the verdict is
    taken again from the closed windows of the latest RECENT_S (against the autopilot's yaw the sums are
    kept per window about a fixed offset, the first sample's: the rms without its mean follows from them)."""

    def __init__(self, window_s: float = LIVE_WINDOW_S) -> None:
        self.window_s = window_s
        self._key: tuple[int, float] | None = None
        self._t0 = math.nan
        self._rows: list[tuple[float, float, float, float, float]] = []  # t, base, cand, ref, autopilot yaw
        self._n: list[float] = []
        self._mse_b: list[float] = []
        self._mse_c: list[float] = []
        self._att: list[tuple[float, float, float, float, float]] = []  # n, sum b, sum b^2, sum c, sum c^2
        self._offset_sums: list[tuple[float, float]] = []  # per window: sum sin, sum cos of (base - cand)
        #: per window: the autopilot's yaw-follow terms (core/yaw_follow.py: rate of D, mean offset)
        self._follow: list[tuple[float, float]] = []
        self._offset: float | None = None  # the windows' offset (None: not computed yet)
        #: the offset held since the correction switched on (None: off, the windows' offset is used)
        self._held: float | None = None
        self._off: tuple[float, float] | None = None
        self.verdict: SelfCheck | None = None
        #: the current estimate judged again on the samples of the latest RECENT_S (the argument: whether the
        #: autopilot's yaw follows the compass judged; None: not measurable): while off, where the windows as
        #: they were judged neither apply nor find the correction worse and it applies, it is the verdict
        #: (:func:`judge_estimate`; consulted only there: on the development logs, consulted also where the
        #: windows found the correction worse, it switched on yladzislay sample-1's compass 1, whose
        #: correction then stood 3.5 deg off the gyro against the autopilot's own heading's 2.1)
        self.rejudge: Callable[[bool], SelfCheck | None] | None = None
        #: :meth:`publishes`'s two bounds (deg) and the verdict they were taken from (read at every sample,
        #: changed only with the verdict)
        self._bounds: tuple[SelfCheck | None, float, float] | None = None
        #: the correction is published: switched on where the verdict applies, off only where it is worse
        #: beyond the noise (hysteresis: a verdict near its bound does not make the heading flip back and
        #: forth between two headings whose constant parts differ)
        self.on = False

    @property
    def offset_rad(self) -> float:
        """The constant (rad) added to the candidate where it is published: while the correction is off, the
        circular mean of (baseline - candidate) over the windows the verdict was taken on (so that it does
        not jump when it switches on); from the switch on, that value held, moved only by :meth:`shift`.
        The windows' mean would wander with the baseline's own error, which changes with the flight (the
        throttle's bias at the throttle of the latest two minutes): on the development logs the windows'
        offset moved over 6-24 deg while published (log171 compass 2: 5.8-20.0 deg; its published heading
        5.1 deg att with it, 2.6 with one constant)."""
        if self._held is not None:
            return self._held
        return self._windows_offset()

    def _windows_offset(self) -> float:
        if not self._offset_sums:
            return 0.0
        if self._offset is None:  # computed once per window closed (read at every published sample)
            s = np.asarray(self._offset_sums)
            self._offset = math.atan2(float(s[:, 0].sum()), float(s[:, 1].sum()))
        return self._offset

    @property
    def holds(self) -> bool:
        """The offset is held (the correction is on): the candidate's re-solves should :meth:`shift` it."""
        return self._held is not None

    def hold(self, offset_rad: float) -> None:
        """While on, hold ``offset_rad`` instead (NaN: keep the held one): the windows' offset mixes the
        estimates each window was judged with, where the caller can measure it with the current one."""
        if self._held is not None and offset_rad == offset_rad:
            self._held = offset_rad

    def shift(self, change_rad: float) -> None:
        """The candidate's constant part changed by ``change_rad`` (a re-solve of the estimate:
        :func:`constant_change_rad`): the held offset takes it out, so that the published heading neither
        jumps nor drifts with the re-solves."""
        if self._held is not None:
            self._held = float(wrap_rad(np.asarray(self._held - change_rad)))

    @property
    def baseline_deg(self) -> float:
        """The error measured of the autopilot's own heading on the verdict's windows (deg): against its yaw
        where that is a reference (:attr:`SelfCheck.att_used`), else the gyro; NaN before a verdict."""
        v = self.verdict
        if v is None:
            return math.nan
        return v.baseline_att_deg if v.att_used else v.baseline_gyro_deg

    @property
    def candidate_bound_deg(self) -> float:
        """How far off the correction itself may be, as measured (deg): the upper P_APPLY bound of the
        candidate's rms on the verdict's windows against the reference of :attr:`baseline_deg`
        (:func:`rms_upper_deg`); inf before MIN_WINDOWS windows. Each window's samples were corrected with
        an estimate solved before them (the live estimate is re-solved as the samples come), so this is the
        realised error of the heading as it would have been published, on the headings and throttles flown;
        it holds the reference's own error too, so it bounds the correction's from above."""
        v = self.verdict
        if v is None or v.n_windows < MIN_WINDOWS:
            return math.inf
        c = v.candidate_att_deg if v.att_used else v.candidate_gyro_deg
        return rms_upper_deg(c, v.n_windows) if c == c else math.inf

    def publishes(self, heading_sigma_deg: float) -> bool:
        """The correction is published: the check is on and the correction's own error is within the error
        measured of the autopilot's own heading (:attr:`baseline_deg`): a correction that may itself be off by
        more than what it corrects cannot be shown to help, whatever a few windows say. Its own error is the
        smaller of two bounds: the estimate's heading uncertainty (deg, 1 sigma, from its covariance: every
        heading, the constant part included, which live comes from the autopilot's calibration) and
        the error measured on the check's windows (:attr:`candidate_bound_deg`). On the development logs the
        first alone held log171's compasses back for 10 s after the check was on (heading uncertainty 13-46
        deg while the windows measured 3-6 deg against 10-14 of the autopilot's own)."""
        if not self.on:
            return False
        b = self._bounds
        if b is None or b[0] is not self.verdict:
            b = self._bounds = (self.verdict, self.candidate_bound_deg, self.baseline_deg)
        return min(heading_sigma_deg, b[1]) <= b[2]

    def add(self, t_s: float, base_rad: float, cand_rad: float, ref_rad: float, segment: float,
            ap_yaw_rad: float) -> bool:  # fmt: skip
        """One sample (rad; ``ap_yaw_rad`` NaN: none); True when a window closed (the verdict was renewed)."""
        if self._t0 != self._t0:
            self._t0 = t_s
        key = (int((t_s - self._t0) // self.window_s), segment)
        closed = False
        if key != self._key:
            closed = self._close()
            self._key = key
        self._rows.append((t_s, base_rad, cand_rad, ref_rad, ap_yaw_rad))
        return closed

    def _close(self) -> bool:
        rows, self._rows = self._rows, []
        if len(rows) < MIN_PER_WINDOW:
            return False
        a = np.asarray(rows, dtype=float)
        t, a = a[:, 0], a[:, 1:]
        ids = np.zeros(a.shape[0], dtype=np.int64)
        n, mb = window_mse(a[:, 0] - a[:, 2], ids)
        _, mc = window_mse(a[:, 1] - a[:, 2], ids)
        self._n.append(float(n[0]))
        dbc = a[:, 0] - a[:, 1]
        self._offset_sums.append((float(np.sin(dbc).sum()), float(np.cos(dbc).sum())))
        self._offset = None
        self._mse_b.append(float(mb[0]))
        self._mse_c.append(float(mc[0]))
        ap = a[:, 3]
        if np.isfinite(ap).all():
            if self._off is None:
                self._off = (float(a[0, 0] - ap[0]), float(a[0, 1] - ap[0]))
            eb = wrap_rad(a[:, 0] - ap - self._off[0])
            ec = wrap_rad(a[:, 1] - ap - self._off[1])
            sums = (float(eb.size), float(eb.sum()), float(eb @ eb), float(ec.sum()), float(ec @ ec))
            self._att.append(sums)
            rate, off = window_follow_terms(t, a[:, 0], ap, a[:, 2], ids)
            if rate.size:
                self._follow.append((float(rate[0]), float(off[0])))
        v = self._decide()
        if self.rejudge is not None and not self.on and not v.applies and not v.worse:
            r = self.rejudge(v.att_circular)
            if r is not None and r.applies:
                v = r
        self.verdict = v
        was = self.on
        self.on = v.applies or (self.on and not v.worse)
        if not self.on:
            self._held = None
        elif not was:  # switched on: the windows' offset, held from here
            self._held = self._windows_offset()
        return True

    def _decide(self) -> SelfCheck:
        k = max(MIN_WINDOWS, int(RECENT_S / self.window_s))
        del self._n[:-k], self._mse_b[:-k], self._mse_c[:-k], self._offset_sums[:-k]
        att_b = att_c = z_att = math.nan
        del self._att[:-k], self._follow[:-k]
        f = np.asarray(self._follow, dtype=float).reshape(-1, 2)
        circular = att_is_circular(fit_follow_gain(f[:, 0], f[:, 1]))
        if self._att:
            s = np.asarray(self._att)
            n = s[:, 0]
            tot = float(n.sum())
            mb, mc = float(s[:, 1].sum()) / tot, float(s[:, 3].sum()) / tot
            att_b = math.degrees(math.sqrt(max(0.0, float(s[:, 2].sum()) / tot - mb * mb)))
            att_c = math.degrees(math.sqrt(max(0.0, float(s[:, 4].sum()) / tot - mc * mc)))
            ms_b = (s[:, 2] - 2.0 * mb * s[:, 1]) / n + mb * mb
            ms_c = (s[:, 4] - 2.0 * mc * s[:, 3]) / n + mc * mc
            z_att = paired_z(ms_b, ms_c)
        n_w, mse_b, mse_c = np.asarray(self._n), np.asarray(self._mse_b), np.asarray(self._mse_c)
        return decide(n_w, mse_b, mse_c, att_b, att_c, z_att, circular)
