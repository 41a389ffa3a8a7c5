"""The self-check on a measured flight (log171, ArduCopter 3.3, three compasses): the corrections that make
the heading agree with the gyro are applied, with the gain printed; in both replay forms the published
heading of a compass is judged against the autopilot's own field."""

from __future__ import annotations

from pathlib import Path

import pytest

from magcomp.adapters.config import Config
from magcomp.service.replay import replay_log

MEASURED = Path(__file__).parents[2].parent / "shared" / "data" / "measured"
LOG171 = MEASURED / "dronekit_log171_copter33_quad.bin"

pytestmark = pytest.mark.needs_shared


def test_log171_corrections_pass_the_self_check() -> None:
    if not LOG171.exists():
        pytest.skip(f"measured log {LOG171.name} not available")
    rep = replay_log(LOG171, Config(), two_pass=True)
    by = {c["index"]: c for c in rep.summary["compasses"]}
    for idx in (1, 2):  # the internal compasses, 10-20 deg off the autopilot's yaw before
        chk = by[idx]["self_check"]
        assert chk is not None and chk["applies"], by[idx]["why"]
        assert chk["candidate_gyro_deg"] < 0.5 * chk["baseline_gyro_deg"]  # measured 0.41 and 0.23
        assert chk["candidate_att_deg"] < chk["baseline_att_deg"]
        assert by[idx]["status"] == "corrected"
        assert "heading vs gyro:" in by[idx]["why"]
