"""The yaw frame of the relative form's window-field rows: the raw gyro's compass-free yaw in place of the
autopilot's (which follows the compass being corrected), and the line fit of that gyro frame's own error
over the closed windows with the tilt error the autopilot's yaw error makes (the tilt model). No I/O."""

from __future__ import annotations

import math
from typing import NamedTuple, Protocol

import numpy as np

from magcomp.core.inflight.base import F64
from magcomp.core.linalg3 import Vec3Like, vec3
from magcomp.core.types import STANDARD_GRAVITY_M_S2

#: with the gyro's yaw, a window's Earth field and yaw rate (the gyro's bias about the vertical) are taken
#: as constant over this long (s): the gyro's own drift is its bias, not a compass correction
GYRO_WINDOW_S = 10.0


class GyroYaw(NamedTuple):
    """The raw gyro's yaw at a sample (``AttitudeStage.gyro_yaw_at``): ``yaw_rad`` integrated since the
    chain's start, ``epoch`` counts its restarts (yaws of two epochs are not comparable)."""

    epoch: int
    yaw_rad: float
    #: the vehicle's horizontal kinematic acceleration (north and east of the chain's yaw frame, m/s^2):
    #: specific force rotated by the autopilot's roll and pitch and this yaw, plus gravity, low-passed over
    #: ACCEL_LP_S (see ``AttitudeStage.accel_h``)
    accel_h_m_s2: tuple[float, float] = (0.0, 0.0)
    #: the gyro's yaw change from the IMU sample to the autopilot's latest ATTITUDE (rad; the last yaw rate
    #: times their time difference): the autopilot's yaw minus the gyro's is taken at one instant
    att_lead_rad: float = 0.0


class WindowFields(Protocol):
    """What the line fit reads of an estimator: its open window's nuisance and the Earth field."""

    field_ned_mgauss: F64

    def window_nuisance(self, window: object) -> F64 | None: ...


#: a yaw turn (cos a, sin a) that an attitude takes: ``Rz(a) R_nb`` (:func:`yaw_turned`)
YawTurn = tuple[float, float]


_TWO_PI = 2.0 * math.pi


class GyroYawFrame:
    """The autopilot's attitude with its yaw replaced by the raw gyro's (the Euler yaw rate from the raw gyro
    and the autopilot's roll and pitch, integrated at the IMU's rate), offset to the autopilot's yaw where
    its chain starts. The autopilot's yaw follows the compass being corrected; the gyro's does not, and
    drifts only by its bias: a yaw rate per GYRO_WINDOW_S window (the window-field rows' nuisance)."""

    def __init__(self, att_lead: bool = True) -> None:
        """``att_lead``: take the autopilot's yaw minus the gyro's at the ATTITUDE's own time
        (``GyroYaw.att_lead_rad``) for a sample not matched to the attitude's time."""
        self.att_lead = att_lead
        #: a gyro yaw is in use
        self.on = False
        self._epoch = -1
        self._offset = 0.0
        self._offset_cs = (1.0, 0.0)  # its cosine and sine (it changes only where a chain starts)
        #: the autopilot's yaw minus the gyro frame's (rad) and the horizontal acceleration in the gyro
        #: frame (m/s^2), at the last sample (the tilt model's inputs)
        self.ap_yaw_dev = 0.0
        self.accel_h = (0.0, 0.0)

    def turn(self, r_nb: F64, gyro_yaw: GyroYaw | None, matched: bool = False) -> tuple[YawTurn | None, bool]:
        """The yaw turn that gives ``r_nb`` the gyro's yaw (None: no gyro yaw, ``r_nb`` as it is; the turned
        attitude is :func:`yaw_turned`'s, made a block of samples at a time), and whether a window sequence
        starts anew (the gyro yaw stopped, or its chain restarted: a window never spans that)."""
        if gyro_yaw is None:
            restart = self.on
            self.on = False
            return None, restart
        restart = False
        epoch, yaw_g = gyro_yaw.epoch, gyro_yaw.yaw_rad
        yaw_ap = math.atan2(r_nb.item(1, 0), r_nb.item(0, 0))  # (item: the element as a float, no scalar)
        if not self.on or epoch != self._epoch:
            self.on, self._epoch = True, epoch
            self._offset = yaw_ap - yaw_g
            self._offset_cs = (math.cos(self._offset), math.sin(self._offset))
            restart = True
        a = yaw_g + self._offset - yaw_ap
        a_att = a + gyro_yaw.att_lead_rad if self.att_lead and not matched else a
        self.ap_yaw_dev = -((a_att + math.pi) % _TWO_PI - math.pi)  # wrapped to [-pi, pi)
        an, ae = gyro_yaw.accel_h_m_s2
        co, so = self._offset_cs
        self.accel_h = (co * an - so * ae, so * an + co * ae)
        return (math.cos(a), math.sin(a)), restart


def yaw_turned(r_nb: F64, cos_a: F64, sin_a: F64) -> F64:
    """``Rz(a) R_nb`` of a stack of attitudes (N, 3, 3) and their turns' cosines and sines (N,), ``Rz(a) =
    [[c, -s, 0], [s, c, 0], [0, 0, 1]]``: one stacked product, each slice the same numbers as its own
    3 x 3 product (numpy multiplies a stack slice by slice)."""
    rz = np.zeros((r_nb.shape[0], 3, 3))
    rz[:, 0, 0] = cos_a
    rz[:, 0, 1] = -sin_a
    rz[:, 1, 0] = sin_a
    rz[:, 1, 1] = cos_a
    rz[:, 2, 2] = 1.0
    return np.asarray(rz @ r_nb, dtype=np.float64)


class YawErrorLine:
    """The autopilot's tilt error that its own yaw error makes, for the tilt model's rows.

    The autopilot subtracts the GPS acceleration ``a`` from the specific force with its own yaw, so a yaw
    error ``psi`` leaves a horizontal ``-psi a`` that it takes for gravity: its tilt is off by the rotation
    ``-psi a / g`` (NED, horizontal; along ``a``, not across it: its attitude error is a rotation by ``psi``
    about the specific force, the one direction its accelerometer cannot see). ``psi`` = the autopilot's
    yaw minus the gyro's (known) + the gyro yaw's own error, which the windows' fields show: their
    direction against the WMM's, a straight line in time over the gyro chain (its bias) fitted to the
    closed windows."""

    def __init__(self) -> None:
        # sums of 1, t, t^2, f, t f of the closed windows of one chain, its epoch, the window being filled
        self._fit = np.zeros(5)
        self._fit_epoch = -1
        self._key: tuple[int, int] | None = None

    def tilt(
        self,
        est: WindowFields,
        t_s: F64,
        key: tuple[int, int],
        h_w: Vec3Like,
        ap_yaw_dev: F64,
        accel_h: F64,
    ) -> tuple[F64, F64]:
        """``psi`` (N,) and ``v x h`` (N, 3; NED, ``v = -a / g``) at times ``t_s`` (N,) in window ``key`` of
        field ``h_w``: the tilt's column per radian of yaw error is R^T (v x h) (``window_nuisance_cols``),
        the right-hand side has ``psi`` times it removed. ``est``: the estimator the rows go to (its windows'
        fields); ``ap_yaw_dev`` (N,), ``accel_h`` (N, 2): :class:`GyroYawFrame`'s at these samples."""
        if key != self._key:
            if self._key is not None:
                self._close(est, self._key)
            self._key = key
        if self._fit[0] < 3 or self._key[0] != self._fit_epoch:
            at: F64 | float = self.frame_of(est, h_w)
        else:
            a, b = self._line()
            at = a + b * t_s
        psi = np.remainder(ap_yaw_dev + at + math.pi, 2.0 * math.pi) - math.pi
        v = accel_h * (-1.0 / STANDARD_GRAVITY_M_S2)
        h1, h2, h3 = vec3(h_w)
        # (v1, v2, 0) x h
        vh = np.empty((t_s.shape[0], 3))
        vh[:, 0] = v[:, 1] * h3
        vh[:, 1] = -v[:, 0] * h3
        vh[:, 2] = v[:, 0] * h2 - v[:, 1] * h1
        return psi, vh

    @staticmethod
    def frame_of(est: WindowFields, h: Vec3Like) -> float:
        """The direction of the horizontal field ``h`` against the Earth field's (rad)."""
        ref = est.field_ned_mgauss
        return math.atan2(float(h[1]), float(h[0])) - math.atan2(float(ref[1]), float(ref[0]))

    def _close(self, est: WindowFields, key: tuple[int, int]) -> None:
        """A window closed: its field direction joins the line fit of the gyro frame's error."""
        e_w = est.window_nuisance(key)
        if e_w is None or key[0] != self._fit_epoch:
            if key[0] != self._fit_epoch:
                self._fit_epoch, self._fit = key[0], np.zeros(5)
            if e_w is None:
                return
        t = (key[1] + 0.5) * GYRO_WINDOW_S
        f = self.frame_of(est, np.asarray(e_w[:2]))
        if self._fit[0] > 0.0:  # unwrap against the line so far
            f = self._value(t) + (f - self._value(t) + math.pi) % (2.0 * math.pi) - math.pi
        self._fit += np.array([1.0, t, t * t, f, t * f])

    def _line(self) -> tuple[float, float]:
        """The line fit's value at t = 0 and its slope (a constant with fewer than three windows)."""
        n, st, stt, sf, stf = self._fit.tolist()
        den = n * stt - st * st
        if n < 3 or abs(den) < 1e-9:
            return sf / n, 0.0
        b = (n * stf - st * sf) / den
        return (sf - b * st) / n, b

    def _value(self, t: float) -> float:
        a, b = self._line()
        return a + b * t
