"""The Rerun adapter: mode parsing, the lazy import, and recordings read back with rerun's own reader."""

from __future__ import annotations

import argparse
import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from magcomp.adapters.rerun_viz import (
    AXES,
    TIMELINE,
    NullViz,
    StreamDecimator,
    TruthHeading,
    Viz,
    add_rerun_argument,
    bias_fit_canvas,
    default_mode_for_demo,
    flag_changes,
    labelled_axis_range,
    nice_range,
    open_viz,
    parse_mode,
    serve_until_interrupt,
    theta_band,
    wrap_deg,
)
from magcomp.core.types import FLAG_CALIBRATED, FLAG_THETA_CONVERGED, HeadingEstimate, flags_text
from magcomp.errors import MagcompError

REPO = Path(__file__).resolve().parents[2]
THETA_TRUE = np.array([42.0, -27.0, 65.0])


def synthetic_estimates(n: int, seed: int, dt_s: float = 0.02) -> tuple[list[HeadingEstimate], np.ndarray]:
    """A run whose theta-hat converges to THETA_TRUE; heading raw = truth + bias-induced error, corrected =
    truth + noise. Returns the estimates and the true heading (deg) at their times."""
    rng = np.random.default_rng(seed)
    t = 3.0 + np.arange(n) * dt_s
    truth = (25.0 * t) % 360.0
    thr = 0.5 + 0.5 * np.sin(t / 2.0)
    out = []
    for i in range(n):
        theta = THETA_TRUE * (1.0 - np.exp(-(t[i] - t[0]) / 5.0)) + rng.normal(0.0, 0.5, 3)
        # the observer's 1-sigma: unknown for the first samples, then shrinking as theta converges
        sd = float("nan") if i < 5 else float(40.0 * np.exp(-i / 60.0) + 1.0)
        flags = FLAG_CALIBRATED | (FLAG_THETA_CONVERGED if i > n // 2 else 0)
        out.append(
            HeadingEstimate(
                t_s=float(t[i]),
                mag_index=0,
                heading_deg=float((truth[i] + rng.normal(0.0, 0.5)) % 360.0),
                heading_raw_deg=float((truth[i] + 12.0 * thr[i] ** 2) % 360.0),
                theta_mgauss=theta,
                bias_mgauss=theta * thr[i] ** 2,
                throttle_01=float(thr[i]),
                flags=flags,
                field_raw_mgauss=rng.normal(size=3) * [300.0, 250.0, 200.0] + [60.0, -30.0, 10.0],
                field_cal_mgauss=rng.normal(size=3) * 150.0,
                residual_norm_mgauss=float(abs(rng.normal(3.0, 1.0))),
                excitation=float("nan") if i < 5 else 0.2,
                theta_sigma_mgauss=(sd, sd, sd),
            )
        )
    return out, truth


def read_rrd(path: Path) -> dict[str, dict[str, np.ndarray]]:
    """Entity path -> {"t_s": times (s, on TIMELINE), "values": each row's scalar, vector or text}."""
    from rerun.chunk import RrdReader

    cols: dict[str, dict[str, list[Any]]] = defaultdict(lambda: {"t_s": [], "values": []})
    for chunk in RrdReader(str(path)).stream():
        rb = chunk.to_record_batch()
        names = rb.schema.names
        value_col = next(
            (c for c in names if c.endswith("Scalars:scalars") or c.endswith("TextLog:text")), None
        )
        if value_col is None or TIMELINE not in names:
            continue
        times = rb.column(TIMELINE).cast("int64").to_numpy(zero_copy_only=False) * 1e-9
        values = rb.column(value_col).to_pylist()
        entry = cols[chunk.entity_path]
        entry["t_s"].extend(times.tolist())
        entry["values"].extend((v[0] if len(v) == 1 else v) if isinstance(v, list) else v for v in values)
    result: dict[str, dict[str, np.ndarray]] = {}
    for path_, entry in cols.items():
        order = np.argsort(np.asarray(entry["t_s"]), kind="stable")
        result[path_] = {k: np.asarray(v)[order] for k, v in entry.items()}
    return result


def _points3d_rows(path: Path, entity: str) -> list[list[object]]:
    from rerun.chunk import RrdReader

    rows: list[list[object]] = []
    for chunk in RrdReader(str(path)).stream():
        if chunk.entity_path == entity:
            rb = chunk.to_record_batch()
            rows.extend(rb.column("Points3D:positions").to_pylist())
    return rows


# -- the lazy import ----------------------------------------------------------------------------------------


def test_open_viz_none_does_not_import_rerun() -> None:
    code = (
        "import sys\n"
        "import numpy as np\n"
        "from magcomp.adapters.rerun_viz import open_viz, NullViz\n"
        "v = open_viz(None, live=False)\n"
        "assert isinstance(v, NullViz)\n"
        "v.log_estimates([]); v.log_truth_heading(np.zeros(2), np.zeros(2))\n"
        "v.log_text(0.0, 'x'); v.close()\n"
        "print('rerun' in sys.modules, any(m.startswith('rerun') for m in sys.modules))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=60, check=True
    )
    assert out.stdout.split() == ["False", "False"], out.stdout + out.stderr


def test_null_viz_satisfies_the_viz_protocol() -> None:
    assert isinstance(NullViz(), Viz)
    assert NullViz().url is None and NullViz().keeps_serving is False


# -- modes --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "bad",
    [
        "",
        "spawnx",
        "serve=9000",
        "save",
        "save=out.txt",
        "save=/nonexistent-dir-h6/x.rrd",
        "connect=",
        "connect=ftp://x",
        "connect=hostonly",
        "web",
    ],
)
def test_invalid_mode_raises_one_line_magcomp_error(bad: str) -> None:
    with pytest.raises(MagcompError) as info:
        parse_mode(bad, environ={"DISPLAY": ":0"})
    message = str(info.value)
    assert message.startswith("--rerun") and "\n" not in message


def test_valid_modes_parse_to_their_targets(tmp_path: Path) -> None:
    display = {"DISPLAY": ":0"}
    assert parse_mode("spawn", display).kind == "spawn"
    assert parse_mode("serve", {}).kind == "serve"
    assert parse_mode("connect", {}).target == "rerun+http://127.0.0.1:9876/proxy"
    assert parse_mode("connect=10.0.0.2:9999", {}).target == "rerun+http://10.0.0.2:9999/proxy"
    assert parse_mode("connect=rerun+https://h:1/proxy", {}).target == "rerun+https://h:1/proxy"
    saved = parse_mode(f"save={tmp_path / 'a.rrd'}", {})
    assert (saved.kind, saved.target) == ("save", str(tmp_path / "a.rrd"))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the display check applies on Linux")
def test_demo_default_is_serve_without_a_display_and_says_why() -> None:
    headless = default_mode_for_demo({})
    assert headless.mode == "serve" and "DISPLAY" in headless.reason
    assert default_mode_for_demo({"WAYLAND_DISPLAY": "wayland-0"}).mode == "spawn"
    auto = parse_mode("auto", {})
    assert auto.kind == "serve" and auto.reason == headless.reason
    with pytest.raises(MagcompError, match="display"):
        parse_mode("spawn", {})


def test_rerun_argument_without_value_means_auto() -> None:
    parser = argparse.ArgumentParser()
    add_rerun_argument(parser)
    assert parser.parse_args([]).rerun is None
    assert parser.parse_args(["--rerun"]).rerun == "auto"
    assert parser.parse_args(["--rerun", "save=x.rrd"]).rerun == "save=x.rrd"


# -- pure helpers -------------------------------------------------------------------------------------------


def test_truth_heading_interpolates_across_north_without_jumping() -> None:
    truth = TruthHeading()
    truth.add(np.array([0.0, 1.0]), np.array([350.0, 10.0]))  # turning right through north
    truth.add(np.array([2.0]), np.array([30.0]))
    got = truth.at(np.array([0.5, 1.5, 2.5, -1.0]))
    np.testing.assert_allclose(got[:2], [0.0, 20.0], atol=1e-9)
    assert np.isnan(got[2:]).all()  # no extrapolation outside the truth's span


def test_wrap_deg_gives_smallest_signed_difference() -> None:
    np.testing.assert_allclose(
        wrap_deg(np.array([359.0 - 1.0, 1.0 - 359.0, 180.0, -190.0])), [-2.0, 2.0, -180.0, 170.0]
    )


def test_stream_decimator_bounds_points_and_spans_the_whole_stream() -> None:
    pick = StreamDecimator(cap=100)
    n = 10_000
    kept = np.flatnonzero([pick.accept() for _ in range(n)])
    assert kept[0] == 0 and kept[-1] >= n - pick.stride  # reaches the end of the stream
    assert len(kept) <= 100 * (1 + np.log2(n / 100)) + 1
    np.testing.assert_array_equal(kept[:100], np.arange(100))  # dense at first, then halving
    assert np.all(np.diff(kept)[100:199] == 2)  # then every 2nd sample for the next 100


def test_flags_text_names_each_bit_and_changes_are_found() -> None:
    assert flags_text(0) == "none"
    assert flags_text(FLAG_CALIBRATED | FLAG_THETA_CONVERGED) == "CALIBRATED|THETA_CONVERGED"
    assert flags_text(1 | 1024) == "CALIBRATED|0x400"
    np.testing.assert_array_equal(flag_changes(np.array([1, 1, 3, 3, 1])), [0, 2, 4])


def test_bias_fit_canvas_puts_exact_model_points_on_the_fitted_line_eq11() -> None:
    rng = np.random.default_rng(7)
    thr2 = rng.uniform(0.0, 1.0, 200)
    bias = np.outer(thr2, THETA_TRUE)  # eq. (11) with no noise
    canvas = bias_fit_canvas(thr2, bias, THETA_TRUE)
    assert canvas.range_mgauss == nice_range(65.0) == 100.0
    assert canvas.lines is not None
    for k in range(3):
        (x0, y0), (x1, y1) = canvas.lines[k]
        on_line = y0 + (canvas.points[k, :, 0] - x0) * (y1 - y0) / (x1 - x0)
        np.testing.assert_allclose(canvas.points[k, :, 1], on_line, atol=1e-9)
        assert np.all(np.abs(canvas.points[k, :, 1]) <= 50.0)
    assert canvas.lines[2][1][1] < 0.0  # positive bias drawn upwards (Rerun's 2D y points down)


# -- recordings read back with rerun's reader ---------------------------------------------------------------


def _drive_replay(path: Path, estimates: list[HeadingEstimate], truth: np.ndarray) -> None:
    viz = open_viz(f"save={path}", live=False, recording_name="replay-test")
    assert viz.url == str(path) and viz.notice is not None and str(path) in viz.notice
    t = np.array([e.t_s for e in estimates])
    viz.log_estimates(estimates)
    viz.log_truth_heading(t, truth)  # after the estimates: the errors must still be sent
    viz.log_reference_theta(THETA_TRUE + 1.5, THETA_TRUE)
    viz.log_power(
        t, np.array([e.throttle_01 for e in estimates]), np.full(t.shape, np.nan), np.full(t.shape, 12.0)
    )
    thr2 = np.linspace(0.0, 1.0, 50)
    viz.log_bias_fit(thr2, np.outer(thr2, THETA_TRUE), THETA_TRUE)
    viz.log_calibration_cloud(np.ones((10, 3)), np.zeros((10, 3)))
    viz.log_text(t[3], "observer reset")
    viz.close()


def test_saved_replay_recording_holds_one_row_per_estimate_and_final_theta(tmp_path: Path) -> None:
    estimates, truth = synthetic_estimates(400, seed=11)
    path = tmp_path / "replay.rrd"
    _drive_replay(path, estimates, truth)
    data = read_rrd(path)
    t = np.array([e.t_s for e in estimates])
    for k, ax in enumerate(AXES):
        series = data[f"/theta/{ax}"]
        assert len(series["values"]) == len(estimates)
        np.testing.assert_allclose(series["t_s"], t, atol=1e-9)
        assert series["values"][-1] == pytest.approx(estimates[-1].theta_mgauss[k], abs=1e-9)
        ref = data[f"/theta/offline/{ax}"]
        np.testing.assert_allclose(ref["values"], THETA_TRUE[k] + 1.5)
        assert ref["t_s"].min() == pytest.approx(t[0]) and ref["t_s"].max() == pytest.approx(t[-1])
    for name, attr in (("raw", "heading_raw_deg"), ("corrected", "heading_deg")):
        series = data[f"/heading/{name}"]
        assert len(series["values"]) == len(estimates)
        np.testing.assert_allclose(series["values"], [getattr(e, attr) for e in estimates])
    # Fig. 9 errors: corrected within the synthetic 0.5 deg noise; raw carries the 12 * throttle^2 deg error
    err_c = data["/heading_error/corrected"]["values"]
    err_r = data["/heading_error/raw"]["values"]
    thr = np.array([e.throttle_01 for e in estimates])
    assert len(err_c) == len(estimates) and np.max(np.abs(err_c)) < 2.5
    np.testing.assert_allclose(err_r, 12.0 * thr**2, atol=1e-6)
    assert "/power/current" not in data  # all-NaN current is not drawn
    flags = data["/status/flags"]["values"]
    assert list(flags) == ["flags: CALIBRATED", "flags: CALIBRATED|THETA_CONVERGED"]


def test_live_logging_matches_replay_row_for_row(tmp_path: Path) -> None:
    estimates, truth = synthetic_estimates(150, seed=12)
    t = np.array([e.t_s for e in estimates])
    live_path = tmp_path / "live.rrd"
    viz = open_viz(f"save={live_path}", live=True)
    viz.log_reference_theta(THETA_TRUE, None)  # before any estimate, as the demo does
    for i, est in enumerate(estimates):
        viz.log_truth_heading(t[i], truth[i])  # per sample, before its estimate
        viz.log_estimate(est)
    viz.close()
    replay_path = tmp_path / "replay.rrd"
    _drive_replay(replay_path, estimates, truth)
    live, replay = read_rrd(live_path), read_rrd(replay_path)
    for path_ in (
        "/theta/x",
        "/theta/y",
        "/theta/z",
        "/heading/raw",
        "/heading/corrected",
        "/bias/estimate",
    ):
        assert len(live[path_]["values"]) == len(estimates), path_
        np.testing.assert_allclose(live[path_]["t_s"], replay[path_]["t_s"], atol=1e-9)
        np.testing.assert_allclose(live[path_]["values"], replay[path_]["values"], atol=1e-12)
    np.testing.assert_allclose(
        live["/heading_error/raw"]["values"], replay["/heading_error/raw"]["values"], atol=1e-9
    )
    n_points = sum(len(v) for v in _points3d_rows(live_path, "/mag/flight/calibrated"))
    assert n_points == len(estimates)  # below the cap every sample is drawn, each once
    bias = np.array([e.bias_mgauss for e in estimates])
    np.testing.assert_allclose(live["/bias/estimate"]["values"], bias, atol=1e-12)  # 3 series, one entity
    assert live["/theta/offline/x"]["t_s"].max() >= t[-1] - 1.0  # the reference line follows the live run


def test_the_theta_band_is_theta_plus_minus_sigma_where_sigma_is_known(tmp_path: Path) -> None:
    estimates, truth = synthetic_estimates(300, seed=13)
    path = tmp_path / "band.rrd"
    _drive_replay(path, estimates, truth)
    data = read_rrd(path)
    known = [e for e in estimates if np.isfinite(e.theta_sigma_mgauss[0])]
    assert 0 < len(known) < len(estimates)
    for k, ax in enumerate(AXES):
        band = data[f"/theta/band/{ax}"]
        assert len(band["values"]) == len(known)  # no row where the estimate carries no sigma
        np.testing.assert_allclose(band["t_s"], [e.t_s for e in known], atol=1e-9)
        lo_hi = np.asarray(band["values"], dtype=float)
        theta = np.array([e.theta_mgauss[k] for e in known])
        sigma = np.array([e.theta_sigma_mgauss[k] for e in known])
        np.testing.assert_allclose(lo_hi[:, 0], theta - sigma, atol=1e-9)
        np.testing.assert_allclose(lo_hi[:, 1], theta + sigma, atol=1e-9)
        width = lo_hi[:, 1] - lo_hi[:, 0]
        assert width[-1] < 0.1 * width[0]  # the band narrows as theta converges


def test_theta_band_leaves_out_unknown_sigma_and_clamps_huge_ones() -> None:
    theta = np.array([[10.0, -5.0, 0.0], [np.nan, 1.0, 2.0]])
    sigma = np.array([[2.0, np.nan, 1e9], [1.0, -1.0, 0.5]])
    rows, edges = theta_band(theta, sigma)
    assert rows.tolist() == [[True, False, True], [False, False, True]]
    np.testing.assert_allclose(edges[0, 0], [8.0, 12.0])
    np.testing.assert_allclose(edges[1, 2], [1.5, 2.5])
    assert edges[0, 2, 1] == 1e5 and edges[0, 2, 0] == -1e5


def _on_grid(x: float, p: float) -> bool:
    return abs(x / p - round(x / p)) < 1e-9


@pytest.mark.parametrize("seed", range(5))
def test_labelled_axis_range_holds_the_data_and_two_labelled_ticks(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(200):
        values = rng.normal(0.0, 10.0 ** rng.uniform(0.5, 3.5), rng.integers(1, 6)).tolist()
        lo, hi = labelled_axis_range(values, above=0.6)
        data_lo, data_hi = min([*values, 0.0]), max([*values, 0.0])
        span = max(data_hi - data_lo, 10.0)
        assert lo <= data_lo - 0.1 * span + 1e-9 and hi >= data_hi + 0.6 * span - 1e-9
        # a power of ten p (the ticks' grid) with both ends 4 % of the range beyond ticks on it, those ticks
        # at most 12 steps apart: every tick is >= 1/13 of the plot's height from the next, so it is labelled
        edge = 0.04 / 1.08 * (hi - lo)
        t_lo, t_hi = lo + edge, hi - edge
        top = 10.0 ** np.floor(np.log10(t_hi - t_lo))
        grids = [
            p
            for p in (top, top / 10.0)
            if (t_hi - t_lo) / p <= 12.0 + 1e-9 and _on_grid(t_lo, p) and _on_grid(t_hi, p)
        ]
        assert grids, (values, lo, hi)
    # the run's theta plot that showed a lone "0" tick: theta from -75 to 26 mgauss
    assert labelled_axis_range([-75.0, 26.0], above=0.6) == pytest.approx((-108.0, 108.0))


def test_live_power_samples_one_at_a_time_do_not_split_the_estimate_blocks(tmp_path: Path) -> None:
    """`run` logs each battery sample as it comes: the power rows are buffered like the estimates, so each
    entity gets a few chunks (one per 0.5 s of message time), not one per sample, which the web viewer took
    in at a fraction of real time."""
    from rerun.chunk import RrdReader

    estimates, _ = synthetic_estimates(300, seed=14)  # 6 s at 50 Hz
    path = tmp_path / "live.rrd"
    viz = open_viz(f"save={path}", live=True)
    for est in estimates:
        viz.log_estimate(est)
        viz.log_power(est.t_s, float("nan"), 20.0 * est.throttle_01**2, 12.0)
    viz.close()
    chunks: dict[str, int] = defaultdict(int)
    for chunk in RrdReader(str(path)).stream():
        chunks[chunk.entity_path] += 1
    span = estimates[-1].t_s - estimates[0].t_s
    most = int(span / 0.5) + 3  # a block per 0.5 s (+ the static style row and the last, partial block)
    for entity in ("/theta/x", "/heading/corrected", "/bias/estimate", "/power/current", "/power/voltage"):
        assert chunks[entity] <= most, (entity, chunks[entity], most)
    data = read_rrd(path)
    assert len(data["/theta/x"]["values"]) == len(estimates)  # every estimate still drawn
    current = data["/power/current"]
    assert 55 <= len(current["values"]) <= 61  # 10 Hz of message time over 6 s
    t = np.array([e.t_s for e in estimates])
    thr = np.interp(current["t_s"], t, [e.throttle_01 for e in estimates])
    np.testing.assert_allclose(current["values"], 20.0 * thr**2, atol=1e-9)
    assert "/power/throttle" not in data  # NaN throttle: not drawn


def test_bad_shapes_raise_magcomp_error(tmp_path: Path) -> None:
    viz = open_viz(f"save={tmp_path / 'bad.rrd'}", live=False)
    try:
        with pytest.raises(MagcompError, match="shape"):
            viz.log_bias_fit(np.zeros(4), np.zeros((4, 2)), None)
        with pytest.raises(MagcompError, match="times"):
            viz.log_truth_heading(np.zeros(3), np.zeros(2))
        with pytest.raises(MagcompError, match="3 components"):
            viz.log_reference_theta(np.zeros(2), None)
    finally:
        viz.close()


def test_serve_until_interrupt_waits_for_ctrl_c_only_when_the_viewer_lives_here() -> None:
    said: list[str] = []
    naps: list[float] = []

    def sleep(dt_s: float) -> None:
        naps.append(dt_s)
        if len(naps) == 3:
            raise KeyboardInterrupt

    serve_until_interrupt(NullViz(), said.append, sleep=sleep)  # nothing served: returns at once
    assert said == [] and naps == []

    class Serving(NullViz):
        keeps_serving = True

    serve_until_interrupt(Serving(), said.append, "msg", sleep=sleep)
    assert said == ["msg"] and naps == [1.0, 1.0, 1.0]
