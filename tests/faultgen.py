"""Seeded faults for tests: tlog records with their MAVLink timestamps rewritten (reboots, clock jumps)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

TIME_FIELDS = (("time_boot_ms", 1e-3), ("time_usec", 1e-6))


def _mav() -> Any:
    from magcomp.adapters.dialect import ensure_dialect

    mod = ensure_dialect()
    mav = mod.MAVLink(None)
    mav.robust_parsing = True
    return mod, mav


def retime(records: list[bytes], new_time_s: Callable[[int, float], float]) -> list[bytes]:
    """Records (8-byte stamp + MAVLink 2 packet) with each message's own time field set to
    ``new_time_s(index, old_time_s)``; the packet is re-encoded (same sender, sequence and CRC rules)."""
    mod, mav = _mav()
    out = []
    for i, rec in enumerate(records):
        msg = mav.decode(bytearray(rec[8:]))
        for name, scale in TIME_FIELDS:
            if hasattr(msg, name):
                old = getattr(msg, name) * scale
                new = new_time_s(i, old)
                if new == old:
                    break
                u32 = name == "time_boot_ms" or msg.get_type() == "SERVO_OUTPUT_RAW"
                width = 0xFFFFFFFF if u32 else 2**64 - 1
                setattr(msg, name, max(0, round(new / scale)) & width)
                sender = mod.MAVLink(None, srcSystem=msg.get_srcSystem(), srcComponent=msg.get_srcComponent())
                sender.seq = msg.get_seq()
                rec = rec[:8] + bytes(msg.pack(sender))
                break
        out.append(rec)
    return out


def record_time_s(rec: bytes) -> float:
    """The tlog stamp of a record (unix seconds)."""
    return int.from_bytes(rec[:8], "big") * 1e-6


def record_msgid(rec: bytes) -> int:
    """The MAVLink 2 message id of a record (24 bits, little-endian, after the stamp and 7 header bytes)."""
    return rec[15] | rec[16] << 8 | rec[17] << 16


def rebooted_copy(records: list[bytes], t0_s: float, reboot_after_s: float) -> list[bytes]:
    """``records`` with the autopilot rebooting ``reboot_after_s`` into the log: from there its clock restarts
    at 0.3 s (``t0_s``: the simulated log's boot time, so that message times before the reboot stay)."""
    u0 = record_time_s(records[0])
    return retime(records, lambda i, old: old - (t0_s + reboot_after_s) + 0.3
                  if record_time_s(records[i]) - u0 >= reboot_after_s else old)  # fmt: skip


def paper_and_rebooted(d: Any, duration_s: float, seed: int, reboot_after_s: float) -> dict[str, Any]:
    """The paper's scenario (hand rotation, then flight, two compasses) written to ``d/paper.tlog``, and the
    same log with the autopilot rebooting ``reboot_after_s`` in, ``d/reboot.tlog``."""
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate
    from tests.conftest import split_tlog_records

    result = simulate(SimConfig(scenario="paper", duration_s=duration_s, seed=seed))
    write_tlog(result, d / "paper.tlog")
    recs = split_tlog_records((d / "paper.tlog").read_bytes())
    (d / "reboot.tlog").write_bytes(b"".join(rebooted_copy(recs, result.t0_s, reboot_after_s)))
    return {"paper": d / "paper.tlog", "reboot": d / "reboot.tlog"}


def rewrite(records: list[bytes], mtype: str, **fields: Any) -> list[bytes]:
    """Records with every ``mtype`` message's ``fields`` set to the given values (re-encoded)."""
    mod, mav = _mav()
    out = []
    for rec in records:
        msg = mav.decode(bytearray(rec[8:]))
        if msg.get_type() == mtype:
            for name, value in fields.items():
                setattr(msg, name, value)
            sender = mod.MAVLink(None, srcSystem=msg.get_srcSystem(), srcComponent=msg.get_srcComponent())
            sender.seq = msg.get_seq()
            rec = rec[:8] + bytes(msg.pack(sender))
        out.append(rec)
    return out


def rewrite_some(
    records: list[bytes], mtype: str, which: Callable[[int], bool], **fields: Any
) -> list[bytes]:
    """Records with the ``fields`` of the k-th ``mtype`` message set when ``which(k)`` (re-encoded, same
    sender, sequence and CRC rules as :func:`rewrite`)."""
    mod, mav = _mav()
    out, k = [], 0
    for rec in records:
        msg = mav.decode(bytearray(rec[8:]))
        if msg.get_type() == mtype:
            if which(k):
                for name, value in fields.items():
                    setattr(msg, name, value)
                sender = mod.MAVLink(None, srcSystem=msg.get_srcSystem(), srcComponent=msg.get_srcComponent())
                sender.seq = msg.get_seq()
                rec = rec[:8] + bytes(msg.pack(sender))
            k += 1
        out.append(rec)
    return out


def _df_fmt(mtype: int, length: int, name: str, fmt: str, columns: str) -> bytes:
    import struct

    return b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", mtype, length, name.encode(), fmt.encode(),
                                         columns.encode())  # fmt: skip


def write_dataflash(result: Any, path: Any) -> int:
    """A minimal ArduPilot binary DataFlash log of a simulated flight: FMT, MSG (vehicle), IMU (rad/s,
    m/s^2), MAG (mgauss, one per compass instance) and CTUN ThO (throttle 0..1). Returns its size."""
    import struct

    import numpy as np

    s = result.samples
    t_us = np.round(s.t_s * 1e6).astype(np.int64)
    fmts = [
        (129, "IMU", "Qffffff", "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ", "<Qffffff"),
        (130, "MAG", "QBfff", "TimeUS,I,MagX,MagY,MagZ", "<QBfff"),
        (131, "CTUN", "Qf", "TimeUS,ThO", "<Qf"),
        (132, "MSG", "QZ", "TimeUS,Message", "<Q64s"),
    ]
    packers = {name: (mtype, struct.Struct(pk)) for mtype, name, _f, _c, pk in fmts}
    out = bytearray()
    for mtype, name, f, cols, pk in fmts:
        out += _df_fmt(mtype, 3 + struct.calcsize(pk), name, f, cols)

    def rec(name: str, *values: Any) -> None:
        mtype, st = packers[name]
        out.extend(b"\xa3\x95" + bytes([mtype]) + st.pack(*values))

    rec("MSG", int(t_us[0]), b"ArduCopter V4.5.0")
    for i in range(s.t_s.size):
        g, a = s.gyro_rad_s[0, i], s.accel_m_s2[0, i]
        rec("IMU", int(t_us[i]), *map(float, g), *map(float, a))
        for k in range(s.mag_mgauss.shape[0]):
            rec("MAG", int(t_us[i]) + k, k, *map(float, s.mag_mgauss[k, i]))
        if i % 2 == 0:
            rec("CTUN", int(t_us[i]) + 5, float(s.throttle_01[i]))
    with open(path, "wb") as fh:
        fh.write(out)
    return len(out)
