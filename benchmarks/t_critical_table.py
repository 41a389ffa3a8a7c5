"""The table of ``core/selfcheck.py`` ``T_CRITICAL``: scipy's own Student-t quantiles, printed as Python.

``t_critical(n)`` is ``scipy.special.stdtrit(n - 1, P_APPLY)``; importing ``scipy.special`` costs 0.15-0.2 s
of CPU in a fresh process (its array-API layer loads numpy.f2py, numpy.ma, numpy.testing), more than a
replay spends in the self-check. The table holds the exact floats scipy returns for n = 2..T_CRITICAL_MAX_N
(``repr`` round-trips a float), so the verdicts are bit for bit those of scipy; beyond it, scipy is
imported. ``tests/unit/test_selfcheck.py`` compares every entry with scipy. Run this script after a change
of P_APPLY or T_CRITICAL_MAX_N and paste its output over the table.

    .venv/bin/python benchmarks/t_critical_table.py
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scipy.special import stdtrit

from magcomp.core.selfcheck import P_APPLY, T_CRITICAL_MAX_N

#: values per line of the printed table
PER_LINE = 5


def table_lines() -> list[str]:
    """The table's source lines: ``T_CRITICAL = (`` ... ``)``, one float per n = 2..T_CRITICAL_MAX_N."""
    values = [repr(float(stdtrit(n - 1, P_APPLY))) for n in range(2, T_CRITICAL_MAX_N + 1)]
    rows = [", ".join(values[i : i + PER_LINE]) + "," for i in range(0, len(values), PER_LINE)]
    return ["T_CRITICAL = (", *("    " + r for r in rows), ")"]


if __name__ == "__main__":
    print("\n".join(table_lines()))
