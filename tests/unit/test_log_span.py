"""The replay's progress total: the span of a tlog or DataFlash log from its two ends, and the bar with its
count of the total and the time left."""

from __future__ import annotations

from pathlib import Path

import pytest

from magcomp.adapters.log_span import estimate_span_s


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, float]:
    from magcomp.adapters.dataflash_writer import write_sim_dataflash
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    d = tmp_path_factory.mktemp("span")
    res = simulate(SimConfig(scenario="tumble", duration_s=20.0, seed=3))
    write_tlog(res, d / "s.tlog")
    write_sim_dataflash(res, d / "s.bin")
    t = res.samples.t_s
    return d / "s.tlog", d / "s.bin", float(t[-1] - t[0])


def test_span_of_tlog_and_dataflash(sim: tuple[Path, Path, float]) -> None:
    tlog, binlog, span = sim
    for path in (tlog, binlog):
        got = estimate_span_s(path)
        assert got is not None and abs(got - span) < 0.05 * span + 1.0, (path, got, span)


def test_span_of_a_log_cut_mid_record(sim: tuple[Path, Path, float], tmp_path: Path) -> None:
    tlog, _, span = sim
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(tlog.read_bytes()[:-7])
    got = estimate_span_s(cut)
    assert got is not None and abs(got - span) < 0.05 * span + 1.0


def test_no_span_for_what_does_not_say(tmp_path: Path) -> None:
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(bytes(range(256)) * 40)
    assert estimate_span_s(junk) is None
    assert estimate_span_s(tmp_path / "missing.tlog") is None
    tiny = tmp_path / "tiny.bin"
    tiny.write_bytes(b"\xa3\x95")
    assert estimate_span_s(tiny) is None


def test_replay_bar_shows_the_total_and_time_left(
    sim: tuple[Path, Path, float], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from magcomp.cli import main
    from magcomp.service import console

    monkeypatch.setattr(console, "progress_enabled", lambda: True)
    tlog, _, span = sim
    assert main(["replay", str(tlog), "--causal"]) == 0
    err = capsys.readouterr().err
    assert f"/{span:.0f} s of log [" in err and "<" in err


def test_fit_reading_bar_shows_the_total_and_time_left(
    sim: tuple[Path, Path, float], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from magcomp.cli import main
    from magcomp.service import console

    monkeypatch.setattr(console, "progress_enabled", lambda: True)
    tlog, _, span = sim
    main(["fit", str(tlog)])  # a tumble has no bench sweep: the fit's own error is not the point here
    err = capsys.readouterr().err
    assert "fit: reading s.tlog" in err and f"/{span:.0f} s of log [" in err and "<" in err


def test_load_log_reports_progress_in_message_time(sim: tuple[Path, Path, float]) -> None:
    from magcomp.adapters.mavlink_source import load_log

    tlog, _, span = sim
    seen: list[float] = []
    load_log(tlog, on_progress=seen.append)
    assert len(seen) >= 3 and seen == sorted(seen)
    assert seen[-1] - seen[0] > 0.5 * span
