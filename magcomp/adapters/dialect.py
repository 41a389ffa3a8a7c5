"""The magcomp MAVLink dialect (``magcomp.xml``): generation, registration and encoding.

``ensure_dialect()`` generates Python bindings for ``magcomp.xml`` with pymavlink's mavgen (MAVLink 2,
Python3) on first use, caches them outside the repository (``$MAGCOMP_CACHE_DIR``, else
``$XDG_CACHE_HOME/magcomp``, else ``~/.cache/magcomp``) under a key made of the XML's hash and the pymavlink
version, and registers the module as ``pymavlink.dialects.v20.magcomp`` so that
``mavutil.mavlink_connection(..., dialect="magcomp")`` finds it without touching site-packages.

``mavgen`` resolves ``<include>`` relative to the including file, so the shipped XMLs are copied next to ours
in a temporary directory first (stack-notes §2). ``MAVLINK20=1`` is set before ``pymavlink.mavutil`` can be
imported by this module: mavutil reads it once at import time.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import io
import os
import shutil
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

from magcomp.core.types import HeadingEstimate
from magcomp.errors import MagcompError

DIALECT_NAME = "magcomp"
MODULE_NAME = f"pymavlink.dialects.v20.{DIALECT_NAME}"
XML_PATH = Path(__file__).with_name("magcomp.xml")
MAGCOMP_HEADING_ID = 45000


def cache_dir() -> Path:
    """Directory for generated bindings (created on demand by :func:`ensure_dialect`)."""
    env = os.environ.get("MAGCOMP_CACHE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg) if xdg else Path.home() / ".cache"
    return base / "magcomp"


def shipped_xml_dir() -> Path:
    """pymavlink's own ``dialects/v20`` directory with the message definitions it ships."""
    import pymavlink.dialects.v20 as v20

    return Path(v20.__file__).parent


def _pymavlink_version() -> str:
    """pymavlink's version: the package's own ``__version__`` (2.4.50 both ways here), else its installed
    distribution's (importing importlib.metadata and asking it cost ~14 ms of CPU after numpy's import,
    0.5-0.8 % of a 10 min replay). Only the bindings' cache key depends on it."""
    import pymavlink

    own = getattr(pymavlink, "__version__", None)
    if isinstance(own, str) and own:
        return own
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("pymavlink")
    except PackageNotFoundError:  # pragma: no cover - pymavlink is a hard dependency
        return "unknown"


def generate_bindings(
    xml_path: Path, out_py: Path, *, validate: bool = True, extra_xmls: Sequence[Path] = ()
) -> None:
    """Run mavgen (MAVLink 2, Python3) on ``xml_path`` with the shipped XMLs beside it; write ``out_py``.

    ``extra_xmls`` are copied beside it too, so that ``xml_path`` can include them.

    Raises MagcompError with mavgen's last lines when generation fails (e.g. a duplicate message id).
    Writes nothing to stdout: mavgen's chatter is captured.
    """
    from pymavlink.generator import mavgen, mavparse

    with tempfile.TemporaryDirectory(prefix="magcomp-mavgen-") as tmp:
        tmp_dir = Path(tmp)
        for shipped in shipped_xml_dir().glob("*.xml"):
            shutil.copy2(shipped, tmp_dir / shipped.name)
        for extra in extra_xmls:
            shutil.copy2(extra, tmp_dir / extra.name)
        local_xml = tmp_dir / xml_path.name
        shutil.copy2(xml_path, local_xml)
        out_tmp = tmp_dir / "generated.py"
        opts = mavgen.Opts(
            str(out_tmp), wire_protocol=mavparse.PROTOCOL_2_0, language="Python3", validate=validate
        )
        log = io.StringIO()
        try:
            with contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
                ok = mavgen.mavgen(opts, [str(local_xml)])
        except SystemExit as exc:  # mavgen exits on some validation errors
            ok = False
            log.write(f"\nmavgen exited: {exc}")
        except Exception as exc:
            ok = False
            log.write(f"\nmavgen raised {type(exc).__name__}: {exc}")
        if not ok or not out_tmp.exists():
            lines = [ln.strip() for ln in log.getvalue().splitlines() if ln.strip()]
            errors = [ln for ln in lines if "error" in ln.lower() or "duplicate" in ln.lower()]
            detail = "; ".join((errors or lines)[-2:])
            raise MagcompError(f"MAVLink dialect generation failed for {xml_path.name}: {detail}")
        out_py.parent.mkdir(parents=True, exist_ok=True)
        staged = out_py.parent / f".{out_py.name}.{os.getpid()}.tmp"
        shutil.copyfile(out_tmp, staged)
        os.replace(staged, out_py)  # atomic: readers see the old file or the whole new one


def bindings_path(xml_path: Path = XML_PATH) -> Path:
    """Where the cached bindings for this XML and this pymavlink version live."""
    key = hashlib.sha256(xml_path.read_bytes() + _pymavlink_version().encode()).hexdigest()[:16]
    return cache_dir() / f"dialect-{key}" / f"{DIALECT_NAME}.py"


def ensure_dialect() -> ModuleType:
    """Return the generated ``magcomp`` dialect module, generating and registering it on first use.

    Also sets ``os.environ["MAVLINK20"] = "1"`` (mavutil reads it when it is first imported and on each
    ``set_dialect``). Idempotent and cheap after the first call in a process.
    """
    os.environ["MAVLINK20"] = "1"
    existing = sys.modules.get(MODULE_NAME)
    if existing is not None:
        return existing
    path = bindings_path()
    if not path.exists():
        generate_bindings(XML_PATH, path)
    import pymavlink.dialects.v20 as v20pkg

    spec = importlib.util.spec_from_file_location(MODULE_NAME, path)
    if spec is None or spec.loader is None:  # pragma: no cover - defensive
        raise MagcompError(f"cannot load generated MAVLink dialect {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[MODULE_NAME] = module
    try:
        spec.loader.exec_module(module)
    except Exception as exc:  # a corrupt cache file: drop it so the next call regenerates
        del sys.modules[MODULE_NAME]
        with contextlib.suppress(OSError):
            path.unlink()
        raise MagcompError(f"cannot load generated MAVLink dialect {path}: {exc}") from exc
    setattr(v20pkg, DIALECT_NAME, module)
    return module


def new_mav(src_system: int = 1, src_component: int = 191) -> Any:
    """A ``MAVLink`` encoder/decoder of the magcomp dialect with no transport (``file=None``)."""
    mod = ensure_dialect()
    return mod.MAVLink(None, srcSystem=src_system, srcComponent=src_component)


def heading_message(est: HeadingEstimate) -> Any:
    """MAGCOMP_HEADING for one estimate. ``time_boot_ms`` is ``est.t_s`` in ms, wrapped to uint32."""
    mod = ensure_dialect()
    time_boot_ms = round(est.t_s * 1000.0) % (1 << 32)
    return mod.MAVLink_magcomp_heading_message(
        time_boot_ms=time_boot_ms,
        heading=float(est.heading_deg),
        heading_raw=float(est.heading_raw_deg),
        theta=[float(v) for v in est.theta_mgauss],
        bias=[float(v) for v in est.bias_mgauss],
        throttle=float(est.throttle_01),
        mag_index=int(est.mag_index) & 0xFF,
        flags=int(est.flags) & 0xFF,
    )


def encode_heading(mav: Any, est: HeadingEstimate) -> bytes:
    """Pack one MAGCOMP_HEADING with ``mav`` (a dialect ``MAVLink`` object; advances its sequence)."""
    return bytes(heading_message(est).pack(mav))


def send_heading(conn: Any, est: HeadingEstimate) -> None:
    """Send one MAGCOMP_HEADING over a mavutil connection opened with ``dialect="magcomp"``."""
    conn.mav.send(heading_message(est))


# ------------------------------------------------------------------------------- installing for other tools

#: the environment that makes any pymavlink program (MAVProxy, mavlogdump.py, scripts) load this dialect
#: once it is installed: mavutil reads MAVLINK_DIALECT when it is imported, MAVLINK20 picks the v20 folder
DIALECT_ENV = {"MAVLINK20": "1", "MAVLINK_DIALECT": DIALECT_NAME}


def default_install_dir() -> Path:
    """pymavlink's ``dialects`` folder (holding ``v10/`` and ``v20/``): where ``mavutil.set_dialect``
    imports a dialect from."""
    return shipped_xml_dir().parent


def install_dialect(dest: Path | None = None) -> list[Path]:
    """Put the generated ``magcomp`` module and ``magcomp.xml`` into ``dest``/v20 and ``dest``/v10 (default:
    pymavlink's own dialects folder), so that ``--dialect magcomp`` (mavlogdump.py, MAVProxy) and
    ``MAVLINK_DIALECT=magcomp`` find it. The v10 copy is the same MAVLink 2 module: a program that does not
    set MAVLINK20 imports the dialect from v10, and MAGCOMP_HEADING (id 45000) exists only in MAVLink 2
    framing, which that module reads as well as MAVLink 1. Returns the files written.

    Raises MagcompError (one line) when the folder is missing or not writable."""
    target = Path(dest) if dest is not None else default_install_dir()
    if not target.is_dir():
        raise MagcompError(f"dialect folder {target} does not exist (pymavlink's is {default_install_dir()})")
    generated = bindings_path()
    if not generated.exists():
        generate_bindings(XML_PATH, generated)
    written: list[Path] = []
    for sub in ("v20", "v10"):
        folder = target / sub
        try:
            folder.mkdir(exist_ok=True)
            for src, name in ((generated, f"{DIALECT_NAME}.py"), (XML_PATH, f"{DIALECT_NAME}.xml")):
                staged = folder / f".{name}.{os.getpid()}.tmp"
                shutil.copyfile(src, staged)
                os.replace(staged, folder / name)
                written.append(folder / name)
        except OSError as exc:
            hint = " (pymavlink was installed by another user: use its environment, or --dest)"
            why = exc.strerror or exc
            raise MagcompError(f"cannot write the dialect into {folder}: {why}{hint}") from None
    return written


def installed_files(dest: Path | None = None) -> list[Path]:
    """The magcomp dialect files present in ``dest`` (default: pymavlink's dialects folder)."""
    target = Path(dest) if dest is not None else default_install_dir()
    found = (sorted((target / sub).glob(f"{DIALECT_NAME}.*")) for sub in ("v20", "v10"))
    return [p for files in found for p in files if p.is_file()]


def uninstall_dialect(dest: Path | None = None) -> list[Path]:
    """Remove what :func:`install_dialect` wrote. Returns the files removed."""
    removed = []
    for p in installed_files(dest):
        try:
            p.unlink()
        except OSError as exc:
            raise MagcompError(f"cannot remove {p}: {exc.strerror or exc}") from None
        removed.append(p)
    return removed
