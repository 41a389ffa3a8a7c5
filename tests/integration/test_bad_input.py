"""Bad input: unreadable, empty or non-MAVLink files fail with one line and a non-zero exit; damage
inside a readable log is skipped, counted and reported, and the intact parts give exactly the headings
they give in a clean log (the oracle: the clean log without the damaged messages)."""

from __future__ import annotations

import math
import subprocess
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.config import Config
from magcomp.core.types import (
    FLAG_NO_THROTTLE,
    HeadingEstimate,
    ImuSample,
    MagSample,
    Sample,
    ThrottleSample,
)
from magcomp.service.pipeline import Pipeline
from magcomp.service.replay import replay_log
from tests.configs import QUICK_CALIBRATION
from tests.faultgen import record_msgid

REPO = Path(__file__).parents[2]


def no_magic(data: bytes) -> bytes:
    """Random bytes without MAVLink start bytes (a start byte could begin a false, valid-looking frame)."""
    return data.replace(b"\xfd", b"\x01").replace(b"\xfe", b"\x01")


RAW_IMU, SERVO_OUTPUT_RAW, RC_CHANNELS, VFR_HUD = 27, 36, 65, 74


@pytest.fixture(scope="module")
def clean(
    tmp_path_factory: pytest.TempPathFactory, split_tlog: Callable[[bytes], list[bytes]]
) -> tuple[Path, list[bytes]]:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    path = tmp_path_factory.mktemp("bad") / "clean.tlog"
    write_tlog(simulate(SimConfig(scenario="paper", duration_s=34.0, seed=11, n_compasses=1)), path)
    return path, split_tlog(path.read_bytes())


def replay_records(
    tmp: Path, name: str, recs: list[bytes] | bytes
) -> tuple[list[HeadingEstimate], dict[str, int]]:
    p = tmp / name
    p.write_bytes(recs if isinstance(recs, bytes) else b"".join(recs))
    rep = replay_log(p, QUICK_CALIBRATION, keep_estimates=True)
    return rep.estimates, rep.counts


def key(e: HeadingEstimate) -> tuple[object, ...]:
    return (e.t_s, e.mag_index, e.heading_deg, e.heading_raw_deg, e.flags, *e.theta_mgauss.tolist())


def same(a: list[HeadingEstimate], b: list[HeadingEstimate]) -> bool:
    return [key(e) for e in a] == [key(e) for e in b]


# ------------------------------------------------------------------------------------------ whole files


@pytest.mark.parametrize("kind", ["empty", "text", "binary", "directory", "missing"])
def test_unusable_file_one_line_error_nonzero_exit(tmp_path: Path, kind: str) -> None:
    path = tmp_path / f"{kind}.tlog"
    if kind == "empty":
        path.write_bytes(b"")
    elif kind == "text":
        path.write_text("timestamp,heading\n1,2\n" * 20)
    elif kind == "binary":
        path.write_bytes(no_magic(np.random.default_rng(3).integers(0, 256, 5000, dtype=np.uint8).tobytes()))
    elif kind == "directory":
        path.mkdir()
    proc = subprocess.run([sys.executable, "-m", "magcomp", "replay", str(path)], capture_output=True,
                          text=True, cwd=REPO, timeout=60)  # fmt: skip
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("magcomp replay: error: "), proc.stderr
    assert "Traceback" not in proc.stderr


# ------------------------------------------------------------------------------------- damage in a log


def test_garbage_bytes_between_packets_are_skipped_and_change_nothing(
    clean: tuple[Path, list[bytes]], tmp_path: Path
) -> None:
    _, recs = clean
    base, _ = replay_records(tmp_path, "a.tlog", recs)
    rng = np.random.default_rng(5)
    damaged = list(recs)
    for i in sorted(rng.choice(len(recs), 15, replace=False), reverse=True):
        junk = no_magic(rng.integers(0, 256, 37, dtype=np.uint8).tobytes())
        damaged.insert(int(i), junk)
    got, counts = replay_records(tmp_path, "b.tlog", damaged)
    assert counts["garbage_bytes"] >= 15 * 37
    assert same(got, base)


def test_bad_crc_packets_are_counted_and_the_rest_matches_the_log_without_them(
    clean: tuple[Path, list[bytes]], tmp_path: Path
) -> None:
    _, recs = clean
    idx = [i for i, r in enumerate(recs) if record_msgid(r) == RAW_IMU][200::97][:8]
    damaged = list(recs)
    for i in idx:
        r = bytearray(recs[i])
        r[8 + 10 + 3] ^= 0x5A  # a payload byte: the CRC no longer matches
        damaged[i] = bytes(r)
    got, counts = replay_records(tmp_path, "crc.tlog", damaged)
    oracle, _ = replay_records(tmp_path, "oracle.tlog", [r for i, r in enumerate(recs) if i not in set(idx)])
    assert counts["bad_crc"] == len(idx)
    assert same(got, oracle)


def test_truncated_log_gives_the_clean_prefix(clean: tuple[Path, list[bytes]], tmp_path: Path) -> None:
    _, recs = clean
    cut = int(0.7 * len(recs))
    data = b"".join(recs[:cut]) + recs[cut][:-5]  # the last packet lost its CRC and more
    got, counts = replay_records(tmp_path, "trunc.tlog", data)
    oracle, _ = replay_records(tmp_path, "prefix.tlog", recs[:cut])
    assert counts["truncated"] == 1
    assert same(got, oracle)


def test_time_going_backwards_is_skipped(clean: tuple[Path, list[bytes]], tmp_path: Path) -> None:
    _, recs = clean
    n = len(recs)
    damaged = recs[: n // 2] + recs[n // 2 - 60 : n // 2 - 10] + recs[n // 2 :]  # 50 stale messages again
    base, _ = replay_records(tmp_path, "a.tlog", recs)
    got, counts = replay_records(tmp_path, "back.tlog", damaged)
    assert counts["time_backwards"] > 0
    assert same(got, base)


def test_gap_resets_the_observer_and_headings_continue(
    clean: tuple[Path, list[bytes]], tmp_path: Path
) -> None:
    _, recs = clean
    n = len(recs)
    a, b = int(0.45 * n), int(0.45 * n) + 600  # about 3 s of messages
    got, counts = replay_records(tmp_path, "gap.tlog", recs[:a] + recs[b:])
    assert counts["gaps"] >= 1 and counts["observer_resets"] >= 1
    t = np.array([e.t_s for e in got])
    assert np.max(np.diff(t)) > 2.0
    assert t[-1] > t[0] + 25.0
    assert all(math.isfinite(e.heading_deg) for e in got)


def test_no_throttle_source_headings_flow_flagged_uncorrected(
    clean: tuple[Path, list[bytes]], tmp_path: Path
) -> None:
    _, recs = clean
    keep = [r for r in recs if record_msgid(r) not in (SERVO_OUTPUT_RAW, RC_CHANNELS, VFR_HUD)]
    p = tmp_path / "nothr.tlog"
    p.write_bytes(b"".join(keep))
    rep = replay_log(p, QUICK_CALIBRATION, keep_estimates=True)
    assert len(rep.estimates) > 1000
    assert all(e.flags & FLAG_NO_THROTTLE and e.heading_deg == e.heading_raw_deg for e in rep.estimates)
    assert any("no throttle source" in w for w in rep.summary["warnings"])


# --------------------------------------------------------------------------------- samples, pipeline level


@pytest.fixture(scope="module")
def samples(clean: tuple[Path, list[bytes]]) -> list[Sample]:
    from magcomp.adapters.mavlink_source import open_source

    with open_source(clean[0]) as src:
        return list(src.samples())


def run(samples: list[Sample], config: Config | None = None) -> tuple[list[HeadingEstimate], Pipeline]:
    p = Pipeline(config or QUICK_CALIBRATION)
    return [e for e in map(p.process, samples) if e is not None], p


def test_nan_inf_and_saturated_samples_are_skipped_and_counted(samples: list[Sample]) -> None:
    base, _ = run(samples)
    bad: list[Sample] = []
    n_bad = 0
    for i, s in enumerate(samples):
        if i % 997 == 500:
            bad.append(MagSample(s.t_s + 0.001, np.array([np.nan, 1.0, 2.0])))
            bad.append(ImuSample(s.t_s + 0.001, np.array([np.inf, 0.0, 0.0]), np.array([0.0, 0.0, -9.8])))
            bad.append(ThrottleSample(s.t_s, float("nan")))
            n_bad += 3
        bad.append(s)
    got, p = run(bad)
    assert p.counts["non_finite"] == n_bad
    assert same(got, base)
    # saturated compass readings: skipped, counted, the gyro of the same message still used
    mags = [i for i, s in enumerate(samples) if isinstance(s, MagSample)][300::211]
    hit = set(mags)
    sat = [MagSample(s.t_s, np.array([9000.0, 0.0, 0.0])) if i in hit else s for i, s in enumerate(samples)]
    got_sat, p_sat = run(sat)
    oracle, _ = run([s for i, s in enumerate(samples) if i not in set(mags)])
    assert p_sat.counts["saturated"] == len(mags)
    assert same(got_sat, oracle)


def test_clock_reset_is_absorbed_and_headings_continue(samples: list[Sample]) -> None:
    n = len(samples)
    shifted = samples[: n // 2] + [replace(s, t_s=s.t_s - 500.0) for s in samples[n // 2 :]]  # type: ignore[type-var]
    got, p = run(shifted)
    assert p.counts["clock_resets"] >= 1
    assert len(got) == sum(isinstance(s, MagSample) for s in samples)


def test_observer_bounded_under_absurd_input() -> None:
    rng = np.random.default_rng(9)
    c = QUICK_CALIBRATION
    c = replace(c, calibration=replace(c.calibration, mode="none"))
    p = Pipeline(c)
    t = 0.0
    out = []
    for _ in range(3000):
        t += float(rng.choice([0.02, 0.0005, 0.5, 0.02, 0.02]))
        p.process(ThrottleSample(t, 1.0))
        p.process(ImuSample(t, rng.normal(0, 5, 3), np.array([0.0, 0.0, -9.8])))
        e = p.process(MagSample(t, rng.normal(0, 3000, 3)))
        if e is not None:
            out.append(e)
    theta = np.array([e.theta_mgauss for e in out])
    assert np.all(np.isfinite(theta))
    assert np.max(np.abs(theta)) <= c.observer.theta_max_mgauss
    assert p.counts["observer_resets"] > 0
