"""MAVLink framing and decoding of tlogs and raw MAVLink streams, without pymavlink's ``MAVLink.decode``.

The reader walks the framing (8-byte big-endian timestamp + MAVLink 1/2 packet) itself and decodes only the
message ids it needs: X.25 CRC with the message's crc_extra (the dialect module's CRC function, i.e. fastcrc
when pymavlink uses it), then the dialect class's precompiled ``Struct`` (zero-truncated MAVLink 2 payloads
padded with zeros) into a named-tuple view in wire order with pymavlink's field values (arrays as lists,
char[N] as str); other ids are skipped unread. Same messages, values and counts as ``MAVLink.decode``
(tests/unit/test_sources_fastpath.py). Signatures of signed frames are not checked. A file is read
``READ_CHUNK_BYTES`` at a time: memory does not grow with the log's length (a frame cut by a chunk's end is
completed from the next chunk; same messages and counts as reading it whole).

Only the ids in the decoders are decoded, CRC-checked (X.25 with the message's crc_extra) and unpacked with a
precompiled Struct (MAVLink 2 payloads cut by zero-truncation padded with zeros); other ids are skipped
unread, their framing checked by the next frame's magic byte (a doubtful frame is resynchronised byte by
byte). Wanted frames that fail their CRC are ``bad_crc``; bytes that start no frame ``garbage_bytes``; a
frame cut by the end of the input ``truncated``.
"""

from __future__ import annotations

import struct
import sys
from collections import namedtuple
from collections.abc import Callable, Generator, Iterator
from typing import Any, BinaryIO

MAGIC_V1 = 0xFE
MAGIC_V2 = 0xFD


def mavlink_module() -> Any:
    from magcomp.adapters.dialect import ensure_dialect

    return ensure_dialect()


def _next_magic(data: bytes, start: int) -> int:
    a = data.find(b"\xfd", start)
    b = data.find(b"\xfe", start)
    if a < 0:
        return b
    if b < 0:
        return a
    return min(a, b)


class _ViewBase(tuple):
    """Base of the decoded-message views: a named tuple of the payload fields in wire order + srcSystem."""

    __slots__ = ()
    msgname = ""

    def get_type(self) -> str:
        return self.msgname

    def get_srcSystem(self) -> int:  # pymavlink's spelling
        return int(self[-1])


# (payload Struct, its size, crc_extra as 1 byte, view builder (fields tuple, srcSystem) -> view, handler)
FrameDecoder = tuple[Any, int, bytes, Callable[[tuple[Any, ...], int], Any], Callable[[Any], Any]]


def _view_builder(msgtype: Any) -> Callable[[tuple[Any, ...], int], Any]:
    """A builder of the message's view from ``Struct.unpack`` output, with pymavlink's field values.

    Fields are in wire order (``ordered_fieldnames``), which is the order of the unpacked tuple, so a
    message without arrays or strings needs no reordering at all. Arrays become lists and ``char[N]``
    fields strings cut at the first NUL (ASCII, errors replaced), as pymavlink's generated classes do.
    """
    names = list(msgtype.ordered_fieldnames)
    base = namedtuple(f"{msgtype.msgname}_view", [*names, "srcSystem"])  # type: ignore[misc]
    cls = type(base.__name__, (base, _ViewBase), {"__slots__": (), "msgname": msgtype.msgname})
    new = tuple.__new__
    fmt = msgtype.unpacker.format
    has_str = "s" in (fmt.decode() if isinstance(fmt, bytes) else fmt)
    lengths = list(msgtype.lengths)
    if not has_str and sum(lengths) == len(lengths):

        def build(t: tuple[Any, ...], src: int) -> Any:
            return new(cls, (*t, src))

        return build
    # a layout of (first element, count, kind): kind 0 scalar, 1 array, 2 string
    layout: list[tuple[int, int, int]] = []
    i = 0
    for n_el, array_len in zip(lengths, msgtype.array_lengths, strict=True):
        is_str = array_len > 0 and n_el == 1  # char[N]: one "Ns" element
        layout.append((i, n_el, 2 if is_str else (1 if n_el > 1 else 0)))
        i += n_el

    def build_slow(t: tuple[Any, ...], src: int) -> Any:
        values: list[Any] = []
        for first, count, kind in layout:
            if kind == 0:
                values.append(t[first])
            elif kind == 1:
                values.append(list(t[first : first + count]))
            else:
                raw = t[first]
                values.append(raw.split(b"\x00", 1)[0].decode("ascii", errors="replace"))
        values.append(src)
        return new(cls, values)

    return build_slow


def frame_decoders(mod: Any, handlers: dict[str, Callable[[Any], Any]]) -> dict[int, FrameDecoder]:
    """Precompiled decoders by message id, from the dialect's message classes, for the ids in ``handlers``."""
    out: dict[int, FrameDecoder] = {}
    for name, handler in handlers.items():
        msgtype = mod.mavlink_map[getattr(mod, f"MAVLINK_MSG_ID_{name}")]
        st = msgtype.unpacker
        out[msgtype.id] = (st, st.size, bytes([msgtype.crc_extra]), _view_builder(msgtype), handler)
    return out


def crc_function(mod: Any) -> Callable[[Any, int], int]:
    """The CRC-16/MCRF4XX (X.25) function of the dialect module: fastcrc's when pymavlink uses it."""
    fast = getattr(mod, "mcrf4xx", None)
    if fast is not None:
        return fast
    x25 = mod.x25crc

    def slow(buf: Any, crc: int) -> int:
        acc = x25()
        acc.crc = crc
        acc.accumulate(bytes(buf))
        return int(acc.crc)

    return slow


_TLOG_STAMP = struct.Struct(">Q")  # a tlog record's receive time, us since 1970

#: bytes read from a log file at a time (the tlog / raw MAVLink reader keeps at most this plus one frame)
READ_CHUNK_BYTES = 1 << 20
#: the longest MAVLink frame (MAVLink 2: 10-byte header, 255-byte payload, CRC, 13-byte signature)
_MAX_FRAME = 280


def iter_mavlink_frames(
    data: bytes,
    decoders: dict[int, FrameDecoder],
    counts: dict[str, int],
    ts_len: int,
    *,
    crc16: Callable[[Any, int], int],
    ignore_crc: bool = False,
    reference_mav: Any = None,
    final: bool = True,
    rx_into: Any = None,
) -> Generator[tuple[Callable[[Any], Any], Any], None, int]:
    """Walk tlog framing (``ts_len`` = 8) or a raw MAVLink stream (0); yield (handler, message) for the ids
    in ``decoders`` (see the module docstring). ``data``: the whole input (``final``) or a chunk of it, the
    walk then stopping where a frame might not be whole yet and returning the offset to resume from.
    ``reference_mav`` (tests): pymavlink's ``MAVLink.decode`` instead. ``rx_into``: gets ``rx_s`` and
    ``rx_src`` (the tlog receive stamp in s, the sender's system id) before each message is yielded."""
    mav_error = sys.modules[type(reference_mav).__module__].MAVError if reference_mav is not None else None
    view, n, p, magics, get = memoryview(data), len(data), 0, (MAGIC_V1, MAGIC_V2), decoders.get
    stamp_rx, unpack_stamp = rx_into is not None and ts_len == 8, _TLOG_STAMP.unpack_from  # the tlog's stamps
    # a chunk: stop while a whole frame, its timestamp and the next frame's magic may still be missing
    limit = n - ts_len - 8 if final else n - 2 * ts_len - _MAX_FRAME - 1
    while p <= limit:
        h = p + ts_len
        magic = data[h]
        if magic == MAGIC_V2:
            if h + 10 > n:
                counts["truncated"] += 1
                break
            mlen = data[h + 1]
            start = h + 10
            crc_at = start + mlen
            end = crc_at + (15 if data[h + 2] & 1 else 2)
            msgid = data[h + 7] | (data[h + 8] << 8) | (data[h + 9] << 16)
            src = data[h + 5]
        elif magic == MAGIC_V1:
            mlen = data[h + 1]
            start = h + 6
            crc_at = start + mlen
            end = crc_at + 2
            msgid = data[h + 5]
            src = data[h + 3]
        else:
            q = _resync(data, h, p, n, ts_len, final)
            counts["garbage_bytes"] += q - p
            p = q
            continue
        if end > n:
            counts["truncated"] += 1
            break
        dec = get(msgid)
        if dec is not None:
            st, size, extra, build, handler = dec
            if mav_error is not None:
                msg = _reference_decode(reference_mav, mav_error, data[h:end])
            elif ignore_crc or crc16(extra, crc16(view[h + 1 : crc_at], 0xFFFF)) == (
                data[crc_at] | (data[crc_at + 1] << 8)
            ):
                if mlen >= size:
                    fields = st.unpack_from(data, start)
                else:  # MAVLink 2 zero-truncation: the missing tail is zeros
                    fields = st.unpack(data[start:crc_at] + bytes(size - mlen))
                msg = build(fields, src)
            else:
                msg = None
            if msg is None:
                p = _after_bad_frame(counts, p, end, _next_ok(data, end, ts_len, n, magics))
                continue
            counts["messages"] += 1
            if stamp_rx:
                rx_into.rx_s = unpack_stamp(data, p)[0] * 1e-6
                rx_into.rx_src = src
            yield handler, msg
        elif end + ts_len < n and data[end + ts_len] not in magics:  # not _next_ok(), inline
            # framing of an unchecked packet is doubtful: resynchronise byte by byte
            counts["garbage_bytes"] += 1
            p += 1
            continue
        p = end
    return p


def _next_ok(data: bytes, end: int, ts_len: int, n: int, magics: tuple[int, int]) -> bool:
    """The next frame's magic byte follows a frame that ends at ``end`` (or the input ends there)."""
    return end + ts_len >= n or data[end + ts_len] in magics


def _resync(data: bytes, h: int, p: int, n: int, ts_len: int, final: bool) -> int:
    """Where the walk goes on after a byte at ``h`` that starts no frame: the next magic byte (less the
    timestamp before it); no magic in the rest of a chunk: up to where the next chunk's first timestamp may
    begin."""
    q = _next_magic(data, h + 1)
    q = (n if final else n - ts_len) if q < 0 else q - ts_len
    return max(q, p + 1)


def _after_bad_frame(counts: dict[str, int], p: int, end: int, next_ok: bool) -> int:
    """A frame of a wanted id that fails its CRC: a bad frame skipped whole when the next frame follows it,
    else a garbage byte (the framing itself is doubtful) and the walk goes on byte by byte."""
    if next_ok:
        counts["bad_crc"] += 1
        return end
    counts["garbage_bytes"] += 1
    return p + 1


def _reference_decode(mav: Any, mav_error: Any, frame: bytes) -> Any:
    """pymavlink's own decode of one frame (tests); None where it refuses it."""
    try:
        return mav.decode(bytearray(frame))
    except mav_error:
        return None


def iter_mavlink_file(
    f: BinaryIO,
    head: bytes,
    decoders: dict[int, FrameDecoder],
    counts: dict[str, int],
    ts_len: int,
    **kw: Any,
) -> Iterator[tuple[Callable[[Any], Any], Any]]:
    """:func:`iter_mavlink_frames` over an open file read ``READ_CHUNK_BYTES`` at a time, ``head`` being what
    was already read from it: memory stays at a chunk, whatever the file's length."""
    buf = head
    while True:
        more = f.read(READ_CHUNK_BYTES)
        if not more:
            yield from iter_mavlink_frames(buf, decoders, counts, ts_len, final=True, **kw)
            return
        buf += more
        p = yield from iter_mavlink_frames(buf, decoders, counts, ts_len, final=False, **kw)
        buf = buf[p:]


def sniff_mavlink_stream(data: bytes) -> int | None:
    """8 for tlog framing, 0 for a raw MAVLink stream, None when neither starts the data."""
    if len(data) >= 16 and data[8] in (MAGIC_V1, MAGIC_V2):
        return 8
    if len(data) >= 8 and data[0] in (MAGIC_V1, MAGIC_V2):
        return 0
    return None
