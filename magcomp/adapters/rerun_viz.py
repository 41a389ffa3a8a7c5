"""The Rerun view of a magcomp run: the ONLY module that imports ``rerun`` (rerun-sdk==0.41.0, pinned).

Rerun renames its API between versions (``Scalar`` -> ``Scalars``, ``set_time_seconds`` -> ``set_time``, ...),
so every ``rr.*`` call lives here and the rest of magcomp talks to the :class:`Viz` protocol. ``rerun``
is imported only inside :func:`open_viz` when a mode is asked for: :class:`NullViz` (no ``--rerun``) costs
nothing, and the 0.5 s import of ``rerun`` is not paid by a plain replay.

Modes (``--rerun MODE``):

- ``spawn``: start the native viewer (needs a display);
- ``serve``: host the web viewer on this machine; :attr:`RerunViz.url` is the page to open;
- ``connect`` / ``connect=URL``: stream to a running viewer (``rerun+http://HOST:PORT/proxy``, ``HOST:PORT``);
- ``save=PATH.rrd``: write a recording file (open it later with ``rerun PATH.rrd``);
- ``auto``: ``spawn`` when there is a display, else ``serve`` (:func:`default_mode_for_demo`).

Everything is stamped on one timeline, :data:`TIMELINE` (seconds of *message* time, a duration), never on
arrival time; rerun's own wall-clock ``log_time`` timeline is kept only for live views (on the rows sent with
``rr.log``, e.g. the clouds). Replay sends whole series as columns (``send_columns``); live buffers estimates
and sends them as columns every 0.5 s of message time (one row per estimate for theta, heading and bias;
throttle, power and observer thinned to 10 Hz).

The blueprint follows the paper's figures (Silic & Mohseni 2019):

- heading raw / corrected / truth and their errors (Fig. 9);
- theta-hat per axis converging, with the offline least-squares theta (Fig. 8) and the simulation's truth as
  horizontal reference lines;
- raw and calibrated magnetometer samples as 3D points: the off-centre ellipsoid becomes a centred sphere
  (Fig. 5);
- bias against throttle^2 with the fitted line ``B = theta * throttle^2`` of eq. (11) (Fig. 7), drawn in a
  2D view (throttle^2 scaled so that 0..1 spans the bias range; y up), plus throttle, current and voltage;
- observer residual norm, rotation excitation (smallest eigenvalue of the excitation Gramian, eq. (21)) and
  status flags as text.

Departures / limits: one compass per view (the entity paths carry no mag index); reference lines are drawn as
two-point series stretched over the time seen so far (Rerun has no horizontal-line primitive in time series).
"""

from __future__ import annotations

import argparse
import math
import os
import socket
import sys
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcomp.core.types import HeadingEstimate, flags_text
from magcomp.errors import MagcompError

if TYPE_CHECKING:  # pragma: no cover
    import rerun as rr_types

F64 = NDArray[np.float64]

TIMELINE = "msg_time"
"""Timeline of every logged row: seconds on the message's own clock (a Rerun duration timeline).

Not ``log_time``: Rerun already owns a wall-clock timeline of that name."""

AXES = ("x", "y", "z")
DEFAULT_GRPC_PORT = 9876
DEFAULT_WEB_PORT = 9090
DEFAULT_CONNECT_URL = "rerun+http://127.0.0.1:9876/proxy"
CLOUD_MAX_POINTS = 3000
"""Replay: largest flight cloud sent per batch; live: points drawn per halving of the sampling rate."""
LIVE_CLOUD_PERIOD_S = 1.0
"""Live: new cloud points and the reference lines' ends are sent at most this often (message time)."""
LIVE_FLUSH_PERIOD_S = 0.5
"""Live: buffered estimates are sent as columns once this much message time has gathered."""
LIVE_SLOW_HZ = 10.0
"""Live: throttle, current, voltage and observer series are thinned to at most this rate (message time)."""
BIAS_FIT_MAX_POINTS = 4000

# Colours (RGB). Heading colours are kept apart from the axis colours so a screenshot can tell them apart.
COLOR_RAW = (245, 120, 30)
COLOR_CORRECTED = (40, 190, 245)
COLOR_TRUTH = (110, 110, 110)
COLOR_TRUTH_LINE = (40, 40, 40, 210)
"""Truth lines (RGBA): thin, slightly translucent dark grey; the wider corrected heading under them shows."""
COLOR_CORRECTION = (170, 120, 230)
COLOR_AXES = ((235, 70, 70), (90, 205, 90), (95, 125, 245))


def wrap_deg(angle_deg: F64) -> F64:
    """Wrap angles to [-180, 180) degrees."""
    return np.asarray((np.asarray(angle_deg, dtype=float) + 180.0) % 360.0 - 180.0, dtype=float)


# ----------------------------------------------------------------------------------------------------------
# The interface the service calls
# ----------------------------------------------------------------------------------------------------------


@runtime_checkable
class Viz(Protocol):
    """A visualisation sink. Times are seconds on the message clock; fields in mgauss; throttle 0..1."""

    @property
    def url(self) -> str | None:
        """Where to look: the web viewer page (``serve``), the gRPC URL or the .rrd path; else None."""
        ...

    @property
    def notice(self) -> str | None:
        """One line the CLI should print (to stderr) after opening, e.g. the URL to open; None for nothing."""
        ...

    @property
    def keeps_serving(self) -> bool:
        """True when the viewer's data lives in this process (``serve``): the CLI waits before close()."""
        ...

    def log_estimate(self, est: HeadingEstimate) -> None:
        """Live: one estimate, logged as it arrives."""
        ...

    def log_estimates(self, estimates: Sequence[HeadingEstimate]) -> None:
        """Replay: a whole run of estimates, sent as columns."""
        ...

    def log_reference_theta(
        self, theta_offline_mgauss: ArrayLike | None, theta_truth_mgauss: ArrayLike | None
    ) -> None:
        """Horizontal lines on the theta plot: offline least-squares theta (Fig. 8) and/or simulated truth."""
        ...

    def log_truth_heading(self, t_s: ArrayLike, heading_deg: ArrayLike) -> None:
        """True magnetic heading (simulated logs), arrays (n,) or one sample."""
        ...

    def log_power(
        self, t_s: ArrayLike, throttle_01: ArrayLike, current_a: ArrayLike, voltage_v: ArrayLike
    ) -> None:
        """Throttle 0..1, battery current (A), voltage (V); arrays (n,) or one sample; NaN = not carried."""
        ...

    def log_bias_fit(
        self, throttle2: ArrayLike, bias_mgauss: ArrayLike, theta_line: ArrayLike | None
    ) -> None:
        """Measured bias (n, 3) against throttle^2 (n,) and the fit bias = theta * throttle^2 (Fig. 7)."""
        ...

    def log_calibration_cloud(self, raw_mgauss: ArrayLike, calibrated_mgauss: ArrayLike) -> None:
        """The calibration data set before and after calibration, (n, 3) each (Fig. 5)."""
        ...

    def log_text(self, t_s: float, msg: str) -> None:
        """A status message at message time ``t_s``."""
        ...

    def close(self) -> None:
        """Flush and close the sink (stops a served viewer)."""
        ...


class NullViz:
    """The sink used without ``--rerun``: every call is a no-op and ``rerun`` is never imported."""

    url: str | None = None
    notice: str | None = None
    keeps_serving: bool = False

    def log_estimate(self, est: HeadingEstimate) -> None:
        return None

    def log_estimates(self, estimates: Sequence[HeadingEstimate]) -> None:
        return None

    def log_reference_theta(
        self, theta_offline_mgauss: ArrayLike | None, theta_truth_mgauss: ArrayLike | None
    ) -> None:
        return None

    def log_truth_heading(self, t_s: ArrayLike, heading_deg: ArrayLike) -> None:
        return None

    def log_power(
        self, t_s: ArrayLike, throttle_01: ArrayLike, current_a: ArrayLike, voltage_v: ArrayLike
    ) -> None:
        return None

    def log_bias_fit(
        self, throttle2: ArrayLike, bias_mgauss: ArrayLike, theta_line: ArrayLike | None
    ) -> None:
        return None

    def log_calibration_cloud(self, raw_mgauss: ArrayLike, calibrated_mgauss: ArrayLike) -> None:
        return None

    def log_text(self, t_s: float, msg: str) -> None:
        return None

    def close(self) -> None:
        return None


# ----------------------------------------------------------------------------------------------------------
# Modes
# ----------------------------------------------------------------------------------------------------------

MODE_HELP = (
    "show the run in Rerun: spawn (native viewer), serve[=ADDRESS] (web viewer on this machine, its data on "
    "127.0.0.1 unless ADDRESS, e.g. 0.0.0.0 for every interface; prints the URL), "
    "connect[=URL] (a running viewer, default "
    + DEFAULT_CONNECT_URL
    + "), save=PATH.rrd (a recording file), "
    "auto (spawn with a display, else serve; the default when --rerun has no value)"
)


#: ``serve``'s data server listens here unless ``serve=ADDRESS`` says otherwise (issue 27: the recording is
#: not offered to the network by default; a headless machine is reached through a port forward)
SERVE_LOCAL = "127.0.0.1"


@dataclass(frozen=True, slots=True)
class VizMode:
    """A parsed ``--rerun`` value: ``kind`` spawn | serve | connect | save; ``target`` the URL or path (serve:
    the data server's bind address)."""

    kind: str
    target: str = ""
    reason: str = ""


class DefaultMode(NamedTuple):
    """What :func:`default_mode_for_demo` chose, and a one-line reason to show the user."""

    mode: str
    reason: str


def has_display(environ: Mapping[str, str] | None = None) -> bool:
    """True when a native viewer can open a window: $DISPLAY or $WAYLAND_DISPLAY set (True off Linux)."""
    env = os.environ if environ is None else environ
    if not sys.platform.startswith("linux"):
        return True
    return bool(env.get("DISPLAY") or env.get("WAYLAND_DISPLAY"))


def default_mode_for_demo(environ: Mapping[str, str] | None = None) -> DefaultMode:
    """``spawn`` when there is a display, else ``serve`` (the web viewer), with the reason."""
    if has_display(environ):
        return DefaultMode("spawn", "a display is available: starting the native Rerun viewer")
    return DefaultMode(
        "serve", "no display ($DISPLAY and $WAYLAND_DISPLAY are unset): serving the Rerun web viewer instead"
    )


def _normalise_connect_url(target: str) -> str:
    if not target:
        return DEFAULT_CONNECT_URL
    if "://" not in target:
        host, sep, port = target.rpartition(":")
        if not sep or not host or not port.isdigit():
            raise MagcompError(
                f"--rerun connect=URL: expected rerun+http://HOST:PORT/proxy or HOST:PORT, got {target!r}"
            )
        return f"rerun+http://{host}:{port}/proxy"
    scheme = target.split("://", 1)[0]
    if scheme not in ("rerun", "rerun+http", "rerun+https"):
        raise MagcompError(
            "--rerun connect=URL: the scheme must be rerun://, rerun+http:// or rerun+https://, "
            f"got {target!r}"
        )
    return target


def parse_mode(mode: str, environ: Mapping[str, str] | None = None) -> VizMode:
    """Parse and check a ``--rerun`` value; raise :class:`MagcompError` (one line) when it is not valid."""
    text = mode.strip()
    kind, sep, target = text.partition("=")
    kind = kind.strip().lower()
    target = target.strip()
    if kind == "auto" and not sep:
        chosen = default_mode_for_demo(environ)
        return VizMode(chosen.mode, "", chosen.reason)
    if kind in ("spawn", "serve") and not sep:
        if kind == "spawn" and not has_display(environ):
            raise MagcompError(
                "--rerun spawn needs a display ($DISPLAY/$WAYLAND_DISPLAY unset); "
                "use --rerun serve or save=PATH.rrd"
            )
        return VizMode(kind, SERVE_LOCAL if kind == "serve" else "")
    if kind == "serve":  # serve=ADDRESS: the data server's bind address (0.0.0.0: every interface)
        import ipaddress

        try:
            ipaddress.ip_address(target)
        except ValueError:
            raise MagcompError(f"--rerun serve=ADDRESS: an IP address to listen on (0.0.0.0: every "
                               f"interface), got {target!r}") from None  # fmt: skip
        return VizMode("serve", target)
    if kind == "connect":
        if sep and not target:
            raise MagcompError("--rerun connect=URL: the URL is empty")
        return VizMode("connect", _normalise_connect_url(target))
    if kind == "save":
        if not target:
            raise MagcompError("--rerun save=PATH.rrd: the path is missing")
        path = Path(target).expanduser()
        if path.suffix != ".rrd":
            raise MagcompError(f"--rerun save=PATH.rrd: the file name must end in .rrd, got {target!r}")
        if path.exists() and path.is_dir():
            raise MagcompError(f"--rerun save=PATH.rrd: {target!r} is a directory")
        if not path.parent.is_dir():
            raise MagcompError(f"--rerun save=PATH.rrd: the directory {str(path.parent)!r} does not exist")
        return VizMode("save", str(path))
    raise MagcompError(
        f"--rerun: unknown mode {mode!r}; expected spawn, serve[=ADDRESS], connect[=URL], save=PATH.rrd "
        "or auto"
    )


def add_rerun_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--rerun [MODE]`` to a subcommand (no value means ``auto``); :func:`open_viz` validates it."""
    parser.add_argument("--rerun", metavar="MODE", nargs="?", const="auto", default=None, help=MODE_HELP)


def _port_is_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


def free_port(preferred: int | None = None) -> int:
    """``preferred`` when nobody listens on it, else a port the OS hands out (a small race either way)."""
    if preferred is not None and _port_is_free(preferred):
        return preferred
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def open_viz(
    mode: str | None,
    *,
    app_id: str = "magcomp",
    live: bool,
    recording_name: str | None = None,
    environ: Mapping[str, str] | None = None,
    grpc_port: int | None = None,
    web_port: int | None = None,
) -> Viz:
    """The sink for ``--rerun MODE``: :class:`NullViz` for None (no ``rerun`` import), else RerunViz.

    ``live`` selects the live layout and keeps Rerun's wall-clock timeline; replay uses column sends.
    ``grpc_port`` / ``web_port`` (``serve``): ports to use; default 9876 / 9090 when free, else any free port.
    """
    if mode is None:
        return NullViz()
    parsed = parse_mode(mode, environ)
    return RerunViz(
        parsed,
        app_id=app_id,
        live=live,
        recording_name=recording_name,
        grpc_port=grpc_port,
        web_port=web_port,
    )


def discard_viz(viz: Viz) -> None:
    """Close ``viz`` after its command failed (the input could not be read, held no compass): a recording
    file it started (``save=PATH.rrd``) is removed, so a failed command leaves nothing behind."""
    viz.close()
    mode = getattr(viz, "mode", None)
    if isinstance(mode, VizMode) and mode.kind == "save":
        Path(mode.target).unlink(missing_ok=True)


SERVING_MESSAGE = "serving the viewer; press ^C to stop"


def serve_until_interrupt(
    viz: Viz,
    say: Callable[[str], None],
    message: str = SERVING_MESSAGE,
    sleep: Callable[[float], None] = time.sleep,
) -> None:
    """When ``viz.keeps_serving`` (its web viewer lives in this process), ``say(message)`` and block until
    ^C (KeyboardInterrupt, swallowed); otherwise return at once. The caller still calls ``viz.close()``."""
    if not viz.keeps_serving:
        return
    say(message)
    try:
        while True:
            sleep(1.0)
    except KeyboardInterrupt:
        pass


# ----------------------------------------------------------------------------------------------------------
# Helpers kept free of rerun (unit-testable without a viewer)
# ----------------------------------------------------------------------------------------------------------


class StreamDecimator:
    """Decides which samples of an unbounded stream to draw, without ever taking one back: every sample until
    ``cap`` are kept, then every 2nd for the next ``cap``, every 4th for the next, ... so a run of n samples
    draws about ``cap * (1 + log2(n / cap))`` points spread over the whole run. Deterministic."""

    def __init__(self, cap: int) -> None:
        if cap < 1:
            raise ValueError("cap must be >= 1")
        self.cap = cap
        self.stride = 1
        self._seen = 0
        self._kept_in_phase = 0
        self.kept = 0

    def accept(self) -> bool:
        """Call once per sample; True when this sample is to be drawn."""
        take = self._seen % self.stride == 0
        self._seen += 1
        if take:
            self.kept += 1
            self._kept_in_phase += 1
            if self._kept_in_phase >= self.cap:
                self._kept_in_phase = 0
                self._seen = 0
                self.stride *= 2
        return take


def thin_rows(rows: F64, cap: int) -> F64:
    """Every k-th row so that at most ``cap`` remain (the whole array when it is already small)."""
    n = rows.shape[0]
    if n <= cap:
        return rows
    step = math.ceil(n / cap)
    return rows[::step]


class TruthHeading:
    """The true heading, accumulated from arrays or single samples, interpolated (unwrapped) at any time.

    Samples that arrive in time order (a live run fed chunk by chunk) extend the unwrapped copy in place, so
    adding and querying stay cheap over a long run; out-of-order samples re-sort and unwrap everything."""

    def __init__(self) -> None:
        self._t: F64 = np.zeros(0)
        self._deg: F64 = np.zeros(0)
        self._unwrapped: F64 = np.zeros(0)
        self._pending_t: list[float] = []
        self._pending_deg: list[float] = []

    def add(self, t_s: F64, heading_deg: F64) -> None:
        self._pending_t.extend(np.asarray(t_s, dtype=float).tolist())
        self._pending_deg.extend(np.asarray(heading_deg, dtype=float).tolist())

    def _merge(self) -> None:
        if not self._pending_t:
            return
        t_new = np.asarray(self._pending_t, dtype=float)
        deg_new = np.asarray(self._pending_deg, dtype=float)
        self._pending_t.clear()
        self._pending_deg.clear()
        ok = np.isfinite(t_new) & np.isfinite(deg_new)
        t_new, deg_new = t_new[ok], deg_new[ok]
        if t_new.size == 0:
            return
        in_order = bool(np.all(np.diff(t_new) >= 0.0))
        if in_order and (self._t.size == 0 or t_new[0] >= self._t[-1]):
            if self._t.size:  # continue the unwrapped angle from the last known sample
                steps = np.degrees(np.unwrap(np.radians(np.concatenate([self._deg[-1:], deg_new]))))
                tail = self._unwrapped[-1] + (steps[1:] - steps[0])
            else:
                tail = np.degrees(np.unwrap(np.radians(deg_new)))
            self._t = np.concatenate([self._t, t_new])
            self._deg = np.concatenate([self._deg, deg_new])
            self._unwrapped = np.concatenate([self._unwrapped, tail])
            return
        t = np.concatenate([self._t, t_new])
        deg = np.concatenate([self._deg, deg_new])
        order = np.argsort(t, kind="stable")
        self._t, self._deg = t[order], deg[order]
        self._unwrapped = np.degrees(np.unwrap(np.radians(self._deg)))

    def __len__(self) -> int:
        self._merge()
        return int(self._t.shape[0])

    def at(self, t_s: F64) -> F64:
        """Truth heading (deg, 0..360) at ``t_s``; NaN outside the truth's time span (no extrapolation)."""
        self._merge()
        t_q = np.asarray(t_s, dtype=float)
        if self._t.shape[0] == 0:
            return np.full(t_q.shape, np.nan)
        value = np.interp(t_q, self._t, self._unwrapped)
        inside = (t_q >= self._t[0]) & (t_q <= self._t[-1])
        return np.where(inside, value % 360.0, np.nan)


def _as_1d(x: ArrayLike) -> F64:
    return np.atleast_1d(np.asarray(x, dtype=float)).reshape(-1)


def _as_rows3(x: ArrayLike, name: str) -> F64:
    arr = np.asarray(x, dtype=float)
    if arr.ndim == 1 and arr.shape[0] == 3:
        arr = arr.reshape(1, 3)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise MagcompError(f"{name}: expected an array of shape (n, 3), got {arr.shape}")
    return arr


@dataclass(frozen=True, slots=True)
class EstimateColumns:
    """A list of HeadingEstimate as columns (what replay sends)."""

    t_s: F64
    heading_deg: F64
    heading_raw_deg: F64
    theta_mgauss: F64
    bias_mgauss: F64
    throttle_01: F64
    flags: NDArray[np.int64]
    field_raw_mgauss: F64
    field_cal_mgauss: F64
    residual_norm_mgauss: F64
    excitation: F64
    theta_sigma_mgauss: F64

    @classmethod
    def from_estimates(cls, estimates: Sequence[HeadingEstimate]) -> EstimateColumns:
        """The columns of a non-empty list: each field stacked from the HeadingEstimate field of its name
        (vectors as (n, 3)); ``flags`` as int64, the rest as float64."""
        cols: dict[str, NDArray[Any]] = {}
        for f in fields(cls):
            dtype = np.int64 if f.name == "flags" else np.float64
            cols[f.name] = np.array([getattr(e, f.name) for e in estimates], dtype=dtype)
        return cls(**cols)


THETA_BAND_LIMIT_MGAUSS = 1e5
"""Band edges are clamped to +-this: an axis not yet excited has a huge sigma, drawn off the plot."""


def theta_band(
    theta_mgauss: F64, sigma_mgauss: F64
) -> tuple[NDArray[np.bool_], F64]:
    """The +-1 sigma band of theta-hat per axis: ``(rows, edges)`` with ``rows`` (n, 3) True where the band is
    drawn (finite theta and sigma >= 0) and ``edges`` (n, 3, 2) = (theta - sigma, theta + sigma), clamped to
    +-:data:`THETA_BAND_LIMIT_MGAUSS`."""
    th = np.asarray(theta_mgauss, dtype=float).reshape(-1, 3)
    sd = np.asarray(sigma_mgauss, dtype=float).reshape(-1, 3)
    rows = np.isfinite(th) & np.isfinite(sd) & (sd >= 0.0)
    sd = np.where(rows, sd, 0.0)
    edges = np.clip(np.stack([th - sd, th + sd], axis=-1), -THETA_BAND_LIMIT_MGAUSS, THETA_BAND_LIMIT_MGAUSS)
    return rows, edges


def flag_changes(flags: NDArray[np.int64]) -> NDArray[np.intp]:
    """Indices where the flags differ from the previous row (always the first row)."""
    if flags.shape[0] == 0:
        return np.zeros(0, dtype=np.intp)
    change = np.ones(flags.shape[0], dtype=bool)
    change[1:] = flags[1:] != flags[:-1]
    return np.flatnonzero(change)


BIAS_CANVAS_X = 100.0
"""Fig. 7 canvas: throttle^2 0..1 is drawn over x = 0..100."""
BIAS_CANVAS_Y = 50.0
"""Fig. 7 canvas: +-bias_range_mgauss is drawn over y = -50..50 (y up: Rerun's 2D y axis points down)."""


def nice_range(value: float) -> float:
    """The smallest 1, 2 or 5 x 10^k at or above ``value`` (at least 1): an axis limit that reads well."""
    v = max(float(value), 1.0)
    exp = 10.0 ** math.floor(math.log10(v))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * exp >= v * (1 - 1e-12):
            return m * exp
    return 10.0 * exp  # pragma: no cover


@dataclass(frozen=True, slots=True)
class BiasFitCanvas:
    """The Fig. 7 view drawn on a fixed 2D canvas, so the view's bounds are known before the data.

    ``points``: (3, n, 2) canvas positions of the measured bias per axis; ``lines``: (3, 2, 2) the fitted
    lines ``B = theta * throttle^2`` (eq. (11)) from throttle^2 = 0 to 1, or None; ``range_mgauss``: the bias
    at the canvas's top edge."""

    range_mgauss: float
    points: F64
    lines: F64 | None

    def to_canvas(
        self, throttle2: F64, bias_mgauss: F64
    ) -> F64:
        """(x, y) canvas coordinates of (throttle^2, bias)."""
        x = np.asarray(throttle2, dtype=float) * BIAS_CANVAS_X
        y = -np.asarray(bias_mgauss, dtype=float) / self.range_mgauss * BIAS_CANVAS_Y
        return np.stack([x, y], axis=-1)


def bias_fit_canvas(
    throttle2: F64, bias_mgauss: F64, theta_line: F64 | None
) -> BiasFitCanvas:
    """Place measured bias (n, 3) against throttle^2 (n,) and the fitted lines on the Fig. 7 canvas."""
    values = [np.abs(bias_mgauss[np.isfinite(bias_mgauss)])]
    th = None if theta_line is None else np.asarray(theta_line, dtype=float).reshape(3)
    if th is not None:
        values.append(np.abs(th[np.isfinite(th)]))
    allv = np.concatenate([v.reshape(-1) for v in values] + [np.zeros(1)])
    canvas = BiasFitCanvas(nice_range(float(np.max(allv))), np.zeros((3, 0, 2)), None)
    pts = np.stack([canvas.to_canvas(throttle2, bias_mgauss[:, k]) for k in range(3)])
    lines = None
    if th is not None:
        ends = np.array([0.0, 1.0])
        lines = np.stack([canvas.to_canvas(ends, th[k] * ends) for k in range(3)])  # eq. (11)
    return BiasFitCanvas(canvas.range_mgauss, pts, lines)


# ----------------------------------------------------------------------------------------------------------
# The Rerun sink
# ----------------------------------------------------------------------------------------------------------


def labelled_axis_range(values: Sequence[float], above: float, below: float = 0.1) -> tuple[float, float]:
    """A y range holding every finite value and 0, with ``below`` x the span as margin under the data and
    ``above`` x the span over it (room for a legend in the top corner), rounded out to multiples of the
    largest power of ten p at or below its span. The plot labels its ticks at multiples of a power of ten
    that are far enough apart on screen; the span is then at most 12 p, so the ticks at multiples of p are
    at least 1/13 of the plot's height apart and labelled, and both rounded ends are such ticks: at least
    two labels (a range of -70..78 showed a single "0"). 4 % of the span is added beyond each rounded end
    so that the end labels are not cut by the plot's edge."""
    finite = [float(v) for v in values if math.isfinite(float(v))] + [0.0]
    lo, hi = min(finite), max(finite)
    span = max(hi - lo, 10.0)
    lo, hi = lo - below * span, hi + above * span
    p = 10.0 ** math.floor(math.log10(hi - lo))
    lo, hi = math.floor(lo / p) * p, math.ceil(hi / p) * p
    edge = 0.04 * (hi - lo)  # the end ticks' labels drawn whole, not cut by the plot's edge
    return (lo - edge, hi + edge)


def theta_axis_range(values_mgauss: Sequence[float]) -> tuple[float, float]:
    """The theta plot's y range (:func:`labelled_axis_range`): 60 % of the span above the data, where the
    legend (theta, its band, the reference lines) sits."""
    return labelled_axis_range(values_mgauss, above=0.6)


def bias_axis_range(values_mgauss: Sequence[float]) -> tuple[float, float]:
    """The bias-over-time plot's y range (:func:`labelled_axis_range`): 40 % above for its 3-line legend."""
    return labelled_axis_range(values_mgauss, above=0.4)


HEADING_AXIS_RANGE = (-10.0, 480.0)
"""Heading plot's y range (deg): 0..360 with room for the legend above."""


def _cloud_views() -> tuple[Any, Any]:
    """Fig. 5's two 3D views: the raw ellipsoid and the calibrated sphere, every row up to the cursor."""
    import rerun.blueprint as rrb

    everything = rrb.VisibleTimeRange(
        TIMELINE, start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.cursor_relative()
    )
    raw, cal = (
        rrb.Spatial3DView(
            name=name, origin="/mag", contents=[cloud, flight, "/mag/origin/**"], time_ranges=everything
        )
        for name, cloud, flight in (
            ("Raw field: ellipsoid (Fig. 5)", "/mag/raw_cloud", "/mag/flight/raw"),
            ("Calibrated: sphere (Fig. 5)", "/mag/calibrated_cloud", "/mag/flight/calibrated"),
        )
    )
    return raw, cal


def build_blueprint(
    live: bool,
    theta_range: tuple[float, float] | None = None,
    bias_fit: bool = False,
    bias_range: tuple[float, float] | None = None,
) -> Any:
    """The view layout (a ``rerun.blueprint.Blueprint``): headings and theta on the left; clouds, bias fit,
    power, observer and status on the right. Every time-series plot shows the whole run on its x axis (not
    Rerun's default window around the time cursor), so theta's transient in the spin segment stays in view.
    ``theta_range``: the theta plot's y range (mgauss), see :func:`theta_axis_range`; None = automatic.
    ``bias_fit``: a Fig. 7 fit was logged: its tab is the one shown, else the bias over time (a live run
    has no fit until it ends, and an empty tab reads "No data available"). ``bias_range``: the bias plot's
    y range, see :func:`bias_axis_range`; None = automatic."""
    import rerun as rr
    import rerun.blueprint as rrb

    del live  # live and replay now share the layout; kept for callers
    whole_run = rrb.TimeAxis(
        link="Independent",
        view_range=rr.TimeRange(start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite()),
    )

    def plot(name: str, origin: str, corner: Any = "LeftTop", y: tuple[float, float] | None = None) -> Any:
        return rrb.TimeSeriesView(
            name=name,
            origin=origin,
            axis_x=whole_run,
            axis_y=None if y is None else rrb.ScalarAxis(range=y),
            plot_legend=rrb.PlotLegend(corner=corner),
        )

    heading = plot(
        "Heading raw / corrected / truth (Fig. 9), deg", "/heading", "RightTop", HEADING_AXIS_RANGE
    )
    heading_error = plot("Heading error (Fig. 9), deg", "/heading_error", "RightBottom")
    theta = plot("theta-hat vs offline / truth (Fig. 8), mgauss", "/theta", "RightTop", theta_range)
    fit_view = rrb.Spatial2DView(
        name="Bias vs throttle² (Fig. 7)",
        origin="/bias/fit",
        visual_bounds=rrb.VisualBounds2D(
            x_range=[-0.25 * BIAS_CANVAS_X, 1.35 * BIAS_CANVAS_X],
            y_range=[-1.3 * BIAS_CANVAS_Y, 1.3 * BIAS_CANVAS_Y],
        ),
    )
    bias_t = plot("Bias theta·throttle², mgauss", "/bias/estimate", "LeftTop", bias_range)
    power = rrb.Vertical(
        plot("Throttle 0..1", "/power/throttle", "LeftTop", (-0.05, 1.8)),
        plot("Current, A", "/power/current", "LeftTop"),
        plot("Voltage, V", "/power/voltage", "LeftBottom"),
        name="Power",
    )
    observer = rrb.Vertical(
        plot("Residual norm, mgauss", "/observer/residual_norm", "RightTop"),
        plot("Rotation excitation (eq. 21), rad²/s²", "/observer/excitation", "RightTop"),
        name="Observer",
    )
    status = rrb.TextLogView(name="Status", origin="/status")
    layout = rrb.Horizontal(
        rrb.Vertical(heading, heading_error, theta, row_shares=[3, 2, 3]),
        rrb.Vertical(
            rrb.Horizontal(*_cloud_views()),
            rrb.Tabs(fit_view, bias_t, active_tab=0 if bias_fit else 1),
            rrb.Tabs(power, observer, status, active_tab=0),
            row_shares=[3, 2, 3],
        ),
        column_shares=[3, 2],
    )
    return rrb.Blueprint(
        layout,
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=TIMELINE),
        auto_views=False,
    )


class RerunViz:
    """The Rerun sink: a dedicated ``RecordingStream`` (not the global one) with one of the four sinks."""

    def __init__(
        self,
        mode: VizMode,
        *,
        app_id: str = "magcomp",
        live: bool,
        recording_name: str | None = None,
        grpc_port: int | None = None,
        web_port: int | None = None,
    ) -> None:
        import rerun as rr

        self._rr = rr
        self.mode = mode
        self.live = live
        self._url: str | None = None
        self._notice: str | None = None
        self._closed = False
        self._page: PageServer | None = None
        rec = rr.RecordingStream(app_id, recording_id=uuid.uuid4())  # distinct runs stay distinct
        self._rec: rr_types.RecordingStream = rec
        if not live:
            # Replay: message time is the only meaningful clock; Rerun's wall-clock/tick timelines are noise.
            rec.set_log_time_enabled(False)
            rec.set_log_tick_enabled(False)
        blueprint = build_blueprint(live)
        prefix = f"{mode.reason}; " if mode.reason else ""
        try:
            if mode.kind == "save":
                rec.save(mode.target, default_blueprint=blueprint)
                self._url = mode.target
                self._notice = f"{prefix}Rerun recording: {mode.target} (open it with: rerun {mode.target})"
            elif mode.kind == "connect":
                rec.connect_grpc(mode.target, default_blueprint=blueprint)
                self._url = mode.target
                self._notice = f"{prefix}streaming to the Rerun viewer at {mode.target}"
            elif mode.kind == "spawn":
                port = free_port(DEFAULT_GRPC_PORT)
                rec.spawn(port=port, connect=True, default_blueprint=blueprint)
                self._url = f"rerun+http://127.0.0.1:{port}/proxy"
                self._notice = f"{prefix}started the Rerun viewer (port {port})"
            elif mode.kind == "serve":
                self._serve(mode.target or SERVE_LOCAL, blueprint, prefix, grpc_port, web_port)
            else:  # pragma: no cover - parse_mode only returns the four kinds
                raise MagcompError(f"--rerun: unknown mode {mode.kind!r}")
        except MagcompError:
            raise
        except Exception as exc:  # rerun raises plain RuntimeError/ValueError from its bindings
            raise MagcompError(f"--rerun {mode.kind}: could not open the Rerun sink: {exc}") from exc
        if recording_name:
            rec.send_recording_name(recording_name)
        self._send_styles()
        # state
        self._t_min = math.inf
        self._t_max = -math.inf
        self._theta_refs: dict[str, F64] = {}
        self._ref_sent_t = -math.inf
        self._truth = TruthHeading()
        # heading rows whose errors against the truth are not sent yet (the truth came later or not at all)
        self._err_pending: list[tuple[F64, F64, F64]] = []
        self._last_flags: int | None = None
        self._live_buffer: list[HeadingEstimate] = []
        self._live_flushed_t = -math.inf
        self._slow_bucket: dict[str, float] = {}
        self._theta_lo = math.inf
        self._theta_hi = -math.inf
        self._theta_range: tuple[float, float] | None = None
        self._bias_fit_shown = False
        self._power_buffer: list[tuple[F64, F64]] = []
        self._bias_lo = math.inf
        self._bias_hi = -math.inf
        self._bias_range: tuple[float, float] | None = None
        self._origin_radius = 0.0
        self._cloud_pick = StreamDecimator(CLOUD_MAX_POINTS)
        self._cloud_raw: list[F64] = []
        self._cloud_cal: list[F64] = []
        self._cloud_sent_t = -math.inf

    def _serve(
        self, bind: str, blueprint: Any, prefix: str, grpc_port: int | None, web_port: int | None
    ) -> None:
        """``serve``: the recording's gRPC server in this process and the page (Rerun's binary, else this
        process), both on ``bind``; the URL to open and the notice."""
        rr = self._rr
        gport = grpc_port if grpc_port is not None else free_port(DEFAULT_GRPC_PORT)
        wport = web_port if web_port is not None else free_port(DEFAULT_WEB_PORT)
        server = rr.GrpcServerSink(bind_ip=bind, port=gport, server_memory_limit="512MiB")
        self._rec.set_sinks(server, default_blueprint=blueprint)
        grpc_url = local_grpc_url(bind, gport, str(server.uri))
        self._page, why_not = start_page_server(bind, wport, grpc_url)
        if self._page is None:  # the page from this process: rerun 0.41 binds it to every interface
            rr.serve_web_viewer(web_port=wport, open_browser=False, connect_to=grpc_url)
        self._url = web_viewer_url(wport, grpc_url)
        self._notice = prefix + serve_notice(self._url, gport, wport)
        if why_not:
            self._notice += f"\n  the page (port {wport}) is served on every interface: {why_not}"

    # -- properties ----------------------------------------------------------------------------------------
    @property
    def url(self) -> str | None:
        return self._url

    @property
    def notice(self) -> str | None:
        return self._notice

    @property
    def keeps_serving(self) -> bool:
        return self.mode.kind == "serve"

    @property
    def recording(self) -> Any:
        """The underlying ``rerun.RecordingStream`` (tests, advanced use)."""
        return self._rec

    # -- static styling --------------------------------------------------------------------------------------
    def _series_style(self, path: str, color: Sequence[int], name: str, width: float = 1.5) -> None:
        rr = self._rr
        self._rec.log(path, rr.SeriesLines(colors=[list(color)], names=[name], widths=[width]), static=True)

    def _send_styles(self) -> None:
        self._rec.log(
            "bias/estimate",
            self._rr.SeriesLines(colors=[list(c) for c in COLOR_AXES], names=[f"B_{ax}" for ax in AXES]),
            static=True,
        )
        for k, ax in enumerate(AXES):
            self._series_style(f"theta/{ax}", COLOR_AXES[k], f"theta_{ax}", 2.0)
            # the +-1 sigma band: two thin lines in a light shade of the axis colour, one legend entry
            light = band_color(COLOR_AXES[k])
            self._rec.log(
                f"theta/band/{ax}",
                self._rr.SeriesLines(colors=[light, light], names=[f"theta_{ax} ±1σ"] * 2, widths=[1.0, 1.0]),
                static=True,
            )
            faded = [int(0.55 * c) for c in COLOR_AXES[k]]
            self._series_style(f"theta/offline/{ax}", faded, f"offline LS theta_{ax}", 5.0)
            self._series_style(f"theta/truth/{ax}", COLOR_TRUTH_LINE, "true theta (x, y, z)", 1.0)
        self._series_style("heading/raw", COLOR_RAW, "raw (B-hat = 0)", 2.0)
        self._series_style("heading/corrected", COLOR_CORRECTED, "corrected (B-hat = theta·throttle²)", 3.0)
        self._series_style("heading/truth", COLOR_TRUTH_LINE, "truth", 1.0)
        self._series_style("heading_error/raw", COLOR_RAW, "raw - truth", 2.0)
        self._series_style("heading_error/corrected", COLOR_CORRECTED, "corrected - truth", 2.0)
        self._series_style("heading_error/raw_minus_corrected", COLOR_CORRECTION, "raw - corrected", 1.0)
        self._series_style("power/throttle", (230, 200, 60), "throttle")
        self._series_style("power/throttle/at_mag", (150, 130, 40), "throttle at mag sample")
        self._series_style("power/current", (230, 120, 60), "current A")
        self._series_style("power/voltage", (120, 200, 230), "voltage V")
        self._series_style("observer/residual_norm", (200, 200, 120), "|residual| mgauss")
        self._series_style("observer/excitation", (150, 220, 150), "lambda_min")

    # -- time helpers --------------------------------------------------------------------------------------
    def _time_col(self, t_s: F64) -> Any:
        return self._rr.TimeColumn(TIMELINE, duration=np.asarray(t_s, dtype=float))

    def _send_scalars(
        self, path: str, t_s: F64, values: F64, drop_nan: bool
    ) -> None:
        if drop_nan:
            ok = np.isfinite(values)
            t_s, values = t_s[ok], values[ok]
        if t_s.shape[0] == 0:
            return
        self._rec.send_columns(
            path, indexes=[self._time_col(t_s)], columns=self._rr.Scalars.columns(scalars=values)
        )

    def _see_times(self, t_s: F64) -> None:
        finite = t_s[np.isfinite(t_s)]
        if finite.size:
            self._t_min = min(self._t_min, float(finite.min()))
            self._t_max = max(self._t_max, float(finite.max()))

    # -- live ----------------------------------------------------------------------------------------------
    def log_estimate(self, est: HeadingEstimate) -> None:
        """Live: buffered and sent as columns every :data:`LIVE_FLUSH_PERIOD_S` of message time (one row per
        estimate and entity, but a few chunks per second instead of ~12 one-row chunks per estimate, which
        the web viewer takes minutes to ingest). Any other call, and close(), sends the buffer first."""
        t = float(est.t_s)
        if self._live_buffer and t < self._live_flushed_t:  # the clock went back: keep blocks in order
            self._flush_live()
        self._live_buffer.append(est)
        if not math.isfinite(self._live_flushed_t) or t < self._live_flushed_t:
            self._live_flushed_t = t
        if t - self._live_flushed_t >= LIVE_FLUSH_PERIOD_S:
            self._flush_live()

    def _flush_live(self) -> None:
        if not self._live_buffer:
            return
        block = self._live_buffer
        self._live_buffer = []
        self._live_flushed_t = float(block[-1].t_s)
        self._send_estimate_block(EstimateColumns.from_estimates(block), live=True)

    def _slow_rows(self, key: str, t_s: F64) -> NDArray[np.bool_]:
        """Live: rows to keep so that entity group ``key`` gets at most one row per 1/LIVE_SLOW_HZ s of
        message time (the first row of each new time bucket)."""
        if not self.live:
            return np.ones(t_s.shape[0], dtype=bool)
        bucket = np.floor(np.asarray(t_s, dtype=float) * LIVE_SLOW_HZ)
        keep = np.zeros(t_s.shape[0], dtype=bool)
        last = self._slow_bucket.get(key, -math.inf)
        for i, bk in enumerate(bucket):
            if math.isfinite(bk) and bk != last:
                keep[i] = True
                last = float(bk)
        self._slow_bucket[key] = last
        return keep

    # -- replay --------------------------------------------------------------------------------------------
    def log_estimates(self, estimates: Sequence[HeadingEstimate]) -> None:
        self._flush_live()
        if not estimates:
            return
        self._send_estimate_block(EstimateColumns.from_estimates(estimates), live=False)

    def _send_estimate_block(self, cols: EstimateColumns, *, live: bool) -> None:
        """One block of estimates as columns: theta, heading, bias one row per estimate; throttle and the
        observer at most LIVE_SLOW_HZ in live mode; flags on change; heading errors once truth is known."""
        t = cols.t_s
        for k, ax in enumerate(AXES):
            self._send_scalars(f"theta/{ax}", t, cols.theta_mgauss[:, k], drop_nan=False)
        self._send_theta_band(t, cols.theta_mgauss, cols.theta_sigma_mgauss)
        n = t.shape[0]
        self._rec.send_columns(
            "bias/estimate",
            indexes=[self._time_col(t)],
            columns=self._rr.Scalars.columns(scalars=cols.bias_mgauss.reshape(-1)).partition(np.full(n, 3)),
        )
        self._send_scalars("heading/raw", t, cols.heading_raw_deg, drop_nan=False)
        self._send_scalars("heading/corrected", t, cols.heading_deg, drop_nan=False)
        self._send_scalars(
            "heading_error/raw_minus_corrected",
            t,
            wrap_deg(cols.heading_raw_deg - cols.heading_deg),
            drop_nan=True,
        )
        slow = self._slow_rows("estimate", t)
        self._send_scalars("power/throttle/at_mag", t[slow], cols.throttle_01[slow], drop_nan=True)
        self._send_scalars("observer/residual_norm", t[slow], cols.residual_norm_mgauss[slow], drop_nan=True)
        self._send_scalars("observer/excitation", t[slow], cols.excitation[slow], drop_nan=True)
        changes = flag_changes(cols.flags)
        if self._last_flags is not None and changes.size and int(cols.flags[0]) == self._last_flags:
            changes = changes[1:]
        if changes.size:
            texts = [f"flags: {flags_text(int(f))}" for f in cols.flags[changes]]
            self._rec.send_columns(
                "status/flags",
                indexes=[self._time_col(t[changes])],
                columns=self._rr.TextLog.columns(text=texts, level=["INFO"] * len(texts)),
            )
        self._last_flags = int(cols.flags[-1])
        self._see_times(t)
        self._err_pending.append((t, cols.heading_raw_deg, cols.heading_deg))
        self._send_heading_errors()
        if live:
            for i in range(n):
                if self._cloud_pick.accept():
                    self._cloud_raw.append(cols.field_raw_mgauss[i])
                    self._cloud_cal.append(cols.field_cal_mgauss[i])
            t_last = float(t[-1])
            if t_last - self._cloud_sent_t >= LIVE_CLOUD_PERIOD_S or t_last < self._cloud_sent_t:
                self._flush_live_cloud(t_last)
        elif t.size:
            self._send_flight_clouds(
                thin_rows(cols.field_raw_mgauss, CLOUD_MAX_POINTS),
                thin_rows(cols.field_cal_mgauss, CLOUD_MAX_POINTS),
                float(np.nanmin(t)) if np.isfinite(t).any() else 0.0,
            )
        theta = cols.theta_mgauss[np.isfinite(cols.theta_mgauss)]
        if theta.size:
            self._theta_lo = min(self._theta_lo, float(theta.min()))
            self._theta_hi = max(self._theta_hi, float(theta.max()))
        bias = cols.bias_mgauss[np.isfinite(cols.bias_mgauss)]
        if bias.size:
            self._bias_lo = min(self._bias_lo, float(bias.min()))
            self._bias_hi = max(self._bias_hi, float(bias.max()))
        if self._theta_refs and (
            not live or t[-1] - self._ref_sent_t >= LIVE_CLOUD_PERIOD_S or t[-1] < self._ref_sent_t
        ):
            self._send_reference_lines()
        self._update_axes()

    def _send_theta_band(
        self, t_s: F64, theta_mgauss: F64, sigma_mgauss: F64
    ) -> None:
        """theta-hat +- its 1-sigma per axis (entity ``theta/band/{x,y,z}``, two scalars a row: lower, upper),
        where the estimate carries a sigma; live: thinned to LIVE_SLOW_HZ of message time."""
        keep = self._slow_rows("band", t_s)
        rows, edges = theta_band(theta_mgauss[keep], sigma_mgauss[keep])
        t_keep = t_s[keep]
        for k, ax in enumerate(AXES):
            ok = rows[:, k]
            n = int(ok.sum())
            if n == 0:
                continue
            self._rec.send_columns(
                f"theta/band/{ax}",
                indexes=[self._time_col(t_keep[ok])],
                columns=self._rr.Scalars.columns(scalars=edges[ok, k].reshape(-1)).partition(np.full(n, 2)),
            )

    def _update_axes(self) -> None:
        """Send the blueprint again with a wider theta (bias) y range when theta-hat or a reference line
        (the bias) left it."""
        theta_values = [self._theta_lo, self._theta_hi]
        for ref in self._theta_refs.values():
            theta_values.extend(float(v) for v in ref)
        theta_range = _grown(self._theta_range, theta_values, theta_axis_range)
        bias_range = _grown(self._bias_range, [self._bias_lo, self._bias_hi], bias_axis_range)
        if theta_range == self._theta_range and bias_range == self._bias_range:
            return
        self._theta_range, self._bias_range = theta_range, bias_range
        self._send_blueprint()

    def _send_blueprint(self) -> None:
        self._rec.send_blueprint(
            build_blueprint(self.live, self._theta_range, self._bias_fit_shown, self._bias_range)
        )

    def _send_heading_errors(self) -> None:
        """Errors against the truth (Fig. 9) for every heading row the truth now covers; rows outside the
        truth's span stay pending until more truth arrives."""
        if not len(self._truth) or not self._err_pending:
            return
        still: list[tuple[F64, F64, F64]] = []
        for t, raw, cor in self._err_pending:
            truth = self._truth.at(t)
            ok = np.isfinite(truth)
            if ok.any():
                self._send_scalars("heading_error/raw", t[ok], wrap_deg(raw[ok] - truth[ok]), drop_nan=True)
                self._send_scalars(
                    "heading_error/corrected", t[ok], wrap_deg(cor[ok] - truth[ok]), drop_nan=True
                )
            if not ok.all():
                still.append((t[~ok], raw[~ok], cor[~ok]))
        self._err_pending = still

    def _flush_live_cloud(self, t_s: float) -> None:
        """Live: the points picked since the last flush, as one row; the 3D views show every row up to the
        cursor (their visible time range starts at -inf), so the cloud grows without being sent again."""
        self._cloud_sent_t = t_s
        if self._cloud_raw:
            self._send_flight_clouds(np.vstack(self._cloud_raw), np.vstack(self._cloud_cal), t_s)
            self._cloud_raw.clear()
            self._cloud_cal.clear()

    def _send_flight_clouds(self, raw: F64, cal: F64, t_s: float) -> None:
        rr, rec = self._rr, self._rec
        rec.set_time(TIMELINE, duration=float(t_s))
        for path, pts, color in (
            ("mag/flight/raw", raw, COLOR_RAW),
            ("mag/flight/calibrated", cal, COLOR_CORRECTED),
        ):
            pts = pts[np.isfinite(pts).all(axis=1)]
            if pts.shape[0] == 0:
                continue
            rec.log(path, rr.Points3D(pts, radii=_cloud_radius(pts), colors=[list(color)]))
        self._log_origin_axes(cal)

    def _log_origin_axes(self, calibrated: F64) -> None:
        """Fig. 5: axes through the origin, +-1.3x the calibrated radius, in both 3D views, so the raw
        ellipsoid's offset from 0 (hard iron) and the calibrated sphere's centring show."""
        pts = calibrated[np.isfinite(calibrated).all(axis=1)]
        if pts.shape[0] == 0:
            return
        radius = 1.3 * float(np.median(np.linalg.norm(pts, axis=1)))
        if not math.isfinite(radius) or radius <= 0.0 or abs(radius - self._origin_radius) < 0.1 * radius:
            return
        self._origin_radius = radius
        rr = self._rr
        unit = np.eye(3)
        strips = [np.stack([-radius * unit[k], radius * unit[k]]) for k in range(3)]
        self._rec.log(
            "mag/origin/axes",
            rr.LineStrips3D(strips, radii=radius / 400.0, colors=[list(c) for c in COLOR_AXES]),
            static=True,
        )
        self._rec.log(
            "mag/origin/labels",
            rr.Points3D(
                np.vstack([1.05 * radius * unit, np.zeros((1, 3))]),
                radii=radius / 100.0,
                colors=[list(c) for c in COLOR_AXES] + [[230, 230, 230]],
                labels=["x", "y", "z", "0"],
                show_labels=True,
            ),
            static=True,
        )

    # -- references, truth, power, fits --------------------------------------------------------------------
    def log_reference_theta(
        self, theta_offline_mgauss: ArrayLike | None, theta_truth_mgauss: ArrayLike | None
    ) -> None:
        for name, value in (("offline", theta_offline_mgauss), ("truth", theta_truth_mgauss)):
            if value is None:
                self._theta_refs.pop(name, None)
                continue
            arr = np.asarray(value, dtype=float).reshape(-1)
            if arr.shape[0] != 3:
                raise MagcompError(
                    f"log_reference_theta: theta_{name} must have 3 components, got {arr.shape[0]}"
                )
            self._theta_refs[name] = arr
        self._flush_live()
        self._send_reference_lines()
        self._update_axes()

    def _send_reference_lines(self) -> None:
        if not self._theta_refs:
            return
        if math.isfinite(self._t_min):
            t = np.array([self._t_min, self._t_max]) if self._t_max > self._t_min else np.array([self._t_min])
        else:
            t = np.array([0.0])
        for name, theta in self._theta_refs.items():
            for k, ax in enumerate(AXES):
                self._send_scalars(f"theta/{name}/{ax}", t, np.full(t.shape[0], theta[k]), drop_nan=True)
        self._ref_sent_t = float(t[-1])

    def log_truth_heading(self, t_s: ArrayLike, heading_deg: ArrayLike) -> None:
        t = _as_1d(t_s)
        deg = _as_1d(heading_deg)
        if t.shape != deg.shape:
            raise MagcompError(f"log_truth_heading: {t.shape[0]} times but {deg.shape[0]} headings")
        self._flush_live()
        self._truth.add(t, deg)
        self._send_scalars("heading/truth", t, deg, drop_nan=True)
        self._send_heading_errors()

    def log_power(
        self, t_s: ArrayLike, throttle_01: ArrayLike, current_a: ArrayLike, voltage_v: ArrayLike
    ) -> None:
        """Live: buffered and sent every :data:`LIVE_FLUSH_PERIOD_S` of message time, apart from the
        estimates (``run`` logs one battery sample at a time: sending each at once, and the estimates
        buffered before it, made ~20 one-row chunks a second that the web viewer took in at a fraction of
        real time)."""
        t = _as_1d(t_s)
        columns = []
        for path, values in (
            ("power/throttle", throttle_01),
            ("power/current", current_a),
            ("power/voltage", voltage_v),
        ):
            v = _as_1d(values)
            if v.shape[0] == 1 and t.shape[0] > 1:
                v = np.full(t.shape[0], v[0])
            if v.shape[0] != t.shape[0]:
                raise MagcompError(f"log_power: {t.shape[0]} times but {v.shape[0]} values for {path}")
            columns.append(v)
        slow = self._slow_rows("power", t)
        if not self.live:
            self._send_power(t[slow], np.stack(columns)[:, slow])
            return
        if not t[slow].size:
            return
        if self._power_buffer and t[slow][0] < self._power_buffer[-1][0][-1]:  # the clock went back
            self._flush_power()
        self._power_buffer.append((t[slow], np.stack(columns)[:, slow]))
        if t[slow][-1] - self._power_buffer[0][0][0] >= LIVE_FLUSH_PERIOD_S:
            self._flush_power()

    def _flush_power(self) -> None:
        if self._power_buffer:
            t = np.concatenate([b[0] for b in self._power_buffer])
            values = np.concatenate([b[1] for b in self._power_buffer], axis=1)
            self._power_buffer.clear()
            self._send_power(t, values)

    def _send_power(self, t: F64, values: F64) -> None:
        """``values`` (3, n): throttle, current, voltage at ``t``."""
        for path, v in zip(("power/throttle", "power/current", "power/voltage"), values, strict=True):
            self._send_scalars(path, t, v, drop_nan=True)

    def log_bias_fit(
        self, throttle2: ArrayLike, bias_mgauss: ArrayLike, theta_line: ArrayLike | None
    ) -> None:
        self._flush_live()
        rr, rec = self._rr, self._rec
        thr2 = _as_1d(throttle2)
        bias = _as_rows3(bias_mgauss, "log_bias_fit bias_mgauss")
        if bias.shape[0] != thr2.shape[0]:
            raise MagcompError(
                f"log_bias_fit: {thr2.shape[0]} throttle^2 values but {bias.shape[0]} bias rows"
            )
        keep = np.isfinite(thr2) & np.isfinite(bias).all(axis=1)
        both = thin_rows(np.column_stack([thr2[keep], bias[keep]]), BIAS_FIT_MAX_POINTS)
        line = None if theta_line is None else np.asarray(theta_line, dtype=float).reshape(3)
        canvas = bias_fit_canvas(both[:, 0], both[:, 1:], line)
        if not self._bias_fit_shown:  # the Fig. 7 tab now has data: show it
            self._bias_fit_shown = True
            self._send_blueprint()
        for k, ax in enumerate(AXES):
            rec.log(
                f"bias/fit/points/{ax}",
                rr.Points2D(canvas.points[k], radii=0.6, colors=[COLOR_AXES[k]]),
                static=True,
            )
            if canvas.lines is not None:
                rec.log(
                    f"bias/fit/line/{ax}",
                    rr.LineStrips2D([canvas.lines[k]], radii=0.35, colors=[COLOR_AXES[k]]),
                    static=True,
                )
                end = canvas.lines[k][1]
                rec.log(
                    f"bias/fit/label/{ax}",
                    rr.Points2D(
                        [end + np.array([2.0, 0.0])],
                        radii=0.01,
                        colors=[COLOR_AXES[k]],
                        labels=[f"theta_{ax} = {line[k]:.1f}" if line is not None else ax],
                        show_labels=True,
                    ),
                    static=True,
                )
        r = canvas.range_mgauss
        grey = [140, 140, 140]
        rec.log(
            "bias/fit/axes",
            rr.LineStrips2D(
                [
                    [[0.0, 0.0], [BIAS_CANVAS_X, 0.0]],
                    [[0.0, -BIAS_CANVAS_Y], [0.0, BIAS_CANVAS_Y]],
                    [[BIAS_CANVAS_X, -1.5], [BIAS_CANVAS_X, 1.5]],
                ],
                radii=0.15,
                colors=[grey],
            ),
            static=True,
        )
        rec.log(
            "bias/fit/ticks",
            rr.Points2D(
                [[0.0, -BIAS_CANVAS_Y], [0.0, BIAS_CANVAS_Y], [BIAS_CANVAS_X, 16.0], [0.0, 6.0]],
                radii=0.01,
                colors=[grey],
                labels=[f"+{r:g} mgauss", f"-{r:g} mgauss", "throttle² = 1", "0"],
                show_labels=True,
            ),
            static=True,
        )

    def log_calibration_cloud(self, raw_mgauss: ArrayLike, calibrated_mgauss: ArrayLike) -> None:
        self._flush_live()
        rr, rec = self._rr, self._rec
        for path, arr, color in (
            ("mag/raw_cloud", raw_mgauss, COLOR_RAW),
            ("mag/calibrated_cloud", calibrated_mgauss, COLOR_CORRECTED),
        ):
            pts = _as_rows3(arr, f"log_calibration_cloud {path}")
            pts = thin_rows(pts[np.isfinite(pts).all(axis=1)], CLOUD_MAX_POINTS)
            faded = [int(0.7 * c) for c in color]
            rec.log(path, rr.Points3D(pts, radii=_cloud_radius(pts), colors=[faded]), static=True)
            if path == "mag/calibrated_cloud":
                self._log_origin_axes(pts)

    def log_text(self, t_s: float, msg: str) -> None:
        self._flush_live()
        self._rec.send_columns(
            "status/messages",
            indexes=[self._time_col(np.array([float(t_s)]))],
            columns=self._rr.TextLog.columns(text=[msg], level=["INFO"]),
        )

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._flush_live()
        self._flush_power()
        if self._cloud_raw:
            self._flush_live_cloud(self._t_max)
        if self._theta_refs:
            self._send_reference_lines()
        try:
            self._rec.flush(timeout_sec=10.0)
        finally:
            self._rec.disconnect()
            if self._page is not None:
                self._page.stop()


def _grown(
    current: tuple[float, float] | None,
    values: Sequence[float],
    make: Callable[[Sequence[float]], tuple[float, float]],
) -> tuple[float, float] | None:
    """``current`` while it holds every finite value (and 0), else ``make(values)``; None before any."""
    finite = [v for v in values if math.isfinite(v)]
    if not finite:
        return current
    lo, hi = min([*finite, 0.0]), max([*finite, 0.0])
    if current is not None and current[0] <= lo and hi <= current[1]:
        return current
    return make(finite)


def band_color(rgb: Sequence[int]) -> list[int]:
    """A light shade of ``rgb`` (60 % of the way to white) for the theta band's lines."""
    return [round(c + 0.6 * (255 - c)) for c in rgb]


def _cloud_radius(pts: F64) -> float:
    """Point radius ~1/80 of the typical field magnitude, so every batch of a cloud draws alike."""
    if pts.shape[0] == 0:
        return 1.0
    return max(float(np.median(np.linalg.norm(pts, axis=1))) / 80.0, 0.5)


def listening_hosts(port: int, proc_net: Path = Path("/proc/net")) -> set[str] | None:
    """The local addresses a TCP socket listens on at ``port`` ("0.0.0.0" / "::" for every interface), read
    from ``/proc/net/tcp`` and ``tcp6``; None where the system does not say (not Linux)."""
    import ipaddress

    found: set[str] | None = None
    for name, width in (("tcp", 8), ("tcp6", 32)):
        try:
            lines = (proc_net / name).read_text().splitlines()[1:]
        except OSError:
            continue
        found = found if found is not None else set()
        for line in lines:
            parts = line.split()
            if len(parts) < 4 or parts[3] != "0A":  # 0A: LISTEN
                continue
            addr_hex, _, port_hex = parts[1].partition(":")
            if int(port_hex, 16) != port or len(addr_hex) != width:
                continue
            raw = bytes.fromhex(addr_hex)
            # the kernel prints each 32-bit word in host (little-endian) order
            packed = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
            found.add(str(ipaddress.ip_address(packed)))
    return found


def _this_host_address() -> str:
    """An address other machines may reach this one at (the route to a private network; no packet sent)."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(("10.255.255.255", 1))
            return str(s.getsockname()[0])
    except OSError:
        return socket.gethostname()


def serve_notice(url: str, grpc_port: int, web_port: int, hosts: set[str] | None = None) -> str:
    """What ``serve`` prints: the page to open here, where the page and data servers really listen
    (``hosts``: their addresses; default read from the system), and how to reach them from another
    machine (a port forward of both ports for a headless machine)."""
    if hosts is None:
        hosts = (listening_hosts(grpc_port) or set()) | (listening_hosts(web_port) or set())
    forward = (f"ssh -L {web_port}:127.0.0.1:{web_port} -L {grpc_port}:127.0.0.1:{grpc_port} "
               "USER@THIS-MACHINE")  # fmt: skip
    lines = [f"Rerun web viewer: {url}"]
    if hosts & {"0.0.0.0", "::"}:
        ip = _this_host_address()
        remote = web_viewer_url(web_port, f"rerun+http://{ip}:{grpc_port}/proxy").replace("127.0.0.1", ip, 1)
        lines.append(f"  the page (port {web_port}) and the data (port {grpc_port}) are offered on every "
                     f"network interface: from another machine open {remote}")  # fmt: skip
    elif hosts:
        where = ", ".join(sorted(hosts))
        lines.append(f"  the page (port {web_port}) and the data (port {grpc_port}) are served on {where} "
                     f"only: from another machine forward both ports ({forward}) and open the URL above; "
                     "--rerun serve=0.0.0.0 offers them to the network")  # fmt: skip
    else:
        lines.append(f"  ports {web_port} (page) and {grpc_port} (data); from another machine forward both "
                     f"({forward}) and open the URL above")  # fmt: skip
    return "\n".join(lines)


class PageServer:
    """The web viewer's page (HTML, JS, Wasm; no data) served by Rerun's own binary on one address.

    rerun 0.41's ``serve_web_viewer`` has no bind address (it listens on every interface); its command line
    does: ``rerun --serve-web --bind ADDRESS --web-viewer-port PORT URL`` serves only the page, pointed at
    the gRPC ``URL`` (this process's recording). The child shares this process's group (a ^C at the
    terminal stops both) and, on Linux, gets SIGTERM when this process dies."""

    def __init__(self, proc: Any) -> None:
        self.proc = proc

    def stop(self) -> None:
        import subprocess

        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5.0)


def rerun_binary() -> Path | None:
    """The Rerun viewer binary shipped in rerun-sdk's wheel (``rerun_cli/rerun``), None where absent."""
    try:
        import rerun_cli
    except ImportError:
        return None
    name = "rerun.exe" if sys.platform.startswith("win") else "rerun"
    path = Path(rerun_cli.__file__).resolve().parent / name
    return path if path.is_file() and os.access(path, os.X_OK) else None


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    try:
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _listening(host: str, port: int) -> bool:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    target = "127.0.0.1" if host == "0.0.0.0" else "::1" if host == "::" else host
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.settimeout(0.5)
        return s.connect_ex((target, port)) == 0


def start_page_server(
    bind: str, web_port: int, grpc_url: str, timeout_s: float = 20.0
) -> tuple[PageServer | None, str]:
    """Serve the web viewer's page on ``bind``:``web_port`` with Rerun's binary (:class:`PageServer`);
    ``(None, why)`` when the binary is absent or did not start listening within ``timeout_s``."""
    import subprocess

    binary = rerun_binary()
    if binary is None:
        return None, "Rerun's viewer binary (rerun_cli) is not installed"
    env = dict(os.environ, RERUN_ANALYTICS=os.environ.get("RERUN_ANALYTICS", "0"))
    try:
        proc = subprocess.Popen(
            [str(binary), "--serve-web", "--bind", bind, "--web-viewer-port", str(web_port), grpc_url],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
            preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
        )  # fmt: skip
    except OSError as exc:
        return None, f"Rerun's viewer binary did not start ({exc})"
    deadline = time.monotonic() + timeout_s
    while not _listening(bind, web_port):
        if proc.poll() is not None or time.monotonic() > deadline:
            PageServer(proc).stop()
            return None, f"Rerun's viewer binary did not serve port {web_port} within {timeout_s:.0f} s"
        time.sleep(0.1)
    return PageServer(proc), ""


def local_grpc_url(bind: str, port: int, server_uri: str) -> str:
    """The gRPC URL to open on this machine: ``server_uri`` (what Rerun reports), but with an address
    that a browser here can reach where the server listens on every interface (0.0.0.0 / ::)."""
    import ipaddress

    try:
        ip = ipaddress.ip_address(bind)
    except ValueError:
        return server_uri
    if ip.is_unspecified:
        return f"rerun+http://127.0.0.1:{port}/proxy"
    host = f"[{ip}]" if ip.version == 6 else str(ip)
    return f"rerun+http://{host}:{port}/proxy"


def web_viewer_url(web_port: int, grpc_url: str) -> str:
    """The page that opens the served web viewer on the gRPC stream ``grpc_url``."""
    from urllib.parse import quote

    return f"http://127.0.0.1:{web_port}/?url={quote(grpc_url, safe='')}"
