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

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcomp.core.rotations import euler_from_quat

F64 = NDArray[np.float64]


def heading_level_deg(m_x: ArrayLike, m_y: ArrayLike) -> F64:
    """Eq. (24) for a level vehicle, quadrant-resolved: ``atan2(-m_y, m_x)`` in [0, 360) deg."""
    psi = np.degrees(np.arctan2(-np.asarray(m_y, dtype=float), np.asarray(m_x, dtype=float)))  # eq. (24)
    return np.mod(psi, 360.0)


def field_level_frame(field_b_mgauss: ArrayLike, roll_rad: ArrayLike, pitch_rad: ArrayLike) -> F64:
    """Rotate body-FRD vectors into the level frame: ``Ry(pitch) @ Rx(roll) @ m``. Shapes (3,) or (n, 3)."""
    m = np.asarray(field_b_mgauss, dtype=float)
    phi = np.asarray(roll_rad, dtype=float)
    th = np.asarray(pitch_rad, dtype=float)
    mx, my, mz = m[..., 0], m[..., 1], m[..., 2]
    cr, sr, cp, sp = np.cos(phi), np.sin(phi), np.cos(th), np.sin(th)
    y_r = cr * my - sr * mz  # after Rx(roll)
    z_r = sr * my + cr * mz
    x_l = cp * mx + sp * z_r  # after Ry(pitch)
    z_l = -sp * mx + cp * z_r
    return np.stack([x_l, y_r, z_l], axis=-1)


def tilt_compensated_heading_deg(
    field_b_mgauss: ArrayLike,
    roll_rad: ArrayLike,
    pitch_rad: ArrayLike,
    declination_deg: float = 0.0,
) -> F64:
    """Heading in [0, 360) deg from the corrected body field and roll/pitch (vectorised).

    Parameters
    ----------
    field_b_mgauss : (3,) or (n, 3) calibrated, bias-corrected field, body FRD, mgauss
    roll_rad, pitch_rad : scalars or (n,), ZYX Euler angles of the body, rad
    declination_deg : added to the magnetic heading (east positive) to give a true heading; 0 -> magnetic

    Returns a 0-d array for one sample, (n,) otherwise.
    """
    lvl = field_level_frame(field_b_mgauss, roll_rad, pitch_rad)
    return np.mod(heading_level_deg(lvl[..., 0], lvl[..., 1]) + declination_deg, 360.0)


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
