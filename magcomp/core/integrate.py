"""Fixed-step integrators for right-hand sides of the SciPy / python-control shape ``rhs(t, x, u, p)``.

Used online (explicit ``dt``, no adaptive step) and in tests against :func:`scipy.integrate.solve_ivp`
on the same right-hand side. ``u`` is either a fixed input held over the step (zero-order hold) or a
callable ``u(t)`` evaluated at each stage, so a smooth input is integrated to the method's full order.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
Rhs = Callable[[float, F64, Any, Any], F64]


def _input_at(u: Any, t: float) -> Any:
    return u(t) if callable(u) else u


def euler_step(rhs: Rhs, t: float, x: F64, u: Any, p: Any, dt: float) -> F64:
    """One explicit Euler step ``x + dt * rhs(t, x, u, p)`` (first order; a reference, not for online use)."""
    x = np.asarray(x, dtype=float)
    return x + dt * np.asarray(rhs(t, x, _input_at(u, t), p), dtype=float)


def rk4_step(rhs: Rhs, t: float, x: F64, u: Any, p: Any, dt: float) -> F64:
    """One classical fourth-order Runge-Kutta step of ``dx/dt = rhs(t, x, u, p)`` from ``t`` to ``t + dt``.

    Parameters
    ----------
    rhs : callable ``(t, x, u, p) -> dx``, x and dx of shape (n,)
    t : start time, s
    x : state at ``t``, shape (n,)
    u : input, held over the step, or a callable ``u(t)`` evaluated at t, t + dt/2 and t + dt
    p : parameters passed through to ``rhs``
    dt : step, s (> 0)
    """
    if not dt > 0.0:
        raise ValueError(f"dt must be > 0, got {dt}")
    x = np.asarray(x, dtype=float)
    h2 = 0.5 * dt
    u0 = _input_at(u, t)
    um = _input_at(u, t + h2)
    u1 = _input_at(u, t + dt)
    k1 = np.asarray(rhs(t, x, u0, p), dtype=float)
    k2 = np.asarray(rhs(t + h2, x + h2 * k1, um, p), dtype=float)
    k3 = np.asarray(rhs(t + h2, x + h2 * k2, um, p), dtype=float)
    k4 = np.asarray(rhs(t + dt, x + dt * k3, u1, p), dtype=float)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
