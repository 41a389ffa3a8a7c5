"""The diagnosis's results: frozen, built complete by :mod:`magcomp.diagnosis.search` and
:mod:`magcomp.diagnosis.engine`; :mod:`magcomp.diagnosis.export` turns them into JSON."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcomp.diagnosis import export
from magcomp.diagnosis import gate as gate_mod
from magcomp.diagnosis.model import CompassData, ModelFit
from magcomp.diagnosis.partial import PriorTheta
from magcomp.diagnosis.suspects import SignalRelation, StepEvent

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Finding:
    effect: str
    cause: str
    params: dict[str, Any]
    evidence: dict[str, Any]
    residual_rms_after: float
    candidates: list[str] = field(default_factory=list)
    candidate_params: dict[str, Any] = field(default_factory=dict)

    @property
    def label(self) -> str:
        """The effect's name, or "a or b" when the data cannot tell the candidates apart."""
        return " or ".join(self.candidates) if len(self.candidates) > 1 else self.effect


@dataclass(frozen=True)
class HeadingErrors:
    """Heading error (deg) against a reference, constant offset removed: rms and max |.|."""

    reference: str
    rms_deg: dict[str, float]
    max_deg: dict[str, float]
    #: the reference heading at the compass's sample times (rad; the report's heading plot), if kept
    reference_yaw_rad: Any = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class CompassDiagnosis:
    index: int
    source: str
    data: CompassData
    baseline: ModelFit
    extended: ModelFit
    findings: list[Finding]
    rejected: dict[str, dict[str, Any]]
    unavailable: dict[str, str]
    suspects: list[SignalRelation]
    step: StepEvent | None
    heading: HeadingErrors | None = None
    autopilot: dict[str, dict[str, float]] = field(default_factory=dict)
    linear_note: str = ""
    excluded: list[tuple[float, float]] = field(default_factory=list)
    field_step: dict[str, Any] | None = None
    gate: gate_mod.GateResult | None = None
    structure: list[dict[str, Any]] = field(default_factory=list)
    #: theta with the autopilot's calibration as prior, when the gate refuses the calibration only
    prior_theta: PriorTheta | None = None

    @property
    def observable(self) -> bool:
        return self.gate is None or self.gate.observable

    def bias_mgauss(self, fit: ModelFit) -> F64:
        return export.bias_mgauss(self.data, fit)

    def to_json(self) -> dict[str, Any]:
        return export.compass_json(self)


@dataclass(frozen=True)
class Diagnosis:
    log_source: str
    primary: int
    compasses: list[CompassDiagnosis]
    notes: list[str]
    #: MAV_AUTOPILOT of the log (3 ArduPilot, 12 PX4, -1 unknown): whose parameters the report prints
    autopilot: int = -1

    def compass(self, index: int) -> CompassDiagnosis:
        for c in self.compasses:
            if c.index == index:
                return c
        raise KeyError(index)

    def to_json(self) -> dict[str, Any]:
        return export.diagnosis_json(self)
