"""The intact messages of a damaged PX4 ULog, as DataFlash ``.bin`` replay keeps them.

pyulog reads a ULog message by message (3-byte header: uint16 payload size, uint8 type); a damaged size
field puts it out of step, and what follows is read as garbage until, by chance, it falls back in step:
a ULog with a few hundred flipped bits lost most of its data after the first damage. Here the file is
walked with every message checked against what the log itself declared: a data message ('D') must name
a subscribed topic and have exactly that topic's size (from its 'F' format), a subscription ('A') must
name a declared format, and so on. At a message that fails, the walk moves on byte by byte until
:data:`CHAIN` messages in a row check out again (a resync). The intact messages are written to a
temporary copy (the header and definitions unchanged) that pyulog then reads; what was dropped is
counted (``ulog_resyncs``, ``ulog_dropped_bytes``).

A flipped bit inside a message's payload passes these checks: its values are for the plausibility
gates downstream (timestamps: :func:`magcomp.adapters.ulog_source` drops lone timestamp glitches).

The file is mapped, not read into memory; the copy is written as the walk goes.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import re
import struct
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

HEADER_BYTES = 16
#: consecutive messages that must check out after a damaged stretch before the walk trusts the stream
CHAIN = 3
#: a text message ('L' / 'C') longer than this is damage
MAX_TEXT = 2048
SYNC = b"\x2f\x73\x13\x20\x25\x0c\xbb\x12"
_BASIC = {"int8_t": 1, "uint8_t": 1, "int16_t": 2, "uint16_t": 2, "int32_t": 4, "uint32_t": 4,
          "int64_t": 8, "uint64_t": 8, "float": 4, "double": 8, "bool": 1, "char": 1}  # fmt: skip
_DEFINITION_TYPES = frozenset(b"BFIMPQ")
_DATA_SECTION_START = frozenset(b"ALC")
_U16 = struct.Struct("<H")


@dataclass
class _Schema:
    """What the log declared: formats (name -> field list) and subscriptions (msg_id -> payload size)."""

    formats: dict[str, list[tuple[str, int, str]]] = field(default_factory=dict)  # (type, count, name)
    sizes: dict[str, int | None] = field(default_factory=dict)
    subs: dict[int, int | None] = field(default_factory=dict)

    def add_format(self, payload: bytes) -> bool:
        try:
            text = payload.decode("ascii")
        except UnicodeDecodeError:
            return False
        name, sep, body = text.partition(":")
        if not sep or not name.isprintable() or " " in name:
            return False
        fields = []
        for item in body.split(";"):
            if not item:
                continue
            type_str, _, fname = item.partition(" ")
            if not fname:
                return False
            count = 1
            if "[" in type_str:
                type_str, _, rest = type_str.partition("[")
                if not rest.endswith("]") or not rest[:-1].isdigit():
                    return False
                count = int(rest[:-1])
            fields.append((type_str, count, fname))
        self.formats[name] = fields
        self.sizes.clear()
        return True

    def size_of(self, name: str, depth: int = 0) -> int | None:
        """The packed size of format ``name`` nested in another one (None when it uses a type the log
        never declared)."""
        if name in _BASIC:
            return _BASIC[name]
        if name in self.sizes:
            return self.sizes[name]
        fields = self.formats.get(name)
        total = None if fields is None or depth > 16 else self._sum(fields, depth)
        self.sizes[name] = total
        return total

    def logged_size(self, name: str) -> int | None:
        """The payload size of a logged message of format ``name``: its fields without the trailing
        padding, which PX4 does not write (the ULog specification)."""
        fields = list(self.formats.get(name, ()))
        if not fields and name not in self.formats:
            return None
        while fields and fields[-1][2].startswith("_padding"):
            fields.pop()
        return self._sum(fields, 0)

    def _sum(self, fields: list[tuple[str, int, str]], depth: int) -> int | None:
        total = 0
        for type_str, count, _ in fields:
            one = self.size_of(type_str, depth + 1)
            if one is None:
                return None
            total += one * count
        return total


def _message_ok(data: mmap.mmap | bytes, q: int, end: int, schema: _Schema, commit: bool) -> int:
    """The size of the data-section message at ``q`` (header included) when it checks out, else 0.
    ``commit``: a subscription that checks out is registered (only while walking trusted messages)."""
    if q + 3 > end:
        return 0
    size = _U16.unpack_from(data, q)[0]
    mtype = data[q + 2]
    n = 3 + size
    if size == 0 or q + n > end:
        return 0
    p = q + 3
    if mtype == 0x44:  # 'D'
        if size < 2:
            return 0
        msg_id = _U16.unpack_from(data, p)[0]
        if msg_id not in schema.subs:
            return 0
        want = schema.subs[msg_id]
        return n if want is None or size == 2 + want else 0
    if mtype == 0x41:  # 'A': multi_id, msg_id, name
        if size < 4:
            return 0
        name = bytes(data[p + 3 : p + size])
        try:
            text = name.decode("ascii")
        except UnicodeDecodeError:
            return 0
        if text not in schema.formats:
            return 0
        if commit:
            schema.subs[_U16.unpack_from(data, p + 1)[0]] = schema.logged_size(text)
        return n
    if mtype == 0x52 or mtype == 0x4F:  # 'R' remove (msg_id), 'O' dropout (duration)
        return n if size == 2 else 0
    if mtype == 0x53:  # 'S' sync
        return n if size == 8 and bytes(data[p : p + 8]) == SYNC else 0
    if mtype == 0x4C:  # 'L' logging: level, timestamp, text
        return n if 9 <= size <= MAX_TEXT else 0
    if mtype == 0x43:  # 'C' tagged logging: level, tag, timestamp, text
        return n if 11 <= size <= MAX_TEXT else 0
    if mtype in (0x49, 0x50, 0x4D, 0x51):  # 'I', 'P', 'M', 'Q': [flag byte], key length, key, value
        k = p + (1 if mtype in (0x4D, 0x51) else 0)
        key_len = data[k]
        if key_len == 0 or k + 1 + key_len > p + size:
            return 0
        key = bytes(data[k + 1 : k + 1 + key_len])
        if not key.isascii() or b" " not in key:
            return 0
        return n
    return 0


def _chain_ok(data: mmap.mmap | bytes, q: int, end: int, schema: _Schema) -> bool:
    """``CHAIN`` messages in a row from ``q`` check out (or the file ends cleanly after them)."""
    for _ in range(CHAIN):
        if q == end:
            return True
        n = _message_ok(data, q, end, schema, commit=False)
        if not n:
            return False
        q += n
    return True


#: the message types of the data section, as a pattern: a resync looks only where one stands two bytes
#: after the candidate start (found at C speed: a long run of zeros or garbage is skipped, not walked)
_DATA_TYPES = re.compile(rb"[ACDILMOPQRS]")


def _resync(data: mmap.mmap | bytes, r: int, end: int, schema: _Schema) -> int:
    """The first position from ``r`` where :data:`CHAIN` messages in a row check out (``end`` if none)."""
    while r < end:
        found = _DATA_TYPES.search(data, r + 2)
        if found is None:
            return end
        r = found.start() - 2
        if _message_ok(data, r, end, schema, commit=False) and _chain_ok(data, r, end, schema):
            return r
        r += 1
    return end


@dataclass
class UlogRepair:
    """Where the intact copy is, and what was dropped."""

    path: Path
    resyncs: int
    dropped_bytes: int


def ulog_intact_copy(path: str | os.PathLike[str]) -> UlogRepair | None:
    """A temporary copy of the damaged ULog at ``path`` holding its intact messages, or None when the
    walk finds nothing to drop (or cannot read the file, or its definitions are damaged: pyulog's own
    reading then stands). The caller removes the copy."""
    name = ""
    try:
        with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
            end = len(data)
            if end < HEADER_BYTES or bytes(data[:4]) != b"ULog":
                return None
            schema = _Schema()
            q = HEADER_BYTES
            while q + 3 <= end:  # definitions: copied as they are, formats learned
                size = _U16.unpack_from(data, q)[0]
                mtype = data[q + 2]
                if mtype in _DATA_SECTION_START:
                    break
                if mtype not in _DEFINITION_TYPES or q + 3 + size > end:
                    return None
                if mtype == 0x46 and not schema.add_format(bytes(data[q + 3 : q + 3 + size])):
                    return None
                q += 3 + size
            definitions_end = q
            spans: list[tuple[int, int]] = [(0, definitions_end)]
            resyncs = dropped = 0
            start = last = q
            while q < end:
                n = _message_ok(data, q, end, schema, commit=True)
                if n:
                    last = q
                    q += n
                    continue
                r = _resync(data, q + 1, end, schema)
                if end - r < 3:  # a short tail that is no message: a log cut mid-write, not damage
                    r = end
                elif last > start:
                    # damage that starts inside a message leaves its header (and size) intact and its
                    # payload's tail garbage: the message just before the damage goes too
                    q = last
                spans.append((start, q))
                dropped += r - q
                if r < end:
                    resyncs += 1
                q = start = last = r
            spans.append((start, q))
            if dropped == 0 or (resyncs == 0 and dropped < 3):
                return None
            fd, name = tempfile.mkstemp(prefix="magcomp-", suffix=".ulg")
            with os.fdopen(fd, "wb") as out:
                for a, b in spans:
                    for c in range(a, b, 1 << 20):
                        out.write(data[c : min(b, c + (1 << 20))])
    except (OSError, ValueError):  # unreadable, empty (nothing to map), or no room for the copy
        if name:
            with contextlib.suppress(OSError):
                os.unlink(name)
        return None
    return UlogRepair(Path(name), resyncs, dropped)
