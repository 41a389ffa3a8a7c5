"""Whole files written at once by the adapters (logs, parameter files): an OS error becomes one line."""

from __future__ import annotations

import os
from pathlib import Path

from magcomp.errors import InputError


def write_file(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path``; a failure is an :class:`InputError` naming the path and the reason."""
    try:
        Path(path).write_bytes(data)
    except OSError as exc:
        raise InputError(f"cannot write {path}: {exc.strerror or exc}") from exc
