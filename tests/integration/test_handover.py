"""Offline hands over to online (issue 9, item 5): `fit` / `diagnose` ``--save-state DIR`` on yesterday's
simulated ordinary flight; today's flight replayed with ``--state-dir DIR`` is corrected from its first
samples and its heading over the first 60 s beats a fresh causal replay's."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from magcomp.adapters.state_store import StateStore
from magcomp.cli import main
from magcomp.core.identity import SIM_UID
from magcomp.core.types import FLAG_CALIBRATED, HeadingEstimate
from magcomp.service.replay import replay_log
from tests.configs import ESTIMATOR_ONLY

pytestmark = pytest.mark.slow

FIRST_S = 60.0


@pytest.fixture(scope="module")
def flights(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Any]:
    """Two ordinary flights of one vehicle (same seed: same compasses, theta and autopilot calibration) with
    different trajectories (the plan's segments scale with the duration; wind and gusts differ)."""
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate
    from magcomp.sim.config import apply_settings

    d = tmp_path_factory.mktemp("handover")
    out = []
    for name, dur in (("yesterday", 120.0), ("today", 150.0)):
        r = simulate(
            apply_settings(SimConfig(scenario="ordinary", duration_s=dur, seed=3), ["telemetry_hz=10"])
        )
        write_tlog(r, d / f"{name}.tlog")
        out.append(r)
    a, b = out
    for ca, cb in zip(a.compasses, b.compasses, strict=True):
        np.testing.assert_array_equal(ca.theta_mgauss, cb.theta_mgauss)
    assert a.samples.t_s.shape != b.samples.t_s.shape
    return d / "yesterday.tlog", d / "today.tlog", b


def _rms_first(result: Any, ests: list[HeadingEstimate], seconds: float) -> float:
    """rms heading error (deg) of compass 0 against the simulated truth over the first ``seconds``."""
    s = result.samples
    e = [x for x in ests if x.mag_index == 0]
    t = np.array([x.t_s for x in e])
    k = np.clip(np.searchsorted(s.t_s, t - 1e-4), 0, len(s.t_s) - 1)
    truth = (np.degrees(result.euler_rad[s.truth_index[k], 2]) - result.declination_deg) % 360.0
    h = np.array([x.heading_deg for x in e])
    m = t < t[0] + seconds
    err = (h[m] - truth[m] + 180.0) % 360.0 - 180.0
    return float(np.sqrt(np.mean(err**2)))


@pytest.mark.parametrize("command", ["fit", "diagnose"])
def test_save_state_then_replay_starts_corrected(
    flights: tuple[Path, Path, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    yesterday, today, result = flights
    state_dir = tmp_path / "state"
    assert main([command, str(yesterday), "--save-state", str(state_dir)]) == 0
    out = capsys.readouterr().out
    saved = [ln for ln in out.splitlines() if ln.startswith("compass ") and " saved " in ln]
    assert len(saved) == 2, out  # one line per compass, each saying what was saved
    assert all("learned in flight" in ln and "theta (" in ln for ln in saved)
    for j in (0, 1):
        doc = json.loads((state_dir / f"vehicle-1-{SIM_UID}-compass-{j}.json").read_text())
        assert doc["state"]["inflight"]["form"] in ("absolute", "relative")
    if command == "fit":  # an ordinary flight has no bench sweep: said in one line, not an error
        assert "note: no offline fit" in out

    warm = replay_log(today, ESTIMATOR_ONLY, store=StateStore(state_dir), keep_estimates=True)
    fresh = replay_log(today, ESTIMATOR_ONLY, keep_estimates=True, two_pass=False)
    for c in warm.summary["compasses"]:
        assert c["inflight"]["started_from_stored_state"] is True
        assert c["status"] == "corrected"
    # corrected from the first sample with a throttle (the throttle stream starts with the log) on
    e0 = [x for x in warm.estimates if x.mag_index == 0]
    first = next(i for i, x in enumerate(e0) if x.flags & FLAG_CALIBRATED)
    assert e0[first].t_s - e0[0].t_s < 0.5
    assert all(x.flags & FLAG_CALIBRATED for x in e0[first:])
    assert not fresh.summary["compasses"][0]["inflight"]["started_from_stored_state"]
    warm_rms = _rms_first(result, warm.estimates, FIRST_S)
    fresh_rms = _rms_first(result, fresh.estimates, FIRST_S)
    print(f"{command}: heading rms over the first {FIRST_S:.0f} s: from stored state {warm_rms:.2f} deg, "
          f"fresh causal {fresh_rms:.2f} deg")  # fmt: skip
    assert warm_rms < 0.7 * fresh_rms


def test_save_state_says_why_a_compass_is_not_saved(
    flights: tuple[Path, Path, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The configuration that `run` would use (--config) disables the throttle: nothing can be corrected,
    nothing is handed over, and each compass's line says why."""
    yesterday, _, _ = flights
    conf = tmp_path / "magcomp.toml"
    conf.write_text('[input]\nthrottle_source = "none"\n')
    state_dir = tmp_path / "state"
    assert main(["fit", str(yesterday), "--save-state", str(state_dir), "--config", str(conf)]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("compass ")]
    assert [ln.split(":")[0] for ln in lines] == ["compass 0", "compass 1"]
    for ln in lines:
        assert "nothing saved: no throttle source (disabled in the configuration)" in ln
    assert not list(state_dir.glob("*.json"))


@pytest.mark.parametrize("command", ["fit", "diagnose"])
def test_save_state_bad_input_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    log = tmp_path / "x.tlog"
    log.write_bytes(b"\0" * 64)
    taken = tmp_path / "a-file"
    taken.write_text("")
    for extra, expect in (
        (["--save-state", str(taken)], "state directory"),
        (["--save-state", str(tmp_path / "s"), "--config", str(tmp_path / "none.toml")], "no such file"),
    ):
        assert main([command, str(log), *extra]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and expect in err[0] and "Traceback" not in err[0]
