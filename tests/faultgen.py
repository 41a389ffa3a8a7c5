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
