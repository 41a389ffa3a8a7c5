"""The vehicles of a MAVLink log (tlog or raw stream) that carries several, each as a log of its own.

A link can carry several vehicles (or several components sending sensor data); ``magcomp run`` follows each
sender (system id, component id) with its own clock, parameters and estimator
(:meth:`~magcomp.adapters.mavlink_source.MavSource.vehicle_samples`). A log of such a link read as one
source mixes their samples (the second vehicle's are dropped as ``time_backwards``). :func:`several_vehicles`
names the senders of vehicle sensor data in a log and :func:`split_by_vehicle` writes each one's frames
(every message it sent, in file order) to a log of its own, so that each is replayed as ``run`` would have
followed it. Frames are cut by their headers only (lengths, no CRC: the replay of each part checks them);
bytes that start no frame are left out.
"""

from __future__ import annotations

import heapq
import mmap
import re
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

from magcomp.adapters.files import write_file
from magcomp.adapters.mavlink_frames import MAGIC_V1, MAGIC_V2, mavlink_module, sniff_mavlink_stream

#: messages that make a sender a vehicle: its IMUs and compasses, its attitude
VEHICLE_DATA = ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "HIGHRES_IMU", "ATTITUDE")

Sender = tuple[int, int]  # (system id, component id)


def frames(data: bytes, ts_len: int) -> Iterator[tuple[int, int, int, Sender]]:
    """(record start, record end, message id, sender) of every whole frame, in file order (a tlog record
    includes its 8-byte timestamp)."""
    n = len(data)
    p = 0
    while p + ts_len + 8 <= n:
        h = p + ts_len
        magic = data[h]
        if magic == MAGIC_V2 and h + 10 <= n:
            end = h + 10 + data[h + 1] + (15 if data[h + 2] & 1 else 2)
            msgid = data[h + 7] | (data[h + 8] << 8) | (data[h + 9] << 16)
            sender = (data[h + 5], data[h + 6])
        elif magic == MAGIC_V1:
            end = h + 6 + data[h + 1] + 2
            msgid, sender = data[h + 5], (data[h + 3], data[h + 4])
        else:
            p += 1
            continue
        if end > n:
            return
        yield p, end, msgid, sender
        p = end


def _read(path: Path) -> tuple[bytes, int] | None:
    """The log's bytes and its framing (8: tlog, 0: raw MAVLink); None for any other file."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    ts_len = sniff_mavlink_stream(data[:64])
    return None if ts_len is None else (data, ts_len)


#: a sender needs this many headers of vehicle data to be a candidate: a payload's bytes can look like a
#: MAVLink 1 header (about once per 10 kB), each time with another sender
MIN_HEADERS = 50


def _candidates(path: Path, ids: list[int]) -> set[Sender]:
    """Senders of at least MIN_HEADERS frames of the message ids ``ids``, found by their headers' bytes
    alone (a C-speed search of the mapped file)."""
    id_class = b"[" + b"".join(re.escape(bytes([i])) for i in ids) + b"]"
    # magic, length, flags, sequence, [system, component], id
    v2 = re.compile(rb"\xfd.{4}(..)" + id_class + rb"\x00\x00", re.DOTALL)
    v1 = re.compile(rb"\xfe..(..)" + id_class, re.DOTALL)  # magic, length, sequence, [system, component], id
    try:
        with path.open("rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
            counts = Counter(v2.findall(data)) + Counter(v1.findall(data))  # type: ignore[call-overload]
    except (OSError, ValueError):  # unreadable, or empty (nothing to map)
        return set()
    return {(sender[0], sender[1]) for sender, n in counts.items() if n >= MIN_HEADERS}


def several_vehicles(path: str | Path) -> list[Sender]:
    """The senders of vehicle data (:data:`VEHICLE_DATA`) of a tlog or raw MAVLink log that has several, in
    the order they first send it; [] when it has one or none, or is no MAVLink log. A log of one vehicle
    costs one search of its bytes; the frames are walked only when the search finds several senders."""
    src = Path(path)
    if not src.is_file():
        return []  # a link, a pipe, a device: read once, by the replay itself
    try:
        with src.open("rb") as f:
            if sniff_mavlink_stream(f.read(64)) is None:
                return []  # DataFlash, ULog, text: no MAVLink senders
    except OSError:
        return []
    mod = mavlink_module()
    ids = [getattr(mod, f"MAVLINK_MSG_ID_{name}") for name in VEHICLE_DATA]
    if len(_candidates(src, ids)) < 2:
        return []
    read = _read(src)
    if read is None:
        return []
    wanted = set(ids)
    found: dict[Sender, int] = {}
    for _, _, msgid, sender in frames(*read):
        if msgid in wanted:
            found[sender] = found.get(sender, 0) + 1
    vehicles = [sender for sender, n in found.items() if n >= MIN_HEADERS]
    return vehicles if len(vehicles) > 1 else []


def split_by_vehicle(path: str | Path, out_dir: str | Path, vehicles: list[Sender]) -> dict[Sender, Path]:
    """Each of ``vehicles``' frames written to a log of its own in ``out_dir`` (same framing as ``path``,
    named ``STEM.sysS.compC.SUFFIX``); frames of other senders (a ground station) go to none."""
    src = Path(path)
    read = _read(src)
    if read is None:
        return {}
    data, ts_len = read
    parts: dict[Sender, list[bytes]] = {v: [] for v in vehicles}
    for start, end, _, sender in frames(data, ts_len):
        chunks = parts.get(sender)
        if chunks is not None:
            chunks.append(data[start:end])
    out: dict[Sender, Path] = {}
    for (system, component), chunks in parts.items():
        target = Path(out_dir) / f"{src.stem}.sys{system}.comp{component}{src.suffix}"
        target.write_bytes(b"".join(chunks))
        out[(system, component)] = target
    return out


def merge_tlogs(parts: list[Path], out: Path) -> bool:
    """The records of several tlogs written as one, in time order (a stable merge by their 8-byte stamps);
    False (nothing written) when they hold none."""
    records: list[list[tuple[int, bytes]]] = []
    for path in parts:
        data = path.read_bytes()
        stamped = [(int.from_bytes(data[a : a + 8], "big"), data[a:b]) for a, b, _, _ in frames(data, 8)]
        records.append(stamped)
    merged = list(heapq.merge(*records, key=lambda r: r[0]))
    if not merged:
        return False
    write_file(out, b"".join(r[1] for r in merged))
    return True
