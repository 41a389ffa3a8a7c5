"""Screenshot `magcomp demo --rerun serve` in Debian's headless Chromium (the picture in docs/demo.md).

    .venv/bin/python scripts/screenshot_demo.py [docs/img/demo-web.png] [--duration 90] [--wait 300]

Runs the demo as a child process (its own process group), waits for the run to finish (the demo then
keeps serving the web viewer), opens the printed URL in Chromium driven over the DevTools protocol, waits
until the heading plot is drawn and the picture stops changing, saves a 1600x1000 PNG, prints the demo's
summary and stops both processes. On 2 busy cores the web viewer (software WebGL) needs 2-4 minutes to
take in the ~100k rows a live run logs; the view is complete when the latency note in its top bar is gone.
Needs chromium, websocket-client and pillow. The Chromium/CDP helpers are those of
tests/integration/test_rerun_browser.py.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.integration.test_rerun_browser import (  # noqa: E402 - needs REPO on sys.path
    MIN_LINE_PIXELS,
    WINDOW,
    _Cdp,
    _chromium,
    _chromium_page,
    _kill_group,
    _screenshot,
    _wait_http,
    count_colour,
    heading_region,
)

URL_PREFIX = "Rerun web viewer: "
DONE_PREFIX = "the viewer keeps serving at "
STABLE_FRACTION = 0.002
"""The view is settled when fewer than this fraction of pixels change between two screenshots 4 s apart."""


class ServingProcess:
    """A magcomp command serving the web viewer (``cmd``: its arguments after ``magcomp``), in its own
    session; stdout lines collected by a reader thread, the viewer URL taken from the first
    ``Rerun web viewer:`` line, ``finished`` set at ``the viewer keeps serving`` (demo) or at the end."""

    def __init__(self, cmd: list[str]) -> None:
        env = dict(os.environ, RERUN_ANALYTICS="0", PYTHONPATH=str(REPO))
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "magcomp", *cmd], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
            text=True, cwd=REPO, env=env, start_new_session=True,
        )  # fmt: skip
        self.lines: list[str] = []
        self.url = ""
        self.finished = threading.Event()
        self._url_ready = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            line = raw.rstrip("\n")
            self.lines.append(line)
            if line.startswith(URL_PREFIX) and not self.url:
                self.url = line[len(URL_PREFIX) :].strip()
                self._url_ready.set()
            if line.startswith(DONE_PREFIX):
                self.finished.set()
        self._url_ready.set()
        self.finished.set()

    def wait_url(self, timeout_s: float) -> str:
        if not self._url_ready.wait(timeout_s) or not self.url:
            raise RuntimeError(f"no viewer URL printed; output: {self.lines[-10:]}")
        return self.url

    def summary(self) -> list[str]:
        """The lines the demo printed after the run (between the 'demo: simulating' line and the last)."""
        start = next((i for i, x in enumerate(self.lines) if x.startswith("demo: simulating")), -1)
        return [x for x in self.lines[start + 1 :] if not x.startswith(DONE_PREFIX)]

    def stop(self) -> None:
        if self.proc.poll() is None:
            try:  # ^C: the command closes the viewer itself (run: saves its state, prints its summary)
                os.killpg(self.proc.pid, signal.SIGINT)
                self.proc.wait(timeout=15)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                pass
        _kill_group(self.proc)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


def open_page(cdp: _Cdp, url: str) -> None:
    """Navigate the page to ``url`` at the picture's size."""
    cdp.call("Page.enable")
    cdp.call("Emulation.setDeviceMetricsOverride", width=WINDOW[0], height=WINDOW[1], deviceScaleFactor=1,
             mobile=False)  # fmt: skip
    cdp.call("Page.navigate", url=url)


def settle(cdp: _Cdp, wait_s: float) -> tuple[np.ndarray, dict[str, int]]:
    """Screenshots 4 s apart until the heading lines are drawn and the view is still (or ``wait_s``)."""
    from magcomp.adapters.rerun_viz import COLOR_CORRECTED, COLOR_RAW

    start = time.monotonic()
    previous: np.ndarray | None = None
    while True:
        img = _screenshot(cdp)
        region = heading_region(img)
        counts = {"raw": count_colour(region, COLOR_RAW), "corrected": count_colour(region, COLOR_CORRECTED)}
        # the corrected heading lies under the truth line once theta has converged: wait for the raw one
        drawn = counts["raw"] >= MIN_LINE_PIXELS
        if previous is not None:
            changed = float(np.any(img != previous, axis=2).mean())
            counts["changed_permille"] = int(1000 * changed)
            if drawn and changed < STABLE_FRACTION:
                return img, counts
        if time.monotonic() - start > wait_s:
            return img, counts
        previous = img
        time.sleep(4.0)


def capture(cdp: _Cdp, url: str, wait_s: float) -> tuple[np.ndarray, dict[str, int]]:
    """Open ``url``; screenshot until the heading lines are drawn and the view is still (or ``wait_s``)."""
    start = time.monotonic()
    open_page(cdp, url)
    time.sleep(12.0)  # the WASM viewer loads and compiles; nothing to see before
    return settle(cdp, wait_s - (time.monotonic() - start))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", default=str(REPO / "docs" / "img" / "demo-web.png"))
    parser.add_argument("--duration", type=float, default=90.0)
    parser.add_argument("--speed", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--wait", type=float, default=300.0, help="longest wait for the view to settle (s)")
    args = parser.parse_args(argv)
    from PIL import Image

    binary = _chromium()
    if binary is None:
        print("no chromium binary (apt-get install chromium)", file=sys.stderr)
        return 2
    demo = ServingProcess(["demo", "--rerun", "serve", "--duration", f"{args.duration:g}", "--speed",
                           f"{args.speed:g}", "--seed", str(args.seed)])  # fmt: skip
    try:
        url = demo.wait_url(60.0)
        base = url.split("?", 1)[0]
        _wait_http(base, 30.0)
        if not demo.finished.wait(args.duration / args.speed + 120.0) or demo.proc.poll() is not None:
            raise RuntimeError(f"the demo did not finish its run; output: {demo.lines[-10:]}")
        with _chromium_page(binary) as cdp:
            img, counts = capture(cdp, url, args.wait)
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        picture = Image.fromarray(img.astype(np.uint8)).quantize(colors=256, dither=Image.Dither.NONE)
        picture.save(out, optimize=True)  # 256 colours: a third of the size, the same to the eye
        print(f"{out}: {img.shape[1]}x{img.shape[0]}, {counts}")
        print("\n".join(demo.summary()))
    finally:
        demo.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
