"""rerun-sdk is imported only when a ``--rerun`` mode asks for it (issue 13): not for ``--help``, not for a
plain replay, fit or diagnose. Each command runs through the CLI's ``main`` in one fresh interpreter."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

_RUN = """
import contextlib, io, sys
from magcomp.cli import main
for argv in [a.split("|") for a in sys.argv[1:]]:
    with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):
        rc = main(argv)
    loaded = sorted(m for m in sys.modules if m.split(".")[0] == "rerun")
    print(argv[0], argv[-1] == "--help" or rc, len(loaded))
"""


@pytest.mark.slow
def test_commands_without_rerun_do_not_import_rerun(tmp_path: Path) -> None:
    from magcomp.adapters.mavlink_emit import write_tlog
    from magcomp.sim import SimConfig, simulate

    log = tmp_path / "bench.tlog"
    write_tlog(simulate(SimConfig(scenario="bench", duration_s=20.0, seed=1)), log)
    commands = [
        "--help",
        "replay|--help",
        f"replay|{log}|--causal",
        f"fit|{log}|--monte-carlo|20|--start|8|--end|20",
        f"diagnose|{log}|--json|{tmp_path / 'd.json'}",
    ]
    out = subprocess.run([sys.executable, "-c", _RUN, *commands], capture_output=True, text=True, cwd=REPO,
                         timeout=300, check=True)  # fmt: skip
    lines = [line.split() for line in out.stdout.splitlines()]
    assert [line[0] for line in lines] == ["--help", "replay", "replay", "fit", "diagnose"], out.stderr
    assert all(line[2] == "0" for line in lines), out.stdout  # no rerun module after any of them
    assert [line[1] for line in lines[2:]] == ["0", "0", "0"], out.stdout + out.stderr  # each command ran
