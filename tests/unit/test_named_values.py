"""NAMED_VALUE_FLOAT for pilots: the status code from the flags, the names (<= 10 characters, documented in
docs/pilots.md), decimation on message time per compass, frames any MAVLink 2 parser decodes."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from magcomp.core import types
from magcomp.service.publish import (
    STATUS_CONVERGED,
    STATUS_LEARNING,
    STATUS_STALE,
    STATUS_UNCORRECTED,
    HeadingEncoder,
    NamedValues,
    named_value_names,
    pilot_status,
)

DOC = Path(__file__).parents[2] / "docs" / "pilots.md"


def test_pilot_status_from_flags() -> None:
    cal, conv = types.FLAG_CALIBRATED, types.FLAG_THETA_CONVERGED
    assert pilot_status(0) == STATUS_UNCORRECTED
    assert pilot_status(cal | types.FLAG_NO_THROTTLE) == STATUS_UNCORRECTED
    assert pilot_status(cal) == STATUS_LEARNING
    assert pilot_status(cal | conv) == STATUS_CONVERGED
    assert pilot_status(cal | conv | types.FLAG_INPUTS_STALE) == STATUS_STALE


def test_names_are_short_and_documented() -> None:
    doc = DOC.read_text()
    for idx in (0, 1, 2, 10):
        for name in named_value_names(idx):
            assert len(name) <= 10
    for name in named_value_names(0):
        assert f"`{name[:-1]}N`" in doc  # the table names them with N for the compass index


def _decode(frames: list[bytes]) -> list[object]:
    from pymavlink.dialects.v20 import common

    mav = common.MAVLink(None)
    return [mav.decode(bytearray(f)) for f in frames]


def test_decimated_per_compass_on_message_time() -> None:
    nv = NamedValues(HeadingEncoder(1), rate_hz=2.0)
    sent: dict[int, list[float]] = {0: [], 1: []}
    for k in range(1000):  # 10 s at 100 Hz, two compasses
        t = k * 0.01
        for idx in (0, 1):
            frames = nv.packets(t, t, idx, 370.0, (3.0, 4.0, 0.0), types.FLAG_CALIBRATED)
            if frames:
                sent[idx].append(t)
                msgs = _decode(frames)
                assert [m.name for m in msgs] == list(named_value_names(idx))  # type: ignore[attr-defined]
                assert [m.value for m in msgs] == pytest.approx([10.0, 5.0, STATUS_LEARNING])  # type: ignore[attr-defined]
                assert msgs[0].time_boot_ms == round(t * 1000)  # type: ignore[attr-defined]
    for idx in (0, 1):
        assert len(sent[idx]) == 20
        assert min(b - a for a, b in zip(sent[idx], sent[idx][1:], strict=False)) >= 0.5 - 1e-9


def test_rate_zero_sends_none_and_a_clock_that_ran_back_sends_at_once() -> None:
    assert NamedValues(HeadingEncoder(1), rate_hz=0.0).packets(0.0, 0.0, 0, 1.0, (0, 0, 0), 0) == []
    nv = NamedValues(HeadingEncoder(1), rate_hz=1.0)
    assert nv.packets(100.0, 100.0, 0, 1.0, (0.0, 0.0, 0.0), 0)
    assert not nv.packets(100.5, 100.5, 0, 1.0, (0.0, 0.0, 0.0), 0)
    assert nv.packets(3.0, 3.0, 0, 1.0, (0.0, 0.0, 0.0), 0)  # the autopilot rebooted


def test_config_option_is_validated(tmp_path: Path) -> None:
    from magcomp.adapters.config import load_config
    from magcomp.errors import MagcompError

    assert re.search(r"named_values_hz\s*=\s*2\.0", (DOC.parents[1] / "config" / "default.toml").read_text())
    bad = tmp_path / "c.toml"
    bad.write_text("[output]\nnamed_values_hz = -1.0\n")
    with pytest.raises(MagcompError, match="named_values_hz"):
        load_config(bad)
    bad.write_text("[output]\nnamed_values_hz = 5.0\n")
    assert load_config(bad).output.named_values_hz == 5.0
