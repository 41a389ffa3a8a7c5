"""Issue 25 (3): `replay --emit` never removes a path it did not create. A device node whose first write
fails (a private copy of /dev/full) survives with one line on stderr; an existing file is replaced only
by a finished tlog, never emptied or removed by a replay that has nothing to write or fails."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from magcomp.cli import main


@pytest.fixture(scope="module")
def log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    path = tmp_path_factory.mktemp("emit") / "clean.tlog"
    write_tlog(simulate(SimConfig(scenario="step", duration_s=3.0, seed=5, n_compasses=1)), path)
    return path


def _last_line(err: str) -> str:
    return [line for line in err.splitlines() if line.strip()][-1]


def test_a_device_whose_first_write_fails_survives(
    log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    full = tmp_path / "full"
    try:
        os.mknod(full, stat.S_IFCHR | 0o666, os.makedev(1, 7))  # the kernel's "full" device
    except (PermissionError, OSError) as exc:
        pytest.skip(f"cannot make a device node here: {exc}")
    capsys.readouterr()
    rc = main(["replay", str(log), "--emit", str(full)])
    err = capsys.readouterr().err
    assert rc != 0
    assert "Traceback" not in err
    assert _last_line(err).startswith("magcomp replay: error: cannot write") and "No space left" in err
    assert full.exists() and stat.S_ISCHR(full.stat().st_mode), "the device node was removed"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["full"]  # no temporary file left either


def test_an_existing_file_survives_a_replay_with_nothing_to_write(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    no_compass = tmp_path / "cut.tlog"
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    write_tlog(simulate(SimConfig(scenario="step", duration_s=3.0, seed=5, n_compasses=1)), no_compass)
    no_compass.write_bytes(no_compass.read_bytes()[:100])  # header messages only: no magnetometer
    out = tmp_path / "headings.tlog"
    out.write_bytes(b"yesterday's headings")
    capsys.readouterr()
    rc = main(["replay", str(no_compass), "--emit", str(out)])
    err = capsys.readouterr().err
    assert rc != 0 and "Traceback" not in err
    assert "no magnetometer" in _last_line(err)
    assert out.read_bytes() == b"yesterday's headings"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cut.tlog", "headings.tlog"]


def test_a_finished_tlog_replaces_the_file_keeping_its_mode(
    log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "headings.tlog"
    out.write_bytes(b"old")
    out.chmod(0o640)
    assert main(["replay", str(log), "--emit", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    data = out.read_bytes()
    assert len(data) > 1000 and data[8] == 0xFD  # stamp + MAVLink 2 frames
    assert stat.S_IMODE(out.stat().st_mode) == 0o640
    assert sorted(p.name for p in tmp_path.iterdir()) == ["headings.tlog"]


def test_a_new_file_gets_the_usual_mode(log: Path, tmp_path: Path) -> None:
    out = tmp_path / "new.tlog"
    mask = os.umask(0o022)
    try:
        assert main(["replay", str(log), "--emit", str(out)]) == 0
    finally:
        os.umask(mask)
    assert stat.S_IMODE(out.stat().st_mode) == 0o644  # not mkstemp's 0600
