"""Issue 9 on real logs (../shared/data/measured; skipped when absent): plain `replay` with no configuration
corrects what it can and says per compass why it cannot."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.adapters.mavlink_source import load_log
from magcomp.core.heading import heading_from_trig_deg
from magcomp.core.selfcheck import offset_removed_rms_deg
from magcomp.service.console import summary_lines, write_json
from magcomp.service.evaluate import heading_agreement
from magcomp.service.replay import replay_log

pytestmark = pytest.mark.needs_shared

MEASURED = Path(__file__).parents[2].parent / "shared" / "data" / "measured"
LOG171 = MEASURED / "dronekit_log171_copter33_quad.bin"
CRASH_AFTER_S = 226.0  # log171 crashes and ends inverted (SOURCES.md); the samples after are left out


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"{path.name} not found (../shared/data/measured is absent in this clone)")
    return path


@pytest.mark.slow
def test_log171_internal_compasses_agree_with_the_external_one() -> None:
    """Acceptance of issue 9: compass 1 within 2.5 deg rms and compass 2 within 3.0 deg rms of compass 0
    (11.0 and 11.5 uncorrected in the issue's measurement; 7.6 and 9.0 with magcomp's in-flight hard iron)."""
    rep = replay_log(_need(LOG171), Config(), keep_estimates=True, two_pass=True)
    assert rep.summary["passes"] == 2
    assert rep.summary["earth_field"]["source"] == "gps"
    forms = [c["inflight"]["form"] for c in rep.summary["compasses"]]
    assert forms == ["relative", "absolute", "absolute"]  # compass 0 is the external primary
    agree = heading_agreement(rep.estimates, 0, CRASH_AFTER_S)
    assert agree[1]["corrected_all_deg"] < 2.5
    assert agree[2]["corrected_all_deg"] < 3.0
    for idx in (1, 2):
        assert agree[idx]["corrected_flying_deg"] < 0.6 * agree[idx]["uncorrected_flying_deg"]


@pytest.mark.slow
def test_log171_causal_replay_improves_in_flight() -> None:
    """What the live daemon would have published: the autopilot's own heading until the self-check switches
    the correction on, then the correction; over the flight its rms against the autopilot's yaw (constant
    offset removed) is well below that of the autopilot's own heading on the two internal compasses
    (measured 10.4 -> 5.2 and 19.9 -> 7.2 deg), and compass 2 ends corrected."""
    rep = replay_log(_need(LOG171), Config(), keep_estimates=True, two_pass=False)
    data = load_log(LOG171, undo_motor_comp=False)
    att = data.attitude_rad
    thr = data.throttle_01
    for idx in (1, 2):
        es = [e for e in rep.estimates if e.mag_index == idx]
        t = np.array([e.t_s for e in es])
        keep = (t - t[0] < CRASH_AFTER_S) & (np.interp(t, thr.t_s, thr.values) > 0.05)
        roll = np.interp(t, att.t_s, att.values[:, 0])
        pitch = np.interp(t, att.t_s, att.values[:, 1])
        yaw = np.interp(t, att.t_s, np.unwrap(att.values[:, 2]))
        m = np.array([e.field_raw_mgauss for e in es])
        own = np.radians(heading_from_trig_deg(m[:, 0], m[:, 1], m[:, 2], np.cos(roll), np.sin(roll),
                                               np.cos(pitch), np.sin(pitch)))  # fmt: skip
        pub = np.radians([e.heading_deg for e in es])
        own_att = offset_removed_rms_deg((own - yaw)[keep])
        pub_att = offset_removed_rms_deg((pub - yaw)[keep])
        assert pub_att < 0.7 * own_att, (idx, pub_att, own_att)
    assert rep.summary["compasses"][2]["status"] == "corrected"


@pytest.mark.parametrize(
    "name", ["ardupilot_loganalyzer_nan_copter311.log", "pyulog_sample_px4_disarmed.ulg"]
)
def test_logs_it_cannot_use_say_so_per_compass(name: str, tmp_path: Path) -> None:
    """A 28 s log with a sparse current and a disarmed PX4 log: each compass gets one line with its state
    and reason; the JSON is strictly valid."""
    rep = replay_log(_need(MEASURED / name), Config(), two_pass=True)
    comps = rep.summary["compasses"]
    assert comps
    for c in comps:
        assert c["status"] in ("corrected", "uncorrected") and c["why"]
    lines = summary_lines(rep.summary)
    assert len(lines) == len(comps)
    if name.endswith(".ulg"):  # disarmed throughout: no throttle change, no theta claimed
        for c in comps:
            assert c["status"] == "uncorrected" or max(abs(v) for v in c["theta_mgauss"]) < 1e-6
    out = tmp_path / "s.json"
    write_json(out, rep.to_json())
    json.loads(out.read_text(), parse_constant=lambda n: pytest.fail(f"non-JSON constant {n}"))
