"""What ArduPilot's and PX4's parameters mean to magcomp, in one place: which compass the autopilot takes
its yaw from, whether that yaw comes from a compass at all, which compasses are external, which the
autopilot calibrated, what motor compensation it applies itself. Pure functions of a parameter dictionary
(name -> value as received); no I/O."""

from __future__ import annotations

import math

from magcomp.core.inflight.base import InflightMode

#: ArduPilot's per-compass "external" flags (0 internal, 1 external, 2 forced external), by compass index
ARDUPILOT_EXTERNAL_PARAMS = ("COMPASS_EXTERNAL", "COMPASS_EXTERN2", "COMPASS_EXTERN3")
#: ArduPilot's hard-iron offsets by compass index (any non-zero: the autopilot calibrated that compass)
ARDUPILOT_OFFSET_PARAMS = ("COMPASS_OFS_", "COMPASS_OFS2_", "COMPASS_OFS3_")


#: ArduPilot's EKF3 yaw sources that are not a compass (EK3_SRC1_YAW, AP_NavEKF_Source): 3 falls back to the
#: compass only while the GPS yaw is lost
EK3_YAW_NOT_COMPASS = {
    2: "GPS",
    3: "GPS",
    6: "external navigation",
    8: "the GSF yaw estimator (GPS velocity and the IMU)",
}


def yaw_reference(params: dict[str, float], mag_index: int) -> tuple[InflightMode, str]:
    """The form for compass ``mag_index`` from the autopilot's parameters, and why (one phrase).

    absolute: the autopilot's yaw comes from no compass (ArduPilot EK3_SRC1_YAW = 2, 3, 6 or 8 with EKF3
    active; PX4 EKF2_GPS_CTRL bit 3, EKF2_MAG_TYPE = 5) or from another compass that is external
    (ArduPilot COMPASS_PRIMARY, instance 0 since 4.1 orders compasses by COMPASS_PRIOn_ID, and
    COMPASS_EXTERNAL*).
    relative: the yaw is fused from this compass, or from an internal one that sees the same currents, or
    the parameters do not say (a tlog without PARAM_VALUE): the safe form.
    """
    src = params.get("EK3_SRC1_YAW")
    ekf3 = int(params.get("AHRS_EKF_TYPE", 3.0)) == 3  # EKF3's sources matter only when it flies
    if ekf3 and src is not None and int(src) in EK3_YAW_NOT_COMPASS:
        why = f"the autopilot's yaw comes from {EK3_YAW_NOT_COMPASS[int(src)]} (EK3_SRC1_YAW = {int(src)})"
        return "absolute", why
    gps_ctrl = params.get("EKF2_GPS_CTRL")
    if gps_ctrl is not None and int(gps_ctrl) & 8:
        return "absolute", "the autopilot's yaw comes from GPS (EKF2_GPS_CTRL bit 3)"
    mag_type = params.get("EKF2_MAG_TYPE")
    if mag_type is not None and int(mag_type) == 5:  # PX4 EKF2: no magnetometer fused (GPS / vision yaw)
        return "absolute", "the autopilot fuses no magnetometer (EKF2_MAG_TYPE = 5)"
    if "COMPASS_PRIMARY" not in params and not any(k in params for k in ARDUPILOT_EXTERNAL_PARAMS):
        return "relative", "the autopilot's yaw source is unknown (no compass parameters): rotations only"
    primary = ardupilot_primary_compass(params)
    if primary == mag_index:
        return "relative", f"the autopilot's yaw is fused from this compass (primary {primary})"
    ext_key = ARDUPILOT_EXTERNAL_PARAMS[primary] if 0 <= primary < len(ARDUPILOT_EXTERNAL_PARAMS) else ""
    ext = params.get(ext_key)
    if ext is not None and int(ext) in (1, 2):
        why = f"the autopilot's yaw comes from compass {primary}, external ({ext_key} = {int(ext)})"
        return "absolute", why
    return "relative", f"the autopilot's yaw comes from compass {primary}, internal: rotations only"


#: ArduPilot's per-compass "use for yaw" flags, by compass index
ARDUPILOT_USE_PARAMS = ("COMPASS_USE", "COMPASS_USE2", "COMPASS_USE3")


def ardupilot_primary_compass(params: dict[str, float]) -> int:
    """The compass ArduPilot's EKF takes its yaw from: COMPASS_PRIMARY (up to 4.0) when that compass is used
    for yaw, else the first compass with COMPASS_USEn set (4.1 on has no COMPASS_PRIMARY: it orders the
    compasses by COMPASS_PRIOn_ID, so the first usable one is the primary); 0 when nothing says."""
    primary = int(params.get("COMPASS_PRIMARY", 0.0))
    usable = [i for i, k in enumerate(ARDUPILOT_USE_PARAMS) if params.get(k, 1.0) != 0.0]
    if primary in usable or not usable:
        return primary
    return usable[0]


def calibrated_by_autopilot(params: dict[str, float], mag_index: int) -> bool | None:
    """True when the autopilot's own hard-iron offsets for this compass are set (its calibration is the
    prior), False when they are all zero, None when the parameters do not say."""
    if 0 <= mag_index < len(ARDUPILOT_OFFSET_PARAMS):
        pre = ARDUPILOT_OFFSET_PARAMS[mag_index]
        vals = [params.get(pre + a) for a in "XYZ"]
        if all(v is not None for v in vals):
            return any(abs(float(v)) > 0.0 for v in vals if v is not None)
    pre_px4 = f"CAL_MAG{mag_index}_"
    vals = [params.get(pre_px4 + a + "OFF") for a in "XYZ"]
    if all(v is not None for v in vals):
        return any(abs(float(v)) > 0.0 for v in vals if v is not None)
    return None


def external_compass(params: dict[str, float], mag_index: int) -> bool | None:
    """True when the autopilot's parameters mark compass ``mag_index`` external (mounted away from the power
    wires, e.g. on a GPS mast), False when internal, None when they do not say."""
    if not 0 <= mag_index < len(ARDUPILOT_EXTERNAL_PARAMS):
        return None
    v = params.get(ARDUPILOT_EXTERNAL_PARAMS[mag_index])
    return None if v is None else int(v) in (1, 2)


def relative_rotation_source(params: dict[str, float], mag_index: int) -> tuple[str, str]:
    """Where the relative form takes its rotations from: ``attitude`` (the autopilot's) whenever it
    streams. Its roll and pitch are GPS-aided; its yaw may follow a disturbed compass, but only slowly
    (the compass correction of its filter), and the relative form carries that slow yaw-rate error as a
    nuisance (InflightEstimator.add). The pipeline's own gyro integral is the fallback: its bias comes
    from an accelerometer-only attitude filter, which in accelerated flight takes the thrust axis for
    down and moves the bias by degrees per second (docs/inflight.md)."""
    if external_compass(params, mag_index):
        return "attitude", "this compass is external (little disturbed): the autopilot's GPS-aided attitude"
    return "attitude", "the autopilot's attitude (GPS-aided tilt; its compass-driven yaw drift estimated)"


# ----------------------------------------------------------------------------------------------------------
# ArduPilot's own motor compensation (COMPASS_MOTCT, COMPASS_MOT*, COMPASS_PMOT_EN; AP_Compass)

#: COMPASS_MOTCT values (ArduPilot AP_COMPASS_MOT_COMP_*): the offset per unit throttle, or per amp
MOTCT_THROTTLE = 1
MOTCT_CURRENT = 2


def is_motor_comp_param(name: str) -> bool:
    """A parameter of ArduPilot's motor compensation (COMPASS_MOTCT, COMPASS_MOT*, COMPASS_PMOT_EN)."""
    return name.startswith("COMPASS_MOT") or name == "COMPASS_PMOT_EN"


def motor_comp_prefix(mag_index: int) -> str:
    """The COMPASS_MOT vector's name prefix of compass ``mag_index``: COMPASS_MOT_ for the first compass,
    COMPASS_MOT2_, COMPASS_MOT3_ for the others (then X, Y, Z)."""
    return "COMPASS_MOT_" if mag_index == 0 else f"COMPASS_MOT{mag_index + 1}_"


def motor_comp_type(params: dict[str, float]) -> int:
    """COMPASS_MOTCT: 0 none, MOTCT_THROTTLE or MOTCT_CURRENT (missing or damaged: 0, none applied)."""
    value = params.get("COMPASS_MOTCT", 0.0)
    return int(value) if math.isfinite(value) else 0


def motor_comp_vector(params: dict[str, float], mag_index: int) -> tuple[float, float, float] | None:
    """COMPASS_MOT*_X/Y/Z of compass ``mag_index`` (mgauss per unit throttle, or per amp); None while any
    is unknown."""
    p = motor_comp_prefix(mag_index)
    try:
        return params[p + "X"], params[p + "Y"], params[p + "Z"]
    except KeyError:
        return None


def per_motor_comp(params: dict[str, float], mag_index: int) -> bool:
    """ArduPilot's per-motor compensation (COMPASS_PMOT_EN, first compass only) is on for this compass."""
    return mag_index == 0 and bool(params.get("COMPASS_PMOT_EN", 0.0))


def motor_comp_known_off(params: dict[str, float], mag_index: int) -> bool:
    """The parameters say the autopilot adds no motor offset to compass ``mag_index``: COMPASS_MOTCT = 0
    and, for the first compass, no per-motor compensation. Unknown parameters (none logged yet): False."""
    if params.get("COMPASS_MOTCT", math.nan) != 0.0:  # NaN (not logged) != 0: not known to be off
        return False
    return not per_motor_comp(params, mag_index)
