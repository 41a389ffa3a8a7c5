"""PX4 ULog compasses in the body frame with PX4's calibration removed, as the in-flight estimator's prior
expects (the autopilot's calibration) and as ArduPilot's fields are: ``vehicle_magnetometer`` when logged
(PX4's default profile logs it at 2 Hz beside ``sensor_mag`` at 1 Hz); ``sensor_mag`` (the driver's frame,
before calibration) only without it, then calibrated here with CAL_MAGn_OFF / SCALE / ODIAG and the
rotation PX4 applies (CAL_MAGn_ROT for an external compass, SENS_BOARD_ROT for an internal one)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcomp.adapters.ulog_writer import write_sim_ulog
from magcomp.core.px4 import px4_calibrated_mag, px4_mag_rotation
from magcomp.core.types import MagSample


def test_px4_rotations_map_the_sensor_axes_as_its_enum_names_say() -> None:
    yaw90 = px4_mag_rotation({"CAL_MAG0_ROT": 2.0}, 0)  # ROTATION_YAW_90, an external compass
    np.testing.assert_allclose(yaw90 @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    roll180 = px4_mag_rotation({"CAL_MAG1_ROT": 8.0}, 1)  # ROTATION_ROLL_180
    np.testing.assert_allclose(roll180 @ [0.0, 1.0, 2.0], [0.0, -1.0, -2.0], atol=1e-12)
    pitch90 = px4_mag_rotation({"CAL_MAG0_ROT": 24.0}, 0)  # ROTATION_PITCH_90: x -> -z
    np.testing.assert_allclose(pitch90 @ [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], atol=1e-12)
    # an internal compass (-1) takes the board's rotation, fine-tuned by the board offsets (deg)
    board = px4_mag_rotation({"CAL_MAG0_ROT": -1.0, "SENS_BOARD_ROT": 4.0, "SENS_BOARD_Z_OFF": 10.0}, 0)
    yaw = np.degrees(np.arctan2(board[1, 0], board[0, 0]))
    assert yaw == pytest.approx(-170.0)
    np.testing.assert_allclose(px4_mag_rotation({}, None), np.eye(3))


def test_calibration_is_offset_then_scale_then_rotation() -> None:
    params = {"CAL_MAG0_ROT": 8.0, "CAL_MAG0_XOFF": 0.1, "CAL_MAG0_YOFF": -0.2, "CAL_MAG0_ZOFF": 0.3,
              "CAL_MAG0_XSCALE": 1.1, "CAL_MAG0_YSCALE": 0.9, "CAL_MAG0_ZSCALE": 1.0,
              "CAL_MAG0_XODIAG": 0.02}  # fmt: skip
    raw = np.array([[0.3, 0.1, 0.6], [-0.2, 0.4, 0.1]])
    s = np.array([[1.1, 0.02, 0.0], [0.02, 0.9, 0.0], [0.0, 0.0, 1.0]])
    want = (np.diag([1.0, -1.0, -1.0]) @ (s @ (raw - [0.1, -0.2, 0.3]).T)).T
    np.testing.assert_allclose(px4_calibrated_mag(params, 0, raw), want, atol=1e-12)


def _fields(path: Path) -> dict[int, np.ndarray]:
    from magcomp.adapters.mavlink_source import open_source

    out: dict[int, list[np.ndarray]] = {}
    with open_source(path) as src:
        for s in src.samples():
            if isinstance(s, MagSample):
                out.setdefault(s.mag_index, []).append(np.asarray(s.field_b_mgauss))
    return {k: np.asarray(v) for k, v in out.items()}


def test_both_topics_and_a_sensor_frame_sensor_mag_give_the_body_frame_field(tmp_path: Path) -> None:
    from magcomp.sim import SimConfig, simulate

    result = simulate(SimConfig(scenario="ordinary", duration_s=20.0, seed=2, n_compasses=2))
    body = tmp_path / "vm.ulg"
    write_sim_ulog(result, body, mag_topic="vehicle_magnetometer")
    both = tmp_path / "both.ulg"
    write_sim_ulog(result, both, mag_topic="both", sensor_frame=True)
    raw = tmp_path / "raw.ulg"
    write_sim_ulog(result, raw, mag_topic="sensor_mag", sensor_frame=True)
    want = _fields(body)
    assert sorted(want) == [0, 1]
    for path in (both, raw):
        got = _fields(path)
        assert sorted(got) == [0, 1]
        for k in want:
            assert got[k].shape == want[k].shape
            # float32 in the log: the raw frame's offsets and rotation round at ~1e-4 mgauss
            np.testing.assert_allclose(got[k], want[k], atol=0.01)
