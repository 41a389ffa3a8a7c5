"""`magcomp run --rerun save=x.rrd` against the simulator (the paper's flight over loopback UDP): the
recording holds what the live view draws (issue 27): theta-hat converging with its +-1 sigma band, the bias
theta * throttle^2, the battery current and voltage, each with data rows read back with rerun's own reader.
The picture of the same view served to a browser is docs/img/run-web.png (scripts/screenshot_run.py)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from magcomp.service.demo import free_udp_port
from tests.waiting import LineReader, wait_for

REPO = Path(__file__).resolve().parents[2]


def _rows(path: Path) -> dict[str, tuple[np.ndarray, list[list[float]]]]:
    """entity -> (times s, values per row) for every Scalars entity on the msg_time timeline."""
    from rerun.chunk import RrdReader

    from magcomp.adapters.rerun_viz import TIMELINE

    got: dict[str, tuple[list[float], list[list[float]]]] = {}
    for chunk in RrdReader(str(path)).stream():
        rb = chunk.to_record_batch()
        col = next((c for c in rb.schema.names if c.endswith("Scalars:scalars")), None)
        if col is None or TIMELINE not in rb.schema.names:
            continue
        t = (rb.column(TIMELINE).cast("int64").to_numpy(zero_copy_only=False) * 1e-9).tolist()
        entry = got.setdefault(chunk.entity_path, ([], []))
        entry[0].extend(t)
        entry[1].extend(list(v) for v in rb.column(col).to_pylist())
    out = {}
    for name, (t, v) in got.items():
        order = np.argsort(t, kind="stable")
        out[name] = (np.asarray(t)[order], [v[i] for i in order])
    return out


@pytest.mark.slow
def test_run_recording_holds_theta_with_its_band_the_bias_current_and_voltage(tmp_path: Path) -> None:
    from magcomp.adapters.mavlink_emit import stream_to_link
    from magcomp.sim import SimConfig, simulate

    result = simulate(SimConfig(scenario="paper", duration_s=90.0, seed=0))
    port = free_udp_port()
    rrd = tmp_path / "run.rrd"
    env = dict(os.environ, PYTHONPATH=str(REPO), RERUN_ANALYTICS="0")
    proc = subprocess.Popen(
        [sys.executable, "-m", "magcomp", "run", "--master", f"udpin:127.0.0.1:{port}", "--state-dir",
         str(tmp_path / "state"), "--rerun", f"save={rrd}"],
        stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO,
        env=env, start_new_session=True,
    )  # fmt: skip
    assert proc.stdout is not None
    out = LineReader(proc.stdout)
    try:
        wait_for(lambda: out.has("listening on") or proc.poll() is not None, 60.0, "run to listen")
        link = stream_to_link(result, f"udpout:127.0.0.1:{port}", speed=10.0)
        assert link.received.get("MAGCOMP_HEADING", 0) > 0
        os.killpg(proc.pid, signal.SIGINT)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
    assert proc.returncode == 0, out.text()[-3000:]
    rows = _rows(rrd)
    truth_theta = np.asarray(result.compasses[0].theta_mgauss, dtype=float)

    for k, ax in enumerate(("x", "y", "z")):
        t_th, theta_rows = rows[f"/theta/{ax}"]
        theta = np.array([v[0] for v in theta_rows])
        assert theta.shape[0] > 2000, ax  # one row per estimate of the primary compass
        t_b, band_rows = rows[f"/theta/band/{ax}"]
        band = np.array(band_rows)
        assert band.shape[0] > 300 and band.shape[1] == 2, ax  # (theta - sigma, theta + sigma) at 10 Hz
        at = np.searchsorted(t_th, t_b)
        ok = (at < t_th.shape[0]) & (t_th[np.minimum(at, t_th.shape[0] - 1)] == t_b)
        assert ok.mean() > 0.99  # every band row sits on an estimate's time
        th = theta[at[ok]]
        np.testing.assert_allclose(band[ok].mean(axis=1), th, atol=1e-6)  # centred on theta-hat
        width = band[ok, 1] - band[ok, 0]
        assert np.all(width >= 0.0)
        # converging: the band's last width is a small part of its width at the start of the motor run,
        # and the final theta-hat is within 3 final sigma (+ 2 mgauss) of the simulated truth
        assert width[-1] < 0.2 * np.max(width), (ax, width[-1], np.max(width))
        assert abs(th[-1] - truth_theta[k]) < 1.5 * width[-1] + 2.0, (ax, th[-1], truth_theta[k], width[-1])

    _, bias_rows = rows["/bias/estimate"]
    bias = np.array(bias_rows)
    assert bias.shape[0] > 2000 and bias.shape[1] == 3
    full = np.asarray(result.samples.throttle_01).max()
    assert np.max(np.abs(bias[:, 0])) > 0.8 * abs(truth_theta[0]) * full**2  # the bias at full throttle

    s = result.samples
    for name, sim in (("current", s.current_a), ("voltage", s.voltage_v)):
        _, p_rows = rows[f"/power/{name}"]
        values = np.array([v[0] for v in p_rows])
        assert values.shape[0] > 300 and np.all(np.isfinite(values)), name
        lo, hi = float(np.min(sim)), float(np.max(sim))
        margin = 0.05 * (hi - lo) + 0.1
        assert lo - margin <= values.min() and values.max() <= hi + margin, (name, values.min(), values.max())
        assert values.max() - values.min() > 0.5 * (hi - lo), name  # the whole flight's range is drawn
