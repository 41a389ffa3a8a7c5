"""The observers of a two-pass replay's first pass, stepped in a process of their own (the second core).

In the first pass (:func:`magcomp.service.replay.replay_log`, two passes) the observer of eq. (20) is a
sink: every step's input (body rate, calibrated field, throttle at the sample's own time, dt) is decided
by the pipeline (service/theta.py: queue, throttle interpolation, resets), and nothing in that pass reads
theta-hat back until the end (no heading is computed; the state it ends with is what the second pass
applies). Its steps are ~40 % of the pass's CPU time on a hand-rotation log, so they go to a forked
child process: the pipeline sends each step as ten float64 numbers down a pipe, in order, a block at a
time; the child runs the same :class:`~magcomp.service.estimators.ThetaEstimator` on the same floats, so
the numbers are identical to stepping it inline. Whoever reads an estimator (:meth:`RemoteTheta.sync`)
waits for the child to catch up and gets its state; the pipeline's close takes the final states over, then
:meth:`ObserverProcess.close` ends the child.

Memory does not grow with the log: at most one block is buffered on each side of the pipe, whose
64 KiB bound stops the pipeline when the child falls behind. A child that dies ends the replay with an
error at the next block; a parent that dies closes the pipe and the child exits on its end. On Linux only,
and only while the process runs no other thread (:func:`start` returns None otherwise: the observers then
step inline). Not in the paper: a way of running eq. (20), not a change of it.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import signal
import struct
import sys
import threading
from array import array
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcomp.adapters.config import Config
from magcomp.errors import MagcompError
from magcomp.service.estimators import ThetaEstimator, ThetaStepInfo

F64 = NDArray[np.float64]

#: one message down the pipe: (op, compass, omega x3, field x3, throttle, dt), float64
_REC = struct.Struct("=10d")  # native order, as array("d") packs it
_STEP, _RESET, _CREATE, _QUERY = 0.0, 1.0, 2.0, 3.0
#: float64s buffered before a write (512 messages, 40 KiB: below the pipe's 64 KiB)
_BLOCK = 512 * 10
_LEN = struct.Struct("<Q")

#: what the child hands back for one compass: the estimator's state, converged, the last step's info
Final = tuple[Any, bool, ThetaStepInfo | None]


class ObserverProcessError(MagcompError, RuntimeError):
    """The child ended early (killed: the OOM killer, a kill of its pid) or failed: the replay ends with
    this one line (the CLI's error), not a traceback."""


class ObserverProcess:
    """The child process and the two pipes to it (commands down, answers up)."""

    def __init__(self, pid: int, cmd_w: int, res_r: int) -> None:
        self._pid = pid
        self._cmd = cmd_w
        self._res = os.fdopen(res_r, "rb")
        self._buf = array("d")
        self._closed = False

    def estimator(self, idx: int, cfg: Config, theta0_mgauss: F64 | None) -> RemoteTheta:
        """The observer of compass ``idx`` (created in the child as ``ThetaEstimator(cfg, theta0)``)."""
        prior = theta0_mgauss is not None
        t = (0.0, 0.0, 0.0) if theta0_mgauss is None else np.asarray(theta0_mgauss, dtype=float).tolist()
        self._buf.extend((_CREATE, float(idx), 0.0, 0.0, 0.0, t[0], t[1], t[2], float(prior), 0.0))
        return RemoteTheta(self, idx, ThetaEstimator(cfg, theta0_mgauss))

    def step(self, idx: int, omega: Sequence[float], u: Sequence[float], thr: float, dt: float) -> None:
        buf = self._buf
        buf.extend((_STEP, idx, omega[0], omega[1], omega[2], u[0], u[1], u[2], thr, dt))
        if len(buf) >= _BLOCK:
            self._flush()

    def reset(self, idx: int) -> None:
        self._buf.extend((_RESET, idx, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))

    def _flush(self) -> None:
        data = memoryview(self._buf.tobytes())
        try:
            with _sigint_held():
                while data:
                    data = data[os.write(self._cmd, data):]
                self._buf = array("d")
        except BrokenPipeError:
            self._answer()  # the child's own error, if it said one
            raise ObserverProcessError(f"the observer process ended early ({self._status()})") from None

    def query(self) -> dict[int, Final]:
        """Every observer's state once the child has run every step sent so far."""
        self._buf.extend((_QUERY, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
        self._flush()
        out = self._answer()
        if out is None:
            raise ObserverProcessError(f"the observer process ended early ({self._status()})")
        return out

    def _answer(self) -> dict[int, Final] | None:
        """The child's next answer (None: it ended without one); its error raised (ObserverProcessError)."""
        with _sigint_held():
            head = self._res.read(_LEN.size)
            if len(head) < _LEN.size:
                return None
            kind, payload = pickle.loads(self._res.read(_LEN.unpack(head)[0]))
        if kind != "ok":
            raise ObserverProcessError(f"the observer process failed: {payload}")
        out: dict[int, Final] = payload
        return out

    def close(self) -> None:
        """Close the pipes (the child exits on their end) and reap the child; idempotent."""
        if self._closed:
            return
        self._closed = True
        os.close(self._cmd)
        self._res.close()
        with contextlib.suppress(ChildProcessError):  # already reaped (by _status)
            os.waitpid(self._pid, 0)

    def _status(self) -> str:
        try:
            pid, status = os.waitpid(self._pid, os.WNOHANG)
        except ChildProcessError:
            return "gone"
        return f"exit status {os.waitstatus_to_exitcode(status)}" if pid else "still running"


class RemoteTheta:
    """A :class:`~magcomp.service.estimators.ThetaEstimator` stepped in the child: steps and resets are
    sent; :meth:`sync` waits for the child and copies its state into ``local`` (the estimator as last
    read, which the owner reads: service/theta.py)."""

    def __init__(self, proc: ObserverProcess, idx: int, local: ThetaEstimator) -> None:
        self._proc = proc
        self._idx = idx
        self.local = local
        self.last_info: ThetaStepInfo | None = None

    def step(self, omega_b_rad_s: Sequence[float], field_b_mgauss: Sequence[float], throttle_01: float,
             dt_s: float) -> None:  # fmt: skip
        """Sent; the step's info is not returned (read :attr:`last_info` after :meth:`sync`)."""
        self._proc.step(self._idx, omega_b_rad_s, field_b_mgauss, throttle_01, dt_s)

    def reset_filters(self) -> None:
        self._proc.reset(self._idx)

    def sync(self) -> None:
        """Take the child's state of every compass (the child first runs every step sent)."""
        self.take(self._proc.query()[self._idx])

    def take(self, final: Final) -> None:
        self.local.state, self.local.converged, self.last_info = final


@contextlib.contextmanager
def _sigint_held() -> Iterator[None]:
    """SIGINT held pending while a block goes down the pipe or an answer comes up, delivered (as the
    KeyboardInterrupt of Python's default handler) once it is whole: a ^C between two partial writes of a
    block (a pipe write larger than PIPE_BUF may be cut short by a signal) would leave the child reading
    every later message shifted by the bytes written, and one between the two reads of an answer would
    leave the next read mid-answer. A SIGINT already pending as this starts is raised at the mask call,
    before anything is written. The main thread only (where Python delivers signals)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _foreign_threads() -> list[str]:
    """The names of this process's native threads that Python's ``threading`` does not see and that do
    not carry the process's own name: a library's own threads (the Rerun SDK's writer, batcher and
    runtime workers, an allocator's background thread) that a fork would copy mid-lock. A BLAS pool's
    threads keep the process's name and are not counted (they hold no lock between calls). Unreadable
    (a thread ending as it is read): reported as one, so no fork."""
    try:
        own = Path("/proc/self/comm").read_text().strip()
        tasks = Path("/proc/self/task")
        names = [(t / "comm").read_text().strip() for t in tasks.iterdir()]
    except OSError:
        return ["?"]
    return [n for n in names if n != own]


def start(cfg: Config) -> ObserverProcess | None:
    """Fork the child; None (the observers then step inline) off Linux, or while this process runs another
    thread (a fork copies no lock another thread holds then: the first pass forks before its workers'
    threads start; a caller's own threads, e.g. a viewer's, keep the observers inline; so do a library's
    native threads, :func:`_foreign_threads`, e.g. ``replay --rerun``'s)."""
    if not sys.platform.startswith("linux") or threading.active_count() > 1 or _foreign_threads():
        return None
    cmd_r, cmd_w = os.pipe()
    res_r, res_w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns into the caller's code
        code = 1
        try:
            os.close(cmd_w)
            os.close(res_r)
            signal.signal(signal.SIGINT, signal.SIG_IGN)  # ^C is the parent's to handle; EOF ends us
            code = _serve(cfg, cmd_r, res_w)
        finally:
            os._exit(code)
    os.close(cmd_r)
    os.close(res_w)
    return ObserverProcess(pid, cmd_w, res_r)


def _serve(cfg: Config, cmd_r: int, res_w: int) -> int:
    """The child's loop: run the messages in order until the parent closes the pipe."""
    ests: dict[int, ThetaEstimator] = {}
    infos: dict[int, ThetaStepInfo | None] = {}
    size = _REC.size
    rest = b""
    with os.fdopen(cmd_r, "rb") as src, os.fdopen(res_w, "wb") as out:
        try:
            while chunk := src.read1(1 << 16):
                data = rest + chunk if rest else chunk
                n = len(data) - len(data) % size
                rest = data[n:]
                for op, fi, w0, w1, w2, u0, u1, u2, thr, dt in _REC.iter_unpack(data[:n] if rest else data):
                    idx = int(fi)
                    if op == _STEP:
                        infos[idx] = ests[idx].step((w0, w1, w2), (u0, u1, u2), thr, dt)
                    elif op == _RESET:
                        ests[idx].reset_filters()
                    elif op == _CREATE:
                        ests[idx] = ThetaEstimator(cfg, np.array((u0, u1, u2)) if thr else None)
                        infos[idx] = None
                    else:
                        states = {i: (e.state, e.converged, infos[i]) for i, e in ests.items()}
                        _send(out, ("ok", states))
        except Exception as exc:  # handed to the parent at its next query
            _send(out, ("error", f"{type(exc).__name__}: {exc}"))
            return 1
    return 0


def _send(out: Any, msg: object) -> None:
    data = pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL)
    out.write(_LEN.pack(len(data)))
    out.write(data)
    out.flush()


__all__ = ["ObserverProcess", "ObserverProcessError", "RemoteTheta", "start"]
