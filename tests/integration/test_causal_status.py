"""The live (``--causal``) summary says "corrected" of a compass only where its published heading is the
correction (service/heading.py decides what is published; the summary said what the check or the hover theta
would allow)."""

from __future__ import annotations

from pathlib import Path

import pytest

from magcomp.adapters.config import Config
from magcomp.core.types import FLAG_CALIBRATED
from magcomp.service.replay import replay_log

pytestmark = pytest.mark.slow


def test_causal_status_matches_what_was_published(tmp_path: Path) -> None:
    """A 90 s simulated flight (10 Hz telemetry). Before, compass 0 was said "corrected" (theta against the
    autopilot's calibration, its check on) with 0 s corrected: the in-flight correction was applied but not
    published (its heading sigma above the autopilot's error), and that blocked the hover theta too."""
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate
    from magcomp.sim.config import apply_settings

    path = tmp_path / "flight.tlog"
    write_tlog(simulate(apply_settings(SimConfig(scenario="ordinary", duration_s=90.0, seed=0),
                                       ["telemetry_hz=10"])), path)  # fmt: skip
    rep = replay_log(path, Config(), keep_estimates=True, two_pass=False)
    applied_not_published = 0
    for c in rep.summary["compasses"]:
        last = [e for e in rep.estimates if e.mag_index == c["index"]][-1]
        published = bool(last.flags & FLAG_CALIBRATED)
        assert (c["status"] == "corrected") == published, (c["index"], c["status"], c["why"])
        if c["status"] == "corrected":
            assert c["time_s"]["corrected"] > 0.0
        applied_not_published += c["inflight"]["applied"] and not published
    assert applied_not_published >= 1  # the case: compass 0 was said "corrected" with 0 s corrected before
