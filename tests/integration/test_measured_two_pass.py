"""A measured log the in-flight calibration cannot use (23 s, 8 deg of yaw, ArduCopter 3.1.1 text log): the
default two-pass replay says so per compass, as the causal replay does, instead of applying an estimate with a
non-physical calibration (soft-iron terms of 5-9) and a 77 deg heading uncertainty. Where it corrects all the
same, it is theta against the autopilot's own calibration (core/hover_theta.py), and only with the
self-check's verdict."""

from __future__ import annotations

from pathlib import Path

import pytest

from magcomp.adapters.config import Config
from magcomp.service.replay import replay_log

TEXT = (
    Path(__file__).parents[2].parent
    / "shared"
    / "data"
    / "measured"
    / "ardupilot_loganalyzer_nan_copter311.log"
)

pytestmark = pytest.mark.needs_shared


def test_two_pass_does_not_apply_what_the_first_pass_could_not() -> None:
    if not TEXT.exists():
        pytest.skip(f"measured log {TEXT.name} not available")
    causal = replay_log(TEXT, Config(), two_pass=False)
    both = replay_log(TEXT, Config(), two_pass=True)
    assert both.summary["passes"] == 2
    for c1, c2 in zip(causal.summary["compasses"], both.summary["compasses"], strict=True):
        assert c1["status"] == "uncorrected"  # too little yaw and throttle to learn from
        assert "not observable" in c2["why"]
        if c2["status"] == "corrected":
            assert c2["calibration"]["source"] == "autopilot", c2["why"]
            assert c2["self_check"]["applies"]
            continue
        assert c2["why"].startswith("publishing the autopilot's own heading")
        assert c2["calibrated"] is False
        assert c2["time_s"]["corrected"] == 0.0
