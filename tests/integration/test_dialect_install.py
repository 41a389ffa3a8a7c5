"""`magcomp dialect install`: afterwards pymavlink's own mavlogdump.py decodes MAGCOMP_HEADING from an
``--emit`` tlog (every compass, every field); before it, it cannot. pymavlink is not modified: the test
installs into a copy of its package made of symlinks, put first on PYTHONPATH."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from magcomp.cli import main

FIELDS = ("time_boot_ms", "heading", "heading_raw", "theta", "bias", "throttle", "mag_index", "flags")


def _pymavlink_overlay(root: Path) -> Path:
    """``root``/pymavlink: pymavlink's files as symlinks, with real ``dialects/v10`` and ``dialects/v20``
    folders (so that installing into them leaves the real package untouched). Returns its dialects folder."""
    import pymavlink

    real = Path(pymavlink.__file__).parent
    pkg = root / "pymavlink"
    pkg.mkdir()
    for entry in real.iterdir():
        if entry.name != "dialects":
            (pkg / entry.name).symlink_to(entry)
    dialects = pkg / "dialects"
    dialects.mkdir()
    for entry in (real / "dialects").iterdir():
        if entry.name in ("v10", "v20"):
            (dialects / entry.name).mkdir()
            for f in entry.iterdir():
                if f.is_file():
                    (dialects / entry.name / f.name).symlink_to(f)
        else:
            (dialects / entry.name).symlink_to(entry)
    return dialects


def _mavlogdump(tlog: Path, overlay_root: Path, *extra: str) -> str:
    script = shutil.which("mavlogdump.py", path=str(Path(sys.executable).parent))
    assert script is not None, "pymavlink's mavlogdump.py is installed beside this interpreter"
    env = {k: v for k, v in os.environ.items() if k not in ("MAVLINK20", "MAVLINK_DIALECT")}
    env["PYTHONPATH"] = str(overlay_root)
    out = subprocess.run([sys.executable, script, *extra, str(tlog)], env=env, capture_output=True, text=True,
                         timeout=300, check=True)  # fmt: skip
    return out.stdout


@pytest.fixture(scope="module")
def emitted(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("emit")
    assert main(["simulate", "--scenario", "paper", "--duration", "20", "--compasses", "2",
                 "--out", str(d / "s.tlog")]) == 0  # fmt: skip
    assert main(["replay", str(d / "s.tlog"), "--emit", str(d / "e.tlog")]) == 0
    return d / "e.tlog"


def test_mavlogdump_decodes_every_compass_after_install(emitted: Path, tmp_path: Path) -> None:
    dialects = _pymavlink_overlay(tmp_path)
    before = _mavlogdump(emitted, tmp_path)  # what a user saw: pymavlink's default dialect
    assert "UNKNOWN_45000" in before and "MAGCOMP_HEADING" not in before

    assert main(["dialect", "install", "--dest", str(dialects)]) == 0
    after = _mavlogdump(emitted, tmp_path, "--dialect", "magcomp", "--types", "MAGCOMP_HEADING")
    lines = [ln for ln in after.splitlines() if "MAGCOMP_HEADING {" in ln]
    assert len(lines) > 100
    for field in FIELDS:
        assert f"{field} :" in lines[0]
    assert {"mag_index : 0", "mag_index : 1"} <= {p.strip() for ln in lines for p in ln.split(",")}


def test_mavlink_dialect_environment_selects_it(emitted: Path, tmp_path: Path) -> None:
    dialects = _pymavlink_overlay(tmp_path)
    assert main(["dialect", "install", "--dest", str(dialects)]) == 0
    env = {k: v for k, v in os.environ.items() if k not in ("MAVLINK20",)}
    env.update(PYTHONPATH=str(tmp_path), MAVLINK_DIALECT="magcomp")  # no MAVLINK20: the v10 copy serves
    code = ("from pymavlink import mavutil\n"
            f"m = mavutil.mavlink_connection({str(emitted)!r}).recv_match(type='MAGCOMP_HEADING')\n"
            "print(m.get_type(), m.mag_index, m.heading)\n")  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300,
                         check=True)  # fmt: skip
    assert out.stdout.startswith("MAGCOMP_HEADING ")


def test_mag_index_is_an_instance_field() -> None:
    from magcomp.adapters.dialect import ensure_dialect

    cls = ensure_dialect().MAVLink_magcomp_heading_message
    assert cls.instance_field == "mag_index"


def test_show_and_uninstall(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    dialects = _pymavlink_overlay(tmp_path)
    assert main(["dialect", "show", "--dest", str(dialects)]) == 1
    assert main(["dialect", "install", "--dest", str(dialects)]) == 0
    assert main(["dialect", "show", "--dest", str(dialects)]) == 0
    assert "MAVLINK_DIALECT=magcomp" in capsys.readouterr().out
    assert main(["dialect", "uninstall", "--dest", str(dialects)]) == 0
    assert not list((dialects / "v20").glob("magcomp.*"))


def test_install_into_a_missing_folder_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["dialect", "install", "--dest", str(tmp_path / "nope")]) != 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("magcomp dialect: error:") and "\n" not in err
