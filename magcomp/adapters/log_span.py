"""How many seconds of messages a log holds, estimated from its first and last few kilobytes without
reading it: the total of the replay's progress bar (its ETA). None when the file does not say (a ULog, a
raw MAVLink stream, damage at either end): the bar then shows the count and the rate only."""

from __future__ import annotations

import contextlib
import mmap
import os
import struct
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

EDGE_BYTES = 1 << 16
#: spans above this are damage, not a flight (a wrong stamp would make a useless total)
MAX_SPAN_S = 30 * 86400.0
_DF_HEAD = b"\xa3\x95"
_DF_FMT = 0x80
_FMT_LEN = 89  # A3 95 80, type, length, name[4], format[16], columns[64]
_TABLES = (b"UNIT", b"MULT", b"FMTU")


FIND_CHUNK_BYTES = 16 << 20
_STOP: list[Callable[[], bool]] = []


@contextlib.contextmanager
def interruptible_scans(should_stop: Callable[[], bool]) -> Iterator[None]:
    """While inside, the long searches of :func:`find_in_chunks` raise KeyboardInterrupt as soon as
    ``should_stop()`` is True: for a command whose ^C handler only sets a flag (replay), so that a search
    through gigabytes (a zero tail) before the first sample still stops at once."""
    _STOP.append(should_stop)
    try:
        yield
    finally:
        _STOP.remove(should_stop)


def find_in_chunks(data: Any, needle: bytes, start: int = 0) -> int:
    """``data.find(needle, start)`` (bytes or mmap), searched 16 MiB at a time: a search through
    gigabytes (the zero tail of a DataFlash log) returns to Python between chunks, where ^C
    (KeyboardInterrupt) is raised, or a stop flag (:func:`interruptible_scans`) is read; a single call in C
    holds it off until the whole file is read."""
    end = len(data)
    while True:
        if _STOP and _STOP[-1]():
            raise KeyboardInterrupt
        stop = min(end, start + FIND_CHUNK_BYTES + len(needle) - 1)
        q: int = data.find(needle, start, stop)
        if q != -1 or stop >= end:
            return q
        start += FIND_CHUNK_BYTES


def chunked_find(data: Any) -> Callable[..., int]:
    """``data.find`` as :func:`find_in_chunks` (same arguments: needle, start)."""
    return lambda needle, start=0: find_in_chunks(data, needle, start)


def estimate_span_s(path: str | os.PathLike[str]) -> float | None:
    """Seconds between the first and the last message of a tlog or DataFlash .bin, else None."""
    p = Path(path)
    try:
        size = p.stat().st_size
        with p.open("rb") as f:
            if size < 64:
                return None
            head = f.read(EDGE_BYTES)
            if head[:2] == _DF_HEAD:
                with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
                    return _dataflash_span(data)
            f.seek(max(0, size - EDGE_BYTES))
            tail = f.read()
    except (OSError, ValueError):
        return None
    return _tlog_span(head, tail)


def _plausible(span: float) -> float | None:
    return span if 0.0 < span <= MAX_SPAN_S else None


def _tlog_span(head: bytes, tail: bytes) -> float | None:
    """A tlog: 8-byte big-endian microsecond stamp + one MAVLink frame per record."""
    if len(head) < 9 or head[8] not in (0xFD, 0xFE):
        return None
    first = int.from_bytes(head[:8], "big")
    last = None
    limit = first + int(MAX_SPAN_S * 1e6)
    for magic in (0xFD, 0xFE):
        q = tail.find(bytes((magic,)), 8)
        while q != -1:
            stamp = int.from_bytes(tail[q - 8 : q], "big")
            if first <= stamp <= limit and (last is None or stamp > last) and _frame_fits(tail, q):
                last = stamp
            q = tail.find(bytes((magic,)), q + 1)
    return None if last is None else _plausible((last - first) * 1e-6)


def _frame_fits(buf: bytes, q: int) -> bool:
    """The MAVLink frame at ``q`` ends at the end of ``buf`` or where the next record's frame starts."""
    if q + 2 > len(buf):
        return False
    n = buf[q + 1] + (12 if buf[q] == 0xFD else 8)
    if buf[q] == 0xFD and q + 3 <= len(buf) and buf[q + 2] & 1:
        n += 13  # signed
    end = q + n
    return end == len(buf) or (end + 8 < len(buf) and buf[end + 8] in (0xFD, 0xFE))


def _dataflash_span(data: mmap.mmap) -> float | None:
    """A DataFlash .bin: the formats (FMT, written anywhere in ArduPilot 4.x logs) give each message's
    length and whether it starts with TimeUS; the first and the last such message give the span."""
    lengths: dict[int, int] = {_DF_FMT: _FMT_LEN}
    timed: set[int] = set()
    p = find_in_chunks(data, b"\xa3\x95\x80")
    while p != -1 and p + _FMT_LEN <= len(data):
        t, n = data[p + 3], data[p + 4]
        fmt = data[p + 9 : p + 25].rstrip(b"\0")
        cols = data[p + 25 : p + 89].rstrip(b"\0")
        name = data[p + 5 : p + 9].rstrip(b"\0")
        if n >= 3:
            lengths[t] = n
            # the tables written once at the start (units, multipliers) may carry a zero TimeUS: not data
            if fmt[:1] == b"Q" and cols.split(b",")[0] == b"TimeUS" and name not in _TABLES:
                timed.add(t)
        p = find_in_chunks(data, b"\xa3\x95\x80", p + 1)
    first = _df_walk(data, 0, min(len(data), EDGE_BYTES), lengths, timed, first_only=True)
    start = max(0, len(data) - EDGE_BYTES)
    q = data.find(_DF_HEAD, start)
    last = None
    while q != -1 and last is None:  # the first position from which the messages chain to the end
        last = _df_walk(data, q, len(data), lengths, timed, first_only=False)
        q = data.find(_DF_HEAD, q + 1)
    if first is None or last is None:
        return None
    return _plausible((last - first) * 1e-6)


def _df_walk(data: mmap.mmap, p: int, end: int, lengths: dict[int, int], timed: set[int],
             first_only: bool) -> int | None:  # fmt: skip
    """Walk the messages from ``p``: the first TimeUS (``first_only``), else the last one when the chain
    reaches ``end`` exactly (None when it breaks: ``p`` was not a message boundary)."""
    last = None
    while p + 3 <= end:
        if data[p : p + 2] != _DF_HEAD or data[p + 2] not in lengths:
            return None if not first_only else last
        t = data[p + 2]
        n = lengths[t]
        if t in timed and p + 11 <= len(data):
            (stamp,) = struct.unpack_from("<Q", data, p + 3)
            if first_only:
                return int(stamp)
            last = int(stamp)
        p += n
    if first_only:
        return last
    return last if p == end else None
