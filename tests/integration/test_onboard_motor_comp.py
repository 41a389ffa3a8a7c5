"""Compensation already on board (issue 9, item 7): an ArduPilot tlog whose RAW_IMU / SCALED_IMU2 compass
fields carry the autopilot's own motor compensation (COMPASS_MOTCT = 1: field + COMPASS_MOT * throttle,
throttle = VFR_HUD.throttle / 100 as the autopilot uses it), with the parameters arriving on the link after
the first samples. The source undoes it from when the parameters are known; the replay learns the same theta
as the uncompensated twin; a wrong onboard compensation is reported, a right one is not."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from magcomp.adapters.mavlink_source import open_source
from magcomp.core.types import MagSample
from magcomp.service.replay import replay_log
from tests.configs import ESTIMATOR_ONLY

PARAMS_AT_S = 1.0  # the ground station fetches the parameters 1 s into the log (motors still off)
_MAG_INDEX = {"RAW_IMU": 0, "SCALED_IMU2": 1}


@pytest.fixture(scope="module")
def twin(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Path]:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate
    from magcomp.sim.config import apply_settings

    result = simulate(
        apply_settings(SimConfig(scenario="ordinary", duration_s=120.0, seed=3), ["telemetry_hz=10"])
    )
    path = tmp_path_factory.mktemp("motcomp") / "twin.tlog"
    write_tlog(result, path)
    return result, path


def _throttle_at_mags(records: list[bytes]) -> np.ndarray:
    """The latest VFR_HUD throttle (0..1) at each compass record after PARAMS_AT_S."""
    from pymavlink.dialects.v20 import ardupilotmega as apm

    mav = apm.MAVLink(None)
    t0 = int.from_bytes(records[0][:8], "big")
    thr, out = 0.0, []
    for r in records:
        msg = mav.decode(bytearray(r[8:]))
        if msg.get_type() == "VFR_HUD":
            thr = msg.throttle * 0.01
        elif msg.get_type() == "RAW_IMU" and (int.from_bytes(r[:8], "big") - t0) * 1e-6 >= PARAMS_AT_S:
            out.append(thr)
    return np.asarray(out)


def _compensate(
    src: Path,
    dst: Path,
    mots: dict[int, np.ndarray],
    split: Callable[[bytes], list[bytes]],
    apply: bool = True,
) -> None:
    """``dst``: ``src`` as an ArduPilot with COMPASS_MOTCT = 1 and these COMPASS_MOT vectors would send it:
    every compass field + MOT * throttle (from the start: the autopilot compensates whether or not anyone
    asked for its parameters), int16 as on the wire; PARAM_VALUE for COMPASS_MOTCT and COMPASS_MOT* at
    PARAMS_AT_S."""
    from pymavlink.dialects.v20 import ardupilotmega as apm

    records = split(src.read_bytes())
    mav = apm.MAVLink(None)
    t0 = int.from_bytes(records[0][:8], "big")
    thr: float = 0.0
    sent, out = False, []
    for r in records:
        if not sent and (int.from_bytes(r[:8], "big") - t0) * 1e-6 >= PARAMS_AT_S:
            enc = apm.MAVLink(None, srcSystem=1, srcComponent=1)
            items = [("COMPASS_MOTCT", 1.0)]
            for jm, m in mots.items():
                prefix = "COMPASS_MOT_" if jm == 0 else f"COMPASS_MOT{jm + 1}_"
                items += [(prefix + ax, float(m[i])) for i, ax in enumerate("XYZ")]
            for k, (name, value) in enumerate(items):
                pv = apm.MAVLink_param_value_message(name.encode(), value, 9, 900, 800 + k)
                out.append(r[:8] + pv.pack(enc))
            sent = True
        msg = mav.decode(bytearray(r[8:]))
        kind = msg.get_type()
        if kind == "VFR_HUD":
            thr = msg.throttle * 0.01
        j = _MAG_INDEX.get(kind)
        if not apply or j is None or j not in mots or not (msg.xmag or msg.ymag or msg.zmag):
            out.append(r)
            continue
        m = mots[j]
        msg.xmag = round(msg.xmag + m[0] * thr)
        msg.ymag = round(msg.ymag + m[1] * thr)
        msg.zmag = round(msg.zmag + m[2] * thr)
        out.append(r[:8] + msg.pack(apm.MAVLink(None, srcSystem=msg.get_srcSystem(),
                                                srcComponent=msg.get_srcComponent())))  # fmt: skip
    dst.write_bytes(b"".join(out))


def _fields(path: Path) -> dict[int, np.ndarray]:
    out: dict[int, list[tuple[float, ...]]] = {}
    src = open_source(path)
    for s in src.samples():
        if isinstance(s, MagSample):
            out.setdefault(s.mag_index, []).append((s.t_s, *s.field_b_mgauss))
    src.close()
    return {k: np.asarray(v) for k, v in out.items()}


def test_onboard_compensation_is_undone_and_a_wrong_one_reported(
    twin: tuple[Any, Path], tmp_path: Path, split_tlog: Callable[[bytes], list[bytes]]
) -> None:
    result, twin_path = twin
    theta_logged = {j: np.asarray(result.theta_logged_mgauss(j), dtype=float) for j in (0, 1)}
    # a compassmot-like linear fit that is off: 0.8 of the full-throttle bias per unit throttle
    wrong = {j: -0.8 * theta_logged[j] for j in (0, 1)}
    comp_path = tmp_path / "wrong.tlog"
    _compensate(twin_path, comp_path, wrong, split_tlog)

    # the source gives back the field the motors disturbed, from when the parameters are known
    a, b = _fields(twin_path), _fields(comp_path)
    for j in (0, 1):
        t0 = a[j][0, 0]
        after = a[j][:, 0] >= t0 + PARAMS_AT_S + 0.2
        diff = np.abs(b[j][after, 1:] - a[j][after, 1:])
        assert diff.max() <= 0.5 + 1e-3 * np.abs(wrong[j]).max()  # int16 rounding, float32 parameters
    twin_rep = replay_log(twin_path, ESTIMATOR_ONLY, two_pass=True)
    rep = replay_log(comp_path, ESTIMATOR_ONLY, two_pass=True)
    assert rep.source_counts["motor_comp_removed"] > 0.9 * sum(len(v) for v in b.values())
    for ct, cc in zip(twin_rep.summary["compasses"], rep.summary["compasses"], strict=True):
        sd = np.asarray(ct["inflight"]["theta_sigma_mgauss"], dtype=float)
        d = np.asarray(cc["theta_mgauss"]) - np.asarray(ct["theta_mgauss"])
        assert np.all(np.abs(d) < sd), (cc["index"], d, sd)  # the undo moves theta by less than its 1 sigma
    onboard = rep.summary["onboard_motor_compensation"]
    assert onboard["0"]["motct"] == 1 and onboard["0"]["differs"] is True
    assert any(
        w.startswith("compass 0: the autopilot's own motor compensation") for w in rep.summary["warnings"]
    )
    assert not any("motor compensation" in w for w in twin_rep.summary["warnings"])


def test_a_right_onboard_compensation_is_not_reported(
    twin: tuple[Any, Path], tmp_path: Path, split_tlog: Callable[[bytes], list[bytes]]
) -> None:
    """MOT chosen so that its equivalent theta over this flight's throttle is the true one: undone, and no
    warning for compass 0 (the learned theta agrees with the truth within its uncertainty)."""
    result, twin_path = twin
    thr = _throttle_at_mags(split_tlog(twin_path.read_bytes()))
    ratio = float(np.sum(thr**4) / np.sum(thr**3))  # theta_equivalent = -MOT * sum(d^3) / sum(d^4)
    right = {0: -np.asarray(result.theta_logged_mgauss(0), dtype=float) * ratio}
    comp_path = tmp_path / "right.tlog"
    _compensate(twin_path, comp_path, right, split_tlog)
    rep = replay_log(comp_path, ESTIMATOR_ONLY, two_pass=True)
    onboard = rep.summary["onboard_motor_compensation"]["0"]
    np.testing.assert_allclose(onboard["theta_equivalent_mgauss"], result.theta_logged_mgauss(0), atol=1.0)
    assert onboard["differs"] is False
    assert not any(w.startswith("compass 0: the autopilot's own") for w in rep.summary["warnings"])


def test_nan_onboard_compensation_is_reported_and_loses_no_sample(
    twin: tuple[Any, Path], tmp_path: Path, split_tlog: Callable[[bytes], list[bytes]]
) -> None:
    """COMPASS_MOTCT = 1 with COMPASS_MOT_X/Y/Z = NaN (as in the measured ArduCopter 3.1.1 log): nothing can
    be undone; the fields pass unchanged (no sample turned into NaN and dropped) and a warning says why."""
    _, twin_path = twin
    path = tmp_path / "nan.tlog"
    _compensate(twin_path, path, {0: np.full(3, np.nan)}, split_tlog, apply=False)
    ref = replay_log(twin_path, ESTIMATOR_ONLY, two_pass=False)
    rep = replay_log(path, ESTIMATOR_ONLY, two_pass=False)
    assert rep.n_estimates == ref.n_estimates and rep.summary["counts"]["non_finite"] == 0
    assert rep.source_counts["motor_comp_invalid"] > 0 and "motor_comp_removed" not in rep.source_counts
    assert rep.summary["onboard_motor_compensation"]["0"]["invalid"] is True
    assert any("COMPASS_MOT_X/Y/Z is not a finite number" in w for w in rep.summary["warnings"])
