import numpy as np

from magcomp.core.lowpass import LowPassParams, group_delay_s, lowpass_filter


def _gain(freq_hz: float, fs_hz: float, p: LowPassParams) -> float:
    t = np.arange(0, 20.0, 1.0 / fs_hz)
    x = np.sin(2 * np.pi * freq_hz * t)
    y = lowpass_filter(t, x, p)
    half = len(t) // 2
    return float(np.sqrt(2) * np.std(y[half:]))


def test_corner_is_minus_3db_at_any_rate() -> None:
    p = LowPassParams(corner_hz=5.0, order=2)
    for fs in (25.0, 50.0, 100.0, 400.0):
        assert abs(_gain(5.0, fs, p) - 1 / np.sqrt(2)) < 0.02, fs
        assert _gain(0.2, fs, p) > 0.99
    assert _gain(20.0, 100.0, p) < 0.1


def test_constant_input_passes_without_transient_and_delay_is_finite() -> None:
    t = np.arange(0, 1, 0.02)
    x = np.tile([100.0, -50.0, 400.0], (len(t), 1))
    np.testing.assert_allclose(lowpass_filter(t, x, LowPassParams()), x, atol=1e-9)
    d = group_delay_s(LowPassParams(5.0, 2), 0.02)
    assert 0.02 < d < 0.06
