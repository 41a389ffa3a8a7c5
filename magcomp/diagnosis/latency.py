"""The compass's latency against the IMU clock, fitted and removed before the search (issue 10, held out).

A log stamps each compass sample with the time it was *logged*, not measured. ArduPilot's RAW_IMU carries
the latest compass reading in every IMU message, so a compass slower than the IMU loop (20 Hz inside a 40 Hz
RAW_IMU from a 50 Hz loop, 75 Hz inside 100 Hz) is held: each logged sample is 0 to one compass period old
(on average 21.8 ms and 7.5 ms in those two simulated cases). The forward model
(:mod:`magcomp.diagnosis.model`) takes the attitude at the logged time, so a sample that is tau old leaves
-tau d(A h_b)/dt in the residual: a rotation-rate error of a few mgauss (500 mgauss field, 1 rad/s, 10 ms:
5 mgauss), repeated manoeuvre by manoeuvre. Measured (``benchmarks/diagnosis_heldout.py`` settings, 20 seeds
each): with the simulator's true attitude and no effect hidden, a 75 Hz compass held in a 100 Hz RAW_IMU
biased a fitted temperature coefficient by (-0.39, 0.22, 0.07) mgauss/degC (sd 0.31 / 0.21 / 0.26); moving
the compass times by the mean staleness (7.5 ms) took the bias to (-0.07, 0.01, 0.01). A 20 Hz compass in a
40 Hz RAW_IMU gave per-motor vectors 1.2-2.4 mgauss of fitted signal on logs with no per-motor effect (a
spread of 0.6-1.8, as large as a true 1.2; Bartlett factor 5-12) and hid a real one: the held-out per-motor
log (seed 107) had effective delta BIC -10 (Bartlett factor 9.1); with this module -113 (factor 3.0).

Only for a held compass: a latency fitted on any log also absorbs model errors that follow the rotation
rate (a compass-free tilt that leans in a turn): on a clean 50 Hz fixed-wing flight with no hold it came
out at -39 ms, and moved the motors-off offset of ``tests/integration/test_diagnose_repeat.py`` by 2.2
mgauss. A hold is seen in the data itself: consecutive samples identical on all three axes
(:func:`held_fraction`); a compass at up to 80 % of its message's rate repeats at least 20 % of them
(:data:`MIN_HELD_FRACTION`), while an unheld moving compass with 1 mgauss noise and resolution repeats
about 2 %.

Here the latency is one least-squares nuisance of the paper's model (eq. (11)) fitted first, linearised:
v(t) = A h_b(t - tau) + ... ~ A h_b(t) - tau d(A h_b)/dt, so tau is the regression of the baseline residual on
-d(A h_b)/dt over all three axes; twice (the second pass on the re-timed attitude refines it). The attitude is
then taken at each sample's measurement time minus tau (:func:`magcomp.diagnosis.inputs.compass_data`): the
measurement times (:func:`magcomp.diagnosis.inputs.measured_times_s`) take each sample's own age out of the
hold, which one tau for all samples cannot (ages 0-40 ms apart in the 40 Hz case), and tau what is left: the
attitude source's own delay (the gyro integral's, the autopilot filter's) and the mean error of the
measurement times (an update is placed halfway between two messages), which is what the model needs. The drive
signals (throttle, motors, battery, temperature) are not moved by tau: their timing against the field is what
``current_lag`` and ``time_skew`` test, and moving them by an attitude delay made a 42 ms current_lag out of a
clean 5 Hz log (``benchmarks/diagnosis_false_alarm.py`` seed 11534, first version of this module). They are
taken at each held sample's own measurement time, read from the hold itself
(:func:`magcomp.diagnosis.inputs.measured_times_s`): the hold's age is the compass's, not the attitude's, and
left in place it was fitted as lag (+26 ms on the held-out current_lag case). Departure from the paper: the
paper's compass and attitude share one clock.

An unheld compass is stale too: a compass updated at 24.7 Hz in a 25 Hz RAW_IMU repeats 1 % of its samples
(no hold to read), but each sample is 0 to one compass period old (30 ms on average in the simulator's 50 Hz
loop). Left at the logged times, that age cost the held-out cases at drawn rates (seeds 6000-6019,
``diagnosis_heldout.py --rates``) the per-motor evidence (GLS delta BIC -23 and +1 on seeds 6001 and 6008
against -290 and -367 with the rotation at the mean age) and biased the skew by +20-50 ms. So the engine fits
the same latency for an unheld compass (``engine._unheld_age``) and takes both the rotation and the drive
that much earlier, within :func:`unheld_age_bounds_s`: not below 0 (a value is not newer than its message:
the clean fixed-wing flight's -39 ms above stays 0), not above one compass period. Only against the gyro's
integral, which travels in the compass's own message: the autopilot's attitude adds its filter's delay,
which the powertrain does not have (the 42 ms lag above).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from magcomp.diagnosis.model import CompassData, earth_dir_body, fit_model

F64 = NDArray[np.float64]

#: bound on the fitted latency (s): more than any compass hold or filter delay in the logs seen (a 10 Hz
#: compass held is at most 0.1 s old); beyond it the estimate is model error, not timing
MAX_LATENCY_S = 0.1
#: the oldest a held compass value can be (s): autopilots read their compasses at 10 Hz or faster (75-100 Hz
#: for the common I2C / SPI parts), so a value repeated for longer than 0.1 s was read again and had not
#: changed (a still vehicle, a 1 mgauss resolution): not a hold
MAX_HOLD_S = 0.1
#: share of consecutive identical samples from which a compass is taken as held (module docstring)
MIN_HELD_FRACTION = 0.2
#: re-timing passes (the linearisation is exact to first order; the second pass takes up what is left)
PASSES = 2


def latency_step_s(data: CompassData) -> tuple[float, float]:
    """(tau, its standard error), s: how much older the samples of ``data`` are than their times, from the
    paper model's residual against the rate of change of its Earth-field part (module docstring). (0, inf)
    when nothing rotates (a stationary log or no rotation to time against)."""
    if data.attitude_source == "stationary" or data.n < 20:
        return 0.0, math.inf
    fit = fit_model(data, ())
    earth = earth_dir_body(data, fit.inc_rad, fit.dec_rad, fit.drift_rad_s) @ fit.a_mgauss.T
    rate = np.gradient(earth, data.t_s, axis=0)  # d(A h_b)/dt, mgauss/s
    power = float(np.sum(rate**2))
    if power <= 0.0:
        return 0.0, math.inf
    tau = -float(np.sum(fit.residual_mgauss * rate)) / power
    resid = fit.residual_mgauss + tau * rate
    se = math.sqrt(float(np.mean(resid**2)) / power)
    return tau, se


def compass_latency_s(
    data: CompassData,
    retime: Callable[[float], CompassData],
    bounds_s: tuple[float, float] = (-MAX_LATENCY_S, MAX_LATENCY_S),
) -> tuple[float, CompassData]:
    """The fitted latency (s) and the data with the attitude taken that much earlier; ``retime(latency_s) ->
    CompassData`` builds that data from the log. The estimate is clipped to ``bounds_s`` (default
    +-MAX_LATENCY_S; an unheld compass: :func:`unheld_age_bounds_s`)."""
    total = 0.0
    out = data
    for _ in range(PASSES):
        tau, se = latency_step_s(out)
        if not math.isfinite(se) or tau == 0.0:
            break
        total = float(np.clip(total + tau, bounds_s[0], bounds_s[1]))
        out = retime(total)
    return total, out


def unheld_age_bounds_s(t_s: F64) -> tuple[float, float]:
    """The range (s) of the mean age of an unheld compass's samples logged at the times ``t_s``: a value
    cannot be newer than its message (0), and a compass that repeats fewer than MIN_HELD_FRACTION of its
    samples updates at least 1 - MIN_HELD_FRACTION as often as its message, so a sample is at most one
    compass period, 1 / (1 - MIN_HELD_FRACTION) message periods old (and never more than MAX_LATENCY_S)."""
    if t_s.shape[0] < 2:
        return 0.0, 0.0
    period = float(np.median(np.diff(t_s)))
    return 0.0, float(min(max(period, 0.0) / (1.0 - MIN_HELD_FRACTION), MAX_LATENCY_S))


def held_fraction(values: F64) -> float:
    """Share of samples (n, 3) identical on every axis to the one before (a held compass)."""
    if values.shape[0] < 2:
        return 0.0
    same = np.all(np.diff(values, axis=0) == 0.0, axis=1)
    return float(np.mean(same))
