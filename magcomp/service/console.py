"""Shared wiring for the service commands: logging to stderr, state directory, summaries as text."""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from magcomp.errors import InputError


def setup_logging(command: str, verbose: bool = False) -> None:
    """One line per event on stderr: ``HH:MM:SS magcomp run: message``."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(f"%(asctime)s magcomp {command}: %(message)s", "%H:%M:%S"))
    root = logging.getLogger("magcomp")
    root.handlers[:] = [handler]
    root.setLevel(logging.DEBUG if verbose else logging.INFO)


def default_state_dir() -> Path:
    """``$MAGCOMP_STATE_DIR``, else ``$XDG_STATE_HOME/magcomp``, else ``~/.local/state/magcomp``."""
    env = os.environ.get("MAGCOMP_STATE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_STATE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".local" / "state") / "magcomp"


def check_output_path(
    path: str | Path | None,
    option: str,
    inputs: tuple[str | Path | None, ...] = (),
    *,
    makes_parents: bool = False,
) -> None:
    """Refuse, before any work is done, an output path that cannot be written or would overwrite an input.

    ``option`` names the command-line option (``--json``) in the one-line message; ``inputs`` are the
    files the command reads (the log, the configuration), which an output must never replace.
    ``makes_parents``: the writer creates missing directories itself.
    """
    if path is None:
        return
    if str(path).strip() == "":
        raise InputError(f"{option}: the path is empty")
    p = Path(path).expanduser()
    if p.is_dir():
        raise InputError(f"{option} {p}: is a directory")
    parent = p.parent
    if makes_parents:
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
    if not parent.is_dir():
        raise InputError(f"{option} {p}: the directory {str(parent)!r} does not exist")
    if p.exists():
        for other in inputs:
            if other is None or str(other) == "":
                continue
            try:
                same = os.path.samefile(p, other)
            except OSError:
                same = False
            if same:
                raise InputError(f"{option} {p}: is an input of this command; refusing to overwrite it")
        if not os.access(p, os.W_OK):
            raise InputError(f"{option} {p}: not writable")
    elif not os.access(parent, os.W_OK):
        raise InputError(f"{option} {p}: the directory {str(parent)!r} is not writable")


def check_distinct_outputs(**paths: str | Path | None) -> None:
    """Two options writing the same file would clobber each other: refuse (one line) before any work."""
    seen: dict[str, str] = {}
    for option, path in paths.items():
        if path is None:
            continue
        key = os.path.abspath(os.path.expanduser(str(path)))
        name = "--" + option.replace("_", "-")
        if key in seen:
            raise InputError(f"{seen[key]} and {name} name the same file {path}")
        seen[key] = name


def write_json(path: str | Path, doc: dict[str, Any]) -> None:
    from magcomp.adapters.files import write_file

    text = json.dumps(json_safe(doc), indent=2, default=_plain, allow_nan=False) + "\n"
    write_file(Path(path), text.encode())  # (a temporary file renamed: never half a summary)


def json_safe(obj: Any) -> Any:
    """Non-finite floats (and numpy scalars/arrays holding them) as None: strictly valid JSON."""
    try:
        import numpy as np

        if isinstance(obj, np.ndarray):
            obj = obj.tolist()
        elif isinstance(obj, np.generic):
            obj = obj.item()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    return obj


def _plain(obj: Any) -> Any:
    try:
        import numpy as np

        if isinstance(obj, np.ndarray):
            return obj.tolist()
        if isinstance(obj, np.generic):
            return obj.item()
    except ImportError:  # pragma: no cover
        pass
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def format_counts(counts: dict[str, int], keys: tuple[str, ...]) -> str:
    parts = [f"{k.replace('_', ' ')} {counts[k]}" for k in keys if counts.get(k)]
    return ", ".join(parts) if parts else "none"


SKIP_KEYS = (
    "bad_crc",
    "garbage_bytes",
    "dataflash_resyncs",
    "dataflash_dropped_bytes",
    "dataflash_bad_instance",
    "time_jumps",
    "reboots",
    "mag_jumps",
    "gyro_jumps",
    "lost_messages",
    "truncated",
    "nonfinite",
    "non_finite",
    "implausible",
    "saturated",
    "time_backwards",
    "clock_resets",
    "gaps",
    "observer_resets",
    "dataflash_errors",
    "unreadable_records",
    "ulog_resyncs",
    "ulog_dropped_bytes",
    "non_finite_params",
    "foreign_datagrams",
    "bad_signature",
)


def earth_field_line(summary: dict[str, Any]) -> str | None:
    """Where the Earth field came from, when it was not the log's GPS (which the run already said as it
    happened): the configured location, silently the built-in default unless ``[location]`` is set."""
    ef = summary.get("earth_field") or {}
    if ef.get("source") != "config":
        return None
    try:
        norm = math.sqrt(sum(float(v) ** 2 for v in ef["ned_mgauss"]))
        where = f"({float(ef['lat_deg']):.4f}, {float(ef['lon_deg']):.4f}), {float(ef['decimal_year']):.1f}"
    except (KeyError, TypeError, ValueError):
        return None
    return (f"Earth field: no GPS fix in the log; WMM at the configured location {where}: {norm:.0f} mgauss "
            "(set [location] in --config for where the log was recorded)")  # fmt: skip


def summary_lines(summary: dict[str, Any]) -> list[str]:
    """Human-readable lines for a pipeline summary (per compass: calibration and theta)."""
    lines = []
    for c in summary.get("compasses", []):
        cal = c.get("calibration")
        cal_txt = "not calibrated"
        if cal is not None:
            cal_txt = f"calibration {cal['source']}"
            if cal["source"] != "identity":
                cal_txt += f" ({cal['n']} samples, eq. (3) residual {cal['residual_rms_mgauss']:.1f} mgauss)"
        th = c["theta_mgauss"]
        conv = "converged" if c["theta_converged"] else "not converged"
        status = c.get("status")
        if status == "uncorrected":
            lines.append(
                f"compass {c['index']}: {c['estimates']} headings, NOT corrected: {c.get('why', '')}"
                f"{_time_text(c)}"
            )
            continue
        if cal is not None and cal["source"] == "autopilot" and status == "corrected":
            sig = cal.get("theta_sigma_mgauss") or [math.nan] * 3
            why = "the flight determines none of its own"
            kept = "the autopilot's calibration kept"
            off = cal.get("offset_change_mgauss") or [0.0, 0.0, 0.0]
            if any(off):
                why = "the flight determines no calibration of its own"
                kept = (
                    f"the autopilot's calibration with its offsets changed by ({off[0]:.0f}, {off[1]:.0f}, "
                    f"{off[2]:.0f}) mgauss, their constant heading change left out"
                )
            if cal.get("yaw_source") == "gyro":
                why += "; theta fitted with the gyro's yaw, which no compass steers"
            if cal.get("theta_sigma_lower_bound"):
                why += "; theta rests on one stretch of the flight, its sigma a lower bound"
            kept += f" ({why})"
            lines.append(_corrected_line(c, kept, sig, ""))
            continue
        if cal is not None and cal["source"] == "in-flight":
            inf = c.get("inflight") or {}
            sig = inf.get("theta_sigma_mgauss") or [math.nan] * 3
            hs = inf.get("heading_sigma_deg")
            mount = "" if inf.get("mount_yaw_observable", True) else " not counting the mount's yaw"
            cal_txt = (
                f"calibrated in flight ({inf.get('form')} form, {cal['n']} samples, residual "
                f"{cal['residual_rms_mgauss']:.1f} mgauss, heading +-{hs:.1f} deg{mount})"
            )
            lines.append(_corrected_line(c, cal_txt, sig, f" ({conv})"))
            continue
        lines.append(
            f"compass {c['index']}: {c['estimates']} headings, {cal_txt}, "
            f"theta = ({th[0]:.1f}, {th[1]:.1f}, {th[2]:.1f}) mgauss ({conv})"
        )
    return lines


def _corrected_line(c: dict[str, Any], cal_txt: str, sig: list[float], conv: str) -> str:
    """A corrected compass's line: its calibration, theta with its sigma, the self-check's gain, the time."""
    th = c["theta_mgauss"]
    chk = c.get("self_check")
    gain = "" if not chk else f"; {_gain_text(chk)}"
    return (
        f"compass {c['index']}: {c['estimates']} headings, corrected, {cal_txt}, "
        f"theta = ({th[0]:.1f}, {th[1]:.1f}, {th[2]:.1f}) "
        f"+- ({sig[0]:.1f}, {sig[1]:.1f}, {sig[2]:.1f}) mgauss{conv}{_bias_text(c)}{gain}{_time_text(c)}"
    )


def _bias_text(c: dict[str, Any]) -> str:
    """:func:`bias_at_flown_text` of a replay summary's compass."""
    return bias_at_flown_text(c["theta_mgauss"], c.get("throttle2_flown"))


def bias_at_flown_text(theta_mgauss: list[float] | None, throttle2: float | None) -> str:
    """theta's bias at the throttle flown (eq. (11): |theta| times the mean throttle^2 flown), as "; its bias
    at the throttle flown N mgauss (rms throttle X)" ("" where either is unknown): what the compass sees,
    where theta itself is large because the throttle flown is low (0.15-0.25 on a development log: theta ~3
    gauss, its bias 70-190 mgauss)."""
    if theta_mgauss is None or throttle2 is None:
        return ""
    th = [float(x) for x in theta_mgauss]
    bias = math.sqrt(th[0] * th[0] + th[1] * th[1] + th[2] * th[2]) * float(throttle2)
    rms = math.sqrt(float(throttle2))
    return f"; its bias at the throttle flown {bias:.0f} mgauss (rms throttle {rms:.2f})"


def _gain_text(chk: dict[str, Any]) -> str:
    """The self-check's gain, as :meth:`magcomp.core.selfcheck.SelfCheck.describe` words it."""
    from magcomp.core.selfcheck import SelfCheck

    return SelfCheck(**chk).describe()


def _time_text(c: dict[str, Any]) -> str:
    ts = c.get("time_s") or {}
    cor, unc = float(ts.get("corrected", 0.0)), float(ts.get("uncorrected", 0.0))
    if cor + unc <= 0.0:
        return ""
    return f"; {cor:.0f} s corrected, {unc:.0f} s uncorrected"


def progress_enabled() -> bool:
    """Progress bars only for a person watching: stderr is a terminal, not CI, not a dumb terminal."""
    return sys.stderr.isatty() and not os.environ.get("CI") and os.environ.get("TERM") != "dumb"


def quiet_tqdm() -> Any:
    """tqdm without its monitor thread (it only retunes ``miniters`` of a stalled bar; ours refresh on
    ``mininterval``): a replay bar then adds no thread to the process."""
    from tqdm import tqdm

    return type("QuietTqdm", (tqdm,), {"monitor_interval": 0})


_quiet_tqdm = quiet_tqdm  # the old name (other branches import it)


class Progress:
    """A tqdm bar on stderr when :func:`progress_enabled`, else nothing (never in logs or JSON).

    ``total`` None: no known end (shows the count and the rate); else the count of the total and the time
    left (ETA). Use as a context manager; ``update(n)`` adds ``n``, ``goto(x)`` moves to ``x`` (an estimated
    total that was short is not passed: the bar stays at its end)."""

    def __init__(self, desc: str, total: float | None = None, unit: str = "it") -> None:
        self._bar: Any = None
        self._total = total
        if progress_enabled():
            known = "{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} " + unit
            known += " [{elapsed}<{remaining}]"
            fmt = known if total else "{desc}: {n:.0f} " + unit + " [{elapsed}, {rate_fmt}]"
            self._bar = quiet_tqdm()(total=total, desc=desc, unit=unit, file=sys.stderr, leave=False,
                                      dynamic_ncols=True, mininterval=0.25, bar_format=fmt)  # fmt: skip

    def update(self, n: float = 1) -> None:
        if self._bar is not None:
            self._bar.update(n)

    def goto(self, x: float) -> None:
        if self._total:
            x = min(x, self._total)
        if self._bar is not None and x > self._bar.n:
            self._bar.update(x - self._bar.n)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextlib.contextmanager
def reading_progress(desc: str, path: str | Path) -> Iterator[Callable[[float], None]]:
    """A :class:`Progress` for reading a log: yields the ``on_progress(t_s)`` to hand the reader; the total
    is the log's span when its two ends say (magcomp.adapters.log_span), so the bar shows the time left."""
    from magcomp.adapters.log_span import estimate_span_s

    first: list[float] = []
    with Progress(desc, total=estimate_span_s(path), unit="s of log") as bar:

        def on_progress(t_s: float) -> None:
            if not math.isfinite(t_s):
                return
            if not first:
                first.append(t_s)
            bar.goto(t_s - first[0])

        yield on_progress


class Busy:
    """An elapsed-time line on a terminal while a long step without its own progress runs (a thread
    refreshes it); nothing otherwise."""

    def __init__(self, desc: str) -> None:
        import threading

        self._stop = threading.Event()
        self._thread: Any = None
        self._bar: Any = None
        if progress_enabled():
            from tqdm import tqdm

            self._bar = tqdm(total=None, desc=desc, file=sys.stderr, leave=False,
                             bar_format="{desc} [{elapsed}]")  # fmt: skip
            self._thread = threading.Thread(target=self._tick, daemon=True)
            self._thread.start()

    def _tick(self) -> None:
        while not self._stop.wait(0.5):
            self._bar.refresh()

    def __enter__(self) -> Busy:
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._bar is not None:
            self._bar.close()


def primary_compass(compasses: tuple[int, ...]) -> int:
    """The compass the viewer shows: the first configured one, else compass 0."""
    return compasses[0] if compasses else 0
