"""Keeping third-party readers (pymavlink's DFReader and indexer, pyulog) from printing: the library must
not print."""

from __future__ import annotations

import contextlib
import io
import sys
from collections.abc import Iterator


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """pymavlink's DFReader prints warnings ("bad header ...") to stdout/stderr; the library must not
    print."""
    sink = io.StringIO()
    with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
        yield


@contextlib.contextmanager
def quiet_c_streams() -> Iterator[None]:
    """Silence file descriptors 1 and 2 for the block: pymavlink's Cython indexer (``dfindexer``, run when a
    DFReader_binary is built) writes "bad header ..." for every byte it cannot frame straight to the C
    streams, out of :func:`quiet`'s reach (122815 lines for 200 kB of random bytes). Used only around that
    constructor (a file replay, not the live daemon); a no-op when the descriptors cannot be duplicated."""
    import ctypes
    import os

    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    saved: list[tuple[int, int]] = []
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
    except OSError:
        yield
        return
    try:
        for fd in (1, 2):
            with contextlib.suppress(OSError):
                saved.append((fd, os.dup(fd)))
                os.dup2(devnull, fd)
        yield
    finally:
        with contextlib.suppress(Exception):
            ctypes.CDLL(None).fflush(None)  # what C stdio still buffers goes to /dev/null too
        for fd, old in saved:
            os.dup2(old, fd)
            os.close(old)
        os.close(devnull)
