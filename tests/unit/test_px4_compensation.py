"""PX4's CAL_MAGn_[XYZ]COMP from a body-frame bias: PX4 adds ``power * COMP`` to the raw sample before its
scale S and rotation R (sensor_calibration/Magnetometer), so the exported COMP, pushed through PX4's own
correction, must cancel the fitted body-frame bias, for a rotated and scaled external compass as for an
internal one."""

from __future__ import annotations

import numpy as np

from magcomp.core.px4 import px4_calibration_matrix
from magcomp.diagnosis.compensation import LinearTerms, px4_params


def _comp(out: dict[str, float], n: int) -> np.ndarray:
    return np.array([out[f"CAL_MAG{n}_{a}COMP"] for a in "XYZ"])


def test_px4_comp_cancels_the_body_frame_bias_through_px4s_correction() -> None:
    k_body = np.array([120.0, -60.0, 240.0])  # mgauss per unit throttle, body frame
    terms = LinearTerms(k_body, None, 0.0, None, (0.0, 0.8))
    params = {"CAL_MAG1_ID": 396809.0, "CAL_MAG1_ROT": 6.0,  # external, yaw 270
              "CAL_MAG1_XSCALE": 1.05, "CAL_MAG1_YSCALE": 0.97, "CAL_MAG1_ZSCALE": 1.0,
              "CAL_MAG1_XODIAG": 0.01}  # fmt: skip
    m = px4_calibration_matrix(params, 1)
    out = px4_params(terms, 1, m)
    assert out["CAL_MAG_COMP_TYP"] == 1.0
    # PX4: m_body = R S (raw + throttle * COMP - OFF); the bias (k_body * throttle, mgauss) must vanish
    np.testing.assert_allclose(m @ _comp(out, 1) * 1000.0, -k_body, atol=0.02)
    # the sensor frame is not the body frame here: the old export (the body-frame bias as COMP) was wrong
    assert np.linalg.norm(_comp(out, 1) * 1000.0 + k_body) > 50.0
    # an internal compass on an unrotated board: COMP is the negated bias itself
    plain = px4_params(terms, 0, px4_calibration_matrix({"CAL_MAG0_ROT": -1.0}, 0))
    np.testing.assert_allclose(_comp(plain, 0) * 1000.0, -k_body, atol=0.01)
