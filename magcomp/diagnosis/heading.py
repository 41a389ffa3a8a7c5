"""Heading of a compass after its fitted calibration and bias removal, and its error against a reference
heading (simulated truth, or a compass far from the wires). Pure, no I/O."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from magcomp.core.heading import tilt_compensated_heading_deg, wrap_deg_180
from magcomp.core.rotations import euler_from_dcms
from magcomp.diagnosis.effects import drive_columns
from magcomp.diagnosis.model import CompassData, ModelFit
from magcomp.diagnosis.results import HeadingErrors

F64 = NDArray[np.float64]


def compass_yaw_rad(data: CompassData, fit: ModelFit, remove_bias: bool = True) -> F64:
    """Heading (rad) implied by the field after the fitted calibration (and bias removal), tilt-compensated
    with the forward model's compass-free roll and pitch; magnetic, up to a constant."""
    v = data.field_mgauss - fit.c_mgauss
    cols, _ = drive_columns(data.drive, fit.ext)
    if remove_bias:
        v = v - cols @ fit.coefs
    elif "temperature" in fit.columns:
        i = list(fit.columns).index("temperature")
        v = v - np.outer(cols[:, i], fit.coefs[i])
    if data.attitude_source == "stationary" or np.linalg.cond(fit.a_mgauss) > 20.0:
        # no rotation, no calibration: the raw field (hard iron and all) still shows heading *changes*
        h_b = np.asarray(v + fit.c_mgauss, dtype=float)
    else:
        h_b = np.asarray(np.linalg.solve(fit.a_mgauss, v.T).T, dtype=float)
    roll, pitch, _ = euler_from_dcms(data.r_nb).T
    # eq. (24), tilt-compensated: the one implementation in core (range [-pi, pi) here)
    return np.radians(wrap_deg_180(tilt_compensated_heading_deg(h_b, roll, pitch)))


def heading_errors(
    data: CompassData, fits: dict[str, ModelFit], ref_t_s: F64, ref_yaw_rad: F64, reference: str
) -> HeadingErrors:
    """rms / max heading error (deg) of each fit against a reference heading, constant offset removed."""
    ref = np.interp(data.t_s, ref_t_s, np.unwrap(ref_yaw_rad))
    r = data.r_nb
    level = r[:, 2, 2] > math.cos(math.radians(45.0))  # heading is defined (tilt below 45 deg)
    if np.count_nonzero(level) < 10:
        level = np.ones(data.n, dtype=bool)
    rms: dict[str, float] = {}
    mx: dict[str, float] = {}
    for name, fit in fits.items():
        yaw = compass_yaw_rad(data, fit, remove_bias=name != "uncompensated")[level]
        e = np.angle(np.exp(1j * (yaw - ref[level])))
        e = np.angle(np.exp(1j * (e - np.angle(np.mean(np.exp(1j * e))))))
        rms[name] = round(math.degrees(float(np.sqrt(np.mean(e**2)))), 3)
        mx[name] = round(math.degrees(float(np.max(np.abs(e)))), 3)
    return HeadingErrors(reference, rms, mx, reference_yaw_rad=ref)
