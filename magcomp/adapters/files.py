"""Whole files written at once (logs, parameter files, JSON summaries): an OS error becomes one line.

A regular file (or a path that does not exist yet) is written beside it under a temporary name and
renamed over it: a reader never sees half a file, and a write that fails leaves the path as it was. A
path that is not a regular file (a device such as /dev/stdout, a FIFO) is written in place. Nothing but
the temporary file, ours, is ever removed.
"""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from pathlib import Path

from magcomp.errors import InputError


def write_file(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path``; a failure is an :class:`InputError` naming the path and the reason."""
    p = Path(path)
    tmp = ""
    try:
        try:
            st: os.stat_result | None = os.stat(p)
        except FileNotFoundError:
            st = None
        if st is not None and not stat.S_ISREG(st.st_mode):
            p.write_bytes(data)
            return
        target = p.resolve() if st is not None else p
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".part", dir=target.parent)
        with os.fdopen(fd, "wb") as f:
            mode = stat.S_IMODE(st.st_mode) if st is not None else 0o666 & ~current_umask()
            with contextlib.suppress(OSError):
                os.fchmod(f.fileno(), mode)
            f.write(data)
        os.replace(tmp, target)
        tmp = ""
    except OSError as exc:
        raise InputError(f"cannot write {path}: {exc.strerror or exc}") from exc
    finally:
        if tmp:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def current_umask() -> int:
    """The process's umask (read by setting it and setting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask
