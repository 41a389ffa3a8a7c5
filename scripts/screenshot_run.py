"""Screenshot `magcomp run --rerun serve`'s live view, fed by the simulator, in Debian's headless Chromium.

    .venv/bin/python scripts/screenshot_run.py [docs/img/run-web.png] [--duration S] [--speed X] [--wait S]

Starts `magcomp run --master udpin:127.0.0.1:PORT --rerun serve` (its own process group, a fresh state
directory), opens the printed URL in Chromium driven over the DevTools protocol, then plays the paper's
simulated flight (`magcomp simulate --link udpout:...`) into it. Once the simulator has finished, it waits
until the heading plot is drawn and the picture stops changing, saves a 1600x1000 PNG (quantised to 256
colours to keep it small), and stops both processes with ^C. The `run` process is live the whole time and
the page has followed it, so the picture is what a pilot sees at the end of the flight, taken within
--wait seconds of its end (the longer the wait, the larger the "latency" in the viewer's top bar: the age
of the newest data). Needs chromium, websocket-client and pillow; the Chromium/CDP helpers are those of
tests/integration/test_rerun_browser.py.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from scripts.screenshot_demo import STABLE_FRACTION, URL_PREFIX  # noqa: E402 - needs REPO on sys.path
from tests.integration.test_rerun_browser import (  # noqa: E402
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


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class RunProcess:
    """`magcomp run --rerun serve` in its own session; stdout lines collected by a reader thread."""

    def __init__(self, port: int, state_dir: str) -> None:
        env = dict(os.environ, RERUN_ANALYTICS="0", PYTHONPATH=str(REPO))
        cmd = [sys.executable, "-m", "magcomp", "run", "--master", f"udpin:127.0.0.1:{port}",
               "--state-dir", state_dir, "--rerun", "serve"]  # fmt: skip
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     cwd=REPO, env=env, start_new_session=True)  # fmt: skip
        self.lines: list[str] = []
        self.url = ""
        self._url_ready = threading.Event()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            line = raw.rstrip("\n")
            self.lines.append(line)
            if line.startswith(URL_PREFIX):
                self.url = line[len(URL_PREFIX) :].strip()
                self._url_ready.set()
        self._url_ready.set()

    def wait_url(self, timeout_s: float) -> str:
        if not self._url_ready.wait(timeout_s) or not self.url:
            raise RuntimeError(f"run printed no viewer URL; output: {self.lines[-10:]}")
        return self.url

    def stop(self) -> None:
        if self.proc.poll() is None:
            try:  # ^C: run saves its state, prints its summary and closes the viewer
                os.killpg(self.proc.pid, signal.SIGINT)
                self.proc.wait(timeout=15)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                pass
        _kill_group(self.proc)


def open_page(cdp: _Cdp, url: str) -> None:
    cdp.call("Page.enable")
    cdp.call("Emulation.setDeviceMetricsOverride", width=WINDOW[0], height=WINDOW[1], deviceScaleFactor=1,
             mobile=False)  # fmt: skip
    cdp.call("Page.navigate", url=url)


def settle(cdp: _Cdp, wait_s: float) -> tuple[np.ndarray, dict[str, int]]:
    """Screenshots 4 s apart until the raw heading is drawn and the picture stops changing (or ``wait_s``)."""
    from magcomp.adapters.rerun_viz import COLOR_CORRECTED, COLOR_RAW

    start = time.monotonic()
    previous: np.ndarray | None = None
    while True:
        img = _screenshot(cdp)
        region = heading_region(img)
        counts = {"raw": count_colour(region, COLOR_RAW), "corrected": count_colour(region, COLOR_CORRECTED)}
        if previous is not None:
            changed = float(np.any(img != previous, axis=2).mean())
            counts["changed_permille"] = int(1000 * changed)
            if counts["raw"] >= MIN_LINE_PIXELS and changed < STABLE_FRACTION:
                return img, counts
        if time.monotonic() - start > wait_s:
            return img, counts
        previous = img
        time.sleep(4.0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", default=str(REPO / "docs" / "img" / "run-web.png"))
    parser.add_argument("--duration", type=float, default=150.0, help="simulated seconds (paper scenario)")
    parser.add_argument("--speed", type=float, default=5.0, help="simulator speed, x real time")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--wait", type=float, default=30.0,
                        help="longest wait after the flight for the view to settle (s)")  # fmt: skip
    args = parser.parse_args(argv)
    from PIL import Image

    binary = _chromium()
    if binary is None:
        print("no chromium binary (apt-get install chromium)", file=sys.stderr)
        return 2
    port = _free_udp_port()
    with tempfile.TemporaryDirectory(prefix="magcomp-run-shot-") as state:
        run = RunProcess(port, state)
        try:
            url = run.wait_url(60.0)
            _wait_http(url.split("?", 1)[0], 30.0)
            with _chromium_page(binary) as cdp:
                # the page is open before the flight starts: the view fills live as the run goes
                open_page(cdp, url)
                time.sleep(12.0)  # the WASM viewer loads and compiles
                sim = subprocess.run(
                    [sys.executable, "-m", "magcomp", "simulate", "--link", f"udpout:127.0.0.1:{port}",
                     "--speed", f"{args.speed:g}", "--duration", f"{args.duration:g}", "--seed",
                     str(args.seed)],
                    cwd=REPO, capture_output=True, text=True, timeout=args.duration / args.speed + 120.0,
                    env=dict(os.environ, PYTHONPATH=str(REPO)),
                )  # fmt: skip
                if sim.returncode != 0:
                    raise RuntimeError(f"simulate failed: {sim.stderr[-2000:]}")
                img, counts = settle(cdp, args.wait)
            out = Path(args.out)
            out.parent.mkdir(parents=True, exist_ok=True)
            picture = Image.fromarray(img.astype(np.uint8)).quantize(colors=256, dither=Image.Dither.NONE)
            picture.save(out, optimize=True)
            print(f"{out}: {img.shape[1]}x{img.shape[0]}, {out.stat().st_size} bytes, {counts}")
        finally:
            run.stop()
            print("\n".join(run.lines[-8:]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
