"""The live pipeline without a link of its own: messages in, MAGCOMP_HEADING and NAMED_VALUE_FLOAT out.

For hosts that own the link and hand magcomp each decoded message: the MAVProxy module
(:mod:`magcomp.mavproxy`). Per sender on the link (system id, component id) it keeps what
:class:`~magcomp.service.daemon.Daemon` keeps: a converter and clock (:mod:`magcomp.adapters.mavlink_source`),
a :class:`~magcomp.service.pipeline.Pipeline` with the state store, an encoder with its own sequence, the
decimated named values; it asks each new sender for AUTOPILOT_VERSION (its unique id keys the state).
Messages of any pymavlink dialect are taken (fields are read by name).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from magcomp.adapters.config import Config
from magcomp.adapters.mavlink_source import WANTED_MAVLINK, sender_stream
from magcomp.adapters.state_store import StateStore
from magcomp.core.types import HeadingEstimate
from magcomp.service.pipeline import Pipeline
from magcomp.service.publish import HeadingEncoder, NamedValues, pilot_status
from magcomp.service.replay import source_throttle
from magcomp.service.workers import Workers

_STATUS_WORDS = {0.0: "not compensated yet", 1.0: "compensating, theta learning", 2.0: "compensating, theta "
                 "converged", 3.0: "inputs late"}  # fmt: skip


@dataclass
class _Vehicle:
    stream: Any
    pipeline: Pipeline
    encoder: HeadingEncoder
    named: NamedValues
    last: dict[int, HeadingEstimate]


class Companion:
    """``send(packet)``: where the packed MAVLink 2 frames go (the host's links). ``on_text``: the
    pipeline's status lines (calibration learned, resets, identity)."""

    def __init__(
        self,
        cfg: Config,
        store: StateStore | None,
        send: Callable[[bytes], None],
        on_text: Callable[[float, str], None] | None = None,
    ) -> None:
        self.cfg = cfg
        self.store = store
        self._send = send
        self._on_text = on_text
        self._wanted = frozenset(WANTED_MAVLINK)
        self.workers = Workers.threads()
        self.vehicles: dict[tuple[int, int], _Vehicle] = {}
        self.published = 0
        self._closed = False

    def handle(self, msg: Any) -> HeadingEstimate | None:
        """One decoded message from the link; returns the last estimate it produced (if any)."""
        if self._closed or msg.get_type() not in self._wanted:
            return None
        key = (int(msg.get_srcSystem()), int(msg.get_srcComponent()))
        v = self.vehicles.get(key) or self._new_vehicle(key)
        out = None
        for sample in v.stream.push(msg):
            est = v.pipeline.process(sample)
            if est is not None:
                self._publish(v, est)
                out = est
        return out

    def _new_vehicle(self, key: tuple[int, int]) -> _Vehicle:
        spec = source_throttle(self.cfg)
        pipeline = Pipeline(self.cfg, store=self.store, system_id=key[0], on_text=self._on_text,
                            workers=self.workers)  # fmt: skip
        enc = HeadingEncoder(self.cfg.output.source_system, self.cfg.output.source_component)
        enc.set_system(key[0])
        v = _Vehicle(sender_stream(spec), pipeline, enc,
                     NamedValues(enc, self.cfg.output.named_values_hz), {})  # fmt: skip
        self.vehicles[key] = v
        for packet in enc.identity_requests(key[0], key[1]):
            self._send(packet)
        return v

    def _publish(self, v: _Vehicle, est: HeadingEstimate) -> None:
        v.last[est.mag_index] = est
        self._send(v.encoder.encode(est))
        t_boot = est.t_boot_s if est.t_boot_s == est.t_boot_s else est.t_s
        for packet in v.named.packets(est.t_s, t_boot, est.mag_index, est.heading_deg, est.theta_mgauss,
                                      est.flags):  # fmt: skip
            self._send(packet)
        self.published += 1

    def status_lines(self) -> list[str]:
        """One line per compass of every vehicle: corrected and raw heading, |theta|, status."""
        lines = []
        for (sysid, _), v in sorted(self.vehicles.items()):
            who = f"vehicle {sysid}" + (f" (id {v.pipeline.vehicle_uid})" if v.pipeline.vehicle_uid else "")
            for idx, est in sorted(v.last.items()):
                th = est.theta_mgauss
                norm = math.sqrt(float(th[0]) ** 2 + float(th[1]) ** 2 + float(th[2]) ** 2)
                lines.append(f"magcomp {who} compass {idx}: heading {est.heading_deg % 360.0:5.1f} deg "
                             f"(uncompensated {est.heading_raw_deg % 360.0:5.1f}), |theta| {norm:.0f} "
                             f"mgauss, {_STATUS_WORDS[pilot_status(est.flags)]}")  # fmt: skip
        return lines or ["magcomp: no magnetometer data from the vehicle yet"]

    def close(self) -> list[dict[str, Any]]:
        """Save every vehicle's state and stop the workers (idempotent). Returns their summaries."""
        if self._closed:
            return []
        self._closed = True
        try:
            out = []
            for v in self.vehicles.values():
                v.pipeline.close()
                out.append(v.pipeline.summary())
            return out
        finally:
            self.workers.shutdown()
