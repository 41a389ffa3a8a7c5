"""`magcomp fleet report DIR`: one static HTML page (plots embedded as base64 PNG, no scripts, no network):
the vehicles to inspect, each vehicle's theta over its flights with intervals and changes, every log's
rows."""

from __future__ import annotations

import base64
import html
import io
import math
import os
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from magcomp import __version__
from magcomp.core.changes import K_INTERVAL
from magcomp.core.pooling import PooledTrack
from magcomp.fleet.vehicles import TRACK_FAMILY_LEVEL, Vehicle, interval_text, track_text

#: vehicles plotted (the most worth inspecting first); the rest are in the tables
MAX_PLOTS = 30
#: per-log rows shown (the dataset has them all)
MAX_ROWS = 5000

_CSS = """
body { font-family: system-ui, sans-serif; margin: 1.5em; color: #222; }
table { border-collapse: collapse; font-size: 0.85em; margin-bottom: 1.5em; }
th, td { border: 1px solid #ccc; padding: 0.2em 0.5em; text-align: left; vertical-align: top; }
th { background: #f0f0f0; }
tr.failed td { background: #fde8e8; }
tr.changed td { background: #fff4d6; }
.num { text-align: right; font-variant-numeric: tabular-nums; }
img { max-width: 100%; border: 1px solid #ddd; }
"""


def _e(v: Any) -> str:
    return html.escape("" if v is None else str(v))


def _num(v: Any, fmt: str = ".1f") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    return format(v, fmt)


def _png(fig: Any) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80, bbox_inches="tight")
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _theta_plot(v: Vehicle) -> str | None:
    """theta x, y, z per flight, one column per compass: each log's own estimate with +-k sigma (grey), the
    vehicle's track (pooled between changes) as a line in its band; changes marked."""
    hist = [h for h in v.compasses if h.flights]
    if not hist:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    fig, axes = plt.subplots(3, len(hist), figsize=(4.2 * len(hist) + 1, 6), squeeze=False, sharex="col")
    try:
        for col, h in enumerate(hist):
            xs = list(range(1, len(h.flights) + 1))
            for row, axis in enumerate("xyz"):
                ax = axes[row][col]
                ys = [f.theta[row] for f in h.flights]
                es = [K_INTERVAL * f.sigma[row] for f in h.flights]
                ax.errorbar(xs, ys, yerr=es, fmt="o", ms=3, capsize=2, color="0.55", label="log")
                if h.track is not None:
                    _plot_track(ax, h.track, xs, row)
                for c in h.changes:
                    ax.axvline(c.index + 0.5, color="tab:red" if c.confirmed else "tab:orange", ls="--")
                ax.set_ylabel(f"theta {axis} (mgauss)")
                if row == 0:
                    ax.set_title(h.label)
            axes[2][col].set_xlabel("flight (applied, in order)")
            axes[2][col].xaxis.set_major_locator(MaxNLocator(integer=True))
        fig.suptitle(v.vehicle)
        return _png(fig)
    finally:
        plt.close(fig)


def _plot_track(ax: Any, t: PooledTrack, xs: list[int], row: int) -> None:
    """The track of one axis: a line in its band, segment by segment (no line across a change)."""
    for a, b in t.segments:
        seg = xs[a:b]
        ax.fill_between(seg, t.lower[a:b, row], t.upper[a:b, row], color="tab:blue", alpha=0.25, lw=0)
        ax.plot(seg, t.mean[a:b, row], color="tab:blue", lw=1.5, marker="_" if b - a == 1 else "")


def write_report(path: Path, vehicles: list[Vehicle], rows: list[dict[str, Any]]) -> None:
    """The page, written atomically."""
    parts: list[str] = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        "<title>magcomp fleet report</title>",
        f"<style>{_CSS}</style></head><body>",
        "<h1>magcomp fleet report</h1>",
    ]
    n_logs = len({r["sha256"] for r in rows})
    n_failed = len({r["sha256"] for r in rows if r.get("status") != "ok"})
    made = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    parts.append(
        f"<p>{len(vehicles)} vehicles, {n_logs} logs ({n_failed} failed). Made {made} by magcomp "
        f"{_e(__version__)}. A log's own theta: &plusmn;{K_INTERVAL:g} standard deviations (grey). A "
        f"vehicle's theta track (blue): the flights between two changes share theta up to a small "
        f"flight-to-flight variation, so each flight's value is pooled with its siblings', with the error "
        f"they all share; its band holds every flight of the compass on all three axes at once with "
        f"{100 * TRACK_FAMILY_LEVEL:.0f} % (at most 1 vehicle in 20 shows a flight falsely outside).</p>"
    )
    parts += _inspect_section(vehicles)
    parts += _theta_section(vehicles)
    parts += _logs_section(rows)
    parts.append("</body></html>\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text("".join(parts), encoding="utf-8")
    os.replace(tmp, path)


def _inspect_section(vehicles: list[Vehicle]) -> list[str]:
    """The inspect list: one table row per vehicle, in rank order."""
    parts = [
        "<h2 id='inspect'>Vehicles to inspect</h2>",
        "<table><tr><th>#</th><th>vehicle</th><th>logs</th><th>failed</th><th>last flight</th>"
        "<th>theta now (mgauss; the track at the last flight)</th><th>score</th><th>why</th>"
        "<th>parameters to set</th></tr>",
    ]
    for i, v in enumerate(vehicles, 1):
        changed = any(c.confirmed for h in v.compasses for c in h.changes)
        thetas = "<br>".join(
            f"{_e(h.label)}: {_e(track_text(h))}"
            for h in v.compasses
            if h.level is not None
        )
        last = v.last_date.strftime("%Y-%m-%d") if v.last_date else ""
        parts.append(
            f"<tr class='{'changed' if changed else ''}'><td class='num'>{i}</td>"
            f"<td><a href='#v{i}'>{_e(v.vehicle)}</a><br><small>{_e(v.identity_source)}; {_e(v.autopilot)} "
            f"{_e(v.firmware)}</small></td><td class='num'>{v.logs}</td><td class='num'>{v.failed}</td>"
            f"<td>{_e(last)}</td><td>{thetas}</td><td class='num'>{v.score:.0f}</td>"
            f"<td>{'<br>'.join(_e(r) for r in v.reasons)}</td><td>{_params_cell(v)}</td></tr>"
        )
    parts.append("</table>")
    return parts


def _params_cell(v: Vehicle) -> str:
    """The compensation parameters diagnose suggests for the vehicle (fleet.vehicles.vehicle_params)."""
    if not v.params:
        return ""
    values = "<br>".join(f"{_e(k)} = {val:g}" for k, val in v.params["values"].items())
    files = ", ".join(_e(Path(f).name) for f in v.params.get("files", []))
    src = f"<small>from {_e(v.params['flight'])}" + (f"; params/{files}" if files else "") + "</small>"
    return f"{values}<br>{src}"


def _theta_section(vehicles: list[Vehicle]) -> list[str]:
    """Per vehicle: its changes in words, and theta per flight as a plot."""
    parts = ["<h2>Theta per vehicle over time</h2>"]
    for i, v in enumerate(vehicles, 1):
        parts.append(f"<h3 id='v{i}'>{i}. {_e(v.vehicle)}</h3>")
        parts += [f"<p><small>{_e(note)}</small></p>" for note in v.notes]
        for h in v.compasses:
            for c in h.changes:
                f = h.flights[c.index]
                state = "changed" if c.confirmed else "may have changed (not yet confirmed)"
                parts.append(
                    f"<p>{_e(h.label)}: theta {state} at {_e(f.file_name)} "
                    f"({_e(f.date_utc.date() if f.date_utc else '')}): "
                    f"{_e(interval_text(c.before.mean.tolist(), c.before.std.tolist()))} &rarr; "
                    f"{_e(interval_text(c.after.mean.tolist(), c.after.std.tolist()))} mgauss</p>"
                )
        img = _theta_plot(v) if i <= MAX_PLOTS else None
        if img is not None:
            parts.append(f"<img alt='theta of {_e(v.vehicle)} per flight' src='data:image/png;base64,{img}'>")
        elif i > MAX_PLOTS:
            parts.append("<p>(not plotted: see the dataset)</p>")
        else:
            parts.append("<p>No flight with theta applied.</p>")
    return parts


def _sensor(r: dict[str, Any]) -> str:
    s = r.get("compass_sensor")
    return f"<br><small>sensor {_e(s)}</small>" if s else ""


def _logs_section(rows: list[dict[str, Any]]) -> list[str]:
    """Every log's rows (failures in red), at most MAX_ROWS."""
    parts = [
        "<h2>Logs</h2>",
        "<table><tr><th>file</th><th>vehicle</th><th>date</th><th>status</th><th>compass</th>"
        "<th>applied</th><th>theta (mgauss)</th><th>interference %</th><th>yaw span deg</th>"
        "<th>throttle</th><th>why / error</th><th>diagnose</th></tr>",
    ]
    ordered = sorted(rows, key=lambda r: (str(r.get("vehicle")), str(r.get("date_utc")), str(r.get("path"))))
    parts += [_log_row(r) for r in ordered[:MAX_ROWS]]
    parts.append("</table>")
    if len(ordered) > MAX_ROWS:
        parts.append(f"<p>{len(ordered) - MAX_ROWS} more rows in the dataset.</p>")
    return parts


def _log_row(r: dict[str, Any]) -> str:
    ok = r.get("status") == "ok"
    theta = ""
    if ok and r.get("theta_x_mgauss") is not None:
        theta = interval_text(
            [r["theta_x_mgauss"], r["theta_y_mgauss"], r["theta_z_mgauss"]],
            [
                r.get("theta_sigma_x_mgauss") or math.nan,
                r.get("theta_sigma_y_mgauss") or math.nan,
                r.get("theta_sigma_z_mgauss") or math.nan,
            ],
        )
    d = r.get("date_utc")
    thr = f"{_num(r.get('throttle_min'), '.2f')}-{_num(r.get('throttle_max'), '.2f')}" if ok else ""
    return (
        f"<tr class='{'' if ok else 'failed'}'>"
        f"<td title='{_e(r.get('path'))}'>{_e(r.get('file_name'))}</td>"
        f"<td>{_e(r.get('vehicle'))}</td><td>{_e(d.strftime('%Y-%m-%d %H:%M') if d else '')}</td>"
        f"<td>{_e(r.get('status'))}</td><td class='num'>{_e(r.get('compass'))}{_sensor(r)}</td>"
        f"<td>{'yes' if r.get('applied') else ('no' if ok else '')}</td><td>{_e(theta)}</td>"
        f"<td class='num'>{_num(r.get('interference_pct'))}</td>"
        f"<td class='num'>{_num(r.get('yaw_span_deg'), '.0f')}</td><td>{thr}</td>"
        f"<td>{_e(r.get('why') if ok else r.get('error'))}</td><td>{_diagnose_cell(r)}</td></tr>"
    )


def _diagnose_cell(r: dict[str, Any]) -> str:
    """diagnose's theta (95 % per axis) and findings for the row, or why it has none."""
    if r.get("diagnose_status") == "failed":
        return f"failed: {_e(r.get('diagnose_error'))}"
    if r.get("diagnose_status") != "ok":
        return ""
    out = _e(r.get("diagnose_findings"))
    if r.get("diagnose_theta_x_mgauss") is not None:
        theta = ", ".join(f"{float(r[f'diagnose_theta_{a}_mgauss']):.0f}" for a in "xyz")
        hw = ", ".join(f"{float(r.get(f'diagnose_theta_ci95_{a}_mgauss') or math.nan):.0f}" for a in "xyz")
        ident = "" if r.get("diagnose_theta_identifiable") else " (not identifiable)"
        frm = _e(r.get("diagnose_theta_from"))
        out += f"<br><small>theta ({theta}) &plusmn; ({hw}) 95 % per axis, {frm}{ident}</small>"
    return out
