"""The diagnosis's results: frozen, built complete by :mod:`magcomp.diagnosis.search` and
:mod:`magcomp.diagnosis.engine`. They live in :mod:`magcomp.diagnosis.export`, beside the functions that turn
them into JSON (one module: no import cycle between the two); this module names them for their users."""

from __future__ import annotations

from magcomp.diagnosis.export import CompassDiagnosis, Diagnosis, Finding, HeadingErrors

__all__ = ["CompassDiagnosis", "Diagnosis", "Finding", "HeadingErrors"]
