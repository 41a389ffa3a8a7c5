"""State store: survives restarts, a damaged file gives a warning and a fresh start, a kill -9 mid-write
leaves either the old or the new state, never a damaged one."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from magcomp.adapters.state_store import CompassState, StateStore

REPO = Path(__file__).parents[2]


def _state(rng: np.random.Generator, sysid: int = 1, idx: int = 0) -> CompassState:
    return CompassState(
        system_id=sysid,
        mag_index=idx,
        calib_l=np.eye(3) + 0.05 * rng.standard_normal((3, 3)),
        calib_d=50.0 * rng.standard_normal(3),
        theta_mgauss=100.0 * rng.standard_normal(3),
        t_s=123.25,
        calib_info={"residual_rms_mgauss": 2.5},
    )


def test_state_survives_restart_per_vehicle_and_compass(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    a, b = _state(rng, 1, 0), _state(rng, 7, 2)
    store = StateStore(tmp_path)
    store.save(a)
    store.save(b)
    again = StateStore(tmp_path)  # a new process would do exactly this
    la, lb = again.load(1, 0), again.load(7, 2)
    assert la is not None and lb is not None
    assert la.calib_l is not None and a.calib_l is not None
    assert_allclose(la.calib_l, a.calib_l, rtol=0, atol=0)
    assert_allclose(lb.theta_mgauss, b.theta_mgauss, rtol=0, atol=0)
    assert la.calib_info == {"residual_rms_mgauss": 2.5}
    assert again.load(1, 1) is None
    assert again.warnings == []


def test_uncalibrated_state_round_trips(tmp_path: Path) -> None:
    s = CompassState(3, 1, None, None, np.array([1.0, -2.0, 3.0]), 4.0)
    store = StateStore(tmp_path)
    store.save(s)
    got = store.load(3, 1)
    assert got is not None and got.calib_l is None and got.calib_d is None
    assert_allclose(got.theta_mgauss, [1.0, -2.0, 3.0])


@pytest.mark.parametrize(
    "damage",
    ["truncate", "garbage", "flip_value", "empty", "wrong_shape", "not_json_object"],
)
def test_damaged_file_gives_warning_and_fresh_start(tmp_path: Path, damage: str) -> None:
    store = StateStore(tmp_path)
    path = store.save(_state(np.random.default_rng(2)))
    text = path.read_text()
    if damage == "truncate":
        path.write_text(text[: len(text) // 2])
    elif damage == "garbage":
        path.write_bytes(b"\x00\xff" * 40)
    elif damage == "flip_value":  # valid JSON, wrong content: the checksum catches it
        doc = json.loads(text)
        doc["state"]["theta_mgauss"][0] += 1.0
        path.write_text(json.dumps(doc))
    elif damage == "empty":
        path.write_text("")
    elif damage == "wrong_shape":
        doc = json.loads(text)
        doc["state"]["theta_mgauss"] = [1.0, 2.0]
        from magcomp.adapters.state_store import _digest

        doc["sha256"] = _digest(doc["state"])
        path.write_text(json.dumps(doc))
    else:
        path.write_text("[1, 2, 3]")
    fresh = StateStore(tmp_path)
    assert fresh.load(1, 0) is None
    assert len(fresh.warnings) == 1
    assert "damaged" in fresh.warnings[0] and str(path) in fresh.warnings[0]


_WRITER = """
import sys, numpy as np
from magcomp.adapters.state_store import CompassState, StateStore
store = StateStore(sys.argv[1])
i = 0
print("ready", flush=True)
while True:
    i += 1
    # a large, self-consistent state: every entry equals the generation number i
    store.save(CompassState(1, 0, np.full((3, 3), float(i)), np.full(3, float(i)), np.full(3, float(i)),
                            float(i), {f"k{j}": float(i) for j in range(2000)}))
"""


@pytest.mark.slow
def test_kill_9_during_writes_leaves_old_or_new_state_never_damaged(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    for trial in range(4):
        d = tmp_path / f"t{trial}"
        proc = subprocess.Popen(
            [sys.executable, "-c", _WRITER, str(d)], stdout=subprocess.PIPE, env=env, cwd=REPO
        )
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == b"ready"
        time.sleep(0.3 + 0.17 * trial)  # land the kill at different points of the write cycle
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
        store = StateStore(d)
        got = store.load(1, 0)
        assert store.warnings == []
        assert got is not None, "a state must exist after many completed writes"
        gen = got.t_s
        assert gen >= 1.0
        assert got.calib_l is not None and got.calib_d is not None
        assert np.all(got.calib_l == gen) and np.all(got.calib_d == gen) and np.all(got.theta_mgauss == gen)
        assert got.calib_info is not None and all(v == gen for v in got.calib_info.values())
        assert not list(d.glob("*.tmp")), "stale temp files are cleaned on open"


def test_unwritable_state_dir_is_input_error(tmp_path: Path) -> None:
    from magcomp.errors import InputError

    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match="state directory"):
        StateStore(f / "sub")
