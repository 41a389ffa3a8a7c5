"""The report's prose (issue 26): no "None" in sentences, a negative yaw-follow rate commented, a nuisance on
its bound flagged, no compensation parameters for a theta that is not identifiable."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace
from typing import Any, cast

import pytest

from magcomp.diagnosis import engine as engine_mod
from magcomp.diagnosis.engine import compass_data, diagnose, with_gate, yaw_follow_comment
from magcomp.diagnosis.export import nuisances_at_bound
from magcomp.diagnosis.gate import NO_POSITION, GateParams
from magcomp.diagnosis.report import markdown
from magcomp.diagnosis.results import CompassDiagnosis
from magcomp.diagnosis.search import diagnose_compass
from tests.unit.test_diagnosis_model import synth_log


def test_report_has_no_none_without_position_or_when_refused() -> None:
    """No GPS position ("WMM None") and a compass the gate refuses ("drift None deg/min")."""
    log, _, _ = synth_log(2)
    ok = markdown(diagnose(log))
    assert "None" not in ok
    assert "no WMM" in ok
    refused = diagnose(log, gate_params=GateParams(max_residual_fraction=1e-6))
    assert not refused.compasses[0].observable
    text = markdown(refused)
    assert "None" not in text
    assert "not reported (the fit failed the validity gate)" in text


def test_negative_yaw_follow_rate_is_commented() -> None:
    assert "negative" in yaw_follow_comment(-0.05, 0.01)
    assert "not distinguishable from zero" in yaw_follow_comment(-0.005, 0.01)
    assert yaw_follow_comment(0.5, 0.01) == ""


def _fake(drift: float, source: str = "gyro", flags: tuple[str, ...] = ()) -> CompassDiagnosis:
    return cast(
        CompassDiagnosis,
        SimpleNamespace(
            data=SimpleNamespace(attitude_source=source, nuisance_flags=flags),
            extended=SimpleNamespace(drift_rad_s=drift),
        ),
    )


def test_heading_drift_on_its_bound_is_flagged() -> None:
    assert any("bound" in s for s in nuisances_at_bound(_fake(-0.05)))
    assert nuisances_at_bound(_fake(0.01)) == []
    assert nuisances_at_bound(_fake(0.05, source="stationary")) == []
    assert nuisances_at_bound(_fake(0.0, flags=("gyro bias on its bound",))) == ["gyro bias on its bound"]


def test_no_compensation_parameters_for_a_theta_not_identifiable(monkeypatch: pytest.MonkeyPatch) -> None:
    log, _, _ = synth_log(1)
    cd = diagnose_compass(compass_data(log, 0), "synthetic", log=log)
    gated = with_gate(cd, log, NO_POSITION)
    assert gated.observable and gated.autopilot  # identifiable: parameters are given

    def not_identifiable(*_: Any) -> dict[str, object]:
        return {"theta_identifiable": False, "theta_consistency_why": "theta is not identifiable here: test"}

    monkeypatch.setattr(engine_mod, "consistency_checks", not_identifiable)
    refused = with_gate(replace(cd), log, NO_POSITION)
    assert refused.observable
    assert refused.autopilot == {}
    assert "No autopilot compensation parameters" in refused.linear_note
    assert "COMPASS_MOT" not in markdown(
        replace(diagnose(log), compasses=[refused])  # the report shows no parameter line either
    )
