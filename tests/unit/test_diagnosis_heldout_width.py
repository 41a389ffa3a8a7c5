"""The held-out benchmark reports each finding's interval width beside its coverage
(``benchmarks/diagnosis_heldout.py``: coverage near 95 % must not come from wide intervals)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest


def test_interval_width_of_scalar_per_motor_and_vector_findings() -> None:
    sys.path.insert(0, str(Path(__file__).parents[2] / "benchmarks"))
    from diagnosis_heldout import interval_width

    offset = {"offset": 0.3, "offset_ci95": [0.27, 0.34]}
    assert interval_width("throttle_offset", offset) == pytest.approx(0.07)
    assert interval_width("per_motor", {"spread": 1.5, "spread_ci95": [1.1, 1.9]}) == pytest.approx(0.8)
    # temperature_drift's parameter is a vector (a joint box, not one interval); no finding: no width
    assert interval_width("temperature_drift", {"mgauss_per_degc": 9.0}) is None
    assert interval_width("throttle_offset", {}) is None
