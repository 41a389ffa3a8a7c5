"""The in-flight calibration of a two-pass replay's first pass, run in forked processes of its own (up to
CHILDREN, the compasses dealt to them in turn), as the observers are
(:mod:`magcomp.service.observer_process`).

In the first pass the in-flight stage (:class:`~magcomp.service.inflight_stage.InflightStage`) is a sink:
every call's inputs (the field, the throttle at the sample's time, the rotations, the gyro's yaw, resets,
the Earth field's restart) are decided by the pipeline, and nothing in that pass reads its answers back
(no heading is computed; ``output``'s correction is not applied to anything the pass keeps: the theta stage
of a learn-only pass steps no observer for a compass without a hand-rotation calibration). Its rows and
solves are ~73 % of a flight log's two-pass replay (10 min at 50 Hz: 6.5 of 8.9 s CPU), so they go to forked
children: the pipeline sends each call
(``feed``, ``output``, ``reset_pairs``, ``restart`` and the side-effecting ``state`` of every save) as
float64 numbers down a pipe, in order, a block at a time; the child makes the same calls with the same
floats on the same stage (created in the parent, sent once pickled), so its numbers are identical to
running it inline. The pipeline's close takes the final stages back (pickled) before its final saves, then
ends the children.

Framing: each call is ``[op, compass, n, payload (n float64)]``. Memory does not grow with the log: at most
one block is buffered on each side of a pipe. A child that dies ends the replay with an error at the next
block; a parent that dies closes the pipes and the children exit on their end. Linux only, and only while the
process runs no other thread (:func:`start` returns None otherwise: the stage then runs inline). Not in the
paper: a way of running the in-flight calibration, not a change of it.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import signal
import sys
import threading
from array import array
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from magcomp.core.inflight import GyroYaw, InflightOutput
from magcomp.service.inflight_stage import InflightStage
from magcomp.service.observer_process import ObserverProcessError, _foreign_threads, _send, _sigint_held

F64 = NDArray[np.float64]

_CREATE, _FEED, _OUTPUT, _RESET_PAIRS, _RESTART, _STATE, _QUERY = (float(i) for i in range(7))
#: float64s buffered before a write (below the pipe's 64 KiB)
_BLOCK = 5000
#: child processes at most (compasses dealt to them in turn; no more than the machine's cores). One would be
#: the critical path alone on a flight log (its two compasses' stages: 6.5 s CPU against the parent's 2.3 s,
#: 10 min at 50 Hz); two share the cores with the parent (docs/benchmarks.md)
CHILDREN = 2
_NONE9 = (0.0,) * 9
_NONE3 = (0.0,) * 3


class InflightError(ObserverProcessError):
    """The in-flight child ended early or failed: one line (the CLI's error), not a traceback."""


class InflightSink(Protocol):
    """What the calibrate stage calls on a compass's in-flight calibration: the stage itself, or
    :class:`RemoteInflight` (its calls sent to the child)."""

    @property
    def mode(self) -> str: ...

    def reset_pairs(self) -> None: ...

    def restart(self, field_norm_mgauss: float) -> None: ...

    def feed(
        self,
        t_s: float,
        field_mgauss: F64 | tuple[float, float, float],
        throttle_01: float,
        motors_01: tuple[float, ...],
        r_abs_nb: F64 | None,
        field_ref_n_mgauss: F64 | None,
        r_rel_nb: F64 | None,
        r_t_s: float | None = None,
        throttle_t_s: float | None = None,
        gyro_yaw: GyroYaw | None = None,
    ) -> None: ...

    def output(
        self,
        t_s: float,
        field_mgauss: tuple[float, float, float],
        throttle_01: float,
        motors_01: tuple[float, ...],
    ) -> InflightOutput | None: ...


class _Child:
    """One child process and the two pipes to it (calls down, answers up)."""

    def __init__(self, pid: int, cmd_w: int, res_r: int) -> None:
        self.pid = pid
        self._cmd = cmd_w
        self._res = os.fdopen(res_r, "rb")
        self._buf = array("d")
        self.closed = False

    def fds(self) -> tuple[int, int]:
        return self._cmd, self._res.fileno()

    def put(self, vals: list[float]) -> None:
        buf = self._buf
        buf.extend(vals)
        if len(buf) >= _BLOCK:
            self.flush()

    def put_bytes(self, head: tuple[float, ...], data: bytes) -> None:
        self._buf.extend(head)
        self._buf.frombytes(data)
        self.flush()

    def flush(self) -> None:
        data = memoryview(self._buf.tobytes())
        try:
            with _sigint_held():
                while data:
                    data = data[os.write(self._cmd, data) :]
                self._buf = array("d")
        except BrokenPipeError:
            self.answer()  # the child's own error, if it said one
            raise InflightError(f"the in-flight process ended early ({self._status()})") from None

    def query(self) -> dict[int, InflightStage]:
        """Its compasses' stages once the child has run every call sent so far."""
        self._buf.extend((_QUERY, 0.0, 0.0))
        self.flush()
        out = self.answer()
        if out is None:
            raise InflightError(f"the in-flight process ended early ({self._status()})")
        return out

    def answer(self) -> dict[int, InflightStage] | None:
        """The child's next answer (None: it ended without one); its error raised (InflightError)."""
        with _sigint_held():
            head = self._res.read(8)
            if len(head) < 8:
                return None
            kind, payload = pickle.loads(self._res.read(int.from_bytes(head, "little")))
        if kind != "ok":
            raise InflightError(f"the in-flight process failed: {payload}")
        out: dict[int, InflightStage] = payload
        return out

    def close(self) -> None:
        """Close the pipes (the child exits on their end) and reap the child; idempotent."""
        if self.closed:
            return
        self.closed = True
        os.close(self._cmd)
        self._res.close()
        with contextlib.suppress(ChildProcessError):
            os.waitpid(self.pid, 0)

    def _status(self) -> str:
        try:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
        except ChildProcessError:
            return "gone"
        return f"exit status {os.waitstatus_to_exitcode(status)}" if pid else "still running"


class InflightProcess:
    """The children (one per core, up to CHILDREN), each running the stages of the compasses dealt to it in
    turn as they appear (compasses are independent: no stage reads another's)."""

    def __init__(self, children: list[_Child]) -> None:
        self.children = children
        self._n_stages = 0

    def stage(
        self, idx: int, stage: InflightStage, replacing: RemoteInflight | None = None
    ) -> RemoteInflight:
        """Compass ``idx``'s stage, as just created by the parent, copied into a child (``replacing``: the
        stage it replaces, in that one's child)."""
        if replacing is not None:
            child = replacing._proc
        else:
            child = self.children[self._n_stages % len(self.children)]
            self._n_stages += 1
        data = pickle.dumps(stage, protocol=pickle.HIGHEST_PROTOCOL)
        pad = -len(data) % 8
        head = (_CREATE, float(idx), float((len(data) + pad) // 8 + 1), float(len(data)))
        child.put_bytes(head, data + b"\0" * pad)
        return RemoteInflight(child, idx, stage.mode)

    def query(self) -> dict[int, InflightStage]:
        """Every compass's stage once the children have run every call sent so far."""
        out: dict[int, InflightStage] = {}
        for child in self.children:
            out.update(child.query())
        return out

    def close(self) -> None:
        """End every child; idempotent."""
        for child in self.children:
            child.close()

    @property
    def closed(self) -> bool:
        return all(c.closed for c in self.children)


class RemoteInflight:
    """A compass's in-flight stage running in the child: every call is sent; ``output`` answers None (the
    first pass applies no correction); :meth:`state` runs the stage's ``state()`` there for its side effects
    on the estimator (a save's), in order."""

    def __init__(self, proc: _Child, idx: int, mode: str) -> None:
        self._proc = proc
        self._idx = float(idx)
        self._mode = mode
        # the last arrays sent and their floats: the attitude stage builds one read-only DCM per attitude or
        # IMU sample, shared by both forms and compasses, and the Earth field changes only at a GPS fix
        self._flats: list[tuple[F64, tuple[float, ...]]] = []

    def _flat(self, a: F64 | None, none: tuple[float, ...]) -> tuple[float, ...]:
        """(1, a's floats) or (0, ``none``): a feed call's layout of an optional array."""
        if a is None:
            return (0.0, *none)
        for arr, flat in self._flats:
            if arr is a:
                return flat
        flat = (1.0, *a.ravel().tolist())
        if not a.flags.writeable:  # only arrays nobody can change later
            self._flats = [(a, flat), *self._flats[:3]]
        return flat

    @property
    def mode(self) -> str:
        return self._mode

    def reset_pairs(self) -> None:
        self._proc.put([_RESET_PAIRS, self._idx, 0.0])

    def restart(self, field_norm_mgauss: float) -> None:
        self._proc.put([_RESTART, self._idx, 1.0, float(field_norm_mgauss)])

    def state(self) -> None:
        self._proc.put([_STATE, self._idx, 0.0])

    def feed(
        self,
        t_s: float,
        field_mgauss: F64 | tuple[float, float, float],
        throttle_01: float,
        motors_01: tuple[float, ...],
        r_abs_nb: F64 | None,
        field_ref_n_mgauss: F64 | None,
        r_rel_nb: F64 | None,
        r_t_s: float | None = None,
        throttle_t_s: float | None = None,
        gyro_yaw: GyroYaw | None = None,
    ) -> None:
        y = field_mgauss.tolist() if isinstance(field_mgauss, np.ndarray) else field_mgauss
        v: list[float] = [_FEED, self._idx, 0.0, t_s, *y, throttle_01]
        v += self._flat(r_abs_nb, _NONE9)
        v += self._flat(field_ref_n_mgauss, _NONE3)
        v += self._flat(r_rel_nb, _NONE9)
        v += (0.0, 0.0) if r_t_s is None else (1.0, r_t_s)
        v += (0.0, 0.0) if throttle_t_s is None else (1.0, throttle_t_s)
        if gyro_yaw is None:
            v += (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        else:
            an, ae = gyro_yaw.accel_h_m_s2
            v += (1.0, float(gyro_yaw.epoch), gyro_yaw.yaw_rad, an, ae, gyro_yaw.att_lead_rad)
        v.append(float(len(motors_01)))
        v += motors_01
        v[2] = float(len(v) - 3)
        self._proc.put(v)

    def output(
        self,
        t_s: float,
        field_mgauss: tuple[float, float, float],
        throttle_01: float,
        motors_01: tuple[float, ...],
    ) -> InflightOutput | None:
        n = 5.0 + len(motors_01)
        self._proc.put([_OUTPUT, self._idx, n, t_s, *field_mgauss, throttle_01, *motors_01])
        return None


def start(n: int | None = None) -> InflightProcess | None:
    """Fork the children (``n``; default: CHILDREN, at most the machine's cores); None (the stages then run
    inline) off Linux or while this process runs another thread (as
    :func:`magcomp.service.observer_process.start`)."""
    if not sys.platform.startswith("linux") or threading.active_count() > 1 or _foreign_threads():
        return None
    n = n if n is not None else max(1, min(CHILDREN, os.cpu_count() or 1))
    children: list[_Child] = []
    for _ in range(n):
        cmd_r, cmd_w = os.pipe()
        res_r, res_w = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: never returns into the caller's code
            code = 1
            try:
                signal.signal(signal.SIGINT, signal.SIG_IGN)  # ^C is the parent's to handle; EOF ends us
                # every other descriptor closed: a pipe to another child (or the observers') left open here
                # would keep that child from seeing its end, and the parent waiting for it
                _close_all_but(cmd_r, res_w)
                code = _serve(cmd_r, res_w)
            finally:
                os._exit(code)
        os.close(cmd_r)
        os.close(res_w)
        children.append(_Child(pid, cmd_w, res_r))
    return InflightProcess(children)


def _close_all_but(*keep: int) -> None:
    """Close this process's file descriptors above stderr except ``keep`` (a forked child's first act)."""
    for name in os.listdir("/proc/self/fd"):
        fd = int(name)
        if fd > 2 and fd not in keep:
            with contextlib.suppress(OSError):
                os.close(fd)


def _serve(cmd_r: int, res_w: int) -> int:
    """The child's loop: run the calls in order until the parent closes the pipe."""
    stages: dict[int, InflightStage] = {}
    rest = b""
    with os.fdopen(cmd_r, "rb") as src, os.fdopen(res_w, "wb") as out:
        try:
            while chunk := src.read1(1 << 16):
                data = rest + chunk if rest else chunk
                used = _run(stages, data, out)
                rest = data[used:]
        except Exception as exc:  # handed to the parent at its next query
            _send(out, ("error", f"{type(exc).__name__}: {exc}"))
            return 1
    return 0


def _run(stages: dict[int, InflightStage], data: bytes, out: Any) -> int:
    """Every whole call in ``data``; returns the bytes used (a call cut at the chunk's end waits)."""
    view = memoryview(data)[: len(data) - len(data) % 8].cast("d")
    vals: list[float] = view.tolist()  # type: ignore[assignment]
    n_all = len(vals)
    i = 0
    while i + 3 <= n_all:
        op, fi, fn = vals[i], vals[i + 1], vals[i + 2]
        end = i + 3 + int(fn)
        if end > n_all:
            break
        idx = int(fi)
        p = i + 3
        if op == _FEED:
            _feed(stages[idx], vals, p)
        elif op == _OUTPUT:
            t, y0, y1, y2, thr = vals[p : p + 5]
            stages[idx].output(t, (y0, y1, y2), thr, tuple(vals[p + 5 : end]))
        elif op == _RESET_PAIRS:
            stages[idx].reset_pairs()
        elif op == _RESTART:
            stages[idx].restart(vals[p])
        elif op == _STATE:
            stages[idx].state()
        elif op == _CREATE:
            stages[idx] = pickle.loads(view[p + 1 : end].tobytes()[: int(vals[p])])
        else:
            # the stages back to the main process (only at its close, whose final saves ask each stage's
            # state() first): asked here first, so that they travel solved and the main process, which
            # would otherwise solve again and import scipy's LAPACK for it (~0.19 s of its CPU), reads the
            # same numbers from their caches
            for st in stages.values():
                st.state()
            _send(out, ("ok", stages))
        i = end
    return i * 8


def _feed(st: InflightStage, v: list[float], p: int) -> None:
    """A ``feed`` call from its floats (:meth:`RemoteInflight.feed`'s layout)."""
    t = v[p]
    y = np.array(v[p + 1 : p + 4])
    thr = v[p + 4]
    r_abs = np.array(v[p + 6 : p + 15]).reshape(3, 3) if v[p + 5] else None
    ref = np.array(v[p + 16 : p + 19]) if v[p + 15] else None
    r_rel = np.array(v[p + 20 : p + 29]).reshape(3, 3) if v[p + 19] else None
    r_t = v[p + 30] if v[p + 29] else None
    thr_t = v[p + 32] if v[p + 31] else None
    gy = None
    if v[p + 33]:
        gy = GyroYaw(int(v[p + 34]), v[p + 35], (v[p + 36], v[p + 37]), v[p + 38])
    n_mot = int(v[p + 39])
    mot = tuple(v[p + 40 : p + 40 + n_mot])
    st.feed(t, y, thr, mot, r_abs, ref, r_rel, r_t_s=r_t, throttle_t_s=thr_t, gyro_yaw=gy)


__all__ = ["InflightError", "InflightProcess", "InflightSink", "RemoteInflight", "start"]
