"""Magnetic heading from a calibrated, bias-corrected field: eq. (24) and its tilt-compensated form.

Reference: M. Silic and K. Mohseni, "Correcting Current-Induced Magnetometer Errors on UAVs: An Online
Model-Based Approach", IEEE Sensors J. 20(2), 2020; equation numbers as in that article.

Eq. (24), ``psi = -atan(m_y / m_x)``, holds for a level vehicle. We generalise it (departure from the
paper): the body field is first de-rotated by roll and pitch into the level ("yaw") frame, then
``psi = atan2(-m_y_level, m_x_level)``, which also resolves the quadrant. Result in [0, 360).

Symbols: m -> field_b_mgauss (calibrated, bias removed; body FRD, mgauss); phi, theta -> roll_rad,
pitch_rad (ZYX Euler, rad); psi -> heading_deg (magnetic, deg, clockwise from magnetic north).
"""

from __future__ import annotations

import math
from typing import Any, overload

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcomp.core.rotations import euler_from_quat

F64 = NDArray[np.float64]


@overload
def heading_from_trig_deg(
    mx: float, my: float, mz: float, cos_roll: float, sin_roll: float, cos_pitch: float, sin_pitch: float
) -> float: ...


@overload
def heading_from_trig_deg(
    mx: F64, my: F64, mz: F64, cos_roll: F64, sin_roll: F64, cos_pitch: F64, sin_pitch: F64
) -> F64: ...


def heading_from_trig_deg(
    mx: Any, my: Any, mz: Any, cos_roll: Any, sin_roll: Any, cos_pitch: Any, sin_pitch: Any
) -> Any:
    """Tilt-compensated eq. (24), in [0, 360) deg: the body field ``(mx, my, mz)`` (mgauss) de-rotated by
    roll and pitch (given as their cosines and sines, computed once per attitude sample) into the level
    frame, then ``atan2(-m_y_level, m_x_level)``. The one place the formula is written; the per-sample
    path (magcomp.service.heading) calls it with floats, the two-pass replay (service/final_pass.py) with
    arrays of a whole log (the same arithmetic; the angle from numpy's arctan2 on arrays)."""
    y_l = cos_roll * my - sin_roll * mz  # after Rx(roll)
    x_l = cos_pitch * mx + sin_pitch * (sin_roll * my + cos_roll * mz)  # after Ry(pitch)
    if type(x_l) is float:  # one sample: math's atan2 (a third of numpy's cost on a float)
        return math.degrees(math.atan2(-y_l, x_l)) % 360.0  # eq. (24), quadrant-resolved
    return np.degrees(np.arctan2(-y_l, x_l)) % 360.0  # eq. (24) on arrays


def heading_level_deg(m_x: ArrayLike, m_y: ArrayLike) -> F64:
    """Eq. (24) for a level vehicle, quadrant-resolved: ``atan2(-m_y, m_x)`` in [0, 360) deg (arrays;
    :func:`heading_from_trig_deg` at zero roll and pitch)."""
    mx, my = np.broadcast_arrays(np.asarray(m_x, dtype=float), np.asarray(m_y, dtype=float))
    xs, ys = mx.ravel().tolist(), my.ravel().tolist()
    out = [heading_from_trig_deg(x, y, 0.0, 1.0, 0.0, 1.0, 0.0) for x, y in zip(xs, ys, strict=True)]
    return np.array(out, dtype=float).reshape(mx.shape)


def tilt_compensated_heading_deg(
    field_b_mgauss: ArrayLike,
    roll_rad: ArrayLike,
    pitch_rad: ArrayLike,
    declination_deg: float = 0.0,
) -> F64:
    """Heading in [0, 360) deg from the corrected body field and roll/pitch (arrays; a loop over
    :func:`heading_from_trig_deg`, used off the per-sample path).

    Parameters
    ----------
    field_b_mgauss : (3,) or (n, 3) calibrated, bias-corrected field, body FRD, mgauss
    roll_rad, pitch_rad : scalars or (n,), ZYX Euler angles of the body, rad
    declination_deg : added to the magnetic heading (east positive) to give a true heading; 0 -> magnetic

    Returns a 0-d array for one sample, (n,) otherwise.
    """
    m = np.asarray(field_b_mgauss, dtype=float)
    shape = m.shape[:-1]
    phi = np.broadcast_to(np.asarray(roll_rad, dtype=float), shape).ravel().tolist()
    th = np.broadcast_to(np.asarray(pitch_rad, dtype=float), shape).ravel().tolist()
    rows = m.reshape(-1, 3).tolist()
    cos, sin = math.cos, math.sin
    out = [heading_from_trig_deg(x, y, z, cos(r), sin(r), cos(p), sin(p))
           for (x, y, z), r, p in zip(rows, phi, th, strict=True)]  # fmt: skip
    return np.mod(np.array(out, dtype=float).reshape(shape) + declination_deg, 360.0)


def heading_from_quat_deg(field_b_mgauss: ArrayLike, q_nb: ArrayLike, declination_deg: float = 0.0) -> float:
    """Tilt-compensated heading using the roll and pitch of ``q_nb`` (its yaw is ignored)."""
    roll, pitch, _ = euler_from_quat(q_nb)
    return float(tilt_compensated_heading_deg(field_b_mgauss, roll, pitch, declination_deg))


def declination_rad(field_ned_mgauss: ArrayLike) -> float:
    """Magnetic declination (rad, east positive) of an NED field vector: ``atan2(east, north)``."""
    f = np.asarray(field_ned_mgauss, dtype=float)
    return math.atan2(float(f[1]), float(f[0]))


def declination_deg(field_ned_mgauss: ArrayLike) -> float:
    """Magnetic declination (deg, east positive) of an NED field vector."""
    return math.degrees(declination_rad(field_ned_mgauss))


def wrap_deg_180(angle_deg: ArrayLike) -> F64:
    """Wrap angles (deg) into [-180, 180): use for heading errors."""
    return np.mod(np.asarray(angle_deg, dtype=float) + 180.0, 360.0) - 180.0
