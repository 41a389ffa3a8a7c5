"""The served Rerun web viewer, opened in Debian's headless Chromium, draws the heading plot.

A child process opens ``--rerun serve`` (magcomp.adapters.rerun_viz) on free ports and logs a synthetic
run; Chromium is driven over the DevTools protocol (websocket-client), because ``--screenshot`` returns
before the WASM viewer has started. The check is on pixels: the raw and corrected heading colours must be
drawn inside the heading view's region of the screenshot. About 20-60 s on 2 cores (SwiftShader WebGL2).

Run as a script (``python tests/integration/test_rerun_browser.py OUT.png``) to save a screenshot.
"""

from __future__ import annotations

import base64
import io
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
WINDOW = (1600, 1000)
MIN_LINE_PIXELS = 500
"""A series drawn across the heading view covers ~1500+ pixels; its legend dot alone ~50."""

# The child: serves the viewer and logs a synthetic run (replay columns), prints the URL, waits to be killed.
SERVER_SCRIPT = r"""
import sys, time
import numpy as np
from magcomp.adapters.rerun_viz import open_viz
from magcomp.core.types import HeadingEstimate

rng = np.random.default_rng(5)
n = 1500
t = np.arange(n) * 0.04
theta_true = np.array([45.0, -30.0, 70.0])
thr = np.clip(0.2 + 0.8 * (t / t[-1]), 0.0, 1.0)
yaw_true = (40.0 * np.sin(t / 6.0) + 180.0) % 360.0
est = []
for i in range(n):
    th = theta_true * (1.0 - np.exp(-t[i] / 8.0))
    sd = float(30.0 * np.exp(-t[i] / 8.0) + 1.0)  # the band narrows as theta converges
    raw = yaw_true[i] + 25.0 * thr[i] ** 2 * np.sin(np.radians(yaw_true[i]))
    cor = yaw_true[i] + rng.normal(0.0, 0.8)
    u = rng.normal(size=3); u /= np.linalg.norm(u)
    est.append(HeadingEstimate(
        t_s=float(t[i]), mag_index=0, heading_deg=float(cor % 360.0), heading_raw_deg=float(raw % 360.0),
        theta_mgauss=th, bias_mgauss=th * thr[i] ** 2, throttle_01=float(thr[i]), flags=1,
        field_raw_mgauss=u * [420.0, 330.0, 260.0] + [120.0, -60.0, 40.0], field_cal_mgauss=u * 480.0,
        residual_norm_mgauss=5.0, excitation=0.3, theta_sigma_mgauss=(sd, sd, sd)))
viz = open_viz("serve", live=False, recording_name="browser-test",
               grpc_port=int(sys.argv[1]), web_port=int(sys.argv[2]))
viz.log_estimates(est)
viz.log_truth_heading(t, yaw_true)
viz.log_reference_theta(theta_true + 2.0, theta_true)
viz.log_power(t, thr, 30.0 * thr ** 2, 12.6 - 0.4 * t / t[-1])
thr2 = np.linspace(0.0, 1.0, 300)
viz.log_bias_fit(thr2, np.outer(thr2, theta_true) + rng.normal(0.0, 2.0, (300, 3)), theta_true)
print(viz.url, flush=True)
while True:
    time.sleep(1.0)
"""


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def _kill_group(proc: subprocess.Popen[Any]) -> None:
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)


@contextmanager
def _served_viewer() -> Iterator[str]:
    grpc_port, web_port = _free_port(), _free_port()
    env = dict(os.environ, PYTHONPATH=str(REPO), RERUN_ANALYTICS="0")
    proc = subprocess.Popen(
        [sys.executable, "-c", SERVER_SCRIPT, str(grpc_port), str(web_port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env=env,
        cwd=REPO,
    )
    try:
        assert proc.stdout is not None
        url = proc.stdout.readline().strip()
        if not url.startswith("http://"):
            err = proc.stderr.read() if proc.poll() is not None and proc.stderr else ""
            raise AssertionError(f"the serving child printed {url!r}; stderr: {err[-2000:]}")
        _wait_http(f"http://127.0.0.1:{web_port}/", 30.0)
        yield url
    finally:
        _kill_group(proc)
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()


def _wait_http(url: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with urllib.request.urlopen(url, timeout=2.0):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


class _Cdp:
    """The smallest DevTools-protocol client: one page target, request/response by id, events ignored."""

    def __init__(self, ws_url: str) -> None:
        import websocket

        self._ws = websocket.create_connection(ws_url, timeout=120, suppress_origin=True)
        self._next = 0

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        self._next += 1
        mid = self._next
        self._ws.send(json.dumps({"id": mid, "method": method, "params": params}))
        while True:
            msg = json.loads(self._ws.recv())
            if msg.get("id") == mid:
                if "error" in msg:
                    raise RuntimeError(f"CDP {method}: {msg['error']}")
                result: dict[str, Any] = msg.get("result", {})
                return result

    def close(self) -> None:
        self._ws.close()


@contextmanager
def _chromium_page(binary: str) -> Iterator[_Cdp]:
    port = _free_port()
    with tempfile.TemporaryDirectory(prefix="magcomp-chromium-") as profile:
        proc = subprocess.Popen(
            [
                binary,
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--enable-unsafe-swiftshader",
                "--use-angle=swiftshader",
                f"--window-size={WINDOW[0]},{WINDOW[1]}",
                f"--user-data-dir={profile}",
                "--remote-debugging-address=127.0.0.1",
                f"--remote-debugging-port={port}",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
        cdp: _Cdp | None = None
        try:
            deadline = time.monotonic() + 30.0
            ws_url = ""
            while not ws_url:
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=2.0) as r:
                        targets = json.loads(r.read())
                    ws_url = next((t["webSocketDebuggerUrl"] for t in targets if t.get("type") == "page"), "")
                except OSError:
                    pass
                if not ws_url:
                    if time.monotonic() > deadline or proc.poll() is not None:
                        raise AssertionError("Chromium did not open its DevTools endpoint within 30 s")
                    time.sleep(0.3)
            cdp = _Cdp(ws_url)
            yield cdp
        finally:
            if cdp is not None:
                with suppress(Exception):  # a clean exit lets Chromium reap its own helper processes
                    cdp.call("Browser.close")
                cdp.close()
                with suppress(subprocess.TimeoutExpired):
                    proc.wait(timeout=10)
            _kill_group(proc)


def _screenshot(cdp: _Cdp) -> np.ndarray:
    from PIL import Image

    data = cdp.call("Page.captureScreenshot", format="png")["data"]
    png = base64.b64decode(data)
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


def count_colour(img: np.ndarray, rgb: tuple[int, int, int], tol: int = 40) -> int:
    """Pixels within ``tol`` of ``rgb`` in every channel."""
    return int(np.all(np.abs(img - np.asarray(rgb, dtype=np.int16)) <= tol, axis=2).sum())


def heading_region(img: np.ndarray) -> np.ndarray:
    """The heading view: top of the left column (3/5 of the width, 3/8 of the height below the top bar)."""
    h, w = img.shape[:2]
    return img[int(0.04 * h) : int(0.40 * h), : int(0.58 * w)]


def capture_served_view(wait_s: float = 90.0) -> tuple[np.ndarray, dict[str, int]]:
    """Serve the synthetic run, open it in Chromium, screenshot until the heading shows (or ``wait_s``)."""
    from magcomp.adapters.rerun_viz import COLOR_CORRECTED, COLOR_RAW

    binary = _chromium()
    if binary is None:
        raise RuntimeError("no chromium binary")
    with _served_viewer() as url, _chromium_page(binary) as cdp:
        cdp.call("Page.enable")
        cdp.call(
            "Emulation.setDeviceMetricsOverride",
            width=WINDOW[0],
            height=WINDOW[1],
            deviceScaleFactor=1,
            mobile=False,
        )
        cdp.call("Page.navigate", url=url)
        start = time.monotonic()
        time.sleep(12.0)  # the WASM bundle loads and compiles on real time; nothing useful to see before this
        while True:
            img = _screenshot(cdp)
            region = heading_region(img)
            counts = {
                "raw": count_colour(region, COLOR_RAW),
                "corrected": count_colour(region, COLOR_CORRECTED),
            }
            if min(counts.values()) >= MIN_LINE_PIXELS or time.monotonic() - start > wait_s:
                return img, counts
            time.sleep(3.0)


def test_serve_mode_hands_back_a_loopback_url_that_serves_the_web_viewer() -> None:
    with _served_viewer() as url:
        assert url.startswith("http://127.0.0.1:") and "?url=rerun%2Bhttp%3A%2F%2F" in url
        with urllib.request.urlopen(url, timeout=10.0) as page:
            assert page.status == 200
            html = page.read().decode("utf-8", "replace").lower()
    assert "<title>rerun viewer</title>" in html and "re_viewer_bg.wasm" in html


@pytest.mark.browser
@pytest.mark.slow
def test_served_web_viewer_draws_heading_plot_in_headless_chromium() -> None:
    if _chromium() is None:
        pytest.skip("Chromium is not installed (apt-get install chromium); the web-viewer check needs it")
    pytest.importorskip("websocket", reason="websocket-client is needed to drive Chromium over CDP")
    pytest.importorskip("PIL", reason="pillow is needed to read the screenshot")
    img, counts = capture_served_view()
    # the heading view shows both series; a page stuck on the loading splash has neither colour
    assert counts["raw"] >= MIN_LINE_PIXELS, counts
    assert counts["corrected"] >= MIN_LINE_PIXELS, counts
    # and the view is not one colour block: the plot background dominates, the lines are thin
    region = heading_region(img)
    assert counts["raw"] + counts["corrected"] < 0.5 * region.shape[0] * region.shape[1], counts


if __name__ == "__main__":  # save a screenshot for docs/img
    from PIL import Image

    out = Path(sys.argv[1] if len(sys.argv) > 1 else "rerun-web.png")
    picture, found = capture_served_view()
    Image.fromarray(picture.astype(np.uint8)).save(out)
    print(out, found)
