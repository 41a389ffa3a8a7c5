"""State that survives restarts: calibration (L, d, eq. (2)) and theta (eq. (11)) per vehicle and compass.

One JSON file per (vehicle, compass index) in the state directory. A vehicle is its MAVLink system id and,
when the link or log names it, its unique hardware id (:mod:`magcomp.core.identity`):
``vehicle-1-<uid>-compass-0.json``; a state learned on one vehicle is never applied to another with the same
system id. A vehicle whose log or link names no identity keeps ``vehicle-1-compass-0.json`` (the name every
state had before identities, version 1; such files are read as they are and are never applied to a vehicle
whose identity is known). Every load and every first write of a file in a run is one log line.
Writes are atomic: the text goes to a temporary file in the same directory, which is flushed and
fsync'ed, renamed over the old file (``os.replace``, atomic on POSIX) and the directory is fsync'ed, so
a crash or ``kill -9`` at any instant leaves either the old or the new file, never a mixture. Each file
carries a SHA-256 of its payload; a file that fails to parse or to verify is reported (``warnings`` list
and the ``magcomp`` logger) and ignored: the vehicle starts fresh.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcomp.core.identity import normal_uid
from magcomp.errors import InputError

log = logging.getLogger("magcomp.state")

FORMAT = "magcomp-state"
VERSION = 2
#: versions read: 1 (before vehicle identities: the state of a system id)
READ_VERSIONS = (1, 2)


@dataclass(frozen=True)
class CompassState:
    """What the daemon keeps for one compass of one vehicle.

    calib_l / calib_d: L (3x3) and d (3,) mgauss of eq. (2), or None when not calibrated yet.
    theta_mgauss: theta-hat of eq. (11) in the calibrated frame. t_s: message time of the last update.
    """

    system_id: int
    mag_index: int
    calib_l: NDArray[np.float64] | None
    calib_d: NDArray[np.float64] | None
    theta_mgauss: NDArray[np.float64]
    t_s: float = 0.0
    calib_info: dict[str, float] | None = None
    #: the in-flight calibration (magcomp.core.inflight): form, motors, parameter mean and std
    inflight: dict[str, Any] | None = None
    #: the vehicle's unique hardware id (lower-case hex), None when the log or link named none
    vehicle_uid: str | None = None

    def to_payload(self) -> dict[str, Any]:
        return {
            "system_id": self.system_id,
            "vehicle_uid": self.vehicle_uid,
            "mag_index": self.mag_index,
            "calib_l": None if self.calib_l is None else np.asarray(self.calib_l, float).tolist(),
            "calib_d": None if self.calib_d is None else np.asarray(self.calib_d, float).tolist(),
            "theta_mgauss": np.asarray(self.theta_mgauss, float).tolist(),
            "t_s": float(self.t_s),
            "calib_info": self.calib_info,
            "inflight": self.inflight,
        }

    @classmethod
    def from_payload(cls, p: dict[str, Any]) -> CompassState:
        """Validate a payload (raises ValueError/KeyError/TypeError on anything malformed)."""

        def vec(x: Any, shape: tuple[int, ...]) -> NDArray[np.float64]:
            a = np.asarray(x, dtype=float)
            if a.shape != shape or not np.all(np.isfinite(a)):
                raise ValueError(f"expected finite array of shape {shape}")
            return a

        l_raw, d_raw = p["calib_l"], p["calib_d"]
        if (l_raw is None) != (d_raw is None):
            raise ValueError("calib_l and calib_d must both be present or both be null")
        info = p.get("calib_info")
        if info is not None and not isinstance(info, dict):
            raise ValueError("calib_info must be a table")
        t_s = float(p["t_s"])
        if not math.isfinite(t_s):
            raise ValueError("t_s must be finite")
        inflight = p.get("inflight")
        if inflight is not None:
            if not isinstance(inflight, dict) or inflight.get("form") not in ("absolute", "relative"):
                raise ValueError("inflight must be a table with form absolute or relative")
            mean = np.asarray(inflight["mean"], dtype=float)
            sd = np.asarray(inflight["sd"], dtype=float)
            if mean.shape != sd.shape or mean.ndim != 1 or not (np.all(np.isfinite(mean)) and np.all(sd > 0)):
                raise ValueError("inflight mean/sd must be finite vectors of one length, sd > 0")
            int(inflight["n_motors"])
        uid = p.get("vehicle_uid")
        if uid is not None and (not isinstance(uid, str) or normal_uid(uid) != uid):
            raise ValueError("vehicle_uid must be lower-case hex or null")
        return cls(
            system_id=int(p["system_id"]),
            mag_index=int(p["mag_index"]),
            calib_l=None if l_raw is None else vec(l_raw, (3, 3)),
            calib_d=None if d_raw is None else vec(d_raw, (3,)),
            theta_mgauss=vec(p["theta_mgauss"], (3,)),
            t_s=t_s,
            calib_info=info,
            inflight=inflight,
            vehicle_uid=uid,
        )


def vehicle_name(system_id: int, uid: str | None) -> str:
    """How the log lines name a vehicle."""
    return f"vehicle {system_id}" + (f" (id {uid})" if uid else " (no identity)")


def _mtime(path: Path) -> str:
    import time

    try:
        return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(path.stat().st_mtime))
    except OSError:
        return "at an unknown time"


def _digest(payload: dict[str, Any]) -> str:
    canon = json.dumps(payload, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canon.encode("utf-8")).hexdigest()


def write_atomic(path: Path, text: str) -> None:
    """Replace ``path`` by ``text`` atomically and durably (temp file, fsync, rename, fsync directory)."""
    directory = path.parent
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    dfd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)


class StateStore:
    """The state directory. ``warnings`` collects one line per damaged file met."""

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"state directory {self.directory}: cannot create ({exc.strerror})") from None
        if not os.access(self.directory, os.W_OK):
            raise InputError(f"state directory {self.directory}: not writable")
        self.warnings: list[str] = []
        self._written: set[Path] = set()  # files written in this run (the first write is logged)
        self._remove_stale_temps()

    def _remove_stale_temps(self) -> None:
        """Temporary files left by a writer killed before its rename are garbage: remove them."""
        for tmp in self.directory.glob(".vehicle-*.tmp"):
            with contextlib.suppress(OSError):
                tmp.unlink()

    def path_for(self, system_id: int, mag_index: int, uid: str | None = None) -> Path:
        if uid is None:
            return self.directory / f"vehicle-{int(system_id)}-compass-{int(mag_index)}.json"
        if normal_uid(uid) != uid:
            raise ValueError(f"vehicle id {uid!r} is not lower-case hex")
        return self.directory / f"vehicle-{int(system_id)}-{uid}-compass-{int(mag_index)}.json"

    def save(self, state: CompassState) -> Path:
        payload = state.to_payload()
        doc = {"format": FORMAT, "version": VERSION, "sha256": _digest(payload), "state": payload}
        path = self.path_for(state.system_id, state.mag_index, state.vehicle_uid)
        if path not in self._written:
            self._written.add(path)
            what = "overwriting the state saved " + _mtime(path) if path.exists() else "new file"
            log.info("state: compass %d of %s -> %s (%s)", state.mag_index,
                     vehicle_name(state.system_id, state.vehicle_uid), path, what)  # fmt: skip
        write_atomic(path, json.dumps(doc, indent=1) + "\n")
        return path

    def load(self, system_id: int, mag_index: int, uid: str | None = None) -> CompassState | None:
        """The stored state of compass ``mag_index`` of vehicle (``system_id``, ``uid``), or None when absent
        or damaged (damage: a warning, then a fresh start). ``uid`` None: a vehicle that named no identity."""
        path = self.path_for(system_id, mag_index, uid)
        state = self._read(path, system_id, mag_index, uid)
        who = vehicle_name(system_id, uid)
        if state is not None:
            log.info("state: compass %d of %s <- %s (saved %s)", mag_index, who, path, _mtime(path))
        elif uid is not None and self.path_for(system_id, mag_index).exists():
            log.info("state: compass %d of %s starts fresh: %s names no vehicle identity (an older magcomp, "
                     "or a log without one) and is not applied to an identified vehicle", mag_index, who,
                     self.path_for(system_id, mag_index))  # fmt: skip
        return state

    def _read(self, path: Path, system_id: int, mag_index: int, uid: str | None) -> CompassState | None:
        try:
            raw = path.read_bytes()
        except FileNotFoundError:
            return None
        except OSError as exc:
            return self._damaged(path, f"cannot read ({exc.strerror})")
        try:
            doc = json.loads(raw.decode("utf-8"))
            if not isinstance(doc, dict) or doc.get("format") != FORMAT:
                return self._damaged(path, "not a magcomp state file")
            if doc.get("version") not in READ_VERSIONS:
                return self._damaged(path, f"unsupported version {doc.get('version')!r}")
            payload = doc["state"]
            if _digest(payload) != doc.get("sha256"):
                return self._damaged(path, "checksum mismatch")
            state = CompassState.from_payload(payload)
        except (ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
            return self._damaged(path, f"unreadable ({exc.__class__.__name__}: {exc})")
        if state.system_id != system_id or state.mag_index != mag_index or state.vehicle_uid != uid:
            return self._damaged(path, "holds another vehicle or compass")
        return state

    def list_states(self) -> list[tuple[Path, CompassState]]:
        """Every readable state in the directory (a damaged file: a warning, left out)."""
        out = []
        for path in sorted(self.directory.glob("vehicle-*-compass-*.json")):
            try:
                doc = json.loads(path.read_text(encoding="utf-8"))
                payload = doc["state"]
                if doc.get("format") != FORMAT or _digest(payload) != doc.get("sha256"):
                    raise ValueError("not a magcomp state file or checksum mismatch")
                out.append((path, CompassState.from_payload(payload)))
            except (OSError, ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
                self._damaged(path, f"unreadable ({exc.__class__.__name__}: {exc})")
        return out

    def adopt(self, system_id: int, uid: str, force: bool = False) -> list[str]:
        """The states of ``system_id`` without identity become vehicle (``system_id``, ``uid``)'s: saved under
        its name, the old files removed (they are no longer anyone else's). A compass for which the vehicle
        has its own state already is skipped unless ``force``. Returns one line per compass."""
        lines = []
        for path, st in self.list_states():
            if st.system_id != system_id or st.vehicle_uid is not None:
                continue
            target = self.path_for(system_id, st.mag_index, uid)
            if target.exists() and not force:
                lines.append(f"compass {st.mag_index}: kept {target.name} (the vehicle's own state; --force "
                             f"replaces it with {path.name})")  # fmt: skip
                continue
            self.save(replace(st, vehicle_uid=uid))
            path.unlink()
            lines.append(f"compass {st.mag_index}: {path.name} -> {target.name}")
        return lines or [f"no state of system {system_id} without identity in {self.directory}"]

    def _damaged(self, path: Path, why: str) -> CompassState | None:
        msg = f"state file {path} is damaged ({why}); starting fresh for this compass"
        self.warnings.append(msg)
        log.warning(msg)
        return None
