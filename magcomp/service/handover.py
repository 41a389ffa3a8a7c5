"""Offline hands over to online (issue 9, item 5): the state a log ends with, saved where `run` and `replay`
start from.

``magcomp fit LOG --save-state DIR`` and ``magcomp diagnose LOG --save-state DIR`` run the first pass of a
two-pass replay (:func:`magcomp.service.replay.learn_pass`) over the log with the same configuration that
``run`` / ``replay`` use, and write each compass's final :class:`~magcomp.adapters.state_store.CompassState`
into the state directory (one file per vehicle and compass). A compass whose headings the pass could not
correct is not saved: a stored in-flight estimate is applied from the first sample of the next run, so an
estimate that never passed the test for being applied must not be handed over. One line per compass says
what was saved or why nothing was.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from magcomp.adapters.config import Config
from magcomp.adapters.state_store import StateStore, vehicle_name
from magcomp.errors import InputError

#: below this standard deviation of throttle^2 theta is not observable (InflightStage.why_not's threshold)
THROTTLE2_STD_MIN = 0.02


def _vec(v: Sequence[Any] | None) -> str:
    if v is None:
        return "?"
    return (
        "("
        + ", ".join("?" if x is None or not math.isfinite(float(x)) else f"{float(x):.1f}" for x in v)
        + ")"
    )


def save_learned_state(log_path: str | Path, cfg: Config, store: StateStore) -> list[str]:
    """Learn from the whole log (the replay's first pass) and save every correctable compass's final state
    into ``store``. Returns one line per compass for the console (what was saved, or why nothing was)."""
    from magcomp.service.replay import learn_pass

    mem = learn_pass(log_path, cfg)
    if mem is None:  # pragma: no cover - learn_pass returns None only when asked to stop
        return ["state: not saved (stopped)"]
    summary: dict[str, Any] = mem.summary or {}
    comps = {int(c["index"]): c for c in summary.get("compasses", [])}
    if not comps:
        return [f"state: nothing saved to {store.directory}: no magnetometer samples in the log"]
    lines = []
    for idx, c in sorted(comps.items()):
        # the vehicle as the log named it at the end (a state saved before its id arrived is not it)
        key = (int(summary.get("system_id") or 1), summary.get("vehicle_uid"), idx)
        state = mem.states.get(key) or next((s for (*_, j), s in mem.states.items() if j == idx), None)
        if c.get("status") != "corrected" or state is None:
            lines.append(f"compass {idx}: nothing saved: {c.get('why') or 'not corrected'}")
            continue
        try:
            path = store.save(state)
        except OSError as exc:
            raise InputError(
                f"state directory {store.directory}: cannot write ({exc.strerror or exc})"
            ) from exc
        cal = c.get("calibration") or {}
        source = cal.get("source", "?")
        inflight = c.get("inflight") or {}
        if source == "in-flight":
            form = inflight.get("form", "?")
            sig = inflight.get("theta_sigma_mgauss")
            thr2 = float(inflight.get("throttle2_std") or 0.0)
            if thr2 < THROTTLE2_STD_MIN:  # the stage's own observability threshold (why_not)
                what = (
                    f"calibration learned in flight ({form} form); theta not observable in this log "
                    f"(throttle^2 std {thr2:.3f}): the next run goes on learning it"
                )
            else:
                what = f"calibration and theta learned in flight ({form} form)"
                if sig is not None:
                    what += f", theta +- {_vec(sig)} mgauss (1 sd)"
        else:
            what = f"calibration {source}, theta from the observer of eq. (20)"
            if not c.get("theta_converged"):
                what += " (not converged)"
        lines.append(
            f"compass {idx}: saved {path} ({vehicle_name(state.system_id, state.vehicle_uid)}): "
            f"theta {_vec(c.get('theta_mgauss'))} mgauss; {what}"
        )
    return lines


def handover_config(config_path: str | None, throttle_source: str | None) -> Config:
    """The configuration `run` / `replay` would use (``--config``, else the defaults), with the command's own
    ``--throttle-source`` when one was given and the configuration leaves the choice to ``auto``."""
    from dataclasses import replace

    from magcomp.adapters.config import load_config

    cfg = load_config(config_path)
    if throttle_source and throttle_source != "auto" and cfg.input.throttle_source == "auto":
        cfg = replace(cfg, input=replace(cfg.input, throttle_source=throttle_source))
    return cfg


def add_save_state_arguments(parser: Any) -> None:
    """``--save-state DIR`` and ``--config FILE`` for the offline commands."""
    parser.add_argument(
        "--save-state",
        metavar="DIR",
        help="learn calibration and theta from the whole log as `replay` does and save each compass's state "
        "in DIR, which `magcomp run --state-dir DIR` and `magcomp replay --state-dir DIR` start from",
    )
    parser.add_argument(
        "--config",
        metavar="FILE",
        help="TOML configuration for --save-state (the one `run` / `replay` use; default: built-in defaults)",
    )
