"""Link errors that waiting cannot heal fail at start with one line and a non-zero exit (instead of
retrying forever); `diagnose --report` without matplotlib says how to get it."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from magcomp.cli import main


@pytest.fixture()
def busy_udp_port() -> Iterator[int]:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    yield s.getsockname()[1]
    s.close()


def _one_line_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if "error:" in ln]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


# pymavlink leaves the socket whose bind failed to the collector (a ResourceWarning that is not ours)
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_udp_port_in_use_fails_at_start(busy_udp_port: int, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", "--master", f"udpin:127.0.0.1:{busy_udp_port}", "--state-dir", "/nonexistent-x"])
    assert code != 0
    assert "in use" in _one_line_error(capsys)


@pytest.mark.parametrize("url", ["tcp:no-such-host.invalid:5760", "udpout:no-such-host.invalid:14550"])
def test_host_that_does_not_resolve_fails_at_start(url: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "--master", url]) != 0
    assert "does not resolve" in _one_line_error(capsys)


def test_missing_serial_device_fails_at_start(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "--master", "/dev/ttyMAGCOMP-NOPE:57600"]) != 0
    assert "no such serial device" in _one_line_error(capsys)


def test_a_device_that_is_not_a_serial_port_fails_at_start(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "--master", "serial:/dev/null:57600"]) != 0
    assert "/dev/null" in _one_line_error(capsys)


def test_diagnose_report_without_matplotlib_says_how_to_get_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "matplotlib" else real(name, *a)
    )
    log = tmp_path / "x.tlog"
    log.write_bytes(b"\0" * 64)
    assert main(["diagnose", str(log), "--report", str(tmp_path / "r.md")]) != 0
    assert "pip install matplotlib" in _one_line_error(capsys)
