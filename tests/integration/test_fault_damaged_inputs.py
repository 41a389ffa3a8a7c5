"""Issue 25 (4): damaged inputs give a result or one line, never a traceback, and keep their intact parts:
non-finite parameters in a DataFlash log (`fit`, `diagnose`), NUL bytes in a text `.log`."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from magcomp.cli import main

MEASURED = Path(__file__).parents[2].parent / "shared" / "data" / "measured"
TEXT = MEASURED / "ardupilot_loganalyzer_nan_copter311.log"
NAN_PARAMS = ("COMPASS_MOTCT", "COMPASS_PRIMARY", "AHRS_EKF_TYPE", "EK3_SRC1_YAW", "SERVO1_FUNCTION",
              "MOT_PWM_MIN")  # fmt: skip


@pytest.fixture(scope="module")
def bench_logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A simulated bench sweep as DataFlash, clean and with six parameters logged as NaN."""
    import magcomp.adapters.dataflash_writer as dw
    from magcomp.sim import SimConfig, simulate

    d = tmp_path_factory.mktemp("nanparams")
    result = simulate(SimConfig(scenario="bench", seed=23, n_compasses=1))
    dw.write_sim_dataflash(result, d / "clean.bin")
    real = dw.sim_parameters
    try:
        dw.sim_parameters = lambda *a, **k: sorted(  # type: ignore[assignment]
            [p for p in real(*a, **k) if p[0] not in NAN_PARAMS] + [(n, math.nan) for n in NAN_PARAMS]
        )
        dw.write_sim_dataflash(result, d / "nan.bin")
    finally:
        dw.sim_parameters = real  # type: ignore[assignment]
    return {"clean": d / "clean.bin", "nan": d / "nan.bin"}


def _no_traceback(capsys: pytest.CaptureFixture[str]) -> str:
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return out


def test_fit_with_nan_parameters_gives_the_clean_logs_fit(
    bench_logs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    thetas = {}
    for name, path in bench_logs.items():
        out = tmp_path / f"{name}.json"
        assert main(["fit", str(path), "--json", str(out), "--monte-carlo", "20"]) == 0
        _no_traceback(capsys)
        thetas[name] = np.asarray(json.loads(out.read_text())["theta"], dtype=float)
    assert np.all(np.isfinite(thetas["nan"])) and np.linalg.norm(thetas["clean"]) > 10.0
    # the parameters do not enter the bench fit: the same window, the same numbers
    np.testing.assert_allclose(thetas["nan"], thetas["clean"], rtol=1e-9, atol=1e-9)


def test_diagnose_with_nan_parameters_reads_the_log_and_counts_them(
    bench_logs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "d.json"
    assert main(["diagnose", str(bench_logs["nan"]), "--json", str(out)]) == 0
    _no_traceback(capsys)
    doc = json.loads(out.read_text())
    assert doc["counts"]["non_finite_params"] == len(NAN_PARAMS)


@pytest.mark.needs_shared
@pytest.mark.parametrize("command", ["replay", "diagnose"])
def test_nul_bytes_in_a_text_log_cost_only_the_damaged_lines(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    if not TEXT.is_file():
        pytest.skip(f"measured log {TEXT.name} not available (expected in {MEASURED})")
    data = bytearray(TEXT.read_bytes())
    rng = np.random.default_rng(2)
    for p in rng.integers(1000, len(data) - 100, 20):  # 20 runs of 50 NUL bytes (a flash page gone)
        data[p : p + 50] = b"\0" * 50
    damaged = tmp_path / "damaged.log"
    damaged.write_bytes(bytes(data))
    docs = {}
    for name, path in (("clean", TEXT), ("damaged", damaged)):
        js = tmp_path / f"{name}.json"
        assert main([command, str(path), "--json", str(js)]) == 0
        _no_traceback(capsys)
        docs[name] = json.loads(js.read_text())
    if command == "replay":
        clean, bad = docs["clean"], docs["damaged"]
        assert bad["estimates"] >= 0.9 * clean["estimates"] > 100
        assert bad["source_counts"]["unreadable_records"] > 0  # the loss is counted, not silent


def test_diagnose_of_a_dataflash_log_with_a_zero_tail_is_bounded(
    bench_logs: dict[str, Path], tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """1 MiB of zero padding after a .bin: diagnose printed a "bad header" line per byte (two million,
    from pymavlink's reader of the events, straight to the C streams); now it reads the repaired log and
    says what it dropped on one line."""
    padded = tmp_path / "padded.bin"
    padded.write_bytes(bench_logs["clean"].read_bytes() + b"\0" * (1 << 20))
    capfd.readouterr()
    assert main(["diagnose", str(padded)]) == 0
    out, err = capfd.readouterr()
    lines = (out + err).splitlines()
    assert len(lines) <= 100, f"{len(lines)} lines, e.g. {lines[-1]!r}"
    assert "Traceback" not in err
    assert any("skipped or absorbed while reading the log: garbage bytes" in line for line in lines)


@pytest.mark.parametrize("command", ["fit", "diagnose"])
def test_clipped_magnetometer_samples_do_not_move_the_fit(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], split_tlog: Any
) -> None:
    """Ten RAW_IMU samples clipped at the int16 limit during the bench sweep: before, `fit` kept them
    (theta moved by tens of mgauss, exit 0, nothing said); now the pipeline's saturation gate drops them
    in fit and diagnose too, and says so."""
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate
    from tests.faultgen import rewrite_some

    clean = tmp_path / "clean.tlog"
    write_tlog(simulate(SimConfig(scenario="bench", seed=23, n_compasses=1)), clean)
    records = split_tlog(clean.read_bytes())
    n_imu = sum(1 for r in records if r[8 + 7 : 8 + 10] == b"\x1b\x00\x00")
    rng = np.random.default_rng(4)
    hits = set(rng.choice(np.arange(n_imu // 3, 2 * n_imu // 3), 10, replace=False).tolist())
    clipped = tmp_path / "clipped.tlog"
    damaged = rewrite_some(records, "RAW_IMU", lambda k: k in hits, xmag=32767, ymag=-32768)
    clipped.write_bytes(b"".join(damaged))
    if command == "fit":
        thetas = {}
        for name, path in (("clean", clean), ("clipped", clipped)):
            js = tmp_path / f"{name}.json"
            assert main(["fit", str(path), "--json", str(js), "--monte-carlo", "20"]) == 0
            doc = json.loads(js.read_text())
            thetas[name] = np.asarray(doc["theta"], dtype=float)
        out = _no_traceback(capsys)
        assert doc["dropped"]["saturated"] == 10 and "dropped before the fit: saturated 10" in out
        assert np.linalg.norm(thetas["clipped"] - thetas["clean"]) < 1.0, thetas
    else:
        js = tmp_path / "d.json"
        assert main(["diagnose", str(clipped), "--json", str(js)]) == 0
        _no_traceback(capsys)
        assert json.loads(js.read_text())["counts"]["saturated"] == 10
