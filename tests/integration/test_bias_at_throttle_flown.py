"""The console gives theta's bias at the throttle flown beside theta (service/heading.py count_flown,
service/console.py).

theta is the field per unit throttle^2 (eq. (11)): where the throttle flown is low, theta is large and tells a
pilot little (a development log flies at throttle 0.15-0.25: theta ~3 gauss, its bias 70-190 mgauss). The
summary carries the mean throttle^2 of the samples the self-check judges, both in the two-pass replay (whose
first pass has no heading stage) and live, and the console line multiplies it with |theta|.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.core.selfcheck import MOTORS_RUNNING_01
from magcomp.service.console import summary_lines
from magcomp.service.replay import replay_log

LOG = Path(__file__).resolve().parents[2] / "replay_logs" / "effect_per_motor.tlog"


@pytest.mark.parametrize("two_pass", [True, False])
def test_the_summary_has_the_throttle_flown_and_the_console_its_bias(two_pass: bool) -> None:
    rep = replay_log(LOG, Config(), keep_estimates=True, two_pass=two_pass)
    comp = rep.summary["compasses"][0]
    thr = np.array([e.throttle_01 for e in rep.estimates if e.mag_index == 0])
    flown = float(np.mean(thr[thr > MOTORS_RUNNING_01] ** 2))
    assert comp["throttle2_flown"] == pytest.approx(flown, rel=0.1)  # tilt-gated and subsampled: close
    line = next(x for x in summary_lines(rep.summary) if x.startswith("compass 0:"))
    if comp["status"] != "corrected":  # no theta published, none printed (the live replay of this log)
        assert "theta =" not in line and "bias at the throttle flown" not in line, line
        return
    th = np.asarray(comp["theta_mgauss"], dtype=float)
    want = float(np.linalg.norm(th)) * comp["throttle2_flown"]
    assert f"its bias at the throttle flown {want:.0f} mgauss" in line, line
    assert f"rms throttle {math.sqrt(comp['throttle2_flown']):.2f}" in line


def test_diagnose_gives_the_bias_at_the_throttle_flown_too(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """diagnose's JSON carries the mean throttle^2 with the motors running and its console line the bias."""
    import json

    from magcomp.cli import main

    out = tmp_path / "d.json"
    assert main(["diagnose", str(LOG), "--json", str(out)]) == 0
    comp = json.loads(out.read_text())["compasses"][0]
    thr = np.array([e.throttle_01 for e in replay_log(LOG, Config(), keep_estimates=True).estimates])
    run = thr[thr > MOTORS_RUNNING_01]
    assert comp["throttle2_flown"] == pytest.approx(float(np.mean(run**2)), rel=0.1)
    theta = comp["theta"] if comp["observable"] else comp["theta_given_prior"]["theta"]
    want = float(np.linalg.norm(theta)) * comp["throttle2_flown"]
    assert f"its bias at the throttle flown {want:.0f} mgauss" in capsys.readouterr().out
