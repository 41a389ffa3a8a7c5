"""Issue 25 (3): whole-file outputs (JSON summaries, parameter files, logs) are written to a temporary
file and renamed: a write that fails half-way (a full disk) leaves the previous file as it was, and
leaves no temporary file behind; a device is written in place, never replaced or removed."""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path
from typing import Any

import pytest

from magcomp.adapters.files import write_file
from magcomp.errors import InputError


def test_a_failed_write_keeps_the_previous_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "summary.json"
    out.write_text('{"previous": true}\n')
    real_fdopen = os.fdopen

    class HalfWriter:
        def __init__(self, f: Any) -> None:
            self.f = f

        def __enter__(self) -> HalfWriter:
            return self

        def __exit__(self, *exc: object) -> None:
            self.f.close()

        def fileno(self) -> int:
            return int(self.f.fileno())

        def write(self, data: bytes) -> int:
            self.f.write(data[:10])
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fdopen", lambda fd, mode="r": HalfWriter(real_fdopen(fd, mode)))
    with pytest.raises(InputError, match="No space left"):
        write_file(out, b'{"new": "a long document that does not fit"}\n')
    monkeypatch.undo()
    assert out.read_text() == '{"previous": true}\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["summary.json"]


def test_a_replaced_file_keeps_its_mode_and_a_device_is_written_in_place(tmp_path: Path) -> None:
    out = tmp_path / "x.params"
    out.write_bytes(b"old")
    out.chmod(0o600)
    write_file(out, b"new")
    assert out.read_bytes() == b"new" and stat.S_IMODE(out.stat().st_mode) == 0o600
    write_file("/dev/null", b"anything")  # not replaced by a regular file
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)
