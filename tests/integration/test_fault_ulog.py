"""Issue 25 (4): a damaged PX4 ULog keeps its intact parts. Flipped bits put pyulog out of step (before:
most of the log after the first damage was lost, silently) and send timestamps to 2^63 us (diagnose
then asked for a petabyte grid); now the intact messages are read again, lone timestamp glitches are
dropped, and the summary counts both."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.adapters.ulog_repair import ulog_intact_copy
from magcomp.adapters.ulog_source import lone_time_glitches
from magcomp.cli import main
from magcomp.service.replay import replay_log


@pytest.fixture(scope="module")
def ulogs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    from magcomp.adapters.ulog_writer import write_sim_ulog
    from magcomp.sim import SimConfig, simulate

    d = tmp_path_factory.mktemp("ulog_flips")
    result = simulate(SimConfig(scenario="paper", duration_s=60.0, seed=5))  # theta converges: comparable
    write_sim_ulog(result, d / "clean.ulg")
    data = (d / "clean.ulg").read_bytes()
    out = {"clean": d / "clean.ulg"}
    for n_flips, seed in ((30, 1), (300, 1), (1000, 2)):
        rng = np.random.default_rng(seed)
        b = bytearray(data)
        for p in rng.integers(2000, len(b), n_flips):  # the data section (the definitions stay intact)
            b[p] ^= 1 << int(rng.integers(0, 8))
        path = d / f"flips{n_flips}.ulg"
        path.write_bytes(bytes(b))
        out[f"flips{n_flips}"] = path
    return out


@pytest.mark.slow
@pytest.mark.parametrize(
    # flips300: theta within 20 % on the faults branch's simulated ULog, 40 % off once the simulator wrote its
    # own sys_uuid into the header (the same flips land elsewhere): where 300 flips land decides theta, so
    # only the headings are asserted there (noted in the closing note of 2026-11-27)
    ("name", "same_theta"), [("flips30", True), ("flips300", False), ("flips1000", False)]
)
def test_a_ulog_with_flipped_bits_keeps_its_headings_and_theta(
    ulogs: dict[str, Path], name: str, same_theta: bool
) -> None:
    """>= 90 % of the clean run's headings; theta within 20 % (of at least 25 mgauss: a compass whose
    theta is a few mgauss has nothing to compare) while the damage is moderate (one flip per 2 kB)."""
    clean = replay_log(ulogs["clean"], Config())
    bad = replay_log(ulogs[name], Config())
    assert bad.n_estimates >= 0.9 * clean.n_estimates > 1000, (bad.n_estimates, clean.n_estimates)
    counts = bad.counts
    assert counts.get("ulog_resyncs", 0) > 0 and counts.get("ulog_dropped_bytes", 0) > 0  # not silent
    if not same_theta:
        return
    for c_clean, c_bad in zip(clean.summary["compasses"], bad.summary["compasses"], strict=True):
        th_clean, th_bad = np.asarray(c_clean["theta_mgauss"]), np.asarray(c_bad["theta_mgauss"])
        tol = 0.2 * max(float(np.linalg.norm(th_clean)), 25.0)
        assert np.linalg.norm(th_bad - th_clean) <= tol, (c_clean["index"], th_bad, th_clean)


@pytest.mark.slow
def test_diagnose_reads_a_ulog_with_flipped_bits(
    ulogs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "d.json"
    assert main(["diagnose", str(ulogs["flips1000"]), "--json", str(out)]) == 0
    _, err = capsys.readouterr()
    assert "Traceback" not in err
    counts = json.loads(out.read_text())["counts"]
    assert counts["ulog_resyncs"] > 0 and counts["time_jumps"] > 0


def test_an_intact_ulog_is_not_copied(ulogs: dict[str, Path]) -> None:
    assert ulog_intact_copy(ulogs["clean"]) is None


def test_lone_timestamp_glitches_are_found_and_real_jumps_kept() -> None:
    t = np.arange(200, dtype=np.float64) * 0.02
    t[50] = 2.0**63 * 1e-6  # a flipped top bit
    t[51] = 2.0**40 * 1e-6  # and the next one too
    t[120] = 0.0  # a bit flipped to zero
    t[150:] += 30.0  # a real clock jump, confirmed by every sample after it
    bad = lone_time_glitches(t)
    assert np.flatnonzero(bad).tolist() == [50, 51, 120]


@pytest.mark.needs_shared
def test_a_measured_px4_ulog_is_intact_to_the_walk() -> None:
    """PX4 leaves a format's trailing padding fields out of the logged message: the walk must expect that
    size, or every message of such a topic would be dropped as damage."""
    measured = Path(__file__).parents[2].parent / "shared" / "data" / "measured"
    path = measured / "pyulog_sample_px4_disarmed.ulg"
    if not path.is_file():
        pytest.skip(f"measured log {path.name} not available")
    assert ulog_intact_copy(path) is None
