"""The published heading's gyro-aided filter (pure numerics: floats in, floats out, explicit dt).

Not in the paper's observer, but what its Table III measured: the yaw of an attitude estimator that fuses
the gyro with the (corrected) magnetometer, not the raw per-sample heading of eq. (24).

Symbols: psi -> psi_deg (heading, deg); the Euler yaw rate yaw_rate_rad_s (rad/s); dt_s (s).
"""

from __future__ import annotations

import math
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

_DEG_PER_RAD = 180.0 / math.pi  # the factor of math.degrees
FloatOrArray = TypeVar("FloatOrArray", float, NDArray[np.float64])

GYRO_SCALE_ERROR = 0.01
"""A MEMS gyro's scale-factor tolerance, which autopilots do not calibrate (datasheets: 0.5-3 %)."""
RESIDUAL_BIAS_DEG_S = 0.1
"""The yaw-rate bias the heading filter's loop leaves (the raw gyro drifts 0.07-0.3 deg/s from the
autopilot's yaw on the development logs before the loop takes out its constant part)."""


class HeadingFilter:
    """Gyro-aided filter on a heading (deg): propagate with the yaw rate, pull toward the magnetometer
    heading with time constant ``tau_s`` in steady flight. ``tau_s = 0`` passes the measurement through.

    Not in the paper's observer, but what its Table III measured: the yaw of an attitude estimator
    that fuses the gyro with the (corrected) magnetometer, not the raw per-sample eq. (24). It removes
    most of the magnetometer noise without the lag a low-pass would add. Near pitch +-90 deg heading is
    undefined and the filter restarts from the measurement.

    A one-state Kalman filter on the heading, its noise in units of the compass's: the heading's variance
    ``p`` grows by q (1 + s^2) dt per step, q = 1 / tau^2 and s = GYRO_SCALE_ERROR x rate /
    RESIDUAL_BIAS_DEG_S (the gyro's heading error grows with the bias it has left and, turning, with its
    scale factor), and the compass (variance 1 / dt, white) pulls with gain p / (p + 1 / dt). In steady,
    slow flight the gain is dt / tau, the complementary filter's; while the vehicle turns fast it trusts
    the compass more, and after a restart or a fast manoeuvre it averages the compass samples since then
    before it settles back to tau.

    With ``gyro_bias`` it also learns the yaw rate's constant bias (deg/s) by a proportional-integral loop
    (as Mahony's attitude filter does for all three axes): b' = -e / (4 tau^2), e = heading - psi,
    critically damped with the steady gain 1 / tau (characteristic s^2 + s / tau + 1 / (4 tau^2)). A filter
    without it stands off by bias x tau; with it none is left, so tau can be long. The bias is learned only
    in slow turns (s < 1), kept across restarts (it is the gyro's) and held within +-MAX_GYRO_BIAS_DEG_S.
    """

    __slots__ = ("_ki", "_p", "_q", "bias_deg_s", "psi_deg", "tau_s")

    MAX_GYRO_BIAS_DEG_S = 5.0
    """An autopilot zeroes its gyros at boot; what is left is within a degree per second (0.07-0.3 deg/s
    against the autopilot's yaw on the development logs; the simulator's uncalibrated 0.57 deg/s). 5 deg/s
    bounds a loop that a long ill-conditioned stretch could wind up."""

    def __init__(self, tau_s: float, gyro_bias: bool = True) -> None:
        self.tau_s = tau_s
        self.psi_deg: float | None = None
        self.bias_deg_s = 0.0
        self._ki = 1.0 / (4.0 * tau_s * tau_s) if gyro_bias and tau_s > 0.0 else 0.0
        self._q = 1.0 / (tau_s * tau_s) if tau_s > 0.0 else 0.0
        self._p: float | None = None  # the heading's variance, None: one compass sample's (1 / dt)

    def reset(self) -> None:
        self.psi_deg = None
        self._p = None

    def update(
        self, psi_meas_deg: float, yaw_rate_rad_s: float, dt_s: float, turn_rad_s: float = 0.0
    ) -> float:
        """One compass sample; ``turn_rad_s``: the body's rotation rate (norm of the gyro), when it is faster
        than the yaw rate the gyro's error grows with it (the yaw integral's roll and pitch err with it)."""
        psi0 = self.psi_deg
        if psi0 is None or dt_s <= 0.0 or self.tau_s <= 0.0 or not math.isfinite(yaw_rate_rad_s):
            self.psi_deg = psi_meas_deg
            self._p = None
            return psi_meas_deg
        rate_deg_s = yaw_rate_rad_s * _DEG_PER_RAD  # as math.degrees
        pred = psi0 + (rate_deg_s - self.bias_deg_s) * dt_s
        innov = (psi_meas_deg - pred + 180.0) % 360.0 - 180.0
        turn_deg_s = turn_rad_s * _DEG_PER_RAD
        abs_rate = abs(rate_deg_s)
        if not turn_deg_s > abs_rate:  # max(|rate|, turn), as max() picks (the first of equals)
            turn_deg_s = abs_rate
        slew = GYRO_SCALE_ERROR * turn_deg_s / RESIDUAL_BIAS_DEG_S
        slew2 = slew * slew
        p0 = self._p
        p = (1.0 / dt_s if p0 is None else p0) + self._q * (1.0 + slew2) * dt_s
        gain = p * dt_s / (p * dt_s + 1.0)
        self._p = p * (1.0 - gain)
        if self._ki and slew2 < 1.0:
            b = self.bias_deg_s - self._ki * innov * dt_s
            lim = self.MAX_GYRO_BIAS_DEG_S
            self.bias_deg_s = lim if b > lim else -lim if b < -lim else b
        psi = (pred + gain * innov) % 360.0
        self.psi_deg = psi
        return psi


STEEP_COS_TILT = math.cos(math.radians(30.0))
"""Beyond 30 deg of tilt the Euler yaw rate's coupling to roll and pitch (1 / cos(pitch), the roll's
sine) makes the yaw integral err with the whole body rate, not only with the yaw rate."""


def turn_rate(gx: FloatOrArray, gy: FloatOrArray, gz: FloatOrArray, cos_tilt: FloatOrArray) -> FloatOrArray:
    """The rotation rate (rad/s) the heading filter's gyro error grows with besides the yaw rate
    (:class:`HeadingFilter`): the body rate's norm where the vehicle is tilted
    beyond 30 deg (``cos_tilt`` = cos(roll) cos(pitch)), else 0 (near level the attitude's errors make the
    integral wander about zero as the vehicle rocks, not drift). Floats, or arrays of a block of samples
    (the same numbers element by element)."""
    if not isinstance(cos_tilt, np.ndarray):
        return math.sqrt(gx * gx + gy * gy + gz * gz) if cos_tilt < STEEP_COS_TILT else 0.0
    return np.where(cos_tilt < STEEP_COS_TILT, np.sqrt(gx * gx + gy * gy + gz * gz), 0.0)
