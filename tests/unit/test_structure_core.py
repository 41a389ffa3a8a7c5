"""Structure rule of the numerical core (issue 24): the in-flight estimator imports nothing of the shell. The
other rules (no import cycle, no core class over 15 methods, no function over 80 lines, no private name
imported across modules) are kept for the whole package by ``tests/test_structure.py``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_importing_the_inflight_estimator_loads_nothing_of_the_shell() -> None:
    code = (
        "import sys, magcomp.core.inflight, magcomp.core.autopilot_params\n"
        "bad = sorted(m for m in sys.modules if m.startswith(('magcomp.service', 'magcomp.adapters')))\n"
        "print(';'.join(bad))\n"
        "assert 'magcomp.core.inflight.estimator' in sys.modules\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "", out.stdout
