"""The live companion: attach to a flight controller's link, run the pipeline, publish MAGCOMP_HEADING.

``Daemon.run()`` keeps going across link loss: a failed open or a dead link is logged on one clear line
and retried every ``link.reconnect_s``; silence on the master is logged once per silent spell. The same
:class:`~magcomp.service.pipeline.Pipeline` object lives across reconnects, so calibration and theta
carry over (and a rebooted autopilot's clock reset is absorbed by the pipeline). State is saved on the
way out. A housekeeping thread sends a companion HEARTBEAT (``link.heartbeat_hz``), watches for
silence and ends the run on :meth:`Daemon.stop`. Signal handlers call :meth:`Daemon.request_stop`, which
only sets a flag (no lock, no I/O: a handler runs between two bytecodes of the main thread, possibly
inside a lock that thread holds); the housekeeping thread turns the flag into :meth:`stop`, and so does
the reading thread itself (between samples, while the link is quiet, while it reconnects), so a stop
never depends on another thread being alive. A housekeeping round that fails is logged once and the
thread goes on; a housekeeping thread that ends anyway is reported and started again. The master is
opened in a helper thread (a connect that hangs cannot delay a stop), and a TCP master is reconnected
by the daemon alone: pymavlink's in-place reconnect (run by whichever thread touched the socket first)
is off, so the heartbeat writer can never race the reader onto a second socket.

Latency: for every estimate the time from the moment its magnetometer sample left the source (i.e.
was parsed) to the moment its MAGCOMP_HEADING was written to every sink is recorded
(:attr:`Daemon.latency_s`, a bounded ring).
"""

from __future__ import annotations

import errno as errno_mod
import logging
import math
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from magcomp.adapters.config import Config
from magcomp.adapters.state_store import StateStore
from magcomp.core.types import HeadingEstimate, PowerSample
from magcomp.errors import InputError
from magcomp.service.pipeline import Pipeline
from magcomp.service.publish import HeadingEncoder, LinkSink, NamedValues
from magcomp.service.replay import source_throttle
from magcomp.service.workers import Workers

log = logging.getLogger("magcomp.daemon")

LATENCY_RING = 200_000
#: messages lost on the link (MAVLink sequence-number gaps) above this fraction over LOSS_WINDOW_S give a
#: warning (at most once per LOSS_WARN_EVERY_S); every loss is counted in the summary (lost_messages)
LOSS_WARN_FRACTION = 0.01
LOSS_WINDOW_S = 2.0
LOSS_WARN_EVERY_S = 30.0


@dataclass
class DaemonReport:
    summary: dict[str, Any]
    source_counts: dict[str, int]
    connects: int
    link_losses: int
    published: int
    latency_ms: dict[str, float] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        out = dict(self.summary)
        out.update(
            source_counts=dict(sorted(self.source_counts.items())),
            connects=self.connects,
            link_losses=self.link_losses,
            published=self.published,
            latency_ms=self.latency_ms,
        )
        return out


def _grow_receive_buffer(connection: Any, size: int = 8 << 20) -> None:
    """Ask for a large socket receive buffer so a stall of the pipeline (a calibration fit, a busy
    machine) does not drop UDP datagrams; the kernel may grant less (net.core.rmem_max)."""
    import socket

    port = getattr(connection, "port", None)
    if isinstance(port, socket.socket):
        try:
            port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
        except OSError as exc:  # not fatal: the default buffer still works
            log.debug("cannot enlarge the receive buffer: %s", exc)


def _link_alive(connection: Any) -> bool:
    """A pymavlink connection whose socket or device is open (after its own reconnect)."""
    if connection is None:
        return False
    port = getattr(connection, "port", None)
    if port is None:
        return False
    fileno = getattr(port, "fileno", None)
    try:
        return fileno is None or fileno() >= 0
    except (OSError, ValueError):
        return False


def latency_stats_ms(samples_s: Sequence[float]) -> dict[str, float]:
    if len(samples_s) == 0:
        return {}
    a = np.asarray(samples_s, dtype=float) * 1e3
    return {
        "n": float(a.size),
        "p50": float(np.percentile(a, 50)),
        "p99": float(np.percentile(a, 99)),
        "max": float(a.max()),
    }


_NET_PREFIXES = ("udpin:", "udpout:", "udp:", "udpbcast:", "tcp:", "tcpin:")
_URL_FORMS = (
    "udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT, serial:DEVICE[:BAUD] "
    "or /dev/DEVICE[:BAUD]"
)


def _is_serial_device(name: str) -> bool:
    import re

    return name.startswith("/dev/") or re.match(r"^COM\d+$", name) is not None


def check_link_url(url: str, option: str = "--master") -> None:
    """Refuse, with one line, a link URL that can never open (a typo, a log file, a bad port or baud).

    A well-formed URL whose other end is not there yet (nothing listening, a serial device not plugged
    in) passes: the daemon retries it every ``link.reconnect_s``.
    """
    import os
    import stat

    text = url.strip()
    if not text:
        raise InputError(f"{option}: the link URL is empty (use {_URL_FORMS})")
    for prefix in _NET_PREFIXES:
        if text.startswith(prefix):
            host, sep, port = text[len(prefix) :].rpartition(":")
            if not sep or not host or not port.isdigit():
                raise InputError(f"{option} {url}: expected {prefix}HOST:PORT")
            listening = prefix in ("udpin:", "tcpin:")
            if not (0 if listening else 1) <= int(port) <= 65535:
                raise InputError(f"{option} {url}: port {port} is out of range")
            return
    serial = text.startswith("serial:")
    device = text.removeprefix("serial:")
    head, sep, baud = device.rpartition(":")
    if sep and (serial or _is_serial_device(head)):
        device = head
        if not baud.isdigit() or int(baud) <= 0:
            raise InputError(f"{option} {url}: the baud rate must be a positive integer, got {baud!r}")
    if not device:
        raise InputError(f"{option} {url}: the serial device is missing")
    if serial or _is_serial_device(device):
        return  # a device that is not there (yet) is retried: USB links appear when the autopilot boots
    try:
        st = os.stat(device)
    except OSError:
        st = None
    if st is not None and stat.S_ISREG(st.st_mode):
        raise InputError(f"{option} {url}: is a log file, not a live link (use `magcomp replay {url}`)")
    if st is not None and stat.S_ISCHR(st.st_mode):
        return
    raise InputError(f"{option} {url}: not a link URL (use {_URL_FORMS})")


#: errors of a first open that waiting cannot heal (the link is misconfigured, not merely down)
_PERMANENT_ERRNOS = frozenset(
    getattr(errno_mod, name)
    for name in (
        "EADDRINUSE",
        "EADDRNOTAVAIL",
        "EACCES",
        "EPERM",
        "ENOENT",
        "ENODEV",
        "ENXIO",
        "ENOTTY",
        "EBUSY",
    )
    if hasattr(errno_mod, name)
)


def _link_target(url: str) -> tuple[str, str]:
    """("net", host) for a network URL, ("serial", device) for a serial one."""
    text = url.strip()
    for prefix in _NET_PREFIXES:
        if text.startswith(prefix):
            return "net", text[len(prefix) :].rpartition(":")[0]
    device = text.removeprefix("serial:")
    if re.search(r":\d+$", device):
        device = device.rpartition(":")[0]
    return "serial", device


def preflight_link(url: str, option: str = "--master") -> None:
    """Refuse, with one line, a link that cannot work however long one waits: a host name that does not
    resolve, a serial device that does not exist, or serial support (pyserial) missing."""
    import importlib.util
    import os
    import socket

    kind, where = _link_target(url)
    if kind == "net":
        if where in ("", "0.0.0.0", "::"):
            return
        try:
            socket.getaddrinfo(where, None)
        except (socket.gaierror, UnicodeError) as exc:
            reason = exc.strerror if isinstance(exc, socket.gaierror) else str(exc)
            raise InputError(f"{option} {url}: the host {where!r} does not resolve ({reason})") from None
        return
    if importlib.util.find_spec("serial") is None:
        raise InputError(f"{option} {url}: serial links need pyserial: pip install pyserial")
    if where.startswith("/dev/") and not os.path.exists(where):
        raise InputError(f"{option} {url}: no such serial device {where!r} (is the autopilot plugged in?)")


def link_error_is_permanent(url: str, exc: BaseException) -> bool:
    """True when the first open of ``url`` failed in a way that retrying cannot heal: the address is in
    use or not ours, the host does not resolve, the serial device is missing, busy or not a serial port,
    serial support is not installed. A refused TCP connection or a silent link is retried."""
    import socket

    cause = exc.__cause__ or exc.__context__
    if isinstance(cause, ImportError | socket.gaierror):
        return True
    if _link_target(url)[0] == "serial":
        return True  # the device exists (preflight) but cannot be opened or configured as a serial port
    return isinstance(cause, OSError) and cause.errno in _PERMANENT_ERRNOS


class Daemon:
    """One live run. ``master``: the flight controller's link (udpin:, udpout:, tcp:, tcpin:, serial);
    ``outs``: more links to publish on. ``on_estimate``: called with each estimate (e.g. the viewer).
    The daemon owns the pipelines' worker threads (refined calibration fits, state writes): created
    here, given to every pipeline, shut down when :meth:`run` ends."""

    def __init__(
        self,
        master: str,
        cfg: Config,
        *,
        outs: Sequence[str] = (),
        store: StateStore | None = None,
        on_estimate: Callable[[HeadingEstimate], None] | None = None,
        on_text: Callable[[float, str], None] | None = None,
        on_power: Callable[[PowerSample], None] | None = None,
        signing_key: bytes | None = None,
    ) -> None:
        """``on_power``: each battery sample of the first vehicle (the viewer's current and voltage)."""
        check_link_url(master, "--master")
        #: MAVLink 2 signing: what is sent is signed with it, and only frames signed with it are read
        self.signing_key = signing_key
        for url in outs:
            check_link_url(url, "--out")
        self.master = master
        self.cfg = cfg
        self.out_urls = list(outs)
        self.last_error: str | None = None
        self.store = store
        self.on_estimate = on_estimate
        self.on_power = on_power
        self.workers = Workers.threads()
        self.pipeline = Pipeline(cfg, store=store, on_text=on_text, workers=self.workers)
        self._on_text = on_text
        # one pipeline and one encoder per sender on the link, (system id, component id): several
        # vehicles (or components) on one link each get their own clocks, calibration and theta, and
        # their headings go out as that vehicle; the first sender gets ``self.pipeline``
        self.pipelines: dict[tuple[int, int], Pipeline] = {}
        self._encoders: dict[tuple[int, int], HeadingEncoder] = {}
        self.encoder = self._new_encoder()
        #: NAMED_VALUE_FLOAT per encoder (vehicle), decimated (``[output] named_values_hz``)
        self._named: dict[HeadingEncoder, NamedValues] = {}
        self.latency_s: deque[float] = deque(maxlen=LATENCY_RING)
        self.published = 0
        self.connects = 0
        self.link_losses = 0
        self.source_counts: dict[str, int] = {}
        self._stop = threading.Event()
        self._stop_requested = False  # set by signal handlers (request_stop), read by housekeeping
        self._lock = threading.Lock()  # one encoder (sequence numbers) and sinks shared with housekeeping
        self._source: Any = None
        self._sinks: list[LinkSink] = []
        self._master_sink: LinkSink | None = None
        self._last_rx = time.monotonic()
        self._silent = False
        self._sysid_set = False
        self._loss_seen: dict[int, tuple[int, int]] = {}
        self._hk_thread: threading.Thread | None = None
        self._hk_errors: dict[str, int] = {}
        self._hk_restarts = 0
        self._loss_warned_at = -math.inf

    def _new_encoder(self) -> HeadingEncoder:
        enc = HeadingEncoder(self.cfg.output.source_system, self.cfg.output.source_component)
        if self.signing_key is not None:
            from magcomp.adapters.signing import sign_outgoing

            sign_outgoing(enc.mav, self.signing_key)
        return enc

    # ------------------------------------------------------------------------------------------- control

    def stop(self) -> None:
        """Ask the run to end (thread- and signal-safe); :meth:`run` returns within about a second."""
        self._stop.set()
        src = self._source
        if src is not None:
            src.close()

    def request_stop(self) -> None:
        """Ask the run to end from a signal handler: sets a flag and nothing else (async-signal-safe, so a
        second signal while the first is being handled cannot deadlock); :meth:`run` returns within about
        a second."""
        self._stop_requested = True

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    # ----------------------------------------------------------------------------------------- outputs

    def _open_outs(self) -> None:
        from magcomp.adapters.dialect import ensure_dialect

        ensure_dialect()
        from pymavlink import mavutil

        for url in self.out_urls:
            try:
                conn = mavutil.mavlink_connection(url, input=False, dialect="magcomp", autoreconnect=True,
                                                  source_system=255, source_component=191)  # fmt: skip
            except Exception as exc:
                raise InputError(f"cannot open output {url}: {exc}") from None
            self._sinks.append(LinkSink(url, conn))
            log.info("publishing on %s", url)

    def _write_all(self, t_s: float, packet: bytes) -> None:
        if self._master_sink is not None:
            self._master_sink.write_packet(t_s, packet)
        for sink in self._sinks:
            sink.write_packet(t_s, packet)

    def _vehicle(self, key: tuple[int, int]) -> tuple[Pipeline, HeadingEncoder]:
        """The pipeline and encoder of a sender on the link (created at its first sample)."""
        p = self.pipelines.get(key)
        if p is None:
            if not self.pipelines:
                p, enc = self.pipeline, self.encoder
                if p.system_id is None:
                    p.system_id = key[0]
            else:
                p = Pipeline(self.cfg, store=self.store, system_id=key[0], on_text=self._on_text,
                             workers=self.workers)  # fmt: skip
                enc = self._new_encoder()
                log.info("another vehicle on the link: system %d component %d", *key)
            enc.set_system(key[0])
            self.pipelines[key] = p
            self._encoders[key] = enc
            self._request_identity(key, enc)
            return p, enc
        return p, self._encoders[key]

    def _request_identity(self, key: tuple[int, int], enc: HeadingEncoder) -> None:
        """Ask a new sender for AUTOPILOT_VERSION (its unique id keys its state: Pipeline._on_identity). An
        autopilot that does not answer keeps the state of its system id."""
        with self._lock:
            sink = self._master_sink
            if sink is None:
                return
            for packet in enc.identity_requests(key[0], key[1]):
                sink.write_packet(0.0, packet)

    def _publish(self, est: HeadingEstimate, t_arrival: float, enc: HeadingEncoder | None = None) -> None:
        with self._lock:
            if enc is None:
                enc = self.encoder
                if not self._sysid_set and self.pipeline.system_id is not None:
                    enc.set_system(self.pipeline.system_id)
                    self._sysid_set = True
            self._write_all(est.t_s, enc.encode(est))
            named = self._named.get(enc)
            if named is None:
                named = self._named[enc] = NamedValues(enc, self.cfg.output.named_values_hz)
            t_boot = est.t_boot_s if est.t_boot_s == est.t_boot_s else est.t_s  # NaN: the same clock
            for packet in named.packets(est.t_s, t_boot, est.mag_index, est.heading_deg, est.theta_mgauss,
                                        est.flags):  # fmt: skip
                self._write_all(est.t_s, packet)
        self.latency_s.append(time.perf_counter() - t_arrival)
        self.published += 1
        if self.on_estimate is not None:
            self.on_estimate(est)

    # ------------------------------------------------------------------------------------- housekeeping

    def _housekeeping(self) -> None:
        """The housekeeping thread's loop: an error in one round is logged (once per kind) and the loop
        goes on; it never ends the thread, and the reading thread would see it if it did."""
        hb_period = 1.0 / self.cfg.link.heartbeat_hz if self.cfg.link.heartbeat_hz > 0 else 0.0
        next_hb = time.monotonic()
        next_loss = next_hb + LOSS_WINDOW_S
        while not self._stop.wait(0.05):
            if self._stop_requested:
                self.stop()
                break
            try:
                next_hb, next_loss = self._housekeeping_round(hb_period, next_hb, next_loss)
            except Exception as exc:  # a bug or a link object in a state we did not foresee
                kind = type(exc).__name__
                if kind not in self._hk_errors:
                    log.error("housekeeping: %s: %s (heartbeats and link checks go on)", kind, exc)
                self._hk_errors[kind] = self._hk_errors.get(kind, 0) + 1
                next_hb = time.monotonic() + max(hb_period, 0.05)

    def _housekeeping_round(self, hb_period: float, next_hb: float, next_loss: float) -> tuple[float, float]:
        """One round of housekeeping: the loss check, the heartbeat, the silence warning."""
        now = time.monotonic()
        if now >= next_loss:
            next_loss = now + LOSS_WINDOW_S
            self._check_loss(now)
        if hb_period and now >= next_hb:
            next_hb = now + hb_period
            with self._lock:
                self._write_all(0.0, self.encoder.heartbeat())
        quiet_s = now - self._last_rx
        if not self._silent and self._source is not None and quiet_s > self.cfg.link.silence_s:
            self._silent = True
            log.warning("no data from %s for %.0f s (still listening)", self.master, now - self._last_rx)
        return next_hb, next_loss

    def _should_stop(self) -> bool:
        """Polled by the reading thread (between samples, while the link is quiet, while it reconnects):
        a stop request from a signal handler ends the run here even if the housekeeping thread is gone;
        a housekeeping thread that died is reported on one line and started again."""
        if self._stop_requested and not self._stop.is_set():
            self.stop()
        if self._stop.is_set():
            return True
        hk = self._hk_thread
        if hk is not None and not hk.is_alive():
            self._hk_restarts += 1
            log.error("the housekeeping thread ended unexpectedly; restarted (%d)", self._hk_restarts)
            self._start_housekeeping()
        return False

    def _start_housekeeping(self) -> None:
        hk = threading.Thread(target=self._housekeeping, name="magcomp-housekeeping", daemon=True)
        self._hk_thread = hk
        hk.start()

    def _sleep(self, seconds: float) -> None:
        """Wait ``seconds`` in the reading thread, or less when the run is asked to stop."""
        deadline = time.monotonic() + seconds
        while not self._should_stop():
            left = deadline - time.monotonic()
            if left <= 0:
                return
            self._stop.wait(min(left, 0.05))

    def _check_loss(self, now: float) -> None:
        """Warn when the link lost more than LOSS_WARN_FRACTION of its messages since the last check."""
        src = self._source
        conn = getattr(src, "connection", None)
        if conn is None:
            return
        loss, count = int(getattr(conn, "mav_loss", 0)), int(getattr(conn, "mav_count", 0))
        last = self._loss_seen.get(id(conn), (0, 0))
        self._loss_seen[id(conn)] = (loss, count)
        d_loss, d_count = loss - last[0], count - last[1]
        if d_loss <= 0 or d_loss < LOSS_WARN_FRACTION * (d_loss + d_count):
            return
        if now - self._loss_warned_at >= LOSS_WARN_EVERY_S:
            self._loss_warned_at = now
            log.warning("the link lost %d of %d messages in the last %.0f s (sequence-number gaps): the "
                        "link or this machine is too slow for the stream", d_loss, d_loss + d_count,
                        LOSS_WINDOW_S)  # fmt: skip

    # ---------------------------------------------------------------------------------------------- run

    def run(self) -> DaemonReport:
        """Run until :meth:`stop`. Raises InputError for links that cannot work (outputs that cannot be
        opened, a master whose first open fails in a way waiting cannot heal: see
        :func:`link_error_is_permanent`); a master that is merely down is retried."""
        preflight_link(self.master, "--master")
        for url in self.out_urls:
            preflight_link(url, "--out")
        self._open_outs()
        self._start_housekeeping()
        try:
            self._connect_loop()
        finally:
            self._stop.set()
            hk = self._hk_thread
            self._hk_thread = None
            if hk is not None:
                hk.join(timeout=1.0)
            self._shutdown()
        return self.report()

    def _open_master(self) -> Any:
        """Open the master in a helper thread, so that a stop request is honoured however long the open
        blocks (a TCP connect to a host that does not answer, a serial device that hangs); None when the
        run was asked to stop first (a source the helper opens after that is closed by it)."""
        from magcomp.adapters.mavlink_source import open_source

        box: dict[str, Any] = {}
        abandoned = threading.Event()

        def opener() -> None:
            try:
                src = open_source(self.master, throttle_source=source_throttle(self.cfg), live_timeout_s=0.2,
                                  signing_key=self.signing_key)  # fmt: skip
            except BaseException as exc:
                box["error"] = exc
                return
            box["source"] = src
            if abandoned.is_set():
                src.close()

        t = threading.Thread(target=opener, name="magcomp-open", daemon=True)
        t.start()
        while t.is_alive():
            if self._should_stop():
                abandoned.set()
                if "source" in box:  # opened just now: ours to close
                    box["source"].close()
                return None
            t.join(timeout=0.05)
        if "error" in box:
            # (popped: the box would keep the error, its traceback and the socket it holds in a cycle
            # with the helper's frame, left to the collector)
            raise box.pop("error")
        return box.pop("source")

    def _connect_loop(self) -> None:
        """Open the master, serve it until it fails, retry every ``link.reconnect_s``; until :meth:`stop`."""
        first_failure = True
        while not self._should_stop():
            try:
                source = self._open_master()
            except InputError as exc:
                self.last_error = str(exc)
                if self.connects == 0 and link_error_is_permanent(self.master, exc):
                    raise
                if first_failure:
                    log.warning("%s; retrying every %.1f s", exc, self.cfg.link.reconnect_s)
                    first_failure = False
                self._sleep(self.cfg.link.reconnect_s)
                continue
            if source is None:
                return
            first_failure = True
            self._serve(source)

    def _serve(self, source: Any) -> None:
        """One connection of the master: samples through the pipelines until the link fails or we stop."""
        conn = source.connection
        source.interrupt = self._should_stop
        self._source = source
        self.connects += 1
        self._last_rx = time.monotonic()
        log.info("%s %s", "listening on" if self.connects == 1 else "reconnected to", self.master)
        _grow_receive_buffer(source.connection)
        with self._lock:
            self._master_sink = LinkSink(self.master, source.connection)
        try:
            while True:
                try:
                    self._pump(source)
                    break
                except InputError as exc:
                    # pymavlink's tcp/serial links reconnect by themselves before reporting the
                    # error; when the link object is usable again, keep reading from it
                    if self._stop.is_set() or not _link_alive(source.connection):
                        raise
                    self.link_losses += 1
                    log.warning("link reset (%s); the link reconnected, resuming", exc)
            if not self._should_stop():  # the source ended by itself: the link is gone
                raise InputError(f"link {self.master} closed")
        except InputError as exc:
            if self._should_stop():
                return
            self.link_losses += 1
            log.warning("link lost (%s); reconnecting in %.1f s", exc, self.cfg.link.reconnect_s)
            self._sleep(self.cfg.link.reconnect_s)
        finally:
            with self._lock:
                self._master_sink = None
            self._merge_counts(source.counts)
            if conn is not None:  # (the link object outlives its closing: its counters too)
                self._merge_counts({"lost_messages": int(getattr(conn, "mav_loss", 0)),
                                    "link_messages": int(getattr(conn, "mav_count", 0))})  # fmt: skip
            self._source = None
            source.close()

    def _shutdown(self) -> None:
        """After the run: the loss warning, every pipeline closed (state saved), the workers and the
        outputs shut down."""
        lost, got = self.source_counts.get("lost_messages", 0), self.source_counts.get("link_messages", 0)
        if lost:
            msg = (f"the link lost {lost} of {lost + got} messages ({100.0 * lost / (lost + got):.1f} %, "
                   "sequence-number gaps)")  # fmt: skip
            log.warning(msg)
            self.pipeline.warnings.append(msg)
        try:
            self.pipeline.close()
            for p in self.pipelines.values():
                if p is not self.pipeline:
                    p.close()
        finally:
            self.workers.shutdown()
            for sink in self._sinks:
                sink.close()
        log.info("stopped after %d estimates", self.published)

    def _pump(self, source: Any) -> None:
        """Samples from the source through the pipeline to the sinks until the source ends or fails."""
        key: tuple[int, int] | None = None
        pipeline, enc = self.pipeline, self.encoder
        on_power = self.on_power
        for sender, sample in source.vehicle_samples():
            if self._stop_requested:  # (a flag read per sample; the rest of _should_stop while quiet)
                self.stop()
                return
            t_arrival = time.perf_counter()
            self._last_rx = time.monotonic()
            if self._silent:
                self._silent = False
                log.info("data from %s again", self.master)
            if sender != key:
                key = sender
                pipeline, enc = self._vehicle(sender)
            if on_power is not None and type(sample) is PowerSample and pipeline is self.pipeline:
                on_power(sample)
            est = pipeline.process(sample)
            if est is not None:
                self._publish(est, t_arrival, enc)

    def _merge_counts(self, counts: dict[str, int]) -> None:
        for k, v in counts.items():
            self.source_counts[k] = self.source_counts.get(k, 0) + int(v)

    def report(self) -> DaemonReport:
        summary = self.pipeline.summary()
        if len(self.pipelines) > 1:  # every vehicle on the link, each with its own summary
            summary["vehicles"] = [
                {"system_id": k[0], "component_id": k[1], **p.summary()}
                for k, p in sorted(self.pipelines.items(), key=lambda kv: kv[0])
            ]
        return DaemonReport(
            summary=summary,
            source_counts=dict(self.source_counts),
            connects=self.connects,
            link_losses=self.link_losses,
            published=self.published,
            latency_ms=latency_stats_ms(list(self.latency_s)),
        )
