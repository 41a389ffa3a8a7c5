"""A gyro logged below MIN_GYRO_HZ, integrated all the same where its rotation explains the compass better
than the autopilot's attitude (telemetry logs: RAW_IMU at 1-10 Hz).

Below :data:`~magcomp.diagnosis.attitude.MIN_GYRO_HZ` the rotation is the autopilot's attitude, whose yaw
is fused from a compass: where that is the compass diagnosed, the yaw follows its bias (the simulator's
autopilot at 0.2-1.5 /s) and takes into the rotation what the forward model is meant to expose.

Measured on held-out telemetry logs (``benchmarks/diagnosis_heldout.py --set telemetry_hz=R``, seeds
6000-6018, the simulator's rotation as the reference): the autopilot's heading is 70-225 mrad rms off (a
linear drift removed); the slow gyro's integral (tilt pulled toward the log's roll and pitch, the gyro
bias's heading removed by :mod:`magcomp.diagnosis.gyro_heading`) 25-29 mrad at 4 Hz, 12-13 mrad at 10 Hz.
With the autopilot's heading, current_lag and per_motor were short of the BIC margin
(GLS delta BIC -47 and -0.3 at 4 Hz, +2 for per_motor at 10 Hz); with the integral -129, -41 and -391,
near those with the simulator's rotation (docs/diagnosis.md, 2026-11-28, "telemetry rates").

The integral is not trusted blindly: a multirotor's attitude loop moves it at up to ~5 Hz, which a slow
gyro aliases, while a real EKF pulls its yaw to the compass at only 0.01-0.05 /s. So each compass decides:
the integral replaces the autopilot's attitude when the paper model (eq. (11)) leaves a smaller residual
with it. Pure, no I/O.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

from magcomp.core.types import LogData
from magcomp.diagnosis.attitude import MIN_GYRO_HZ, AttitudeSource
from magcomp.diagnosis.gate import median_rate_hz
from magcomp.diagnosis.gyro_heading import with_gyro_bias_heading
from magcomp.diagnosis.inputs import compass_data, log_attitude
from magcomp.diagnosis.model import CompassData, fit_model
from magcomp.diagnosis.results import CompassDiagnosis


def slow_gyro_source(log: LogData) -> AttitudeSource | None:
    """The integral of ``log``'s gyro whatever its rate (tilt toward the log's roll and pitch), or None when
    even then the rotation is not the gyro's (no gyro, no attitude, or a vehicle that does not rotate)."""
    src = log_attitude(log, min_gyro_hz=0.0)
    return src if src.source.startswith("gyro") else None


def slow_gyro_data(log: LogData, index: int, source: AttitudeSource) -> CompassData:
    """Compass ``index`` of ``log`` with the rotation of ``source`` (the slow gyro's integral), at its logged
    times (``prefer_slow_gyro``'s ``retime`` re-times it as the engine does)."""

    def attitude() -> AttitudeSource:
        return source

    data = compass_data(log, index, attitude=attitude)
    hz = median_rate_hz(log.imu_t_s)
    note = (
        f"the gyro is logged at {hz:.1f} Hz (< {MIN_GYRO_HZ:.0f} Hz), integrated all the same: its "
        "rotation leaves this compass a smaller paper-model residual than the autopilot's attitude, whose "
        "yaw is fused from a compass; "
    )
    return replace(data, attitude_note=note + data.attitude_note)


def paper_rms_mgauss(data: CompassData) -> float:
    """The paper model's (eq. (11)) residual rms on ``data``, mgauss."""
    return fit_model(data, ()).rms_mgauss


def prefer_slow_gyro(
    log: LogData,
    comps: list[CompassDiagnosis],
    search: Callable[[CompassData], CompassDiagnosis],
    given: dict[int, CompassData],
    notes: list[str],
    retime: Callable[[int, CompassData, AttitudeSource, list[str]], CompassData] | None = None,
) -> list[CompassDiagnosis]:
    """Each compass whose rotation is the autopilot's because the gyro is slow: searched again (``search``)
    with the slow gyro's integral when the paper model leaves a smaller residual with it (module docstring);
    ``given`` (index -> the data searched) is updated, the change noted. ``retime``: the engine's re-timing
    of the compass's samples against that rotation (a hold's latency, or an unheld compass's age: the gyro's
    integral is what the age is fitted against; the autopilot's attitude was not), its notes kept only where
    the slow gyro is taken."""
    out = list(comps)
    source: AttitudeSource | None = None
    for i, c in enumerate(comps):
        if c.data.attitude_source != "autopilot" or c.index not in given:
            continue
        source = source or slow_gyro_source(log)
        if source is None:
            return out
        alt = slow_gyro_data(log, c.index, source)
        timing: list[str] = []
        if retime is not None:
            alt = retime(c.index, alt, source, timing)
        rms_autopilot = paper_rms_mgauss(given[c.index])
        rms_gyro = paper_rms_mgauss(with_gyro_bias_heading(alt))
        if not rms_gyro < rms_autopilot:
            continue
        notes.append(
            f"compass {c.index}: rotation from the gyro's integral ({median_rate_hz(log.imu_t_s):.1f} Hz) "
            f"instead of the autopilot's attitude (paper-model residual {rms_autopilot:.1f} -> "
            f"{rms_gyro:.1f} mgauss)"
        )
        notes.extend(timing)
        out[i] = search(alt)
        given[c.index] = alt
    return out
