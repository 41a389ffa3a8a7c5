"""ArduPilot's onboard motor compensation rebuilt from its parameters (COMPASS_MOTCT 1 / 2), its equivalent
theta of eq. (11), and the test that it disagrees with the learned theta."""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np
import pytest

from magcomp.adapters.ardupilot_motcomp import CHI2_3DOF_99, OnboardMotorComp, onboard_comp_warnings

MOT = (10.0, -20.0, 5.0)


def _comp(motct: float, **extra: float) -> OnboardMotorComp:
    c = OnboardMotorComp()
    c.param("COMPASS_MOTCT", motct)
    for i, ax in enumerate("XYZ"):
        c.param(f"COMPASS_MOT_{ax}", MOT[i])
        c.param(f"COMPASS_MOT2_{ax}", 2.0 * MOT[i])
    for k, v in extra.items():
        c.param(k, v)
    return c


def test_offset_is_mot_times_throttle_or_current_from_when_known() -> None:
    counts: Counter[str] = Counter()
    c = _comp(1.0)
    assert c.offset(0, counts) is None and counts["motor_comp_unknown"] == 1  # no throttle yet
    c.throttle_01 = 0.5
    assert c.offset(0, counts) == pytest.approx((5.0, -10.0, 2.5))
    assert c.offset(1, counts) == pytest.approx((10.0, -20.0, 5.0))
    assert c.offset(2, counts) is None  # no COMPASS_MOT3_*
    cur = _comp(2.0)
    cur.throttle_01 = 0.5
    assert cur.offset(0, counts) is None  # current-based: the throttle does not drive it
    cur.current_a = 12.0
    assert cur.offset(0, counts) == pytest.approx((120.0, -240.0, 60.0))
    assert _comp(0.0).offset(0, counts) is None  # COMPASS_MOTCT = 0: nothing was added
    pm = _comp(1.0, COMPASS_PMOT_EN=1.0)
    pm.throttle_01 = 0.5
    assert pm.offset(0, counts) is None and counts["motor_comp_per_motor"] == 1
    assert pm.offset(1, counts) is not None  # per-motor applies to the first compass only


def test_equivalent_theta_is_the_least_squares_throttle_squared_fit() -> None:
    counts: Counter[str] = Counter()
    c = _comp(1.0)
    thr = np.linspace(0.0, 0.9, 91)
    for d in thr:
        c.throttle_01 = float(d)
        c.offset(0, counts)
    rep = c.report()[0]
    ratio = float(np.sum(thr**3) / np.sum(thr**4))
    np.testing.assert_allclose(rep["theta_equivalent_mgauss"], -np.asarray(MOT) * ratio, rtol=1e-9)
    assert rep["samples_undone"] == 91 and rep["motct"] == 1


def _summary(theta: list[float], sd: float, l_mat: Any = None) -> dict[str, Any]:
    cal = {"source": "in-flight", "L": l_mat if l_mat is not None else np.eye(3).tolist()}
    return {"compasses": [{"index": 0, "status": "corrected", "theta_mgauss": theta, "calibration": cal,
                           "inflight": {"theta_sigma_mgauss": [sd] * 3}}]}  # fmt: skip


def test_warning_only_when_the_difference_exceeds_the_learned_uncertainty() -> None:
    onboard = [-60.0, 25.0, 0.0]
    report = {0: {"motct": 1, "mot": list(MOT), "samples_undone": 100, "theta_equivalent_mgauss": onboard}}
    sd = 5.0
    # just inside / outside the 99 % chi-square bound along one axis
    edge = sd * float(np.sqrt(CHI2_3DOF_99))
    inside = [onboard[0] + 0.9 * edge, onboard[1], onboard[2]]
    outside = [onboard[0] + 1.1 * edge, onboard[1], onboard[2]]
    assert onboard_comp_warnings(report, _summary(inside, sd)) == []
    assert report[0]["differs"] is False
    w = onboard_comp_warnings(report, _summary(outside, sd))
    assert len(w) == 1 and "compass 0" in w[0] and "COMPASS_MOT*" in w[0]
    # compared in the calibrated frame: L maps the onboard theta there
    l_mat = (1.1 * np.eye(3)).tolist()
    mapped = (1.1 * np.asarray(onboard)).tolist()
    assert onboard_comp_warnings(report, _summary(mapped, sd, l_mat)) == []
    # a compass the flight did not correct is not judged
    s = _summary(outside, sd)
    s["compasses"][0]["status"] = "uncorrected"
    assert onboard_comp_warnings(report, s) == []


def test_motct_changed_mid_log_is_taken_at_each_parameter() -> None:
    """COMPASS_MOTCT set again during the log (1 -> 0 -> 2): the type and the offset follow the latest value,
    not the first one seen (``motct`` is cached per parameter)."""
    counts: Counter[str] = Counter()
    c = _comp(1.0)
    c.throttle_01 = 0.5
    c.current_a = 12.0
    assert c.motct == 1
    assert c.offset(0, counts) == pytest.approx((5.0, -10.0, 2.5))  # mot x throttle
    c.param("COMPASS_MOTCT", 0.0)
    assert c.motct == 0
    assert c.offset(0, counts) is None  # compensation switched off: nothing added
    c.param("COMPASS_MOTCT", 2.0)
    assert c.motct == 2
    assert c.offset(0, counts) == pytest.approx((120.0, -240.0, 60.0))  # mot x current
    c.param("COMPASS_MOT_X", 1.0)  # another motor-compensation parameter keeps the type
    assert c.motct == 2
