"""``crtk-ctl plot``: a recording's joints, measured against setpoint (docs/recording.md).

One row of axes per joint, one column per quantity recorded (position, velocity, effort where
present): the measured value solid, the setpoint dashed, in the joint's own colour; operating
state changes marked by a vertical line with the new state, events by a vertical line coloured by
kind (error red, warning orange, status grey). Time is the recording's clock: seconds after the
recording's first message (whose UTC time the axis label gives).

matplotlib is an optional extra (``pip install 'crtk-bridge[plot]'``), imported only here, and
only when plotting: the Agg canvas, never a GUI backend. ``.png`` / ``.svg`` are matplotlib's;
``.html`` is one self-contained page holding the SVG and the list of events (no script).
"""

from __future__ import annotations

import html
import time
from pathlib import Path

import numpy as np

from crtk_bridge.client.bagfile import BagError, Recording, read
from crtk_bridge.errors import CrtkBridgeError
from crtk_bridge.vocabulary import JOINT_UNITS

FORMATS = (".png", ".svg", ".html")
QUANTITIES = ("position", "velocity", "effort")
EVENT_COLOURS = {"error": "tab:red", "warning": "tab:orange", "status": "0.5"}


class PlotError(CrtkBridgeError):
    """crtk-ctl plot cannot do what was asked (one line, naming the fix)."""


def _matplotlib():
    try:
        import matplotlib
    except ImportError:
        raise PlotError("plot needs matplotlib, an optional extra: pip install 'crtk-bridge[plot]'") from None
    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure
    return Figure


def figure(rec: Recording, ns: str | None = None, joints: list[str] | None = None,
           t_from: float | None = None, t_to: float | None = None):
    """The matplotlib Figure of ``rec`` (see the module); ``t_from`` / ``t_to``: seconds after
    the recording's start. Raises :class:`BagError` / :class:`PlotError` naming what is wrong."""
    Figure = _matplotlib()
    ns = ns or (rec.namespaces[0] if rec.namespaces else None)
    if ns is None or ns not in rec.namespaces:
        raise BagError(f"{rec.path}: namespace {ns} is not in this recording (recorded: "
                       f"{', '.join(rec.namespaces) or 'none'})")
    measured = rec.series(ns, "measured_js")
    setpoint = rec.joints.get((ns, "setpoint_js"))
    names = measured.names
    if joints:
        unknown = [j for j in joints if j not in names]
        if unknown:
            raise BagError(f"{rec.path}: {ns} has no joint {unknown[0]} (joints: {', '.join(names)})")
        picked = [names.index(j) for j in joints]
    else:
        picked = list(range(len(names)))
    t0 = rec.start
    lo = -np.inf if t_from is None else t_from
    hi = np.inf if t_to is None else t_to
    if lo >= hi:
        raise PlotError(f"--from {t_from:g} is not before --to {t_to:g}")
    quantities = [q for q in QUANTITIES if measured.has(q) or (setpoint is not None and setpoint.has(q))]
    # each joint in its unit: the recording's metadata names the prismatic ones (m, m/s, N)
    prismatic = set(filter(None, str(rec.custom.get("prismatic_joints") or "").split(",")))
    fig = Figure(figsize=(4.2 * len(quantities), 1.9 * len(picked) + 0.8), layout="constrained")
    axes = fig.subplots(len(picked), len(quantities), sharex=True, squeeze=False)
    changes = [(t - t0, state) for t, state, _, _ in _state_changes(rec.states.get(ns, []))]
    events = [(t - t0, kind, text) for t, kind, _, text in rec.events]
    changes = [c for c in changes if lo <= c[0] <= hi]
    events = [e for e in events if lo <= e[0] <= hi]
    for row, j in enumerate(picked):
        colour = f"C{j % 10}"
        units = dict(zip(QUANTITIES, JOINT_UNITS["m" if names[j] in prismatic else "rad"]))
        for col, q in enumerate(quantities):
            ax = axes[row][col]
            for series, style, label in ((measured, "-", "measured"), (setpoint, "--", "setpoint")):
                if series is None or not series.has(q):
                    continue
                t = series.t - t0
                keep = (t >= lo) & (t <= hi)
                ax.plot(t[keep], getattr(series, q)[keep, j], style, color=colour, linewidth=1.0,
                        label=f"{names[j]} {label}")
            for t, state in changes:
                ax.axvline(t, color="tab:blue", linewidth=0.6, alpha=0.5)
                if row == 0:
                    ax.annotate(state, (t, 1.0), xycoords=("data", "axes fraction"), fontsize=6,
                                rotation=90, va="top", ha="right", color="tab:blue")
            for t, kind, _ in events:
                ax.axvline(t, color=EVENT_COLOURS.get(kind, "0.5"), linewidth=0.8, linestyle=":")
            ax.set_ylabel(f"{names[j]}\n{q} ({units[q]})", fontsize=7)
            ax.tick_params(labelsize=6)
            if row == 0 and col == 0:
                ax.legend(fontsize=6, loc="upper right")
    start = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(t0))
    for ax in axes[-1]:
        ax.set_xlabel(f"s since {start}", fontsize=7)
    fig.suptitle(f"{rec.robot or '?'} {ns}: measured (solid) vs setpoint (dashed); {rec.path.name}", fontsize=8)
    return fig


def _state_changes(states: list) -> list:
    out, last = [], None
    for s in states:
        if s[1] != last:
            out.append(s)
            last = s[1]
    return out


def write(path: str, output: str, ns: str | None = None, joints: list[str] | None = None,
          t_from: float | None = None, t_to: float | None = None) -> Path:
    """Read the bag at ``path`` and write its plot to ``output`` (.png, .svg or .html)."""
    out = Path(output).expanduser()
    if out.suffix.lower() not in FORMATS:
        raise PlotError(f"-o {output}: give a .png, .svg or .html file")
    _matplotlib()  # the missing extra is said before the bag is read
    rec = read(path, [ns] if ns else None, topics=("measured_js", "setpoint_js"))
    fig = figure(rec, ns, joints, t_from, t_to)
    if out.suffix.lower() == ".html":
        import io
        buf = io.StringIO()
        fig.savefig(buf, format="svg")
        svg = buf.getvalue()
        svg = svg[svg.find("<svg"):]  # the XML declaration and doctype are not HTML
        rows = "".join(f"<tr><td>{t - rec.start:.3f}</td><td>{html.escape(kind)}</td><td>{html.escape(ns_)}</td>"
                       f"<td>{html.escape(text)}</td></tr>" for t, kind, ns_, text in rec.events)
        title = html.escape(f"{rec.robot or '?'}: {rec.path.name}")
        out.write_text(f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{title}</title>"
                       "<style>body{font-family:sans-serif}td{padding:0 .5em;font-size:small}</style></head>"
                       f"<body><h1>{title}</h1>{svg}<h2>Events</h2><table><tr><th>s</th><th>kind</th><th>ns</th>"
                       f"<th>message</th></tr>{rows}</table></body></html>\n", encoding="utf-8")
    else:
        fig.savefig(out, dpi=100)
    return out
