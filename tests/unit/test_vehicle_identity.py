"""Vehicle identity: the ids the inputs carry agree with each other, the state store keys by (system id,
unique id), reads version-1 files (system id only) and never applies them to an identified vehicle, and says
every load and first overwrite in one log line."""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.state_store import CompassState, StateStore, _digest
from magcomp.core.identity import (
    SIM_UID,
    board_msg,
    normal_uid,
    uid2_bytes,
    uid64,
    uid_from_autopilot_version,
    uid_from_board_msg,
)

UID_A = "0033002b3139511134383233"
UID_B = "0044002b3139511134383299"


def _state(sysid: int = 1, idx: int = 0, uid: str | None = None, theta: float = 10.0) -> CompassState:
    return CompassState(sysid, idx, np.eye(3), np.zeros(3), np.array([theta, 0.0, 0.0]), 5.0, vehicle_uid=uid)


def test_autopilot_version_and_board_msg_name_the_same_board() -> None:
    # ArduPilot prints each 32-bit word of the id most significant byte first
    assert uid_from_board_msg("CubeOrange 2B003300 11513931 33323834") == UID_A
    assert uid_from_board_msg(board_msg(UID_A, "CubeOrange")) == UID_A
    assert uid_from_autopilot_version(uid64(UID_A), uid2_bytes(UID_A)) == UID_A
    assert uid_from_autopilot_version(0, [0] * 18) is None
    assert uid_from_autopilot_version(0x0102, [0] * 18) == "0201"  # uid alone: its little-endian bytes
    assert uid_from_board_msg("ArduCopter V4.5.7 (1234abcd)") is None
    assert normal_uid("0x00") is None and normal_uid("ABC") == "0abc" and normal_uid("zz") is None
    assert normal_uid(SIM_UID) == SIM_UID


def test_states_of_two_vehicles_with_one_system_id_are_separate(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    store.save(_state(uid=UID_A, theta=1.0))
    store.save(_state(uid=UID_B, theta=2.0))
    store.save(_state(uid=None, theta=3.0))
    a, b, anon = store.load(1, 0, UID_A), store.load(1, 0, UID_B), store.load(1, 0)
    assert a is not None and b is not None and anon is not None
    assert (a.theta_mgauss[0], b.theta_mgauss[0], anon.theta_mgauss[0]) == (1.0, 2.0, 3.0)
    assert store.load(1, 0, "0055") is None  # a third vehicle starts fresh
    assert len(list(tmp_path.glob("vehicle-1-*compass-0.json"))) == 3


def test_a_file_renamed_to_another_vehicle_is_refused(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    path = store.save(_state(uid=UID_A))
    path.rename(store.path_for(1, 0, UID_B))
    assert store.load(1, 0, UID_B) is None
    assert any("another vehicle" in w for w in store.warnings)


def test_version_1_file_is_read_as_the_state_of_a_system_id(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    payload = _state(theta=7.0).to_payload()
    del payload["vehicle_uid"]  # what magcomp wrote before identities
    doc = {"format": "magcomp-state", "version": 1, "sha256": _digest(payload), "state": payload}
    (tmp_path / "vehicle-1-compass-0.json").write_text(json.dumps(doc))
    store = StateStore(tmp_path)
    old = store.load(1, 0)
    assert old is not None and old.theta_mgauss[0] == 7.0 and old.vehicle_uid is None
    with caplog.at_level(logging.INFO, logger="magcomp.state"):
        assert store.load(1, 0, UID_A) is None  # never applied to an identified vehicle
    assert any("names no vehicle identity" in r.getMessage() for r in caplog.records)
    store.save(replace(old, theta_mgauss=np.array([8.0, 0.0, 0.0])))  # rewritten as version 2
    assert json.loads((tmp_path / "vehicle-1-compass-0.json").read_text())["version"] == 2


def test_every_load_and_first_overwrite_is_one_log_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.INFO, logger="magcomp.state"):
        store = StateStore(tmp_path)
        store.save(_state(uid=UID_A))
        store.save(_state(uid=UID_A))  # the periodic saves of one run: not repeated
        again = StateStore(tmp_path)
        again.load(1, 0, UID_A)
        again.save(_state(uid=UID_A))
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 3, lines
    assert "new file" in lines[0] and UID_A in lines[0]
    assert "<-" in lines[1] and "overwriting the state saved" in lines[2]


def test_state_adopt_moves_a_system_ids_states_to_one_vehicle(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from magcomp.cli import main

    store = StateStore(tmp_path)
    store.save(_state(idx=0, theta=5.0))
    store.save(_state(idx=1, theta=6.0))
    store.save(_state(idx=1, uid=UID_A, theta=9.0))  # the vehicle already has its own compass 1
    assert main(["state", "list", "--state-dir", str(tmp_path)]) == 0
    listed = capsys.readouterr().out
    assert "vehicle 1 (no identity) compass 0" in listed and f"vehicle 1 id {UID_A} compass 1" in listed
    assert main(["state", "adopt", "1", UID_A.upper(), "--state-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "compass 0: vehicle-1-compass-0.json ->" in out and "compass 1: kept" in out
    again = StateStore(tmp_path)
    a0, a1 = again.load(1, 0, UID_A), again.load(1, 1, UID_A)
    assert a0 is not None and a0.theta_mgauss[0] == 5.0
    assert a1 is not None and a1.theta_mgauss[0] == 9.0  # not replaced without --force
    assert again.load(1, 0) is None and again.load(1, 1) is not None
    assert main(["state", "adopt", "1", "zz", "--state-dir", str(tmp_path)]) != 0
