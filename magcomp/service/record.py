"""The one record a magnetometer sample becomes on its way through the pipeline's stages.

:class:`MagRecord` is created by the align stage and filled in, field group by field group, by each stage
in turn (align -> attitude -> calibrate -> theta -> heading -> publish -> persist; see
:mod:`magcomp.service.pipeline`). Vectors are three plain floats: the per-sample path builds no arrays.
The publish stage turns it into a :class:`~magcomp.core.types.HeadingEstimate` only for consumers that ask.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from magcomp.core.inflight import InflightOutput
from magcomp.core.types import MagSample
from magcomp.service.estimators import ThetaStepInfo

Float3 = tuple[float, float, float]
ZERO3: Float3 = (0.0, 0.0, 0.0)


class Tilt(NamedTuple):
    """cos / sin of roll and pitch: what eq. (24) takes of the attitude (derived once per IMU or ATTITUDE
    sample by the attitude stage, carried by each magnetometer sample's record)."""

    cos_roll: float
    sin_roll: float
    cos_pitch: float
    sin_pitch: float


#: the tilt before any attitude: level
LEVEL = Tilt(1.0, 0.0, 1.0, 0.0)


@dataclass(slots=True)
class MagRecord:
    """One magnetometer sample and everything the stages derived from it (mutable, one per sample)."""

    # ---- align (service/align.py)
    sample: MagSample
    t_s: float
    mag_index: int
    #: the field as received (mgauss, the compass's own frame)
    raw: Float3
    #: the previous accepted sample's time of this compass (None: the first one)
    prev_t: float | None
    #: a gap or a clock reset before this sample: the filters restart
    reset: bool
    #: the observer's discrete step cannot span the interval before this sample
    obs_reset: bool
    #: the latest throttle (0..1), 0 without one; have_throttle: a throttle sample has been received
    throttle_01: float
    have_throttle: bool
    #: FLAG_* bits so far
    flags: int
    #: with ``obs_reset``: the interval has samples missing in it (no more): the observer skips it, its
    #: filters kept (core.observer.observer_skip), rather than restarting them
    obs_skip: bool = False
    # ---- attitude (service/attitude.py)
    #: the settled down vector of the attitude filter in body axes (None while not settled)
    down: Float3 | None = None
    #: cos / sin of roll and pitch for eq. (24)
    tilt: Tilt = LEVEL
    #: the gyro (and the attitude derived from it) may be used for this sample
    gyro_fresh: bool = False
    #: the bias-corrected body rate of the latest IMU sample (rad/s)
    gyro: Float3 = ZERO3
    #: the gyro as logged (rad/s, body), without the attitude filter's bias: what the published heading's
    #: filter propagates with (core/heading_filter.py learns its own yaw-rate bias)
    gyro_raw: Float3 = ZERO3
    #: the raw gyro's yaw integrated at the IMU's rate up to the latest IMU sample (rad), its epoch
    #: (restarts of the integral); the heading filter propagates with its change between two samples
    gyro_yaw: float = math.nan
    gyro_epoch: float = -1.0
    #: the autopilot's yaw (rad, NaN: no ATTITUDE yet) and whether the IMU comes fast enough (selfcheck's
    #: MAX_GYRO_DT_S) for its integral to be the self-check's reference
    ap_yaw: float = math.nan
    imu_fast: bool = False
    #: the IMU's interval (s; NaN: unknown)
    imu_dt: float = math.nan
    #: the in-flight solution not yet applied (L and d as 12 floats, theta): judged by the self-check in the
    #: shadow, so that its evidence is there when the stage applies it
    shadow: tuple[tuple[float, ...], Float3] | None = None
    # ---- calibrate (service/calibrate.py): eq. (2) u = L v - d; calibrated: a calibration is applied
    field_cal: Float3 = ZERO3
    calibrated: bool = False
    #: the in-flight calibration's correction when it is the one applied (it carries theta and the bias)
    inflight: InflightOutput | None = None
    # ---- theta (service/theta.py): theta-hat, the bias of eq. (11), the field with it removed
    theta: Float3 = ZERO3
    bias: Float3 = ZERO3
    field_corrected: Float3 = ZERO3
    info: ThetaStepInfo | None = None
    # ---- heading (service/heading.py): eq. (24) after the heading filter, corrected and not
    heading_deg: float = 0.0
    heading_raw_deg: float = 0.0
