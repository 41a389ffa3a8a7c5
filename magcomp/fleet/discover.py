"""Finding the logs under the given paths, and the user's file -> vehicle mapping."""

from __future__ import annotations

import fnmatch
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from magcomp.errors import InputError

#: the file name endings taken for logs (case-insensitive)
LOG_SUFFIXES = (".tlog", ".bin", ".log", ".ulg")


def find_logs(paths: list[str], exclude: Path | None = None) -> list[Path]:
    """Every log under ``paths`` (files given directly are taken whatever their name), sorted, each once.
    Hidden folders and ``exclude`` (the output folder) are not entered."""
    found: dict[str, Path] = {}
    excl = exclude.resolve() if exclude is not None else None
    for raw in paths:
        p = Path(raw)
        if p.is_file():
            found.setdefault(str(p.resolve()), p)
            continue
        if not p.exists():
            raise InputError(f"{raw}: no such file or folder")
        if not p.is_dir():
            raise InputError(f"{raw}: not a file or folder")
        for root, dirs, files in os.walk(p):
            here = Path(root)
            dirs[:] = sorted(
                d for d in dirs if not d.startswith(".") and (excl is None or (here / d).resolve() != excl)
            )
            for name in sorted(files):
                if name.lower().endswith(LOG_SUFFIXES) and not name.startswith("."):
                    f = here / name
                    found.setdefault(str(f.resolve()), f)
    return sorted(found.values(), key=lambda q: str(q))


@dataclass
class VehicleMap:
    """``[vehicles]`` of a TOML file: ``name = ["pattern", ...]``. A pattern (shell-style, ``*`` crossing
    folders) matches a log's path (as found or absolute), its file name, its sha256 or the vehicle id the log
    itself gave (to rename ``ardupilot:CubeOrange-0040...``). The first vehicle with a matching pattern
    wins."""

    rules: list[tuple[str, list[str]]] = field(default_factory=list)

    def vehicle(self, path: str, sha256: str, detected: str) -> str | None:
        keys = (path, str(Path(path).resolve()), Path(path).name, sha256, detected)
        for name, patterns in self.rules:
            for pat in patterns:
                if any(fnmatch.fnmatchcase(k, pat) for k in keys if k):
                    return name
        return None


def load_vehicle_map(path: str | None) -> VehicleMap:
    if path is None:
        return VehicleMap()
    p = Path(path)
    try:
        doc = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"--vehicles {path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"--vehicles {path}: unreadable ({type(exc).__name__})") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"--vehicles {path}: not valid TOML ({exc})") from None
    table = doc.get("vehicles")
    if not isinstance(table, dict) or not table:
        raise InputError(f'--vehicles {path}: expected a [vehicles] table: name = ["pattern", ...]')
    rules: list[tuple[str, list[str]]] = []
    for name, pats in table.items():
        if isinstance(pats, str):
            pats = [pats]
        if not isinstance(pats, list) or not all(isinstance(x, str) and x for x in pats):
            raise InputError(f"--vehicles {path}: {name} = ...: expected a list of patterns (strings)")
        rules.append((str(name), list(pats)))
    return VehicleMap(rules)
