"""Glue between the pipeline and the pure core: parameters from the configuration, one-sample helpers.

Kept separate from :mod:`magcomp.service.pipeline` so the per-sample path stays short to read.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.config import Config, ObserverForm
from magcomp.core.dpi import DpiParams, calibrate_dpi
from magcomp.core.heading import heading_from_trig_deg
from magcomp.core.linalg3 import Vec3Like
from magcomp.core.lowpass import LowPassParams
from magcomp.core.mahony import MahonyParams
from magcomp.core.observer import (
    ObserverParams,
    ObserverState,
    Prefilter,
    Scheme,
    StepInfo,
    Variant,
    observer_init,
    observer_reset,
    observer_skip,
    observer_step,
)
from magcomp.core.types import STANDARD_GRAVITY_M_S2
from magcomp.geomag import earth_field_ned_mgauss

F64 = NDArray[np.float64]



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
    """Tilt-compensated magnetic heading in [0, 360) deg of one sample from roll and pitch (rad):
    :func:`magcomp.core.heading.heading_from_trig_deg`."""
    mx, my, mz = float(field_b_mgauss[0]), float(field_b_mgauss[1]), float(field_b_mgauss[2])
    return heading_from_trig_deg(
        mx, my, mz, math.cos(roll_rad), math.sin(roll_rad), math.cos(pitch_rad), math.sin(pitch_rad)
    )


#: what one observer step reports (flags, z_unobservable, saturated, residual_norm_mgauss, excitation, ...)
ThetaStepInfo = StepInfo


class ThetaEstimator:
    """Mutable shell around :func:`magcomp.core.observer.observer_step` for one compass: it holds the
    immutable :class:`ObserverState` between samples.

    Where the 5 Hz filter of sec. II-D goes follows the observer's own advice: in the default
    regression form it filters ``y`` and ``Phi`` alike (exact, no bias); the paper's form filters the
    field, gyro and throttle alike ("inputs"), never the field alone (which biases theta).
    """

    __slots__ = ("converged", "params", "state")

    def __init__(self, cfg: Config, theta0_mgauss: F64 | None) -> None:
        """``theta0_mgauss``: a stored theta (a prior: see :func:`magcomp.core.observer.observer_init`);
        None or all zeros: nothing known, start from 0."""
        self.params = observer_params(cfg)
        known = theta0_mgauss is not None and bool(np.any(np.asarray(theta0_mgauss) != 0.0))
        prior = theta0_mgauss if known else None
        self.state: ObserverState = observer_init(self.params, prior)
        self.converged = False

    @property
    def theta_mgauss(self) -> F64:
        """theta-hat (mgauss), a new array."""
        return np.array(self.state.theta_hat_mgauss, dtype=float)

    def theta_values(self) -> Sequence[float]:
        """theta-hat (mgauss) as three floats."""
        return self.state.theta_hat_mgauss

    def reset_filters(self) -> None:
        """Soft reset (gap, clock reset, new calibration): keeps theta and its information."""
        self.state = observer_reset(self.state, self.params, keep_theta=True)

    def skip(self) -> None:
        """Samples missing before the next one: no step across them, the filters kept
        (:func:`~magcomp.core.observer.observer_skip`)."""
        self.state = observer_skip(self.state)

    def hold(self, theta_mgauss: F64, converged: bool) -> None:
        """theta from elsewhere (the batch solve of a learn-only pass: service/theta.py), its filters as they
        are."""
        t = np.asarray(theta_mgauss, dtype=float).reshape(3)
        self.state = self.state._replace(theta_hat_mgauss=(float(t[0]), float(t[1]), float(t[2])))
        self.converged = converged

    def step(
        self,
        omega_b_rad_s: Vec3Like,
        field_b_mgauss: Vec3Like,
        throttle_01: float,
        dt_s: float,
    ) -> ThetaStepInfo:
        """One observer step; the vectors as floats (lists, tuples or arrays of three)."""
        self.state, info = observer_step(
            self.state, omega_b_rad_s, field_b_mgauss, throttle_01, dt_s, self.params
        )
        c = self.state.converged
        self.converged = c[0] and c[1] and c[2]
        return info


#: ``[observer] form`` -> (scheme, variant, prefilter) of :class:`ObserverParams`
_FORMS: dict[ObserverForm, tuple[Scheme, Variant, Prefilter]] = {
    "default": ("regression", "delta_dot", "regression"),
    "regression": ("regression", "delta_dot", "regression"),
    "delta_dot": ("observer", "delta_dot", "inputs"),  # eq. (20) with the throttle-rate term of eq. (16)
    "paper": ("observer", "paper", "inputs"),  # eq. (20) as printed, discretised by the observer module
}


def observer_params(cfg: Config) -> ObserverParams:
    """:class:`ObserverParams` from the ``[observer]`` and ``[filter]`` sections: the one place the
    configuration becomes observer parameters (the defaults agree; tests/unit/test_config.py)."""
    o = cfg.observer
    scheme, variant, prefilter = _FORMS[o.form]
    return ObserverParams(
        k1_1_s=o.k1,
        k2=o.k2,
        scheme=scheme,
        variant=variant,
        prefilter=prefilter,
        lowpass=LowPassParams(corner_hz=cfg.filter.corner_hz, order=cfg.filter.order),
        forget_s=o.forget_s,
        theta_max_mgauss=o.theta_max_mgauss,
        dt_min_s=o.dt_min_s,
        dt_max_s=o.dt_max_s,
    )


def mahony_params(cfg: Config) -> MahonyParams:
    """:class:`MahonyParams` from the ``[mahony]`` section: the one place the configuration becomes the
    attitude filter's parameters (as :func:`observer_params` for the observer)."""
    m = cfg.mahony
    return MahonyParams(kp=m.kp, ki=m.ki, accel_gate_frac=m.accel_gate_m_s2 / STANDARD_GRAVITY_M_S2)



