"""A write that fails at the last flush of ``replay --causal --emit`` (a full disk) is the run's failure,
reported as such, and the final state of every compass is still saved: the frames of ``--emit`` are queued
(service/publish.py FrameQueue) and the last block is written after the log has been read."""

from __future__ import annotations

from pathlib import Path

import pytest

from magcomp.adapters.config import Config
from magcomp.adapters.mavlink_emit import write_tlog
from magcomp.errors import InputError
from magcomp.service.publish import TlogWriter
from magcomp.service.replay import MemoryStore, replay_log
from magcomp.sim import SimConfig, simulate


def test_a_failing_last_flush_still_saves_the_final_state(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    result = simulate(SimConfig(scenario="step", duration_s=6.0, seed=5, n_compasses=1))
    path = tmp_path / "log.tlog"
    write_tlog(result, path)
    ref = MemoryStore()
    replay_log(path, Config(), store=ref)
    t_end = max(s.t_s for s in ref.states.values())

    def full_disk(self: TlogWriter, *args: object) -> None:
        raise InputError(f"cannot write {self.path}: No space left on device")

    monkeypatch.setattr(TlogWriter, "write_frames", full_disk)
    store = MemoryStore()
    with pytest.raises(InputError, match="No space left"):
        replay_log(path, Config(), store=store, emit=tmp_path / "out.tlog")
    assert store.states, "no state saved"
    assert max(s.t_s for s in store.states.values()) == t_end  # the final save, not a periodic one
