"""Parameters that arrive late in a tlog (issue 23, item 5): COMPASS_EXTERNAL / COMPASS_PRIMARY sent 6-9 s
after the first RAW_IMU re-decide each compass's in-flight reference, as if they had come first."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from magcomp.adapters.config import Config
from magcomp.service.replay import replay_log
from tests.conftest import split_tlog_records
from tests.faultgen import record_time_s

LATE_S = 8.0  # after the first RAW_IMU, as on the squilter tlogs (6-9 s)


def _decoded(records: list[bytes]) -> list[Any]:
    from magcomp.adapters.dialect import ensure_dialect

    mav = ensure_dialect().MAVLink(None)
    return [mav.decode(bytearray(r[8:])) for r in records]


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """An ordinary flight with an external compass 0 (the autopilot's primary: compass 1 gets the absolute
    form), and the same tlog with every COMPASS_* parameter moved LATE_S s after the first RAW_IMU."""
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate
    from magcomp.sim.config import apply_settings

    cfg = apply_settings(SimConfig(scenario="ordinary", duration_s=60.0, seed=2), ["external_compass0=on"])
    result = simulate(cfg)
    d = tmp_path_factory.mktemp("late_params")
    early = d / "early.tlog"
    write_tlog(result, early)
    recs = split_tlog_records(early.read_bytes())
    msgs = _decoded(recs)
    t_raw = next(record_time_s(r) for r, m in zip(recs, msgs, strict=True) if m.get_type() == "RAW_IMU")
    is_late = [m.get_type() == "PARAM_VALUE" and m.param_id.startswith("COMPASS_") for m in msgs]
    late = [r for r, k in zip(recs, is_late, strict=True) if k]
    assert late, "the simulated tlog carries compass parameters"
    stamp = round((t_raw + LATE_S) * 1e6).to_bytes(8, "big")
    rest = [r for r, k in zip(recs, is_late, strict=True) if not k]
    at = next(i for i, r in enumerate(rest) if record_time_s(r) >= t_raw + LATE_S)
    moved = rest[:at] + [stamp + r[8:] for r in late] + rest[at:]
    path = d / "late.tlog"
    path.write_bytes(b"".join(moved))
    return early, path


def _forms(path: Path, two_pass: bool) -> dict[int, tuple[str, str]]:
    rep = replay_log(path, Config(), two_pass=two_pass)
    out = {}
    for c in rep.summary["compasses"]:
        inf = c.get("inflight") or {}
        out[int(c["index"])] = (str(inf.get("form")), str(inf.get("form_why")))
    return out


@pytest.mark.parametrize("two_pass", [True, False], ids=["two-pass", "causal"])
def test_late_compass_parameters_re_decide_the_reference(logs: tuple[Path, Path], two_pass: bool) -> None:
    """Two-pass: the first pass's stages run in the in-flight process (re-created in the same child);
    causal: in the pipeline."""
    early, late = logs
    want = _forms(early, two_pass)
    # the twin: compass 0 is the external primary
    assert want[1][0] == "absolute" and "external" in want[1][1]
    got = _forms(late, two_pass)
    # without the re-decision: both "relative", "the autopilot's yaw source is unknown (no compass
    # parameters)"
    assert got == want
