"""State per vehicle, not per system id: two simulated vehicles with system id 1 and different unique ids keep
separate states in one state directory; the id is read from tlogs (AUTOPILOT_VERSION), DataFlash (the board's
boot MSG) and ULog (sys_uuid); an id that arrives after the first samples drops a state that was loaded for
the system id alone."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.state_store import StateStore
from magcomp.service.replay import replay_log
from tests.configs import QUICK_CALIBRATION
from tests.faultgen import record_msgid

UID_A = "0033002b3139511134383233"
UID_B = "0044002b3139511134383299"


@pytest.fixture(scope="module")
def logs(
    tmp_path_factory: pytest.TempPathFactory, split_tlog: Callable[[bytes], list[bytes]]
) -> dict[str, Path]:
    from magcomp.adapters.dataflash_writer import write_sim_dataflash
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.adapters.ulog_writer import write_sim_ulog
    from magcomp.sim import SimConfig, simulate

    d = tmp_path_factory.mktemp("ident")
    a = simulate(SimConfig(scenario="paper", duration_s=40.0, seed=7, uid=UID_A, n_compasses=1))
    b = simulate(SimConfig(scenario="paper", duration_s=40.0, seed=8, uid=UID_B, n_compasses=1,
                           theta_mgauss=(150.0, -80.0, 40.0)))  # fmt: skip
    paths = {"a": d / "a.tlog", "b": d / "b.tlog", "a_bin": d / "a.bin", "a_ulg": d / "a.ulg"}
    write_tlog(a, paths["a"])
    write_tlog(b, paths["b"])
    write_sim_dataflash(a, paths["a_bin"])
    write_sim_ulog(a, paths["a_ulg"])
    recs = split_tlog(paths["a"].read_bytes())
    paths["a_anon"] = d / "a_anon.tlog"  # the same flight, no AUTOPILOT_VERSION in it
    paths["a_anon"].write_bytes(b"".join(r for r in recs if record_msgid(r) != 148))
    recs_b = split_tlog(paths["b"].read_bytes())
    ident = [r for r in recs_b if record_msgid(r) == 148]
    rest = [r for r in recs_b if record_msgid(r) != 148]
    paths["b_late"] = d / "b_late.tlog"  # vehicle B, its id answered after ~3 s of samples
    paths["b_late"].write_bytes(b"".join(rest[:3000] + ident + rest[3000:]))
    return paths


def _source(report_summary: dict[str, object]) -> str:
    comps = report_summary["compasses"]
    assert isinstance(comps, list)
    cal = comps[0]["calibration"]
    return "none" if cal is None else str(cal["source"])


def test_two_vehicles_with_one_system_id_keep_separate_states(logs: dict[str, Path], tmp_path: Path) -> None:
    store_dir = tmp_path / "state"
    first = replay_log(logs["a"], QUICK_CALIBRATION, store=StateStore(store_dir))
    assert first.summary["vehicle_uid"] == UID_A and first.summary["system_id"] == 1
    saved_a = StateStore(store_dir).load(1, 0, UID_A)
    assert saved_a is not None
    bytes_a = StateStore(store_dir).path_for(1, 0, UID_A).read_bytes()

    other = replay_log(logs["b"], QUICK_CALIBRATION, store=StateStore(store_dir))
    assert other.summary["vehicle_uid"] == UID_B
    assert _source(other.summary) != "stored"  # learned on its own, not vehicle A's calibration
    saved_b = StateStore(store_dir).load(1, 0, UID_B)
    assert saved_b is not None
    assert np.linalg.norm(saved_b.theta_mgauss - saved_a.theta_mgauss) > 20.0
    assert StateStore(store_dir).path_for(1, 0, UID_A).read_bytes() == bytes_a  # A's state untouched

    again = replay_log(logs["a"], QUICK_CALIBRATION, store=StateStore(store_dir))
    assert _source(again.summary) == "stored"  # vehicle A gets its own state back


@pytest.mark.parametrize("kind", ["a_bin", "a_ulg"])
def test_identity_read_from_dataflash_and_ulog(logs: dict[str, Path], kind: str) -> None:
    assert replay_log(logs[kind], QUICK_CALIBRATION).summary["vehicle_uid"] == UID_A


def test_late_identity_drops_the_state_of_the_system_id(logs: dict[str, Path], tmp_path: Path) -> None:
    store_dir = tmp_path / "state"
    anon = replay_log(logs["a_anon"], QUICK_CALIBRATION, store=StateStore(store_dir))
    assert anon.summary["vehicle_uid"] is None
    assert StateStore(store_dir).load(1, 0) is not None  # the state of "system 1", no identity
    texts: list[str] = []
    late = replay_log(
        logs["b_late"], QUICK_CALIBRATION, store=StateStore(store_dir), on_text=lambda t, s: texts.append(s)
    )
    assert late.summary["vehicle_uid"] == UID_B
    assert any("is dropped" in s for s in texts)
    assert _source(late.summary) != "stored"
    assert StateStore(store_dir).load(1, 0, UID_B) is not None
