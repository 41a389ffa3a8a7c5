"""diagnose's report: heading plots wrapped to +-180 deg at any log length, no "None" in the prose, only the
log's own autopilot's parameters."""

from __future__ import annotations

import numpy as np

from magcomp.diagnosis.report import _autopilot_lines, _own_params, _text, heading_change_deg


def test_heading_change_of_thirty_turns_stays_within_180_deg() -> None:
    yaw = np.linspace(0.0, 30 * 2 * np.pi, 20_000)  # a long log: 30 full turns (10,800 deg unwrapped)
    change = heading_change_deg(yaw)
    assert change[0] == 0.0
    assert change.min() >= -180.0 and change.max() < 180.0
    np.testing.assert_allclose(heading_change_deg(np.array([0.1, 0.2, -0.3])), np.degrees([0.0, 0.1, -0.4]))


def test_missing_values_read_unknown_not_none() -> None:
    assert _text(None) == "unknown" and _text(float("nan"), " deg") == "unknown"
    assert _text(12.5, " deg") == "12.5 deg"


def test_only_the_logs_autopilot_parameters_are_printed() -> None:
    cj = {"linearisation": "note", "autopilot": {"ardupilot": {"COMPASS_MOT_X": 1.0},
                                                 "px4": {"CAL_MAG0_XCOMP": 1.0},
                                                 "px4_throttle": {"CAL_MAG0_XCOMP": 2.0}}}  # fmt: skip
    ardupilot = "\n".join(_autopilot_lines(cj, [], ".", 3))
    px4 = "\n".join(_autopilot_lines(cj, [], ".", 12))
    unknown = "\n".join(_autopilot_lines(cj, [], ".", -1))
    assert "COMPASS_MOT_X" in ardupilot and "CAL_MAG" not in ardupilot
    assert "CAL_MAG0_XCOMP" in px4 and "COMPASS_MOT" not in px4
    assert "COMPASS_MOT_X" in unknown and "CAL_MAG0_XCOMP" in unknown
    assert _own_params("px4_current", 12) and not _own_params("px4_current", 3)
