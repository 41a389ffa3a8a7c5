"""The compass-free heading's wander from the gyro bias, removed before the search (issue 10, repeatability).

The forward model (:mod:`magcomp.diagnosis.model`) takes the gyro-integrated heading with a drift that is
linear in time: a gyro bias about the *vertical*. But a gyro's bias is constant in *body* axes, b_b; what
turns the heading is its projection on the vertical, d(psi)/dt = (R_nb b_b)_z = sum_k b_k (R_nb)_zk, which
changes with every bank and pitch (eq. (18) integrated with a biased rate; the tilt filter of
:mod:`magcomp.diagnosis.attitude` removes the tilt part but nothing observes the heading part). So in a flight
with turns the heading wanders around its linear drift; in the simulated pairs of
``benchmarks/diagnosis_flight_pairs.py`` by 1.9-3.5 deg rms, and a 1 deg heading error is ~9 mgauss on a 500
mgauss field: the largest cause of theta differing between two flights of one vehicle (with the simulator's
true attitude the two thetas agree to their intervals). Regressing the simulated heading error on the three
integrals I_k(t) = int (R_nb)_zk dt left 0.9 / 1.2 / 0.2 deg rms of 3.5 / 1.9 / 0.4.

Here the three body-axis bias components are fitted with the paper's model (eq. (11), linear parameters by
least squares as in the model, inc / dec / drift refitted with them) and the heading of R_nb is corrected by
sum_k b_k I_k(t) before anything else sees it. I_z's linear part is left to the model's own drift term.
Departure from the paper: the paper's attitude comes from a Mahony filter with the compass; ours never sees
the compass, so its heading needs this nuisance. Only for a gyro-integrated heading (not the autopilot's
attitude, not a stationary log).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from magcomp.diagnosis.effects import ExtensionParams, drive_columns
from magcomp.diagnosis.model import CompassData, earth_dir_body, initial_fit

F64 = NDArray[np.float64]

#: bound on each body-axis gyro bias component (rad/s), as the model's heading drift (0.05 rad/s = 2.9 deg/s)
MAX_BIAS_RAD_S = 0.05


def vertical_integrals(t_s: F64, r_nb: F64) -> F64:
    """(n, 3) I_k(t) = int (R_nb)_zk dt (trapezoid), zero at mid-log; I_z with its least-squares line in t
    removed (the linear drift is the model's own parameter)."""
    rz = r_nb[:, 2, :]
    dt = np.diff(t_s)
    integ = np.vstack([np.zeros((1, 3)), np.cumsum(0.5 * (rz[1:] + rz[:-1]) * dt[:, None], axis=0)])
    integ = integ - integ[integ.shape[0] // 2]
    tt = t_s - t_s.mean()
    a = np.column_stack([np.ones_like(tt), tt])
    coef, *_ = np.linalg.lstsq(a, integ[:, 2], rcond=None)
    integ[:, 2] = integ[:, 2] - a @ coef
    return np.asarray(integ)


def turn_heading(r_nb: F64, psi_rad: F64) -> F64:
    """Rz(psi) R_nb per sample: the heading of ``r_nb`` turned by ``psi_rad`` (n,) about NED down."""
    c, s = np.cos(psi_rad)[:, None], np.sin(psi_rad)[:, None]
    r0, r1, r2 = r_nb[:, 0, :], r_nb[:, 1, :], r_nb[:, 2, :]
    # the product with Rz = [[c, -s, 0], [s, c, 0], [0, 0, 1]] written out, its zero terms kept: the same
    # numbers as the 3x3 product per sample, a third of the time (it runs once per step of the fit)
    out = np.empty_like(r_nb)
    out[:, 0, :] = c * r0 - s * r1 + 0.0 * r2
    out[:, 1, :] = s * r0 + c * r1 + 0.0 * r2
    out[:, 2, :] = 0.0 * r0 + 0.0 * r1 + r2
    return out


def with_gyro_bias_heading(data: CompassData) -> CompassData:
    """``data`` with its gyro-integrated heading corrected for the fitted body-axis gyro bias (docstring);
    unchanged for other attitude sources or when the fit does not lower the residual."""
    if not data.attitude_source.startswith("gyro") or data.n < 50:
        return data
    start = initial_fit(data)
    integ = vertical_integrals(data.t_s, data.r_nb)
    cols, _ = drive_columns(data.drive, ExtensionParams())
    v = data.field_mgauss

    turned: list[tuple[tuple[float, ...], CompassData]] = []  # the last bias and its data

    def rotated(b: F64) -> CompassData:
        # a finite-difference step in inc, dec or drift keeps the bias: the same turned rotations
        key = tuple(b.tolist())
        if not turned or turned[0][0] != key:
            turned[:] = [(key, replace(data, r_nb=turn_heading(data.r_nb, integ @ b)))]
        return turned[0][1]

    def residual(z: F64) -> F64:
        d2 = rotated(z[3:])
        h = earth_dir_body(d2, float(z[0]), float(z[1]), float(z[2]))
        x = np.column_stack([h, np.ones(data.n), cols])
        beta, *_ = np.linalg.lstsq(x, v, rcond=1e-10)
        return np.asarray((x @ beta - v).ravel())

    z0 = np.array([start.inc_rad, start.dec_rad, start.drift_rad_s, 0.0, 0.0, 0.0])
    lo = np.array([-math.pi / 2, -4 * math.pi, -0.05, -MAX_BIAS_RAD_S, -MAX_BIAS_RAD_S, -MAX_BIAS_RAD_S])
    z0 = np.clip(z0, lo + 1e-9, -lo - 1e-9)
    scale = [0.1, 0.1, 1e-3, 1e-3, 1e-3, 1e-3]
    sol = least_squares(residual, z0, bounds=(lo, -lo), max_nfev=60, x_scale=scale)
    if float(np.sum(sol.fun**2)) >= float(np.sum(residual(z0) ** 2)):
        return data
    b = sol.x[3:]
    note = (
        data.attitude_note
        + "; the heading is corrected for the gyro bias's projection on the vertical through tilt (body bias "
        + ", ".join(f"{1e3 * x:.2f}" for x in b)
        + " mrad/s, fitted with the paper's model)"
    )
    at_bound = [f"{'xyz'[i]}" for i in range(3) if abs(float(b[i])) >= MAX_BIAS_RAD_S * (1.0 - 1e-3)]
    flags = data.nuisance_flags
    if at_bound:
        flags = (
            *flags,
            f"the gyro bias fitted to the heading sits on its +-{1e3 * MAX_BIAS_RAD_S:.0f} mrad/s bound "
            f"(body {', '.join(at_bound)}): the heading wants more correction than a gyro bias can be, so "
            "something else (a heading error of the attitude source, a magnetic disturbance) is being "
            "absorbed and the rotation, and what is fitted through it, is less certain than the intervals "
            "say",
        )
    return replace(rotated(b), attitude_note=note, nuisance_flags=flags)
