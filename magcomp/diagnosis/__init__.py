"""Model diagnosis (issue #6): simulation vs measurement, model extensions, residual suspects, the gain.

Pure numerics (numpy/scipy) except :mod:`magcomp.diagnosis.report`, which writes the Markdown and PNGs.
Entry point: :func:`magcomp.diagnosis.engine.diagnose` ``(LogData) -> Diagnosis`` (``.to_json()``).
"""

from magcomp.diagnosis.effects import EFFECTS, ExtensionParams
from magcomp.diagnosis.engine import CompassDiagnosis, Diagnosis, Finding, diagnose

__all__ = ["EFFECTS", "CompassDiagnosis", "Diagnosis", "ExtensionParams", "Finding", "diagnose"]
