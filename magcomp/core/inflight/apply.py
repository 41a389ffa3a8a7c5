"""When the in-flight estimate is good enough to correct with, and the correction it gives: the apply
decision (a 2-sigma test that the correction is real, a quarter turn of yaw for the relative form, an
Earth-like corrected field, the split check), the bias of eq. (11) with the per-motor terms, and the
correction value the pipeline applies (:class:`InflightOutput`). Pure; no I/O."""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import NamedTuple

import numpy as np

from magcomp.core.inflight.base import F64, InflightMode, InflightSolution
from magcomp.core.inflight.rows import regressors
from magcomp.core.inflight.yawframe import YawTurn, yaw_turned
from magcomp.core.types import EARTH_MAX_MGAUSS, EARTH_MIN_MGAUSS

#: the correction is applied once its heading uncertainty is below half the heading change it makes (a
#: 2-sigma test that the correction is real) or below ``heading_ok_deg``
APPLY_Z = 2.0
#: never applied while the heading uncertainty is above this, whatever heading change the correction makes:
#: the uncertainty atan(err / h) is a linearisation, meaningful only while the error stays well inside the
#: horizontal field (err <= h / 2, atan(0.5) = 26.6 deg); above it a correction that turns the heading by
#: 150 deg would "justify" itself with a 75 deg uncertainty (seen on a 23 s log with 8 deg of yaw)
MAX_APPLY_HEADING_SIGMA_DEG = math.degrees(math.atan(0.5))
#: the relative form is applied only once the heading has covered this span (deg; as the diagnosis's gate)
MIN_RELATIVE_YAW_SPAN_DEG = 90.0
#: the corrected field's strength must be an Earth field's: Earth's surface range (core.types) widened by the
#: +-35 % a compass calibration within tolerance can leave (the diagnosis's gate, ``max_scale_error``). A
#: compass stuck at one value learns a hard iron equal to its reading and corrects to ~0 mgauss: its heading
#: is then noise, whatever the statistical sigma says.
CORRECTED_FIELD_RANGE_MGAUSS = (0.65 * EARTH_MIN_MGAUSS, 1.35 * EARTH_MAX_MGAUSS)

Float3 = tuple[float, float, float]


class InflightOutput(NamedTuple):
    """What the pipeline applies: L and d of eq. (2) as 12 floats, theta and the bias at this sample. A
    named tuple, made once per magnetometer sample (a frozen dataclass took 1 us more)."""

    coeffs: tuple[float, ...]
    theta_mgauss: Float3
    bias_mgauss: Float3
    converged: bool
    #: started from a stored state (a previous flight's correction): the self-check starts it published
    warm_started: bool = False
    #: the relative form: the heading's constant part (the mount's yaw) is not observable
    relative: bool = False
    #: the estimate's own heading uncertainty (deg, 1 sigma)
    heading_sigma_deg: float = 0.0


def bias_at(
    sol: InflightSolution, theta3: Float3, throttle_01: float, motors_01: tuple[float, ...] | None
) -> Float3:
    """The bias at this throttle: ``theta delta^2`` (eq. (11); ``theta3``: the solution's theta as floats)
    and, with the motor outputs, the per-motor terms (``regressors``)."""
    d2 = throttle_01 * throttle_01
    t0, t1, t2 = theta3
    bias3 = (t0 * d2, t1 * d2, t2 * d2)  # eq. (11)
    if motors_01 is not None:
        x = regressors(throttle_01, motors_01)
        b = sol.theta_mgauss * x[0] + sol.motor_theta_mgauss.T @ x[1:]
        bias3 = (float(b[0]), float(b[1]), float(b[2]))
    return bias3


def horizontal_angle_deg(a: F64, b: F64) -> float:
    """Angle between the body-horizontal parts of two field vectors (deg): the heading change a correction
    makes when the vehicle is level (an upper bound's worth of its effect elsewhere)."""
    ang = math.atan2(float(a[1]), float(a[0])) - math.atan2(float(b[1]), float(b[0]))
    return abs(math.degrees((ang + math.pi) % (2.0 * math.pi) - math.pi))


def apply_decision(
    sol: InflightSolution,
    mode: InflightMode,
    field_mgauss: Float3,
    bias3: Float3,
    heading_ok_deg: float,
    yaw_span_deg: float,
    sigma_checked: bool,
) -> tuple[bool, float]:
    """Whether to start applying ``sol`` at this sample (the field as received, the bias at its throttle),
    and the corrected field's strength (mgauss). Applied once the heading uncertainty is below
    ``max(heading_ok_deg, change / APPLY_Z)`` (change: the heading change the correction makes here) and
    below MAX_APPLY_HEADING_SIGMA_DEG, the corrected field is an Earth field's (CORRECTED_FIELD_RANGE_MGAUSS),
    the relative form has turned through MIN_RELATIVE_YAW_SPAN_DEG (below a quarter turn its statistical
    sigma hides the misalignment and gyro errors it cannot model; the diagnosis's gate uses the same span)
    and the sigma has been checked on a second stretch of data (``sigma_checked``). The absolute form's
    sigma leaves the split-half term out (reported, not decided on: on log171's absolute-form compasses it
    delayed the causal correction by 30 s)."""
    bias = np.asarray(bias3)
    y = np.asarray(field_mgauss, dtype=float)
    corrected = sol.calib_l @ y - sol.calib_d - bias
    change = horizontal_angle_deg(corrected, y)
    sig = sol.heading_sigma_deg
    if mode == "absolute":
        sig = math.sqrt(max(sig * sig - sol.heading_split_deg**2, 0.0))
    ok = sig < max(heading_ok_deg, change / APPLY_Z)
    turned = mode == "absolute" or yaw_span_deg >= MIN_RELATIVE_YAW_SPAN_DEG
    strength = math.sqrt(float(corrected @ corrected))
    lo, hi = CORRECTED_FIELD_RANGE_MGAUSS
    earthly = lo <= strength <= hi
    return ok and turned and earthly and sig < MAX_APPLY_HEADING_SIGMA_DEG and sigma_checked, strength


_TWO_PI = 2.0 * math.pi
#: the most turned attitudes YawSpan holds before it takes them (a block's worth: memory stays small)
_SPAN_PENDING_MAX = 256


class YawSpan:
    """The heading span covered by the samples used (unwrapped yaw of their attitudes). An attitude that
    takes a yaw turn first (the gyro's yaw, ``core.inflight.yawframe``) is held and turned with the others
    held when the span is next read: one stacked product instead of one per sample."""

    def __init__(self) -> None:
        self.yaw_min = math.inf
        self.yaw_max = -math.inf
        self._prev: float | None = None
        self._unwrapped = 0.0
        self._pending: list[tuple[F64, float, float]] = []
        self._rz = np.eye(3)  # one held attitude's turn, rewritten in place

    def track(self, r_nb: F64, turn: YawTurn | None = None) -> None:
        """One used sample's attitude; ``turn``: the yaw turn it takes first (:func:`yaw_turned`)."""
        if turn is not None:
            self._pending.append((r_nb, turn[0], turn[1]))
            if len(self._pending) >= _SPAN_PENDING_MAX:
                self._take_pending()
            return
        if self._pending:
            self._take_pending()
        self._track(r_nb)

    def _take_pending(self) -> None:
        """The held attitudes turned and tracked, in their order."""
        held, self._pending = self._pending, []
        if len(held) == 1:  # a 3 x 3 product: the same numbers as a stack's slice, without the stack
            r_nb, c, s = held[0]
            rz = self._rz
            rz[0, 0], rz[0, 1], rz[1, 0], rz[1, 1] = c, -s, s, c
            self._track(rz @ r_nb)
            return
        turned = yaw_turned(np.array([h[0] for h in held]), np.array([h[1] for h in held]),
                            np.array([h[2] for h in held]))  # fmt: skip
        # _track's steps over the block's yaws (the same floats as indexing each attitude)
        self._track_yaws(map(math.atan2, turned[:, 1, 0].tolist(), turned[:, 0, 0].tolist()))

    def _track(self, r_nb: F64) -> None:
        self._track_yaws((math.atan2(r_nb.item(1, 0), r_nb.item(0, 0)),))

    def _track_yaws(self, yaws: Iterable[float]) -> None:
        """Unwrap ``yaws`` (rad) onto the span, in order."""
        prev, unwrapped, lo, hi = self._prev, self._unwrapped, self.yaw_min, self.yaw_max
        for yaw in yaws:
            if prev is not None:
                unwrapped += (yaw - prev + math.pi) % _TWO_PI - math.pi
            prev = yaw
            if unwrapped < lo:  # min() and max() as they were, without the calls
                lo = unwrapped
            if unwrapped > hi:
                hi = unwrapped
        self._prev, self._unwrapped, self.yaw_min, self.yaw_max = prev, unwrapped, lo, hi

    @property
    def span_deg(self) -> float:
        """Heading span covered so far (deg)."""
        if self._pending:
            self._take_pending()
        return math.degrees(self.yaw_max - self.yaw_min) if self.yaw_max > self.yaw_min else 0.0
