"""The magcomp MAVLink dialect: no id clash with any shipped dialect, exact field names, round trip."""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters import dialect
from magcomp.core import types
from magcomp.core.types import HeadingEstimate
from magcomp.errors import MagcompError

EXPECTED_FIELDS = [
    "time_boot_ms",
    "heading",
    "heading_raw",
    "theta",
    "bias",
    "throttle",
    "mag_index",
    "flags",
]


def _estimate(**overrides: object) -> HeadingEstimate:
    values: dict[str, object] = dict(
        t_s=1234.5678,
        mag_index=2,
        heading_deg=359.25,
        heading_raw_deg=3.5,
        theta_mgauss=np.array([12.5, -40.25, 210.0]),
        bias_mgauss=np.array([3.125, -10.0625, 52.5]),
        throttle_01=0.5,
        flags=types.FLAG_CALIBRATED | types.FLAG_THETA_CONVERGED | types.FLAG_SATURATED,
        field_raw_mgauss=np.array([200.0, 10.0, -500.0]),
        field_cal_mgauss=np.array([197.0, 20.0, -552.5]),
    )
    values.update(overrides)
    return HeadingEstimate(**values)  # type: ignore[arg-type]


def test_generation_against_all_shipped_dialects_has_no_id_clash(tmp_path: Path) -> None:
    wrapper = tmp_path / "magcomp_all.xml"
    wrapper.write_text(
        '<?xml version="1.0"?>\n<mavlink>\n  <include>all.xml</include>\n  <include>magcomp.xml</include>\n'
        "  <messages/>\n</mavlink>\n"
    )
    out = tmp_path / "magcomp_all.py"
    dialect.generate_bindings(wrapper, out, extra_xmls=[dialect.XML_PATH])
    text = out.read_text()
    assert "MAVLINK_MSG_ID_MAGCOMP_HEADING = 45000" in text
    assert "MAVLINK_MSG_ID_ICAROUS_HEARTBEAT = 42000" in text  # all.xml really was included


def test_generation_fails_on_id_42000_clash_with_icarous(tmp_path: Path) -> None:
    clashing = tmp_path / "magcomp.xml"
    clashing.write_text(dialect.XML_PATH.read_text().replace('id="45000"', 'id="42000"'))
    with pytest.raises(MagcompError, match="42000"):
        dialect.generate_bindings(clashing, tmp_path / "out.py")
    assert not (tmp_path / "out.py").exists()


def test_xml_field_names_types_and_flag_bits_match_core_types() -> None:
    root = ET.parse(dialect.XML_PATH).getroot()
    msg = root.find("messages/message[@name='MAGCOMP_HEADING']")
    assert msg is not None and msg.get("id") == str(dialect.MAGCOMP_HEADING_ID)
    fields = {f.get("name"): f.get("type") for f in msg.findall("field")}
    assert list(fields) == EXPECTED_FIELDS
    assert (
        fields["time_boot_ms"] == "uint32_t"
        and fields["theta"] == "float[3]"
        and fields["bias"] == "float[3]"
    )
    assert fields["mag_index"] == "uint8_t" and fields["flags"] == "uint8_t"
    entries = root.findall("enums/enum[@name='MAGCOMP_HEADING_FLAGS']/entry")
    bits = {
        e.get("name", "").removeprefix("MAGCOMP_HEADING_FLAGS_"): int(e.get("value", "-1")) for e in entries
    }
    core_bits = {k.removeprefix("FLAG_"): v for k, v in vars(types).items()
                 if k.startswith("FLAG_") and isinstance(v, int)}  # fmt: skip
    assert bits == core_bits


def test_ensure_dialect_registers_module_and_sets_mavlink20() -> None:
    mod = dialect.ensure_dialect()
    import pymavlink.dialects.v20 as v20

    assert os.environ.get("MAVLINK20") == "1"
    assert v20.magcomp is mod
    assert mod.MAVLINK_MSG_ID_MAGCOMP_HEADING == 45000
    assert dialect.bindings_path().exists()
    assert dialect.ensure_dialect() is mod


def test_magcomp_heading_round_trip_keeps_exact_field_names_and_values() -> None:
    est = _estimate()
    buf = dialect.encode_heading(dialect.new_mav(), est)
    assert buf[0] == 0xFD  # MAVLink 2 (id > 255 cannot be sent as v1)
    msg = dialect.new_mav().decode(bytearray(buf))
    d = msg.to_dict()
    assert d.pop("mavpackettype") == "MAGCOMP_HEADING"
    assert list(d) == EXPECTED_FIELDS
    assert d["time_boot_ms"] == 1234568  # 1234.5678 s -> ms, rounded
    assert d["heading"] == pytest.approx(359.25) and d["heading_raw"] == pytest.approx(3.5)
    np.testing.assert_allclose(d["theta"], est.theta_mgauss, rtol=1e-7)
    np.testing.assert_allclose(d["bias"], est.bias_mgauss, rtol=1e-7)
    assert d["throttle"] == pytest.approx(0.5)
    assert d["mag_index"] == 2 and d["flags"] == 1 | 2 | 64


def test_encoded_heading_with_corrupted_byte_fails_crc() -> None:
    buf = bytearray(dialect.encode_heading(dialect.new_mav(), _estimate()))
    buf[14] ^= 0x40  # inside the payload
    with pytest.raises(Exception, match="CRC"):
        dialect.new_mav().decode(buf)


def test_mavutil_connection_with_magcomp_dialect_decodes_heading(tmp_path: Path) -> None:
    dialect.ensure_dialect()
    from pymavlink import mavutil

    mav = dialect.new_mav()
    path = tmp_path / "h.tlog"
    with path.open("wb") as f:
        for k in range(3):
            f.write((1_700_000_000_000_000 + k).to_bytes(8, "big"))
            f.write(dialect.encode_heading(mav, _estimate(t_s=10.0 + k)))
    conn = mavutil.mavlink_connection(str(path), dialect="magcomp")
    try:
        got = [conn.recv_match(type="MAGCOMP_HEADING") for _ in range(3)]
    finally:
        conn.close()
    assert [m.time_boot_ms for m in got] == [10000, 11000, 12000]


def test_bindings_are_keyed_by_the_installed_pymavlink_version() -> None:
    """The bindings' cache key takes pymavlink's version from the package (no importlib.metadata at start-up):
    the same key as the installed distribution's version gives, so the cached bindings are found again."""
    import hashlib
    from importlib.metadata import version

    key = hashlib.sha256(dialect.XML_PATH.read_bytes() + version("pymavlink").encode()).hexdigest()[:16]
    assert dialect.bindings_path().parent.name == f"dialect-{key}"
