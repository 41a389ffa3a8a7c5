"""A damaged PARAM_VALUE (a NaN value) is dropped and counted, not read as an integer: the parameters decide
each compass's in-flight form (core/autopilot_params.py ``yaw_reference``), and ``int(nan)`` raised there."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from magcomp.adapters.config import Config
from magcomp.service.replay import replay_log


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate
    from magcomp.sim.config import apply_settings

    path = tmp_path_factory.mktemp("nanparam") / "flight.tlog"
    write_tlog(simulate(apply_settings(SimConfig(scenario="ordinary", duration_s=60.0, seed=5),
                                       ["telemetry_hz=10"])), path)  # fmt: skip
    return path


def test_a_nan_parameter_is_dropped_and_the_rest_replays_as_without_it(
    flight: Path, tmp_path: Path, split_tlog: Callable[[bytes], list[bytes]]
) -> None:
    from pymavlink.dialects.v20 import ardupilotmega as apm

    records = split_tlog(flight.read_bytes())
    enc = apm.MAVLink(None, srcSystem=1, srcComponent=1)
    bad = [records[0][:8] + apm.MAVLink_param_value_message(name, float("nan"), 9, 900, k).pack(enc)
           for k, name in enumerate((b"COMPASS_PRIMARY", b"EK3_SRC1_YAW", b"AHRS_EKF_TYPE"))]  # fmt: skip
    damaged = tmp_path / "damaged.tlog"
    damaged.write_bytes(b"".join([records[0], *bad, *records[1:]]))
    clean = replay_log(flight, Config())
    rep = replay_log(damaged, Config())
    assert rep.summary["counts"].get("non_finite_params", 0) == 3
    a, b = clean.summary["compasses"], rep.summary["compasses"]
    assert [c["status"] for c in b] == [c["status"] for c in a]
    assert [c["theta_mgauss"] for c in b] == [c["theta_mgauss"] for c in a]
