"""diagnose's JSON as fleet row columns (magcomp/fleet/diagnosed.py): which theta, its interval, the findings
with their intervals and the rival sets."""

from __future__ import annotations

import json

from magcomp.fleet.diagnosed import compass_columns, finding_text


def test_a_named_cause_and_a_rival_set_with_each_interval() -> None:
    one = {"effect": "time_skew", "params": {"skew_s": 0.168, "skew_s_ci95": [0.146, 0.19]}}
    assert finding_text(one) == "time_skew skew_s=0.168 [0.146, 0.19]"
    rivals = {
        "effect": "throttle_exponent or throttle_offset",
        "candidates": ["throttle_exponent", "throttle_offset"],
        "candidate_params": {
            "throttle_exponent": {"exponent": 3.18, "exponent_ci95": [2.91, 3.48]},
            "throttle_offset": {"offset": 0.287, "offset_ci95": [0.237, 0.332]},
        },
    }
    assert finding_text(rivals) == (
        "one of {throttle_exponent exponent=3.18 [2.91, 3.48], throttle_offset offset=0.287 [0.237, 0.332]}"
    )


def test_theta_from_the_free_fit_the_prior_or_none() -> None:
    free = {
        "observable": True,
        "theta": [1.0, 2.0, 3.0],
        "theta_ci95_halfwidth": [0.5, 0.5, 0.5],
        "theta_ci95_joint_halfwidth": [0.6, 0.6, 0.7],
        "gate": {"theta_identifiable": False},
        "findings": [],
        "autopilot": {},
    }
    c = compass_columns(free)
    assert c["diagnose_theta_from"] == "free fit" and c["diagnose_theta_identifiable"] is False
    assert (c["diagnose_theta_z_mgauss"], c["diagnose_theta_ci95_z_mgauss"]) == (3.0, 0.5)
    assert c["diagnose_theta_ci95_joint_z_mgauss"] == 0.7  # the joint 95 % box beside the per-axis interval
    assert c["diagnose_findings"] == "no finding" and c["diagnose_params_json"] is None
    prior = {
        "observable": False,
        "unobservable_why": "the heading covers only 47 deg (< 90)",
        "theta_given_prior": {
            "theta": [4.0, 5.0, 6.0],
            "theta_ci95_halfwidth": [1, 1, 1],
            "theta_ci95_joint_halfwidth": [1.2, 1.2, 1.2],
            "identifiable": True,
        },
        "autopilot": {"ardupilot": {"COMPASS_MOT_X": 1.0}},
    }
    c = compass_columns(prior)
    assert c["diagnose_theta_from"] == "autopilot calibration as prior" and c["diagnose_theta_identifiable"]
    assert c["diagnose_why"].startswith("the heading covers only")
    assert c["diagnose_theta_ci95_joint_x_mgauss"] == 1.2
    assert json.loads(c["diagnose_params_json"]) == {"ardupilot": {"COMPASS_MOT_X": 1.0}}
    none = compass_columns({"observable": False, "unobservable_why": "the throttle spans only 0.00"})
    assert none["diagnose_theta_x_mgauss"] is None and none["diagnose_theta_identifiable"] is None


def test_no_parameters_for_a_theta_that_does_not_help_the_heading() -> None:
    """A compass whose theta the self-check against the gyro finds makes the heading worse
    (diagnosis/gyro_check.py) gets no compensation parameters in its row, as ``diagnose --params-out`` writes
    none for it; one it helps, with no clear gain, or not judged keeps them. With its primary left out the
    set follows the next compass's type."""
    from magcomp.adapters.param_files import compensation_params

    sugg = {"ardupilot": {"COMPASS_MOT2_X": 1.0, "COMPASS_MOTCT": 1.0}}
    base = {"observable": True, "theta": [1.0, 2.0, 3.0], "findings": [], "autopilot": sugg}
    cases = ((None, True), ({"helps": True, "worse": False}, True), ({"helps": False, "worse": False}, True),
             ({"helps": False, "worse": True}, False))  # fmt: skip
    for check, kept in cases:
        c = compass_columns({**base, "heading_vs_gyro": check})
        assert (c["diagnose_params_json"] is not None) == kept, check
    values, notes = compensation_params([(1, sugg)], 0, 3)
    assert values == {"COMPASS_MOT2_X": 1.0, "COMPASS_MOTCT": 1.0}
    assert "follows compass 1" in notes[0]
    assert compensation_params([], 0, 3) == ({}, ["no compensation parameters: no compass has any"])
