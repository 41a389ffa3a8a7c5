"""PX4's magnetometer calibration (src/lib/sensor_calibration/Magnetometer): how a ``sensor_mag`` sample, in
its driver's frame, becomes the body-frame field PX4 fuses, and back. Pure numpy, no I/O.

PX4 corrects ``m_body = R S (m + power * COMP - OFF)``: CAL_MAGn_OFF the offsets, S the symmetric scale
(CAL_MAGn_SCALE on the diagonal, CAL_MAGn_ODIAG off it), R the rotation (CAL_MAGn_ROT for an external compass,
the board's SENS_BOARD_ROT fine-tuned by SENS_BOARD_X/Y/Z_OFF for an internal one, whose CAL_MAGn_ROT is -1),
``power * COMP`` its optional linear power compensation (CAL_MAG_COMP_TYP). Units: gauss; angles in degrees
in the parameters.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from magcomp.core.rotations import dcm_from_euler

F64 = NDArray[np.float64]

#: PX4's sensor rotations (src/lib/conversion/rotation.h ``rot_lookup``): roll, pitch, yaw in degrees by
#: enum value, applied as the ZYX Euler DCM (board or external compass frame -> body FRD)
PX4_ROTATIONS_DEG = (
    (0, 0, 0), (0, 0, 45), (0, 0, 90), (0, 0, 135), (0, 0, 180), (0, 0, 225), (0, 0, 270), (0, 0, 315),
    (180, 0, 0), (180, 0, 45), (180, 0, 90), (180, 0, 135), (0, 180, 0), (180, 0, 225), (180, 0, 270),
    (180, 0, 315), (90, 0, 0), (90, 0, 45), (90, 0, 90), (90, 0, 135), (270, 0, 0), (270, 0, 45),
    (270, 0, 90), (270, 0, 135), (0, 90, 0), (0, 270, 0), (0, 180, 90), (0, 180, 270), (90, 90, 0),
    (180, 90, 0), (270, 90, 0), (90, 180, 0), (270, 180, 0), (90, 270, 0), (180, 270, 0), (270, 270, 0),
    (90, 180, 90), (90, 0, 270), (90, 68, 293), (0, 315, 0), (90, 315, 0), (270, 0, 180), (270, 0, 270),
    (0, 90, 180), (0, 9, 180), (0, 45, 0), (270, 0, 225), (270, 0, 315),
)  # fmt: skip


def px4_mag_rotation(params: Mapping[str, float], cal_index: int | None) -> F64:
    """The rotation PX4 applies to compass ``cal_index``'s ``sensor_mag`` (sensor frame -> body FRD): an
    external compass's CAL_MAGn_ROT (>= 0), else the board's (an internal compass: CAL_MAGn_ROT = -1),
    SENS_BOARD_ROT fine-tuned by SENS_BOARD_X/Y/Z_OFF (deg). Identity when the parameters do not say."""

    def table(value: float | None) -> F64 | None:
        if value is None or not np.isfinite(value) or not 0 <= int(value) < len(PX4_ROTATIONS_DEG):
            return None
        return dcm_from_euler(*np.radians(PX4_ROTATIONS_DEG[int(value)]))

    rot = None if cal_index is None else params.get(f"CAL_MAG{cal_index}_ROT")
    external = table(rot) if rot is not None and rot >= 0 else None
    if external is not None:
        return external
    board = table(params.get("SENS_BOARD_ROT", 0.0))
    offs = [params.get(f"SENS_BOARD_{a}_OFF", 0.0) for a in "XYZ"]
    fine = dcm_from_euler(*np.radians(offs)) if all(np.isfinite(offs)) else np.eye(3)
    return fine @ (np.eye(3) if board is None else board)


def px4_calibrated_mag(params: Mapping[str, float], cal_index: int | None, xyz_gauss: F64) -> F64:
    """``sensor_mag`` (sensor frame, before PX4's calibration) as PX4's own calibration leaves it, without
    its power compensation: ``R S (m - offset)`` (sensor_calibration/Magnetometer: CAL_MAGn_OFF, the
    symmetric scale CAL_MAGn_SCALE / ODIAG, the rotation of :func:`px4_mag_rotation`), so that it is in the
    body frame with the autopilot's calibration removed, as ``vehicle_magnetometer`` and ArduPilot's fields
    are (the in-flight estimator's prior is that calibration)."""

    off = _vec(params, cal_index, "OFF", 0.0)
    m = px4_calibration_matrix(params, cal_index)
    return np.asarray((xyz_gauss - off) @ m.T, dtype=np.float64)


def px4_calibration_matrix(params: Mapping[str, float], cal_index: int | None) -> F64:
    """``R S`` of compass ``cal_index``: what PX4 multiplies a raw sample (offsets removed) by; its inverse
    takes a body-frame bias back to the raw frame CAL_MAGn_COMP is added in."""
    diag, odiag = _vec(params, cal_index, "SCALE", 1.0), _vec(params, cal_index, "ODIAG", 0.0)
    scale = np.array(
        [[diag[0], odiag[0], odiag[1]], [odiag[0], diag[1], odiag[2]], [odiag[1], odiag[2], diag[2]]]
    )
    return np.asarray(px4_mag_rotation(params, cal_index) @ scale, dtype=np.float64)


def _vec(params: Mapping[str, float], cal_index: int | None, key: str, default: float) -> F64:
    """CAL_MAGn_{X,Y,Z}<key> (non-finite or missing: ``default``)."""
    if cal_index is None:
        return np.full(3, default)
    v = np.array([params.get(f"CAL_MAG{cal_index}_{a}{key}", default) for a in "XYZ"], dtype=np.float64)
    return np.where(np.isfinite(v), v, default)
