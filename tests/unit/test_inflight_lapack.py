"""The in-flight solver's LAPACK (``core/inflight/base.py`` ``lapack``): scipy's compiled wrappers loaded on
their own, without the ``scipy.linalg`` package (~120 ms of CPU a process), and the very functions
``scipy.linalg.lapack`` re-exports, so a later import of the package shares them."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from magcomp.core.inflight.base import lapack

ROOT = Path(__file__).resolve().parents[2]


def test_lapack_loads_without_the_linalg_package_and_is_scipys_own() -> None:
    code = (
        "import sys\n"
        "from magcomp.core.inflight.base import lapack\n"
        "m = lapack()\n"
        "print('scipy.linalg' in sys.modules)\n"
        "import scipy.linalg.lapack as sl\n"
        "print(sl.dposv is m.dposv and sl.dpotrs is m.dpotrs)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.split() == ["False", "True"], out.stdout + out.stderr


def test_lapack_cholesky_solves_a_positive_definite_system() -> None:
    rng = np.random.default_rng(3)
    a = rng.normal(size=(8, 8))
    spd = a @ a.T + 8.0 * np.eye(8)
    b = rng.normal(size=(8, 2))
    cho, x, info = lapack().dposv(spd, b)
    assert info == 0
    np.testing.assert_allclose(spd @ x, b, rtol=0.0, atol=1e-10)
    inv, fail = lapack().dpotrs(cho, np.eye(8))
    assert fail == 0
    np.testing.assert_allclose(inv @ spd, np.eye(8), rtol=0.0, atol=1e-10)
    _, _, info = lapack().dposv(-spd, b)  # not positive definite: LAPACK says so
    assert info != 0
