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
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from scripts.screenshot_demo import ServingProcess, open_page, settle  # noqa: E402 - needs REPO on sys.path
from tests.integration.test_rerun_browser import _chromium, _chromium_page, _wait_http  # noqa: E402


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", default=str(REPO / "docs" / "img" / "run-web.png"))
    parser.add_argument("--duration", type=float, default=150.0, help="simulated seconds (paper scenario)")
    parser.add_argument("--speed", type=float, default=1.0, help="simulator speed, x real time")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--wait", type=float, default=150.0,
                        help="longest wait after the flight for the view to settle (s)")  # fmt: skip
    args = parser.parse_args(argv)
    from PIL import Image

    binary = _chromium()
    if binary is None:
        print("no chromium binary (apt-get install chromium)", file=sys.stderr)
        return 2
    port = _free_udp_port()
    with tempfile.TemporaryDirectory(prefix="magcomp-run-shot-") as state:
        run = ServingProcess(["run", "--master", f"udpin:127.0.0.1:{port}", "--state-dir", state, "--rerun",
                              "serve"])  # fmt: skip
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
