"""`replay` of a tlog that carries two vehicles analyses each one, as `run` follows each sender live
(issue 25, item 7): each vehicle's headings and theta are those of replaying its own tlog alone."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from magcomp.adapters.mavlink_emit import default_start_unix_s, encode_stream
from magcomp.adapters.tlog_split import several_vehicles, split_by_vehicle
from magcomp.cli import main
from magcomp.sim import SimConfig, simulate


def _two_vehicle_tlog(tmp_path: Path) -> tuple[Path, dict[int, Path]]:
    """Two simulated flights (different seeds and compass errors) sent by systems 1 and 3 over one link,
    their records interleaved by time, the second autopilot booted 3 s after the first (its clock behind);
    and each flight's own tlog."""
    records: list[tuple[int, int, bytes]] = []
    alone: dict[int, Path] = {}
    for system, seed, t0_s in ((1, 5, 10.0), (3, 6, 7.0)):
        result = simulate(SimConfig(scenario="flight", duration_s=60.0, seed=seed, t0_s=t0_s))
        start = default_start_unix_s(result) + (10.0 - t0_s)  # the same wall time, a clock 3 s behind
        own = [(round((start + t_s) * 1e6), system, pkt)
               for t_s, pkt in encode_stream(result, src_system=system, start_unix_s=start)]  # fmt: skip
        records += own
        alone[system] = tmp_path / f"alone{system}.tlog"
        alone[system].write_bytes(b"".join(stamp.to_bytes(8, "big") + pkt for stamp, _, pkt in own))
    records.sort(key=lambda r: r[0])  # stable: a tie keeps system 1 first
    both = tmp_path / "two.tlog"
    both.write_bytes(b"".join(stamp.to_bytes(8, "big") + pkt for stamp, _, pkt in records))
    return both, alone


@pytest.mark.slow
def test_each_vehicle_of_a_two_vehicle_tlog_is_replayed_as_its_own_log(tmp_path: Path) -> None:
    both, alone = _two_vehicle_tlog(tmp_path)
    assert several_vehicles(both) == [(1, 1), (3, 1)]
    assert several_vehicles(alone[1]) == []
    parts = split_by_vehicle(both, tmp_path, several_vehicles(both))
    # a vehicle's part holds exactly its frames: byte for byte its own tlog
    assert parts[(1, 1)].read_bytes() == alone[1].read_bytes()
    assert parts[(3, 1)].read_bytes() == alone[3].read_bytes()

    out = tmp_path / "two.json"
    emit = tmp_path / "two.emit.tlog"
    assert main(["replay", str(both), "--causal", "--json", str(out), "--emit", str(emit)]) == 0
    doc = json.loads(out.read_text())
    assert [(v["system_id"], v["component_id"]) for v in doc["vehicles"]] == [(1, 1), (3, 1)]
    n_emitted = 0
    for vehicle in doc["vehicles"]:
        system = vehicle["system_id"]
        single = tmp_path / f"alone{system}.json"
        assert main(["replay", str(alone[system]), "--causal", "--json", str(single)]) == 0
        ref = json.loads(single.read_text())
        assert vehicle["estimates"] > 1000
        assert vehicle["estimates"] == ref["estimates"]
        assert vehicle["source_counts"] == ref["source_counts"]
        assert vehicle["compasses"] == ref["compasses"]  # calibration, theta, self-check: all the same
        n_emitted += vehicle["emitted"]
    # the two vehicles learned different compass errors (different seeds): not one mixed estimate
    fits = [[c["theta_mgauss"] for c in v["compasses"]] for v in doc["vehicles"]]
    assert fits[0] != fits[1]
    assert emit.stat().st_size > 0 and n_emitted > 0


def test_the_mixed_replay_drops_the_second_vehicle_which_the_split_keeps(tmp_path: Path) -> None:
    """Control: read as one source, the second vehicle's samples are lost (time going backwards)."""
    from magcomp.adapters.mavlink_source import open_source
    from magcomp.core.types import MagSample

    both, alone = _two_vehicle_tlog(tmp_path)
    with open_source(both) as src:
        mixed = sum(isinstance(s, MagSample) for s in src.samples())
        backwards = src.counts["time_backwards"]
    own = 0
    for path in alone.values():
        with open_source(path) as src:
            own += sum(isinstance(s, MagSample) for s in src.samples())
    assert backwards > 100 and mixed < 0.9 * own
