"""Markdown report with plots (matplotlib, Agg) for a :class:`~magcomp.diagnosis.engine.Diagnosis`.

This is the one module of :mod:`magcomp.diagnosis` that writes files; the CLI calls it, the math never does.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcomp.diagnosis.effects import drive_columns
from magcomp.diagnosis.engine import CompassDiagnosis, Diagnosis, compass_yaw_rad
from magcomp.diagnosis.model import ModelFit, design

F64 = NDArray[np.float64]


def earth_part(c: CompassDiagnosis, fit: ModelFit) -> F64:
    x, _ = design(c.data, fit.inc_rad, fit.dec_rad, fit.drift_rad_s, fit.ext)
    return np.asarray(x[:, :4] @ np.vstack([fit.a_mgauss.T, fit.c_mgauss]))


def write_plots(c: CompassDiagnosis, out_dir: Path, stem: str) -> list[tuple[str, str]]:
    """PNG figures for compass ``c``; returns (file name, caption) pairs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    figs = [_plot_residual(c, plt, out_dir, stem), _plot_bias(c, plt, out_dir, stem)]
    for plot in (_plot_motors_off_step, _plot_heading):
        fig_cap = plot(c, plt, out_dir, stem)
        if fig_cap is not None:
            figs.append(fig_cap)
    return figs


def _plot_residual(c: CompassDiagnosis, plt: Any, out_dir: Path, stem: str) -> tuple[str, str]:
    """Residual of both models over time, with the throttle."""
    t = c.data.t_s - c.data.t_s[0]
    thr = c.data.throttle_01
    fig, axes = plt.subplots(4, 1, figsize=(10, 8), sharex=True)
    for i, ax in enumerate(axes[:3]):
        ax.plot(
            t, c.baseline.residual_mgauss[:, i], ".", ms=1.5, color="tab:red", label="paper model eq. (11)"
        )
        ax.plot(t, c.extended.residual_mgauss[:, i], ".", ms=1.5, color="tab:green", label="extended model")
        ax.set_ylabel(f"{'XYZ'[i]} residual\nmgauss")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right", markerscale=6, fontsize=8)
    axes[3].plot(t, thr, color="k", lw=0.8)
    axes[3].set_ylabel("throttle 0..1")
    axes[3].set_xlabel("time since first compass sample, s")
    fig.suptitle(f"Compass {c.index}: measured minus predicted field")
    name = f"{stem}_compass{c.index}_residual.png"
    fig.tight_layout()
    fig.savefig(out_dir / name, dpi=90)
    plt.close(fig)
    return name, "Measured minus predicted field, per axis (red: the paper's model; green: extended)."


def _plot_bias(c: CompassDiagnosis, plt: Any, out_dir: Path, stem: str) -> tuple[str, str]:
    """Bias against throttle: measured field minus the fitted Earth part, with both models' bias curves."""
    thr = c.data.throttle_01
    meas = c.data.field_mgauss - earth_part(c, c.extended)
    cols_b, _ = drive_columns(c.data.drive, c.baseline.ext)
    bias_b = cols_b @ c.baseline.coefs
    bias_e = c.bias_mgauss(c.extended)
    order = np.argsort(thr)
    pick = thin_indices(len(thr))  # a 2 h log: a readable cloud, not a solid bar
    centres, medians = binned_median(thr, meas)
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.8))
    for i, ax in enumerate(axes):
        ax.plot(thr[pick], meas[pick, i], ".", ms=1.5, color="0.6", label="measured")
        ax.plot(centres, medians[:, i], "o-", ms=3, lw=1, color="k", label="measured, median per bin")
        ax.plot(thr[order], bias_b[order, i], color="tab:red", lw=1, label="theta throttle^2 (eq. 11)")
        ax.plot(thr[pick], bias_e[pick, i], ".", ms=1, color="tab:green", label="extended")
        ax.set_xlabel("throttle 0..1")
        ax.set_title(f"{'XYZ'[i]} bias, mgauss")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, markerscale=2)
    fig.tight_layout()
    name = f"{stem}_compass{c.index}_bias.png"
    fig.savefig(out_dir / name, dpi=90)
    plt.close(fig)
    return (
        name,
        "Bias against throttle: the measured field minus the fitted Earth field and hard iron "
        "(grey; black: its median per throttle bin), the paper's model (red), the extended model (green).",
    )


#: points drawn per scatter series: more make a solid bar at the figure's size
MAX_POINTS = 4000


def thin_indices(n: int, cap: int = MAX_POINTS) -> NDArray[np.int64]:
    """At most ``cap`` indices spread evenly over ``0..n-1`` (all of them when ``n <= cap``)."""
    if n <= cap:
        return np.arange(n, dtype=np.int64)
    return np.unique(np.linspace(0, n - 1, cap).round().astype(np.int64))


def binned_median(x: F64, y: F64, bins: int = 20) -> tuple[F64, F64]:
    """Median of ``y`` (n, k) in ``bins`` equal-width bins of ``x`` holding at least 10 samples."""
    finite = np.isfinite(x) & np.all(np.isfinite(y), axis=1)
    x, y = x[finite], y[finite]
    if x.size == 0:
        return np.zeros(0), np.zeros((0, y.shape[1]))
    edges = np.linspace(float(x.min()), float(x.max()) + 1e-12, bins + 1)
    which = np.digitize(x, edges) - 1
    cs, ms = [], []
    for b in range(bins):
        m = which == b
        if np.count_nonzero(m) >= 10:
            cs.append(0.5 * (edges[b] + edges[b + 1]))
            ms.append(np.median(y[m], axis=0))
    return np.asarray(cs), np.asarray(ms).reshape(len(ms), y.shape[1])


def _plot_motors_off_step(c: CompassDiagnosis, plt: Any, out_dir: Path, stem: str) -> tuple[str, str] | None:
    """The largest step of the field with the motors off: measured against predicted."""
    if c.field_step is None or c.field_step.get("t_s") is None:
        return None
    ts = float(c.field_step["t_s"])
    win = (c.data.t_s > ts - 6.0) & (c.data.t_s < ts + 6.0)
    pred = c.data.field_mgauss - c.extended.residual_mgauss
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.5))
    for i, ax in enumerate(axes):
        ax.plot(
            c.data.t_s[win],
            c.data.field_mgauss[win, i],
            ".-",
            ms=3,
            lw=0.6,
            color="0.3",
            label="measured",
        )
        ax.plot(c.data.t_s[win], pred[win, i], lw=1.2, color="tab:blue", label="forward model (gyro)")
        ax.axvline(ts, color="tab:red", lw=0.8, ls="--")
        ax.set_title(f"{'XYZ'[i]}, mgauss")
        ax.set_xlabel("log time, s")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    name = f"{stem}_compass{c.index}_motors_off_step.png"
    fig.savefig(out_dir / name, dpi=90)
    plt.close(fig)
    return name, f"Largest field step with the motors off (t = {ts:.1f} s): measured and predicted."


def _plot_heading(c: CompassDiagnosis, plt: Any, out_dir: Path, stem: str) -> tuple[str, str] | None:
    """Heading change of the compass under each model and of the reference heading (the truth, or the compass
    far from the wires), wrapped to +-180 deg, when there is a reference."""
    t = c.data.t_s - c.data.t_s[0]
    if c.heading is None:
        return None
    fig, ax = plt.subplots(figsize=(10, 3.5))
    ref = c.heading.reference_yaw_rad
    if ref is not None and len(ref) == len(t):
        ax.plot(t, heading_change_deg(ref), ".", ms=0.6, color="k", zorder=5,
                label=f"reference: {c.heading.reference}")  # fmt: skip
    for label, fit, remove, color in (
        ("uncompensated", c.baseline, False, "tab:red"),
        ("paper", c.baseline, True, "tab:orange"),
        ("extended", c.extended, True, "tab:green"),
    ):
        change = heading_change_deg(compass_yaw_rad(c.data, fit, remove))
        ax.plot(t, change, ".", ms=1.0, color=color, label=label)
    ax.set_ylim(-180.0, 180.0)
    ax.set_yticks(np.arange(-180.0, 181.0, 90.0))
    ax.set_ylabel("compass heading change, deg")
    ax.set_xlabel("time, s")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    name = f"{stem}_compass{c.index}_heading.png"
    fig.savefig(out_dir / name, dpi=90)
    plt.close(fig)
    return name, f"Heading from the compass (reference: {c.heading.reference})."


def heading_change_deg(yaw_rad: F64) -> F64:
    """Heading change since the first sample, wrapped to [-180, 180) deg: a long log with many turns stays on
    one readable axis instead of climbing by 360 deg a turn (plotted as points: no lines across the wrap)."""
    yaw = np.degrees(np.asarray(yaw_rad, dtype=float))
    if yaw.size == 0:
        return yaw
    return np.asarray((yaw - yaw[0] + 180.0) % 360.0 - 180.0)


def _text(v: Any, unit: str = "") -> str:
    """A value in the report's prose: ``unknown`` for a missing one (never "None")."""
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "unknown"
    return f"{v}{unit}"


def _vec(v: Any) -> str:
    return "[" + ", ".join(f"{float(x):.1f}" for x in v) + "]"


def markdown(
    d: Diagnosis, figures: dict[int, list[tuple[str, str]]] | None = None, rel_dir: str = ".",
    checks: dict[int, dict[str, Any] | None] | None = None,
) -> str:  # fmt: skip
    """The report as Markdown; ``figures`` maps compass index -> (file, caption) under ``rel_dir``;
    ``checks``: compass index -> its theta's check against the gyro (diagnose's ``heading_vs_gyro``)."""
    j = d.to_json()
    lines = [f"# magcomp diagnosis: `{Path(d.log_source).name}`", ""]
    lines += [
        "What this is: the paper's model of the compass (calibration + Earth field + "
        "bias = theta * throttle^2, "
        "eq. (11)) is driven with this log's own rotation, throttle, battery and temperature and compared "
        "with what the compass measured. Extensions (physical causes the paper ignores) are kept only when "
        "they predict unseen parts of the log better (blocked cross-validation) and win on BIC.",
        "",
        "| compass | theta at full throttle (mgauss, compass frame) | residual paper "
        "(mgauss) | residual extended "
        "| findings |",
        "|---|---|---|---|---|",
    ]
    for c in d.compasses:
        if not c.observable:
            lines.append(
                f"| {c.index} | not observable | {c.baseline.rms_mgauss:.2f} | "
                f"{c.extended.rms_mgauss:.2f} | - |"
            )
            continue
        names = ", ".join(f.label for f in c.findings) or "none"
        hw = c.to_json()["theta_ci95_joint_halfwidth"]  # the whole vector: the joint box (intervals module)
        lines.append(
            f"| {c.index} | {_vec(c.extended.theta_mgauss)} +- {_vec(hw)} (95 % joint) | "
            f"{c.baseline.rms_mgauss:.2f} | {c.extended.rms_mgauss:.2f} | {names} |"
        )
    lines.append("")
    g = j["gain"]
    if j.get("observable", True):
        lines += [
            f"Primary compass {d.primary}: residual {_text(j['residual_rms_baseline'])} -> "
            f"{_text(j['residual_rms_extended'])} mgauss per axis (ratio {_text(g['residual_rms_ratio'])})."
        ]
    else:
        lines += [f"Primary compass {d.primary} is not observable in this log: {j['unobservable_why']}."]
    if "heading_error_rms_deg" in g:
        h = g["heading_error_rms_deg"]
        lines.append(
            f"Heading error against {g['heading_reference']} (rms, deg; tilt under 45 deg): "
            f"uncompensated {_text(h['uncompensated'])}, paper {_text(h['paper'])}, "
            f"extended {_text(h['extended'])}."
        )
    lines.append("")
    for note in d.notes:
        lines.append(f"- note: {note}")
    for c in d.compasses:
        lines += _compass_section(c, (figures or {}).get(c.index, []), rel_dir, d.autopilot)
        lines += _check_lines((checks or {}).get(c.index))
    return "\n".join(lines) + "\n"


def _check_lines(h: dict[str, Any] | None) -> list[str]:
    """theta's check against the gyro (diagnosis/gyro_check.py), as diagnose prints it."""
    if not h:
        return []
    out = [
        f"**Against the gyro** (10 s windows, motors running, {h['windows']} windows): the field as logged "
        f"{h['baseline_gyro_deg']:.1f} deg -> with this theta removed {h['model_gyro_deg']:.1f} deg: "
        f"**{h['result']}** ({h['verdict']})."
    ]
    if h.get("worse"):
        out.append("These compensation parameters would make the heading worse: `--params-out` leaves them "
                   "out.")  # fmt: skip
    return [*out, ""]


def _compass_section(
    c: CompassDiagnosis, figs: list[tuple[str, str]], rel_dir: str, autopilot: int = -1
) -> list[str]:
    cj = c.to_json()
    out = ["", f"## Compass {c.index}", ""]
    if c.sensor is not None and c.sensor.device_id is not None:
        # what to compare between flights: the slot's sensor changes when a GPS compass is unplugged
        out.append(f"Sensor: {c.sensor.describe()} ({c.sensor.source}).")
    out.append(f"Rotation used by the model: {c.data.attitude_note}.")
    out.append(
        f"Earth field through the calibration: {_text(cj['field_strength_mgauss'], ' mgauss')}, inclination "
        f"{_text(cj['inclination_deg'], ' deg')}; {_drift_text(c, cj)}."
    )
    for flag in cj.get("nuisances_at_bound", []):
        out.append(f"**Nuisance on its bound:** {flag}.")
    gate = cj["gate"]
    if gate:
        g = {k: _text(v) for k, v in gate.items()}
        out.append(
            f"Validity gate ({g['earth_reference']}): fitted field {g['fitted_strength_mgauss']} "
            f"mgauss {_wmm_text(gate)}, calibration condition {g['calibration_condition']}, "
            f"heading span {g['yaw_span_deg']} deg, tilt span {g['tilt_span_deg']} deg, throttle span "
            f"{g['throttle_span']}, residual {g['residual_rms_mgauss']} mgauss (white-noise floor "
            f"{g['noise_floor_mgauss']}), compass {g['magnetometer_hz']} Hz, gyro {g['gyro_hz']} Hz."
        )
        if gate.get("theta_consistency_why"):  # theta's interval is a lower bound (diagnosis.consistency)
            out.append(f"**theta caveat:** {gate['theta_consistency_why']}.")
    out.append("")
    if not c.observable:
        pt = cj.get("theta_given_prior")
        if pt:
            out.append(
                f"**Calibration not observable:** {cj['unobservable_why']}. No finding or autopilot "
                "parameter is given from the free fit. **theta is**: the throttle varies at a near-constant "
                f"attitude, so with the {pt['prior']}, theta = {_vec(pt['theta'])} +- "
                f"{_vec(pt['theta_ci95_joint_halfwidth'])} mgauss (95 % joint over the axes, compass frame; "
                f"residual {pt['residual_rms_mgauss']} mgauss): {pt['note']}."
            )
        else:
            out.append(
                f"**Not observable:** {cj['unobservable_why']}. No theta, finding or autopilot parameter is "
                "given for this compass: a fit that fails these checks is not a result."
            )
        out.append("")
        return out
    out += _findings_lines(c, cj)
    out += _residual_lines(c)
    out += _autopilot_lines(cj, figs, rel_dir, autopilot)
    return out


def _findings_lines(c: CompassDiagnosis, cj: dict[str, Any]) -> list[str]:
    """Unexplained structure, the findings, and what this log cannot test."""
    out: list[str] = []
    if cj["unexplained_structure"]:
        out.append("### Unexplained structure (outside the named causes)")
        out.append("")
        for u in cj["unexplained_structure"]:
            when = f" at t = {u['t_s']} s" if "t_s" in u else ""
            corr = ", ".join(f"{k['signal']} ({100 * k['r2']:.0f} %)" for k in u.get("best_correlates", []))
            out.append(
                f"- **{u['kind']}**{when}: size {u['size_mgauss']} mgauss, {u['rms_reduction_pct']} % of the "
                f"residual rms; best correlates: {corr or 'none'}"
            )
        out.append("")
    if c.findings:
        out.append("### What the paper's model gets wrong here")
        out.append("")
        for k, f in enumerate(c.findings, 1):
            ev = f.evidence
            out.append(
                f"{k}. **{f.label}** {f.params}: {f.cause} Held-out residual "
                f"{ev['cv_rms_without']} -> {ev['cv_rms_with']} mgauss "
                f"({ev['cv_gain_pct']} %{_cv_t_text(ev)}), "
                f"delta BIC {ev['delta_bic']}; residual after: {f.residual_rms_after:.2f} mgauss."
                + _witness_text(ev)
            )
        out.append("")
    else:
        out.append(
            "No extension improves the prediction of held-out data: the paper's model explains this "
            "compass as far as the log can tell."
        )
        out.append("")
    if cj["unavailable"]:
        out.append(
            "Not testable in this log: " + "; ".join(f"{k} ({v})" for k, v in cj["unavailable"].items()) + "."
        )
        out.append("")
    return out


def _residual_lines(c: CompassDiagnosis) -> list[str]:
    """What the remaining residual follows, and its largest step."""
    out: list[str] = []
    if c.suspects:
        out.append("### What the remaining residual follows")
        out.append("")
        out.append("| signal | lag s | share of residual variance |")
        out.append("|---|---|---|")
        for s in c.suspects[:6]:
            out.append(f"| {s.signal} | {s.lag_s:+.1f} | {100 * s.r2:.1f} % |")
        out.append("")
    if c.step is not None and c.step.size_sigma > 8.0:
        st = c.step
        co = ", ".join(f"{k} ({v:+.2f} sd)" for k, v in list(st.co_stepping.items())[:4])
        evs = "; ".join(e for _, e in st.events[:5]) or "none logged"
        out.append(
            f"Largest step in the residual: {_vec(st.size_mgauss)} mgauss at t = {st.t_s:.1f} s "
            f"({st.size_sigma:.0f} noise units). Signals stepping at the same time: {co or 'none'}. "
            f"Events within 2 s: {evs}."
        )
        out.append("")
    return out


#: MAV_AUTOPILOT values and the parameter families (keys of the export's ``autopilot``) of each
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12


def _own_params(key: str, autopilot: int) -> bool:
    """Whether the parameter family ``key`` (ardupilot, px4, px4_throttle, ...) belongs to the log's
    autopilot (both when the log does not say which)."""
    if autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return key.startswith("ardupilot")
    if autopilot == MAV_AUTOPILOT_PX4:
        return key.startswith("px4")
    return True


def _autopilot_lines(
    cj: dict[str, Any], figs: list[tuple[str, str]], rel_dir: str, autopilot: int = -1
) -> list[str]:
    """The compensation in the log's autopilot's terms (both autopilots' when unknown), then the figures."""
    out: list[str] = []
    out.append("### Compensation in autopilot terms")
    out.append("")
    out.append(cj["linearisation"])
    out.append("")
    for k, v in cj["autopilot"].items():
        if not _own_params(k, autopilot):
            continue
        out.append(f"- {k}: " + ", ".join(f"`{p}={val}`" for p, val in v.items()))
    out.append("")
    for name, caption in figs:
        out.append(f"![{caption}]({rel_dir}/{name})")
        out.append("")
        out.append(f"*{caption}*")
        out.append("")
    return out


def write_report(
    d: Diagnosis,
    path: Path,
    img_dir: Path | None = None,
    checks: dict[int, dict[str, Any] | None] | None = None,
) -> list[Path]:
    """Write the Markdown report to ``path`` and its PNGs to ``img_dir`` (default: beside it); ``checks``: as
    :func:`markdown`'s."""
    path.parent.mkdir(parents=True, exist_ok=True)
    img_dir = img_dir or path.parent / (path.stem + "_img")
    stem = path.stem
    figs = {c.index: write_plots(c, img_dir, stem) for c in d.compasses if c.observable}
    try:
        rel = img_dir.resolve().relative_to(path.parent.resolve()).as_posix()
    except ValueError:
        rel = img_dir.resolve().as_posix()
    path.write_text(markdown(d, figs, rel, checks), encoding="utf-8")
    written = [path] + [img_dir / f for fl in figs.values() for f, _ in fl]
    return written


def _witness_text(ev: dict[str, Any]) -> str:
    """The logged current's testimony (:mod:`magcomp.diagnosis.current`) as a sentence, or ""."""
    w = ev.get("witnessed_by_current")
    if not w:
        return ""
    return (
        " The compass alone leaves it short of the BIC margin; the logged battery current shows the same "
        f"load shape on its own (value {w['value']}, delta BIC {w['delta_bic']}), inside the compass's "
        "interval."
    )


def _cv_t_text(ev: dict[str, Any]) -> str:
    """The held-out test as ", Diebold-Mariano 4.1 >= 1.96", or "" when the evidence has none."""
    t, crit = ev.get("cv_t"), ev.get("cv_t_critical")
    if t is None or crit is None:
        return ""
    return f", Diebold-Mariano {t:.1f} >= {crit:.2f}"


def _drift_text(c: CompassDiagnosis, cj: dict[str, Any]) -> str:
    """The heading drift clause, never "None": not fitted without rotation, withheld if not observable."""
    drift = cj.get("heading_drift_deg_per_min")
    if c.data.attitude_source == "stationary":
        return "no heading drift fitted (the vehicle does not rotate, so no gyro is integrated)"
    if drift is None:
        return "heading drift of the gyro not reported (the fit failed the validity gate)"
    return f"heading drift of the gyro {drift} deg/min"


def _wmm_text(gate: dict[str, Any]) -> str:
    """The WMM comparison, or what the fit was checked against when the log has no position."""
    if gate.get("wmm_strength_mgauss") is None:
        return (
            f"(no WMM: the log has no position, so only Earth's surface range is checked), inclination "
            f"{gate['fitted_inclination_deg']} deg"
        )
    return (
        f"vs WMM {gate['wmm_strength_mgauss']}, inclination {gate['fitted_inclination_deg']} vs "
        f"{gate['wmm_inclination_deg']} deg"
    )
