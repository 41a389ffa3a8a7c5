"""A default replay does not import scipy.optimize (issue 13): the refined DPI fit of eq. (3) with the
field-norm constraint runs on the core's own Levenberg-Marquardt (magcomp/core/dpi.py), so a replay does not
pay scipy.optimize's start-up. One fresh interpreter runs the CLI's ``main`` on a simulated hand rotation
followed by a spin (the refined fit is made when the motors start) and lists what it loaded."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

_RUN = """
import contextlib, io, sys
from magcomp.cli import main
with contextlib.redirect_stdout(io.StringIO()):
    rc = main(sys.argv[1:])
print(rc, sorted(m for m in sys.modules if m == "scipy.optimize" or m.startswith("scipy.optimize.")))
"""


@pytest.mark.slow
def test_default_replay_with_refined_calibration_leaves_scipy_optimize_unloaded(tmp_path: Path) -> None:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    log = tmp_path / "paper.tlog"
    write_tlog(simulate(SimConfig(scenario="paper", duration_s=133.0, seed=0)), log)
    summary = tmp_path / "s.json"
    out = subprocess.run([sys.executable, "-c", _RUN, "replay", str(log), "--json", str(summary)],
                         capture_output=True, text=True, cwd=REPO, timeout=300, check=True)  # fmt: skip
    rc, loaded = out.stdout.strip().split(" ", 1)
    assert rc == "0", out.stderr
    assert loaded == "[]", out.stdout
    # the refined fit was made and adopted for both compasses ("motors on, calibration final")
    assert out.stderr.count("calibration final") == 2, out.stderr
    assert all(c["calibrated"] for c in json.loads(summary.read_text())["compasses"])
