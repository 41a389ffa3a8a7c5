"""The MAVProxy module (``module load magcomp``) with a fake MAVProxy state: every message of a simulated
flight handed to ``mavlink_packet`` as MAVProxy would (decoded with its ardupilotmega dialect) gives
MAGCOMP_HEADING for every compass and the NAMED_VALUE_FLOAT values on the master link and on each output,
`magcomp status` prints a line per compass, unloading saves the state of the simulated vehicle."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from magcomp.core.identity import SIM_UID


class FakeLink:
    def __init__(self) -> None:
        self.data = bytearray()

    def write(self, packet: bytes) -> None:
        self.data += packet


class FakeConsole:
    def __init__(self) -> None:
        self.lines: list[str] = []
        self.status: dict[str, str] = {}

    def writeln(self, text: str) -> None:
        self.lines.append(text)

    def set_status(self, name: str, text: str, row: int = 0) -> None:
        self.status[name] = text


def _mpstate(master: FakeLink, out: FakeLink) -> Any:
    return SimpleNamespace(command_map={}, completions={}, public_modules={}, console=FakeConsole(),
                           master=lambda: master, mav_outputs=[out])  # fmt: skip


def _decode(data: bytes | bytearray) -> list[Any]:
    from magcomp.adapters.dialect import ensure_dialect

    mav = ensure_dialect().MAVLink(None)
    mav.robust_parsing = True
    return [m for m in mav.parse_buffer(bytes(data)) or [] if m.get_type() != "BAD_DATA"]


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    path = tmp_path_factory.mktemp("mp") / "f.tlog"
    write_tlog(simulate(SimConfig(scenario="paper", duration_s=30.0, seed=4)), path)
    return path


def test_module_load_publishes_corrected_headings(
    flight: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MAGCOMP_STATE_DIR", str(tmp_path / "state"))
    monkeypatch.delenv("MAGCOMP_CONFIG", raising=False)
    from pymavlink import mavutil

    import mavproxy_magcomp  # the top-level module MAVProxy's `module load magcomp` imports

    master, out = FakeLink(), FakeLink()
    mpstate = _mpstate(master, out)
    module = mavproxy_magcomp.init(mpstate)
    assert "magcomp" in mpstate.command_map and mpstate.public_modules["magcomp"] is module

    conn = mavutil.mavlink_connection(str(flight), dialect="ardupilotmega")  # as MAVProxy decodes its link
    n_mag = 0
    try:
        while (m := conn.recv_msg()) is not None:
            n_mag += m.get_type() in ("RAW_IMU", "SCALED_IMU2")
            module.mavlink_packet(m)
            module.idle_task()
    finally:
        conn.close()
    assert master.data == out.data  # the vehicle's link and every output get the same frames
    msgs = _decode(master.data)
    headings = [m for m in msgs if m.get_type() == "MAGCOMP_HEADING"]
    assert len(headings) == n_mag  # one per magnetometer sample, both compasses
    assert {h.mag_index for h in headings} == {0, 1}
    named = {m.name for m in msgs if m.get_type() == "NAMED_VALUE_FLOAT"}
    assert named == {"MC_HDG0", "MC_THETA0", "MC_STAT0", "MC_HDG1", "MC_THETA1", "MC_STAT1"}
    asks = [m for m in msgs if m.get_type() == "COMMAND_LONG"]
    assert asks and asks[0].param1 == 148  # AUTOPILOT_VERSION requested from the vehicle

    console: FakeConsole = mpstate.console
    mpstate.command_map["magcomp"][0](["status"])
    status = [ln for ln in console.lines if "compass" in ln and "heading" in ln]
    assert len(status) == 2 and all("deg" in ln and "mgauss" in ln for ln in status)
    assert f"id {SIM_UID}" in status[0]
    mpstate.command_map["magcomp"][0](["bogus"])
    assert console.lines[-1].startswith("usage: magcomp")

    module.unload()
    assert "magcomp" not in mpstate.command_map
    from magcomp.adapters.state_store import StateStore

    store = StateStore(tmp_path / "state")
    assert store.load(1, 0, SIM_UID) is not None and store.load(1, 1, SIM_UID) is not None


def test_a_bad_configuration_is_one_console_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MAGCOMP_CONFIG", str(tmp_path / "missing.toml"))
    monkeypatch.setenv("MAGCOMP_STATE_DIR", str(tmp_path / "state"))
    from magcomp.mavproxy import init

    mpstate = _mpstate(FakeLink(), FakeLink())
    module = init(mpstate)
    assert any("missing.toml" in ln and "no such file" in ln for ln in mpstate.console.lines)
    module.mavlink_packet(SimpleNamespace(get_type=lambda: "HEARTBEAT"))  # ignored, no traceback
    mpstate.command_map["magcomp"][0](["status"])
    assert "not running" in mpstate.console.lines[-1]
    module.unload()
