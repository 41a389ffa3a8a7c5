"""Glue between the pipeline and the pure core: parameters from the configuration, one-sample helpers.

Kept separate from :mod:`magcomp.service.pipeline` so the per-sample path stays short to read, and so
that the scalar fast paths here can be tested against the vectorised core functions they mirror.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.config import Config
from magcomp.core.dpi import DpiParams, calibrate_dpi
from magcomp.core.lowpass import LowPassParams
from magcomp.core.observer import ObserverParams, ObserverState, observer_init, observer_reset, observer_step
from magcomp.geomag import earth_field_ned_mgauss
from magcomp.service.fastpath import FastObserver, FastStepInfo
from magcomp.service.fastpath import supports as fast_supports

F64 = NDArray[np.float64]

_DEG_PER_RAD = 180.0 / math.pi  # the factor of math.degrees


def earth_field(cfg: Config) -> F64:
    """WMM-2025 Earth field (N, E, D) mgauss at the configured location and date."""
    loc = cfg.location
    return earth_field_ned_mgauss(loc.lat_deg, loc.lon_deg, loc.alt_m, loc.decimal_year)


@dataclass(frozen=True)
class LearnedCalibration:
    calib_l: F64
    calib_d: F64
    residual_rms_mgauss: float
    coverage: float
    n: int


def calibrate(
    down_b: F64, field_raw_mgauss: F64, earth_ned_mgauss: F64, refine: bool = True
) -> LearnedCalibration | None:
    """DPI calibration, eq. (3), scaled to the WMM down component; None while the data cannot determine it.

    ``refine``: also the field-norm refinement of :mod:`magcomp.core.dpi` (a nonlinear least squares,
    tens of ms; the linear eq. (3) solve alone takes a few ms).
    """
    res = calibrate_dpi(
        down_b,
        field_raw_mgauss,
        field_down_mgauss=float(earth_ned_mgauss[2]),
        field_norm_mgauss=float(np.linalg.norm(earth_ned_mgauss)),
        p=DpiParams(min_samples=min(100, down_b.shape[0]), refine_with_norm=refine),
    )
    if not res.success:
        return None
    return LearnedCalibration(
        calib_l=np.asarray(res.L, dtype=float),
        calib_d=np.asarray(res.d, dtype=float),
        residual_rms_mgauss=float(res.residual_rms_mgauss),
        coverage=float(res.coverage.down_spread),
        n=int(res.n),
    )


def heading_deg(field_b_mgauss: F64, roll_rad: float, pitch_rad: float) -> float:
    """Tilt-compensated magnetic heading in [0, 360) deg; scalar twin of
    :func:`magcomp.core.heading.tilt_compensated_heading_deg` (eq. (24) after de-rotating roll and pitch)."""
    mx, my, mz = float(field_b_mgauss[0]), float(field_b_mgauss[1]), float(field_b_mgauss[2])
    return heading_from_trig(
        mx, my, mz, math.cos(roll_rad), math.sin(roll_rad), math.cos(pitch_rad), math.sin(pitch_rad)
    )


def heading_from_trig(mx: float, my: float, mz: float, cr: float, sr: float, cp: float, sp: float) -> float:
    """:func:`heading_deg` from the cosines and sines of roll and pitch (computed once per attitude)."""
    y_l = cr * my - sr * mz
    x_l = cp * mx + sp * (sr * my + cr * mz)
    return math.degrees(math.atan2(-y_l, x_l)) % 360.0  # eq. (24), quadrant-resolved


#: what one observer step reports (converged, z_unobservable, saturated, residual_norm_mgauss,
#: excitation): the fast path's own small record, also for the core path
ThetaStepInfo = FastStepInfo


class ThetaEstimator:
    """Mutable shell around :func:`magcomp.core.observer.observer_step` for one compass.

    Where the 5 Hz filter of sec. II-D goes follows the observer's own advice: in the default
    regression form it filters ``y`` and ``Phi`` alike (exact, no bias); the paper's form filters the
    field, gyro and throttle alike ("inputs"), never the field alone (which biases theta).
    """

    def __init__(self, cfg: Config, theta0_mgauss: F64) -> None:
        self.params = observer_params(cfg)
        state = observer_init(self.params, theta0_mgauss)
        self._fast = FastObserver(self.params, state) if fast_supports(self.params) else None
        self._state = state
        self.converged = False

    @property
    def theta_mgauss(self) -> F64:
        """theta-hat (mgauss), a new array."""
        return np.array(self.theta_values(), dtype=float)

    def theta_values(self) -> Sequence[float]:
        """theta-hat (mgauss) as three floats (not to be modified)."""
        if self._fast is not None:
            return self._fast.theta
        th = self._state.theta_hat_mgauss
        return float(th[0]), float(th[1]), float(th[2])

    @property
    def state(self) -> ObserverState:
        """The observer state as the core's :class:`ObserverState`."""
        return self._fast.to_state() if self._fast is not None else self._state

    def reset_filters(self) -> None:
        """Soft reset (gap, clock reset, new calibration): keeps theta and its information."""
        if self._fast is not None:
            self._fast.reset()
        else:
            self._state = observer_reset(self._state, self.params, keep_theta=True)

    def step(
        self,
        omega_b_rad_s: Sequence[float],
        field_b_mgauss: Sequence[float],
        throttle_01: float,
        dt_s: float,
    ) -> ThetaStepInfo:
        """One observer step; the vectors as floats (lists, tuples or arrays of three)."""
        if self._fast is not None:
            fi = self._fast.step(omega_b_rad_s, field_b_mgauss, throttle_01, dt_s)
            self.converged = fi.converged
            return fi
        self._state, info = observer_step(
            self._state, np.asarray(omega_b_rad_s, dtype=float), np.asarray(field_b_mgauss, dtype=float),
            throttle_01, dt_s, self.params,
        )  # fmt: skip
        self.converged = all(self._state.converged)
        return ThetaStepInfo(
            info.status,
            info.flags,
            self.converged,
            info.z_unobservable,
            info.residual_norm_mgauss,
            info.excitation_min_rad2_s2,
        )


def observer_params(cfg: Config) -> ObserverParams:
    """:class:`ObserverParams` from the ``[observer]`` and ``[filter]`` sections."""
    o = cfg.observer
    lp = LowPassParams(corner_hz=cfg.filter.corner_hz, order=cfg.filter.order)
    if o.form in ("default", "regression"):
        scheme, variant, prefilter = "regression", "delta_dot", "regression"
    elif o.form == "delta_dot":
        scheme, variant, prefilter = "observer", "delta_dot", "inputs"
    else:  # "paper": eq. (20) as printed, discretised by the observer module
        scheme, variant, prefilter = "observer", "paper", "inputs"
    return ObserverParams(
        k1_1_s=o.k1,
        k2=o.k2,
        scheme=scheme,  # type: ignore[arg-type]
        variant=variant,  # type: ignore[arg-type]
        prefilter=prefilter,  # type: ignore[arg-type]
        lowpass=lp,
        forget_s=o.forget_s,
        theta_max_mgauss=o.theta_max_mgauss,
        dt_min_s=o.dt_min_s,
        dt_max_s=o.dt_max_s,
    )


class HeadingFilter:
    """Gyro-aided complementary filter on a heading (deg): propagate with the yaw rate, pull toward the
    magnetometer heading with time constant ``tau_s``. ``tau_s = 0`` passes the measurement through.

    Not in the paper's observer, but what its Table III measured: the yaw of an attitude estimator
    that fuses the gyro with the (corrected) magnetometer, not the raw per-sample eq. (24). It removes
    most of the magnetometer noise (gain dt / tau) without the lag a low-pass would add. Near pitch
    +-90 deg heading is undefined and the filter restarts from the measurement.
    """

    __slots__ = ("psi_deg", "tau_s")

    def __init__(self, tau_s: float) -> None:
        self.tau_s = tau_s
        self.psi_deg: float | None = None

    def reset(self) -> None:
        self.psi_deg = None

    def update(self, psi_meas_deg: float, yaw_rate_rad_s: float, dt_s: float) -> float:
        if self.tau_s <= 0.0 or self.psi_deg is None or not math.isfinite(yaw_rate_rad_s) or dt_s <= 0.0:
            self.psi_deg = psi_meas_deg
            return psi_meas_deg
        pred = self.psi_deg + yaw_rate_rad_s * dt_s * _DEG_PER_RAD  # as math.degrees
        innov = (psi_meas_deg - pred + 180.0) % 360.0 - 180.0
        gain = dt_s / self.tau_s
        if gain > 1.0:
            gain = 1.0
        psi = (pred + gain * innov) % 360.0
        self.psi_deg = psi
        return psi


def yaw_rate_rad_s(gyro_b_rad_s: Sequence[float], roll_rad: float, pitch_rad: float) -> float:
    """Euler yaw rate from body rates (ZYX): (q sin(roll) + r cos(roll)) / cos(pitch); NaN near +-90 deg."""
    cp = math.cos(pitch_rad)
    if abs(cp) < 0.25:
        return float("nan")
    return (float(gyro_b_rad_s[1]) * math.sin(roll_rad) + float(gyro_b_rad_s[2]) * math.cos(roll_rad)) / cp
