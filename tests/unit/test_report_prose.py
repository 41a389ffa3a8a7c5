"""diagnose's report: heading plots wrapped to +-180 deg at any log length, no "None" in the prose, only the
log's own autopilot's parameters."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from magcomp.diagnosis.report import _autopilot_lines, _own_params, _text, heading_change_deg


def test_heading_change_of_thirty_turns_stays_within_180_deg() -> None:
    yaw = np.linspace(0.0, 30 * 2 * np.pi, 20_000)  # a long log: 30 full turns (10,800 deg unwrapped)
    change = heading_change_deg(yaw)
    assert change[0] == 0.0
    assert change.min() >= -180.0 and change.max() < 180.0
    np.testing.assert_allclose(heading_change_deg(np.array([0.1, 0.2, -0.3])), np.degrees([0.0, 0.1, -0.4]))


def test_missing_values_read_unknown_not_none() -> None:
    assert _text(None) == "unknown" and _text(float("nan"), " deg") == "unknown"
    assert _text(12.5, " deg") == "12.5 deg"


def test_only_the_logs_autopilot_parameters_are_printed() -> None:
    cj = {"linearisation": "note", "autopilot": {"ardupilot": {"COMPASS_MOT_X": 1.0},
                                                 "px4": {"CAL_MAG0_XCOMP": 1.0},
                                                 "px4_throttle": {"CAL_MAG0_XCOMP": 2.0}}}  # fmt: skip
    ardupilot = "\n".join(_autopilot_lines(cj, [], ".", 3))
    px4 = "\n".join(_autopilot_lines(cj, [], ".", 12))
    unknown = "\n".join(_autopilot_lines(cj, [], ".", -1))
    assert "COMPASS_MOT_X" in ardupilot and "CAL_MAG" not in ardupilot
    assert "CAL_MAG0_XCOMP" in px4 and "COMPASS_MOT" not in px4
    assert "COMPASS_MOT_X" in unknown and "CAL_MAG0_XCOMP" in unknown
    assert _own_params("px4_current", 12) and not _own_params("px4_current", 3)


class _Axes:
    def __init__(self) -> None:
        self.lines: list[tuple[str, np.ndarray]] = []

    def plot(self, t: np.ndarray, y: np.ndarray, *args: object, label: str = "", **kw: object) -> None:
        self.lines.append((label, np.asarray(y)))

    def __getattr__(self, name: str) -> object:  # set_ylim, set_yticks, legend, grid, ...
        return lambda *a, **k: None


def test_heading_plot_draws_the_reference_and_stays_wrapped(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from magcomp.diagnosis import report
    from magcomp.diagnosis.results import HeadingErrors

    ax = _Axes()
    fig = SimpleNamespace(tight_layout=lambda: None, savefig=lambda *a, **k: None)
    plt = SimpleNamespace(subplots=lambda **k: (fig, ax), close=lambda f: None)
    n = 5000
    monkeypatch.setattr(report, "compass_yaw_rad", lambda data, fit, remove: np.linspace(0.0, 60 * np.pi, n))
    ref = np.linspace(0.0, 60 * np.pi, n) + 0.01
    c = SimpleNamespace(data=SimpleNamespace(t_s=np.arange(n) * 0.1), index=0, baseline=None, extended=None,
                        heading=HeadingErrors("truth", {}, {}, reference_yaw_rad=ref))  # fmt: skip
    out = report._plot_heading(c, plt, tmp_path, "r")  # type: ignore[arg-type]
    assert out is not None
    labels = [label for label, _ in ax.lines]
    assert labels[0] == "reference: truth" and len(labels) == 4
    assert all(y.min() >= -180.0 and y.max() < 180.0 for _, y in ax.lines)


def test_bias_plot_points_are_thinned_at_any_log_length() -> None:
    from magcomp.diagnosis.report import MAX_POINTS, binned_median, thin_indices

    assert len(thin_indices(100)) == 100
    idx = thin_indices(2 * 3600 * 50)  # 2 h at 50 Hz
    assert len(idx) <= MAX_POINTS and idx[0] == 0 and idx[-1] == 2 * 3600 * 50 - 1
    x = np.linspace(0.0, 1.0, 10_000)
    centres, med = binned_median(x, np.column_stack([x**2, -x, 0 * x]))
    assert len(centres) == 20
    np.testing.assert_allclose(med[:, 0], centres**2, atol=0.01)


def test_diagnose_json_writes_a_damaged_logs_nan_as_null(tmp_path: Path) -> None:
    """A NaN a damaged log puts in a finding (the hostile corpus: a ULog with 1000 flipped bits) is written
    as null, not a traceback from the strict JSON writer (issue 25)."""
    import argparse
    import json

    from magcomp.commands.diagnose import _write_outputs

    out = tmp_path / "d.json"
    args = argparse.Namespace(json=str(out), params_out=None, report=None, rerun=None)
    _write_outputs(args, None, {"co_stepping_signals": {"body_rate": float("nan")}, "n": 1.5}, 3, None)
    assert json.loads(out.read_text()) == {"co_stepping_signals": {"body_rate": None}, "n": 1.5}
