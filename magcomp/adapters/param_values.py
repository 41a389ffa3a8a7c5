"""Parameter values as the autopilot meant them: PARAM_VALUE's float field decoded per MAV_PARAM_TYPE, and
damaged (non-finite) values left out and counted."""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping

#: MAV_PARAM_TYPE's integer types (UINT8 .. INT64) as their struct codes, the value in the float's low bytes
_PARAM_INT_CODES = {1: "<B", 2: "<b", 3: "<H", 4: "<h", 5: "<I", 6: "<i", 7: "<I", 8: "<i"}


def param_value(value: float, param_type: int, bytewise: bool) -> float:
    """A PARAM_VALUE's value. ArduPilot casts every parameter to the float field (C cast); PX4 copies an
    integer parameter's bytes into it (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE: EKF2_GPS_CTRL = 15
    reads 2.1e-44 as a float, PWM_MAIN_MIN1 = 1000 reads 1.4e-42). Integer types are decoded from their bytes
    for a PX4 vehicle (``bytewise``), and whenever the float is no integer at all (the HEARTBEAT not seen
    yet: a C-cast integer is always a whole float, a byte copy of a nonzero integer below 2^30 never is)."""
    code = _PARAM_INT_CODES.get(param_type)
    if code is None or not (bytewise or not math.isfinite(value) or value != math.floor(value)):
        return value
    raw = struct.pack("<f", value)
    return float(struct.unpack_from(code, raw)[0])


def finite_params(params: Mapping[str, float], counts: dict[str, int]) -> dict[str, float]:
    """``params`` without the non-finite values (a damaged PARAM_VALUE / PARM / ULog parameter), each
    counted in ``non_finite_params``: the parameters decide compass forms, channels and rotations, and
    ``int(nan)`` raised in each of those places."""
    out = {}
    for name, value in params.items():
        if math.isfinite(value):
            out[name] = value
        else:
            counts["non_finite_params"] = counts.get("non_finite_params", 0) + 1
    return out
