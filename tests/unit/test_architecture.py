"""Layering: the numerical core stays free of the MAVLink/Rerun/plotting shell and of I/O and clocks.

Each import check runs in a fresh interpreter, because other tests in the same process import
pymavlink and rerun and would hide a leak.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PKG = Path(__file__).parents[2] / "magcomp"
SHELL_MODULES = (
    "pymavlink",
    "rerun",
    "matplotlib",
    "magcomp.adapters",
    "magcomp.service",
    "magcomp.commands",
)
# The only module of the pure packages allowed to touch files (documented in its docstring).
IO_ALLOWED = {"diagnosis/report.py"}


def _run(code: str) -> str:
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    return out.stdout


def _leaked_modules(package: str) -> list[str]:
    code = (
        "import importlib, pkgutil, sys\n"
        f"p = importlib.import_module({package!r})\n"
        f"skip = {sorted(IO_ALLOWED)!r}\n"
        "for m in pkgutil.walk_packages(p.__path__, p.__name__ + '.'):\n"
        "    if any(m.name.replace('.', '/').endswith(s[:-3]) for s in skip):\n"
        "        continue\n"
        "    importlib.import_module(m.name)\n"
        f"shell = {SHELL_MODULES!r}\n"
        "hits = (k for k in sys.modules if any(k == s or k.startswith(s + '.') for s in shell))\n"
        "print('\\n'.join(sorted(hits)))\n"
    )
    return [line for line in _run(code).splitlines() if line]


@pytest.mark.parametrize("package", ["magcomp.core", "magcomp.sim", "magcomp.diagnosis"])
def test_importing_pure_package_leaves_pymavlink_rerun_and_shell_out_of_sys_modules(package: str) -> None:
    assert _leaked_modules(package) == []


def test_importing_magcomp_core_alone_leaves_pymavlink_and_rerun_out() -> None:
    code = (
        "import sys, magcomp.core\n"
        "print(sorted(k for k in sys.modules if k.split('.')[0] in ('pymavlink', 'rerun')))\n"
    )
    assert _run(code).strip() == "[]"


_FORBIDDEN_CALLS = {"print", "open", "input", "exit", "quit"}
_FORBIDDEN_ATTRS = {
    ("time", "time"),
    ("time", "monotonic"),
    ("time", "perf_counter"),
    ("time", "sleep"),
    ("sys", "exit"),
    ("datetime", "now"),
    ("datetime", "utcnow"),
    ("date", "today"),
}
_FORBIDDEN_METHODS = {"write_text", "write_bytes", "read_text", "read_bytes", "savefig", "mkdir"}


def _violations(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            if isinstance(f, ast.Name) and f.id in _FORBIDDEN_CALLS:
                found.append(f"{path.name}:{node.lineno} {f.id}()")
            elif isinstance(f, ast.Attribute):
                base = f.value.id if isinstance(f.value, ast.Name) else ""
                if (base, f.attr) in _FORBIDDEN_ATTRS or f.attr in _FORBIDDEN_METHODS:
                    found.append(f"{path.name}:{node.lineno} .{f.attr}()")
    return found


@pytest.mark.parametrize("package", ["core", "sim", "diagnosis"])
def test_pure_packages_do_no_io_print_exit_or_clock_reads(package: str) -> None:
    files = sorted((PKG / package).glob("*.py"))
    assert files, f"no modules found under {PKG / package}"
    bad = [v for f in files if f"{package}/{f.name}" not in IO_ALLOWED for v in _violations(f)]
    assert bad == []


def test_io_checker_flags_a_print_and_a_clock_read(tmp_path: Path) -> None:
    probe = tmp_path / "probe.py"
    probe.write_text("import time\nprint(1)\nt = time.monotonic()\n", encoding="utf-8")
    assert len(_violations(probe)) == 2


def test_simulate_cli_help_lists_the_scenarios_and_effects_of_sim_config() -> None:
    # the CLI keeps its own copies so that `magcomp --help` does not import the simulator
    from magcomp.commands import simulate as cmd
    from magcomp.sim.config import EFFECTS, SCENARIO_ALIASES, SCENARIOS

    assert set(cmd._SCENARIOS) == set(SCENARIOS) | set(SCENARIO_ALIASES)
    assert set(cmd._EFFECTS) == set(EFFECTS)
