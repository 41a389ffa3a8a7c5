"""DataFlash MAG records carry the motor compensation the autopilot applied; the source removes it under
either of ArduPilot's two spellings: MOfsX/Y/Z (MAG, MAG2, MAG3; up to 4.0) and MOX/MOY/MOZ (one MAG with
the instance field I; 4.1 on, AP_Compass/LogStructure.h)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.mavlink_source import open_source
from magcomp.core.types import MagSample
from tests.faultgen import _df_fmt

#: the field the compass saw (mgauss), and what the autopilot added for its motors
TRUE = (210.0, -35.0, 420.0)
MOTOR = ((12.0, -7.0, 30.0), (-4.0, 9.0, -15.0))


def _log(path: Path, columns: str) -> None:
    """Two compass instances, 20 samples each, logged as ArduPilot does: int16 fields, the applied motor
    offset added to MagX..Z and logged beside them."""
    fmt, pack = "QBhhhhhhhhhBI", "<QBhhhhhhhhhBI"
    out = bytearray(_df_fmt(129, 3 + struct.calcsize(pack), "MAG", fmt, columns))
    for k in range(20):
        for i, mo in enumerate(MOTOR):
            scale = k / 19.0  # the throttle-driven offset grows through the log
            m = [round(c * scale) for c in mo]
            mag = [round(t) + c for t, c in zip(TRUE, m, strict=True)]
            t_us = 1_000_000 + 100_000 * k + i
            out += b"\xa3\x95\x81" + struct.pack(pack, t_us, i, *mag, 5, 6, 7, *m, 1, 0)
    path.write_bytes(bytes(out))


@pytest.mark.parametrize(
    "columns",
    [
        "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S",  # ArduPilot 4.1 on
        "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOfsX,MOfsY,MOfsZ,Health,S",  # the older names
    ],
)
def test_the_applied_motor_offset_is_removed_under_either_name(tmp_path: Path, columns: str) -> None:
    path = tmp_path / "mo.bin"
    _log(path, columns)
    src = open_source(path)
    fields: dict[int, list[np.ndarray]] = {}
    for s in src.samples():
        if isinstance(s, MagSample):
            fields.setdefault(s.mag_index, []).append(np.asarray(s.field_b_mgauss))
    counts = dict(src.counts)
    src.close()
    assert sorted(fields) == [0, 1]
    for got in fields.values():
        assert len(got) == 20
        # every sample back to the compass's own field (int16 rounding only), at zero and full offset alike
        np.testing.assert_allclose(np.asarray(got), np.tile(TRUE, (20, 1)), atol=0.51)
    assert counts.get("motor_comp_removed", 0) == 2 * 19  # the first sample's offset is zero
