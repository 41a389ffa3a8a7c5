"""A synthetic compass for the diagnosis's unit tests: a vehicle that does not rotate, its field given per
sample, its throttle (or motor commands) on the same time grid."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from magcomp.diagnosis.effects import DriveInputs
from magcomp.diagnosis.model import CompassData

F64 = NDArray[np.float64]


def stationary_compass(t_s: F64, field_mgauss: F64, dt_s: float, throttle_01: F64,
                       motors_01: F64 | None = None) -> CompassData:  # fmt: skip
    """Compass 0 at times ``t_s`` (uniform, ``dt_s`` apart) reading ``field_mgauss`` (n, 3), the body frame
    the Earth frame throughout; ``throttle_01`` the collective, ``motors_01`` (n, motors) if per motor."""
    drive = DriveInputs(
        t_s=t_s,
        grid_t_s=t_s,
        grid_dt_s=dt_s,
        throttle_grid=throttle_01,
        motors_grid=motors_01,
        voltage_grid=None,
        v_full_v=12.6,
        temperature_degc=None,
        throttle_dt_s=dt_s,
    )
    r = np.repeat(np.eye(3)[None], t_s.size, axis=0)
    why = "the vehicle does not rotate (synthetic)"
    return CompassData(0, t_s, field_mgauss, r, drive, "stationary", why)
