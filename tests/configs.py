"""Configurations the tests share.

``ESTIMATOR_ONLY``: the in-flight estimator's correction published as soon as it is learned, without the
self-check against the gyro and the autopilot's yaw (``[output] self_check = false``). For tests of the
estimator on simulated flights whose autopilot pulls its yaw to the disturbed compass at 0.5 /s (the
simulator's default; log171's EKF: 0.009-0.019 /s, README): there the autopilot's yaw carries the compass's
bias, so the self-check's comparison with it refuses a correction that the truth shows is right. The
self-check itself is tested in tests/unit/test_selfcheck.py and on measured logs.

``QUICK_CALIBRATION``: the hand rotation's calibration first tried on 200 (down, field) pairs and again every
100 (defaults 500 and 250), so that the short rotations of the simulated test flights are calibrated.
"""

from __future__ import annotations

from dataclasses import replace

from magcomp.adapters.config import Config, OutputConfig

ESTIMATOR_ONLY = Config(output=OutputConfig(self_check=False))
_DEFAULT = Config()
QUICK_CALIBRATION = replace(
    _DEFAULT, calibration=replace(_DEFAULT.calibration, min_samples=200, check_every=100)
)
