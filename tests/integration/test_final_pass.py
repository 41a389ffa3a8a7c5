"""The default (two-pass) replay's second pass: every heading with the first pass's final state held fixed,
computed over the whole log at once (service/final_pass.py). Checked against the per-sample pipeline run
with that same state and learning switched off, on seeded simulated logs."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.core.types import FLAG_THETA_CONVERGED, HeadingEstimate
from magcomp.service import final_pass
from magcomp.service.replay import learn_pass, replay_log
from magcomp.sim import SimConfig, simulate
from tests.faultgen import paper_and_rebooted


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The paper's scenario (hand rotation, then flight), 150 s, two compasses; and the same log with the
    autopilot rebooting 100 s in (its clock restarts at 0.3 s: boot offset and heading filters restart)."""
    d = tmp_path_factory.mktemp("final")
    return paper_and_rebooted(d, 150.0, 4, 100.0)


@pytest.fixture(scope="module")
def paper_log(logs: dict[str, Path]) -> Path:
    return logs["paper"]


def _columns(ests: list[HeadingEstimate]) -> dict[str, np.ndarray]:
    return {
        "t": np.array([e.t_s for e in ests]),
        "mag": np.array([e.mag_index for e in ests]),
        "heading": np.array([e.heading_deg for e in ests]),
        "heading_raw": np.array([e.heading_raw_deg for e in ests]),
        "theta": np.array([e.theta_mgauss for e in ests]),
        "bias": np.array([e.bias_mgauss for e in ests]),
        "flags": np.array([e.flags for e in ests]),
    }


def _wrap(d: np.ndarray) -> np.ndarray:
    return (d + 180.0) % 360.0 - 180.0


@pytest.mark.parametrize("name", ["paper", "reboot"])
def test_two_pass_headings_equal_the_per_sample_pipeline_with_the_final_state_fixed(
    logs: dict[str, Path], name: str
) -> None:
    path = logs[name]
    rep = replay_log(path, Config(), keep_estimates=True, two_pass=True)
    assert rep.summary["passes"] == 2
    assert rep.summary["counts"]["reboots"] == (name == "reboot")
    mem = learn_pass(path, Config())  # the same first pass: the states the second one holds fixed
    assert mem is not None
    assert all(s.calib_l is not None for s in mem.states.values())  # the hand rotation was learned
    base = Config()
    fixed = replace(base, observer=replace(base.observer, learn=False))  # no theta steps, no re-learning
    ref = replay_log(path, fixed, store=mem, keep_estimates=True)
    a, b = _columns(rep.estimates), _columns(ref.estimates)
    np.testing.assert_array_equal([e.t_boot_s for e in rep.estimates], [e.t_boot_s for e in ref.estimates])
    assert len(rep.estimates) == len(ref.estimates) > 1000
    np.testing.assert_array_equal(a["t"], b["t"])
    np.testing.assert_array_equal(a["mag"], b["mag"])
    assert np.abs(_wrap(a["heading"] - b["heading"])).max() < 1e-6
    assert np.abs(_wrap(a["heading_raw"] - b["heading_raw"])).max() < 1e-6
    np.testing.assert_allclose(a["theta"], b["theta"], rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(a["bias"], b["bias"], rtol=0.0, atol=1e-9)
    # the reference's observer never steps, so it never calls theta converged; otherwise the same flags
    np.testing.assert_array_equal(a["flags"] & ~FLAG_THETA_CONVERGED, b["flags"] & ~FLAG_THETA_CONVERGED)
    # the summary describes the second pass: estimates and time in each state per compass
    assert rep.summary["counts"]["estimates"] == ref.summary["counts"]["estimates"] == len(rep.estimates)
    for c1, c2 in zip(rep.summary["compasses"], ref.summary["compasses"], strict=True):
        assert c1["estimates"] == c2["estimates"]
        assert c1["time_s"] == pytest.approx(c2["time_s"], abs=1e-9)
        assert c1["status"] == "corrected"
    # and the correction is real: theta moved the heading where the throttle was up
    assert np.abs(_wrap(a["heading"] - a["heading_raw"])).max() > 1.0


def test_the_sample_log_spilled_to_disk_gives_the_same_replay(
    paper_log: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Memory does not grow with the log: the first pass spills its sample log every CHUNK_ROWS rows and
    the second reads it back a chunk at a time; the headings and the --emit bytes do not depend on it."""
    whole = replay_log(paper_log, Config(), keep_estimates=True, two_pass=True, emit=tmp_path / "a.tlog")
    monkeypatch.setattr(final_pass, "CHUNK_ROWS", 1000)
    spilled = replay_log(paper_log, Config(), keep_estimates=True, two_pass=True, emit=tmp_path / "b.tlog")
    assert whole.n_estimates == spilled.n_estimates == whole.emitted > 5000
    assert (tmp_path / "a.tlog").read_bytes() == (tmp_path / "b.tlog").read_bytes()
    a, b = _columns(whole.estimates), _columns(spilled.estimates)
    np.testing.assert_array_equal(a["heading"], b["heading"])


def test_per_motor_terms_take_the_per_sample_second_pass(tmp_path: Path) -> None:
    """An in-flight estimate with per-motor terms (its bias follows the motor outputs, which the sample log
    does not record) is replayed per sample from the stored state: still two passes, every heading there."""
    path = tmp_path / "ordinary.tlog"
    write_tlog(simulate(SimConfig(scenario="ordinary", duration_s=100.0, seed=1)), path)
    base = Config()
    cfg = replace(base, inflight=replace(base.inflight, per_motor="auto"))
    rep = replay_log(path, cfg, two_pass=True)
    assert rep.summary["passes"] == 2
    assert rep.n_estimates == rep.summary["counts"]["mag"] > 1000
    for c in rep.summary["compasses"]:
        assert c["inflight"]["per_motor"] and c["status"] == "corrected"
        assert c["inflight"]["started_from_stored_state"]  # the per-sample second pass's warm start
