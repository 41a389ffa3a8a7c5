"""The command line as a pilot types it: every bad input ends in one clear line on stderr and a non-zero
exit, never a traceback, and never at the cost of what is already there (an input log is never
overwritten, a ^C'd replay keeps its summary and state).

All cases run in-process through :func:`magcomp.cli.main`; each fails before any long work starts.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from magcomp.cli import main

SHARED = Path(__file__).parents[2].parent / "shared"
DATAFLASH = SHARED / "data" / "measured" / "dronekit_log171_copter33_quad.bin"

# argv templates: {log} a small clean tlog, {tmp} a scratch directory, {dir} an existing directory,
# {text}/{rand}/{empty}/{cut} bad logs, and TOML files named after their defect
BAD_TOML = {
    "syntax.toml": "[observer\nk1 = 1\n",
    "unknown_key.toml": "[observer]\nfoo = 1\n",
    "unknown_section.toml": "[bogus]\nx = 1\n",
    "wrong_type.toml": '[observer]\nk1 = "fast"\n',
    "out_of_range.toml": "[observer]\nk1 = -1\n",
    "nan.toml": "[observer]\nk1 = nan\n",
    "huge_buffer.toml": "[calibration]\nmax_samples = 999999999999\n",
    "heartbeat_flood.toml": "[link]\nheartbeat_hz = 1e9\n",
}


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    tmp = tmp_path_factory.mktemp("cli_bad")
    log = tmp / "clean.tlog"
    write_tlog(simulate(SimConfig(scenario="step", duration_s=3.0, seed=5, n_compasses=1)), log)
    data = log.read_bytes()
    (tmp / "a_dir").mkdir()
    (tmp / "empty.tlog").write_bytes(b"")
    (tmp / "notes.tlog").write_text("takeoff at 10:32, compass looked fine\n")
    rng = np.random.default_rng(3)
    raw = rng.integers(0, 256, 20_000, dtype="uint8").tobytes()
    (tmp / "random.tlog").write_bytes(raw.replace(b"\xfd", b"\x01").replace(b"\xfe", b"\x01"))
    (tmp / "cut.tlog").write_bytes(data[:100])  # a few header messages, cut mid-record, no compass
    for name, text in BAD_TOML.items():
        (tmp / name).write_text(text)
    return {
        "log": str(log),
        "tmp": str(tmp),
        "dir": str(tmp / "a_dir"),
        "empty": str(tmp / "empty.tlog"),
        "text": str(tmp / "notes.tlog"),
        "rand": str(tmp / "random.tlog"),
        "cut": str(tmp / "cut.tlog"),
        **{name.removesuffix(".toml"): str(tmp / name) for name in BAD_TOML},
    }


@pytest.fixture(autouse=True)
def restore_logging() -> Iterator[None]:
    """The commands point the 'magcomp' logger at the (captured) stderr; give later tests theirs back."""
    logger = logging.getLogger("magcomp")
    handlers, level = logger.handlers[:], logger.level
    yield
    logger.handlers[:] = handlers
    logger.setLevel(level)


SIM = ["simulate", "--out", "{tmp}/s.tlog"]

# (case id, argv template, a fragment the one-line message must contain)
CASES: list[tuple[str, list[str], str]] = [
    # replay: unreadable inputs
    ("replay-missing", ["replay", "{tmp}/nope.tlog"], "no such file"),
    ("replay-directory", ["replay", "{dir}"], "not a file"),
    ("replay-empty", ["replay", "{empty}"], "empty file"),
    ("replay-text", ["replay", "{text}"], "not a MAVLink log"),
    ("replay-random-bytes", ["replay", "{rand}"], "no valid MAVLink messages"),
    ("replay-cut-no-compass", ["replay", "{cut}"], "no magnetometer messages"),
    # replay: outputs that cannot be written or would destroy the input
    ("replay-emit-over-input", ["replay", "{log}", "--emit", "{log}"], "refusing to overwrite"),
    ("replay-json-over-input", ["replay", "{log}", "--json", "{log}"], "refusing to overwrite"),
    ("replay-emit-is-dir", ["replay", "{log}", "--emit", "{dir}"], "is a directory"),
    ("replay-json-no-dir", ["replay", "{log}", "--json", "{tmp}/missing/x.json"], "does not exist"),
    ("replay-emit-equals-json", ["replay", "{log}", "--emit", "{tmp}/o", "--json", "{tmp}/o"], "same file"),
    ("replay-emit-as-ulog", ["replay", "{log}", "--emit", "{tmp}/out.ulg"], "name it .tlog"),
    # replay: configuration
    ("config-missing", ["replay", "{log}", "--config", "{tmp}/nope.toml"], "no such file"),
    ("config-directory", ["replay", "{log}", "--config", "{dir}"], "is a directory"),
    ("config-syntax", ["replay", "{log}", "--config", "{syntax}"], "not valid TOML"),
    ("config-unknown-key", ["replay", "{log}", "--config", "{unknown_key}"], "unknown key 'foo'"),
    ("config-unknown-section", ["replay", "{log}", "--config", "{unknown_section}"], "unknown section"),
    ("config-wrong-type", ["replay", "{log}", "--config", "{wrong_type}"], "k1 must be a number"),
    ("config-out-of-range", ["replay", "{log}", "--config", "{out_of_range}"], "k1 must be > 0"),
    ("config-nan", ["replay", "{log}", "--config", "{nan}"], "must be finite"),
    ("config-huge-buffer", ["replay", "{log}", "--config", "{huge_buffer}"], "max_samples must be in"),
    ("config-heartbeat-flood", ["replay", "{log}", "--config", "{heartbeat_flood}"], "heartbeat_hz"),
    ("replay-rerun-mode", ["replay", "{log}", "--rerun", "bogus"], "unknown mode"),
    # run: links that can never open, numbers that make no sense; all refused before listening
    ("run-udpin-nonsense", ["run", "--master", "udpin:nonsense"], "expected udpin:HOST:PORT"),
    ("run-unknown-scheme", ["run", "--master", "bogus:x:y"], "not a link URL"),
    ("run-empty-url", ["run", "--master", ""], "empty"),
    ("run-port-range", ["run", "--master", "udpin:0.0.0.0:99999"], "out of range"),
    ("run-bad-baud", ["run", "--master", "/dev/ttyNOPE:fast"], "baud rate"),
    ("run-log-as-master", ["run", "--master", "{log}"], "magcomp replay"),
    ("run-bad-out", ["run", "--master", "udpin:127.0.0.1:14551", "--out", "tcp:host"], "--out"),
    ("run-duration-negative", ["run", "--master", "udpin:127.0.0.1:14551", "--duration", "-1"], "--duration"),
    ("run-duration-nan", ["run", "--master", "udpin:127.0.0.1:14551", "--duration", "nan"], "--duration"),
    ("run-duration-inf", ["run", "--master", "udpin:127.0.0.1:14551", "--duration", "inf"], "--duration"),
    ("run-json-no-dir", ["run", "--master", "udpin:127.0.0.1:14551", "--json", "{tmp}/m/x.json"], "exist"),
    ("run-no-such-device", ["run", "--master", "/dev/ttyNOPE", "--duration", "0.2"], "no such serial device"),
    # simulate
    ("simulate-effect-no-value", [*SIM, "--effect", "current_lag"], "NAME=VALUE"),
    ("simulate-effect-text", [*SIM, "--effect", "current_lag=abc"], "number"),
    ("simulate-effect-nan", [*SIM, "--effect", "current_lag=nan"], "must be in"),
    ("simulate-effect-unknown", [*SIM, "--effect", "gremlins=1"], "gremlins"),
    ("simulate-scenario", [*SIM, "--scenario", "loop"], "unknown scenario"),
    ("simulate-duration-nan", [*SIM, "--duration", "nan"], "duration"),
    ("simulate-duration-huge", [*SIM, "--duration", "1e12"], "duration"),
    ("simulate-speed-nan", ["simulate", "--link", "udpout:127.0.0.1:14552", "--speed", "nan"], "--speed"),
    ("simulate-speed-tiny", ["simulate", "--link", "udpout:127.0.0.1:14552", "--speed", "1e-9"], "--speed"),
    ("simulate-seed-negative", [*SIM, "--seed", "-1"], "--seed"),
    ("simulate-out-empty", ["simulate", "--out", ""], "empty"),
    ("simulate-out-no-dir", ["simulate", "--out", "{tmp}/missing/s.tlog"], "does not exist"),
    ("simulate-bad-link", ["simulate", "--link", "bogus"], "udpout:HOST:PORT"),
    # fit
    ("fit-missing", ["fit", "{tmp}/nope.tlog"], "no such file"),
    ("fit-empty-path", ["fit", ""], "empty"),
    ("fit-text", ["fit", "{text}"], "not a MAVLink log"),
    ("fit-seed-negative", ["fit", "{log}", "--seed", "-1"], "--seed"),
    ("fit-mag-negative", ["fit", "{log}", "--mag", "-1"], "--mag"),
    ("fit-mag-absent", ["fit", "{log}", "--mag", "5", "--monte-carlo", "0"], "no compass 5"),
    ("fit-start-nan", ["fit", "{log}", "--start", "nan"], "--start"),
    ("fit-end-inf", ["fit", "{log}", "--end", "inf"], "--end"),
    ("fit-window-reversed", ["fit", "{log}", "--start", "2", "--end", "1"], "empty window"),
    ("fit-monte-carlo-huge", ["fit", "{log}", "--monte-carlo", "1000000000"], "--monte-carlo"),
    ("fit-json-over-input", ["fit", "{log}", "--json", "{log}"], "refusing to overwrite"),
    ("fit-throttle-source", ["fit", "{log}", "--throttle-source", "servo:x"], "throttle source"),
    # diagnose
    ("diagnose-directory", ["diagnose", "{dir}"], "is a directory"),
    ("diagnose-missing", ["diagnose", "{tmp}/nope.tlog"], "no such file"),
    ("diagnose-random-bytes", ["diagnose", "{rand}"], "no valid MAVLink messages"),
    ("diagnose-json-over-input", ["diagnose", "{log}", "--json", "{log}"], "refusing to overwrite"),
    ("diagnose-report-over-input", ["diagnose", "{log}", "--report", "{log}"], "refusing to overwrite"),
    ("diagnose-truth-not-npz", ["diagnose", "{log}", "--truth", "{text}"], "not a NumPy .npz file"),
    ("diagnose-rerun-save-no-dir", ["diagnose", "{log}", "--rerun", "save={tmp}/m/x.rrd"], "does not exist"),
    ("diagnose-mag-index-negative", ["diagnose", "{log}", "--mag-index", "-1"], "--mag-index"),
    ("diagnose-year-1900", ["diagnose", "{log}", "--year", "1900"], "outside [2010, 2030)"),
    ("diagnose-year-nan", ["diagnose", "{log}", "--year", "nan"], "--year nan is outside"),
    # demo (all refused before the simulator starts)
    ("demo-duration-short", ["demo", "--duration", "10"], "--duration"),
    ("demo-speed-nan", ["demo", "--speed", "nan"], "--speed"),
    ("demo-seed-negative", ["demo", "--seed", "-1"], "--seed"),
    ("demo-json-no-dir", ["demo", "--json", "{tmp}/m/x.json"], "does not exist"),
    ("demo-config-syntax", ["demo", "--config", "{syntax}"], "not valid TOML"),
]
if Path("/dev/full").exists():
    CASES.append(("replay-emit-disk-full", ["replay", "{log}", "--emit", "/dev/full"], "No space left"))


def run_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    capsys.readouterr()
    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


def assert_one_line_error(rc: int, err: str, command: str, fragment: str) -> None:
    assert rc != 0, err
    assert "Traceback" not in err
    last = [line for line in err.splitlines() if line.strip()][-1]
    assert last.startswith(f"magcomp {command}: error: "), err
    assert fragment in last, last


@pytest.mark.parametrize(("argv", "fragment"), [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_and_nonzero(
    argv: list[str], fragment: str, files: dict[str, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = [a.format(**files) for a in argv]
    if args[0] in ("run", "demo"):
        args += ["--state-dir", str(tmp_path / "state")]
    before = Path(files["log"]).read_bytes()
    rc, _, err = run_cli(args, capsys)
    assert_one_line_error(rc, err, args[0], fragment)
    assert Path(files["log"]).read_bytes() == before  # the input log is never touched


def test_json_over_the_config_file_is_refused(
    files: dict[str, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "mine.toml"
    cfg.write_text("[observer]\nk1 = 3.0\n")
    rc, _, err = run_cli(["replay", files["log"], "--config", str(cfg), "--json", str(cfg)], capsys)
    assert_one_line_error(rc, err, "replay", "refusing to overwrite")
    assert cfg.read_text() == "[observer]\nk1 = 3.0\n"


def test_argparse_errors_exit_2_without_traceback(capsys: pytest.CaptureFixture[str]) -> None:
    for argv in (["replay"], ["run"], ["fit", "x.tlog", "--start", "soon"], ["bogus"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err and "error:" in err.splitlines()[-1]


@pytest.mark.parametrize("command", ["run", "replay", "simulate", "fit", "diagnose", "demo"])
def test_every_command_has_help(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    assert f"usage: magcomp {command}" in capsys.readouterr().out


def test_interrupted_replay_keeps_summary_state_and_emitted_headings(
    files: dict[str, str], tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """^C in the middle of a replay: exit 130 with one line, but the summary, the JSON, the state
    directory and every heading published so far are kept (the emitted tlog ends on a whole record)."""
    from magcomp.service.pipeline import Pipeline

    real_feed = Pipeline.feed
    calls = {"n": 0}

    def feed_then_interrupt(self: Pipeline, sample: object) -> bool:
        calls["n"] += 1
        if calls["n"] == 400:  # of the 478 samples the replay's source yields (658 with those it leaves out)
            raise KeyboardInterrupt
        return bool(real_feed(self, sample))  # type: ignore[arg-type]

    monkeypatch.setattr(Pipeline, "feed", feed_then_interrupt)
    emit, summary, state = tmp_path / "out.tlog", tmp_path / "sum.json", tmp_path / "state"
    argv = ["replay", files["log"], "--emit", str(emit), "--json", str(summary), "--state-dir", str(state)]
    rc, out, err = run_cli(argv, capsys)
    assert rc == 130
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == "magcomp replay: interrupted"
    assert "interrupted: the summary covers the log up to" in out
    doc = json.loads(summary.read_text())
    assert doc["estimates"] > 0 and doc["emitted"] == doc["estimates"]
    assert doc["interrupted_at_s"] > 0.0
    assert list(state.iterdir()), "the state directory is saved on ^C"
    data = emit.read_bytes()
    p, n = 0, 0
    while p < len(data):  # 8-byte stamp + MAVLink 2 frame (len at +9, signature flag at +10)
        p += 8 + 12 + data[p + 9] + (13 if data[p + 10] & 1 else 0)
        n += 1
    assert p == len(data) and n == doc["emitted"]


def _cut(src: Path, dst: Path, n_bytes: int) -> Path:
    with src.open("rb") as f:
        dst.write_bytes(f.read(n_bytes))
    return dst


@pytest.mark.skipif(not DATAFLASH.is_file(), reason=f"measured DataFlash log not found at {DATAFLASH}")
@pytest.mark.parametrize(
    ("n_bytes", "outcome"),
    [(1_000, "error"), (os.path.getsize(DATAFLASH) // 2 if DATAFLASH.is_file() else 0, "ok")],
    ids=["headers-only", "cut-in-half"],
)
def test_truncated_dataflash(
    n_bytes: int, outcome: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A .bin cut in half replays what it holds (exit 0); one cut inside its format headers is one line."""
    cut = _cut(DATAFLASH, tmp_path / "cut.bin", n_bytes)
    rc, out, err = run_cli(["replay", str(cut)], capsys)
    assert "Traceback" not in err
    if outcome == "ok":
        assert rc == 0
        assert int(out.split(": ", 1)[1].split()[0]) > 1000  # "cut.bin: N headings in ..."
    else:
        assert_one_line_error(rc, err, "replay", "no DataFlash messages")


@pytest.mark.parametrize("command", ["replay", "diagnose"])
def test_random_bytes_named_bin_is_one_line_at_the_file_descriptors(
    command: str, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """200 kB of random bytes named .bin go to pymavlink's DataFlash reader, whose Cython indexer writes a
    "bad header" line per unframed byte straight to file descriptor 2 (capsys does not see it): the user
    must still see one line."""
    path = tmp_path / "noise.bin"
    path.write_bytes(np.random.default_rng(3).integers(0, 256, 200_000, dtype=np.uint8).tobytes())
    capfd.readouterr()
    rc = main([command, str(path)])
    out, err = capfd.readouterr()
    assert rc != 0
    lines = [line for line in (out + err).splitlines() if line.strip()]
    assert len(lines) == 1, f"{len(lines)} lines, first: {lines[:3]}"
    assert lines[0].startswith(f"magcomp {command}: error: ") and "DataFlash" in lines[0], lines[0]
