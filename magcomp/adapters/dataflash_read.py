"""Reading ArduPilot DataFlash logs: the intact messages of a damaged binary log (DataFlash has no
checksum), a repaired temporary copy holding only those, and pymavlink's reader over it, quietly.

Binary ``.bin`` logs are first checked by :func:`dataflash_intact_spans`; a damaged one is read through a
copy of its believed messages (``counts["garbage_bytes"]``, ``dataflash_resyncs``,
``dataflash_dropped_bytes``). Text ``.log`` files are read as they are. pymavlink's reader stops indexing
at the first unknown message type, dropping the rest of a damaged log, and prints about every bad byte: it
gets the believed messages only. Messages of a type whose FMT was lost are skipped, not taken for damage
(else one lost FMT quarantined the whole log).
"""

from __future__ import annotations

import contextlib
import gc
import mmap
import os
import struct
import warnings
from collections import deque
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

from magcomp.adapters.log_span import chunked_find
from magcomp.adapters.mavlink_frames import READ_CHUNK_BYTES
from magcomp.adapters.quiet import quiet, quiet_c_streams
from magcomp.errors import InputError

WANTED_DATAFLASH = (
    "MAG",
    "MAG2",
    "MAG3",
    "IMU",
    "IMU2",
    "IMU3",
    "ATT",
    "RCOU",
    "CTUN",
    "CURR",
    "CURR2",
    "BAT",
    "BAT2",
    "PARM",
    "MSG",
    "GPS",
    "GPS2",
    "POS",
)
#: ArduPilot logs at most this many compasses (MAG instance I) and IMUs (IMU I): COMPASS_MAX_INSTANCES and
#: INS_MAX_INSTANCES are 3; a larger instance in a DataFlash log is a corrupt byte, not a sensor
DATAFLASH_MAX_INSTANCES = 3

_DF_HEAD = b"\xa3\x95"
_DF_FMT_TYPE = 0x80
_DF_FMT_LEN = 89


# Bytes around each point of damage that are not believed. DataFlash has no checksum: a corrupt byte is
# seen only when it breaks the framing (a header, a type or a length: ~3 of a message's bytes), while every
# other corrupt byte silently changes a value that may stay plausible. Damage at a rate p per byte is seen
# about every 1/(3p) messages and leaves ~L/3 (10-30) unseen corrupt messages per point seen, spread at the
# same density. A margin wider than the spacing of the points seen drops the whole damaged region: 8 KiB
# (0.05-0.5 s of a log at 16-160 KiB/s) covers points seen every ~5 KiB, i.e. damage rates down to ~0.03 %
# of bytes, for at most 16 KiB of lost data per isolated point.
DAMAGE_MARGIN_BYTES = 8192
#: bytes of each DataFlash format character (ArduPilot's AP_Logger; what DFReader unpacks)
_DF_CHAR_BYTES = {
    "a": 64, "b": 1, "B": 1, "g": 2, "h": 2, "H": 2, "i": 4, "I": 4, "f": 4, "n": 4, "N": 16, "Z": 64, "c": 2,
    "C": 2, "e": 4, "E": 4, "L": 4, "d": 8, "M": 1, "q": 8, "Q": 8,
}  # fmt: skip


def _df_fmt_valid(data: Any, p: int) -> bool:
    """An FMT message at ``p`` whose definition holds together: known format characters whose sizes add up to
    its length, a name and one column per character. DataFlash has no checksum: a byte hit in a format string
    would otherwise define a message wrongly (or make pymavlink's reader raise)."""
    body = bytes(data[p + 3 : p + _DF_FMT_LEN])
    length = body[1]
    fmt = body[6:22].split(b"\0", 1)[0]
    cols = body[22:86].split(b"\0", 1)[0]
    name = body[2:6].split(b"\0", 1)[0]
    try:
        fmt_s, cols_s, name_s = fmt.decode("ascii"), cols.decode("ascii"), name.decode("ascii")
    except UnicodeDecodeError:
        return False
    if not name_s.isprintable() or not name_s or not cols_s.isprintable():
        return False
    if any(c not in _DF_CHAR_BYTES for c in fmt_s):
        return False
    if body[0] == _DF_FMT_TYPE:
        return length == _DF_FMT_LEN
    n_cols = len(cols_s.split(",")) if cols_s else 0  # old logs define empty messages (STRT: no fields)
    return 3 + sum(_DF_CHAR_BYTES[c] for c in fmt_s) == length and n_cols == len(fmt_s)


class IntactSpans(NamedTuple):
    """What :func:`dataflash_intact_spans` believes of a binary DataFlash log."""

    spans: list[tuple[int, int]]  # [start, end) byte ranges of believed messages, in file order
    damaged_bytes: int  # bytes that are no message (corrupt framing, or garbage)
    dropped_bytes: int  # whole messages not believed: within the margin of damage
    resyncs: int  # points of damage resynchronised past


def _df_framed_next(data: Any, q: int, lengths: dict[int, int], n: int) -> bool:
    """A message of a known type starts at ``q`` and ends where the next header (or the file) starts."""
    if q < 0 or q + 3 > n:
        return False
    mlen = lengths.get(data[q + 2])
    end = q + mlen if mlen else -1
    return bool(mlen) and (end == n or (end + 2 <= n and data[end] == 0xA3 and data[end + 1] == 0x95))


def _whole_after_lost(data: Any, find: Callable[[bytes, int], int], p: int, lost: set[int],
                      lengths: dict[int, int]) -> int:  # fmt: skip
    """Where a whole message of a known type starts after the message at ``p`` and any more messages of
    types whose FMT was lost (at most 8 of them); -1 when none does."""
    n = len(data)
    q, hops = find(_DF_HEAD, p + 1), 0
    while q >= 0 and q + 3 <= n and data[q + 2] in lost and hops < 8:
        q, hops = find(_DF_HEAD, q + 1), hops + 1  # more messages of types whose FMT was lost
    return q if _df_framed_next(data, q, lengths, n) else -1


def _spans_before_damage(
    data: Any, p: int, start: int, recent: deque[int], margin_bytes: int
) -> list[tuple[int, int]]:
    """The intact span from ``start`` closed short of the margin before damage at ``p`` (the believed
    messages within it popped from ``recent``), and the FMT messages within the margin, kept all the same."""
    cut = p
    formats: list[int] = []
    while recent and recent[-1] > p - margin_bytes and recent[-1] >= start:
        cut = recent.pop()
        if data[cut + 2] == _DF_FMT_TYPE:
            formats.append(cut)
    out = [(start, cut)] if cut > start else []
    out.extend((f, f + _DF_FMT_LEN) for f in reversed(formats))
    return out


def dataflash_intact_spans(
    data: bytes | memoryview | mmap.mmap, margin_bytes: int = DAMAGE_MARGIN_BYTES
) -> IntactSpans:
    """The byte ranges of a binary DataFlash log that hold whole messages, and how many bytes lie between
    them (damage). A message is believed when its type is known (from the FMT messages before it), the next
    header (or the end of the file) follows it exactly, and it lies more than ``margin_bytes`` from any
    damage (FMT messages excepted, also within the margin: later messages stay readable); anything else is
    skipped up to the next header. An FMT that does not hold together (a byte hit inside it) is not
    believed; messages of its type are skipped, not taken for damage, when a whole message follows them."""
    n = len(data)
    lengths: dict[int, int] = {_DF_FMT_TYPE: _DF_FMT_LEN}
    lost: set[int] = set()  # types whose FMT was seen but not believed
    spans: list[tuple[int, int]] = []
    skipped = 0
    find = chunked_find(bytes(data) if isinstance(data, memoryview) else data)  # ^C between 16 MiB chunks
    p = find(_DF_HEAD)
    if p < 0:
        return IntactSpans([], n, 0, 0)
    skipped += p
    start = p
    resyncs = 0
    quarantine_end = -1  # messages starting before this offset follow damage too closely to be believed
    recent: deque[int] = deque(maxlen=4096)  # starts of the latest believed messages (each >= 3 bytes)
    while p + 3 <= n:
        mtype = data[p + 2]
        mlen = lengths.get(mtype)
        end = p + mlen if mlen else -1
        framed = mlen and (end == n or (end + 2 <= n and data[end] == 0xA3 and data[end + 1] == 0x95))
        if framed and mtype == _DF_FMT_TYPE and not _df_fmt_valid(data, p):
            # a whole FMT whose definition does not hold together (a byte hit inside it): skipped alone, its
            # type's messages then skipped as types without an FMT, the rest believed
            if p > start and p >= quarantine_end:
                spans.append((start, p))
            lost.add(data[p + 3])
            skipped += end - p
            p = start = end
            continue
        if framed:
            if mtype == _DF_FMT_TYPE and data[p + 4] >= 3:
                lengths[data[p + 3]] = data[p + 4]
            if p < quarantine_end:
                if mtype == _DF_FMT_TYPE:
                    spans.append((p, end))
                start = end
            else:
                recent.append(p)
            p = end
            continue
        if mlen and end > n:  # a message cut by the end of the file
            break
        q = _whole_after_lost(data, find, p, lost, lengths) if mtype in lost else -1
        if q >= 0:
            # types whose FMT was seen but not believed, before a whole message: those messages only are
            # skipped, not damage (counting each of them as damage quarantined the whole log); any other
            # unknown type is damage (a hit type byte)
            if p > start and p >= quarantine_end:
                spans.append((start, p))
            skipped += q - p
            p = start = q
            continue
        # damage: close the intact span short of the margin and resynchronise on the next header (no header
        # after it: the log's unfinished last write, nothing to distrust)
        if mtype == _DF_FMT_TYPE and p + 4 <= n and data[p + 3] not in lengths:
            lost.add(data[p + 3])  # an FMT not believed (its framing hit): its type's messages have no format
        q = find(_DF_HEAD, p + 1)
        q = n if q < 0 else q
        if q < n:
            spans += _spans_before_damage(data, p, start, recent, margin_bytes)
        elif p > start:  # no header after it: the span is closed at the damage, nothing of it distrusted
            spans.append((start, p))
        recent.clear()
        skipped += q - p
        resyncs += q < n
        p = start = q
        quarantine_end = q + margin_bytes
    if p > start:
        spans.append((start, min(p, n)))
    skipped += max(0, n - max(p, spans[-1][1] if spans else 0))
    kept = sum(b - a for a, b in spans)
    return IntactSpans(spans, skipped, max(0, n - kept - skipped), resyncs)


def dataflash_repaired(path: Path, counts: dict[str, int]) -> Path | None:
    """A temporary copy of a damaged binary DataFlash log holding its intact messages only (None when the
    log is intact, or cannot be read). The log is mapped, not read into memory."""
    import tempfile

    name = ""
    try:
        with path.open("rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
            spans, skipped, dropped, resyncs = dataflash_intact_spans(data)
            tail = len(data) - (spans[-1][1] if spans else 0)
            if not spans or (len(spans) == 1 and spans[0][0] == 0 and tail < 528):
                return None  # intact (a short tail of garbage is normal at the end of a log)
            counts["garbage_bytes"] += skipped
            counts["dataflash_resyncs"] += resyncs
            counts["dataflash_dropped_bytes"] += dropped
            fd, name = tempfile.mkstemp(prefix="magcomp-", suffix=".bin")
            with os.fdopen(fd, "wb") as out:
                for a, b in spans:
                    for c in range(a, b, READ_CHUNK_BYTES):
                        out.write(data[c : min(b, c + READ_CHUNK_BYTES)])
    except (OSError, ValueError):  # unreadable, empty (nothing to map), or no room for the copy
        if name:
            with contextlib.suppress(OSError):
                os.unlink(name)
        return None
    return Path(name)


#: what pymavlink's DataFlash readers raise on a log they cannot read: damaged bytes, and records its clock
#: does not know (ArduCopter 3.0 text logs: GPS with the time of week and no week, a TypeError building the
#: time base)
READER_ERRORS: tuple[type[Exception], ...] = (
    UnicodeDecodeError, ValueError, IndexError, KeyError, TypeError, AttributeError, ArithmeticError,
    struct.error, OSError,
)


def iter_dataflash(path: Path, counts: dict[str, int], text: bool) -> Iterator[Any]:
    repaired = None if text else dataflash_repaired(path, counts)
    try:
        yield from _iter_dataflash_file(repaired or path, path, counts, text)
    finally:
        if repaired is not None:
            with contextlib.suppress(OSError):
                repaired.unlink()


def _iter_dataflash_file(path: Path, shown: Path, counts: dict[str, int], text: bool) -> Iterator[Any]:
    from pymavlink import DFReader

    failed = ""
    try:
        with quiet(), quiet_c_streams():
            reader: Any = (
                DFReader.DFReader_text(str(path), zero_time_base=False)
                if text
                else DFReader.DFReader_binary(str(path), zero_time_base=False)
            )
    except READER_ERRORS as exc:
        failed = type(exc).__name__
    if failed:  # the half-built reader's open file, freed with the traceback: closed here, not at a later gc
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ResourceWarning)
            gc.collect()
        raise InputError(f"{shown}: not a readable DataFlash log ({failed})")
    wanted = list(WANTED_DATAFLASH)
    try:
        while True:
            batch: list[Any] = []
            with quiet():
                for _ in range(2000):
                    m = reader.recv_match(type=wanted)
                    if m is None:
                        break
                    batch.append(m)
            for m in batch:
                counts["messages"] += 1
                yield m
            if len(batch) < 2000:
                break
    except READER_ERRORS as exc:
        counts["dataflash_errors"] += 1
        if counts["messages"] == 0:
            raise InputError(f"{shown}: not a readable DataFlash log ({type(exc).__name__})") from None
    finally:
        with contextlib.suppress(Exception):
            reader.close()
