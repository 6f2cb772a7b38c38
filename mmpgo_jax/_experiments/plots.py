"""Figures for the CLI (``solve --plot``, ``demo``, ``bench``): trajectories and convergence.

Everything is drawn on :class:`matplotlib.figure.Figure` objects with an explicit Agg canvas, so
importing this module neither imports :mod:`matplotlib.pyplot` nor switches the process-wide
backend (a Jupyter session keeps its own).  PNG files are rendered into memory and written with
:func:`~mmpgo_jax._io.atomic.atomic_write`, so a reader never sees a half-written image.

Objective values are f = 2F (the paper's Tables I/II, docs/conventions.md §2).  Relative suboptimality is
(f - f*)/f*; values <= 0 (an iterate at or below the reference f*, which happens when f* is itself
only a tolerance-converged estimate) cannot be drawn on a log axis and are shown at a floor one
decade below the smallest positive value, which the axis label says.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from .._io.atomic import atomic_write

__all__ = [
    "RELATIVE_FLOOR",
    "plot_convergence",
    "plot_trajectory",
    "printed_half_unit",
    "robot_colors",
    "save_convergence_figure",
    "save_solve_figure",
]

RELATIVE_FLOOR = 1e-12  # lowest level at which (f - f*)/f* <= 0 is drawn on the log axis
MAX_LEGEND_ROBOTS = 10
_TOLERANCES = (1e-2, 1e-3, 1e-4)


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def _new_figure(figsize) -> Figure:
    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save_png(fig: Figure, path, dpi: int = 120) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    with atomic_write(path, "wb") as fh:
        fh.write(buf.getvalue())


def robot_colors(num_robots: int) -> np.ndarray:
    """(A, 4) RGBA colours: tab10 up to 10 robots, tab20 up to 20, else samples of turbo."""
    from matplotlib import colormaps

    if num_robots <= 10:
        return np.asarray(colormaps["tab10"].colors)[:num_robots]
    if num_robots <= 20:
        return np.asarray(colormaps["tab20"].colors)[:num_robots]
    return colormaps["turbo"](np.linspace(0.05, 0.95, num_robots))


def _f_array(h: Any) -> np.ndarray:
    """f values from a History (``.f``), a SolveResult (``.history.f``) or an array."""
    if hasattr(h, "history"):
        h = h.history
    f = getattr(h, "f", h)
    return np.asarray(f, dtype=np.float64).reshape(-1)


def _runs(idx: np.ndarray) -> list[np.ndarray]:
    """Split sorted pose indices into runs of consecutive indices (one polyline each)."""
    if len(idx) == 0:
        return []
    breaks = np.flatnonzero(np.diff(idx) != 1) + 1
    return np.split(idx, breaks)


def _is_3d(ax) -> bool:
    return getattr(ax, "name", "") == "3d"


# --------------------------------------------------------------------------------------------
# trajectory
# --------------------------------------------------------------------------------------------


def _draw_segments(ax, segs, three_d: bool, **style):
    """Line segments (k, 2, d) on a 2D or 3D axes."""
    if three_d:
        from mpl_toolkits.mplot3d.art3d import Line3DCollection

        ax.add_collection3d(Line3DCollection(segs[..., :3], **style))
    else:
        ax.add_collection(LineCollection(segs[..., :2], **style))


def plot_trajectory(ax, graph, poses, robot_of_pose, *, inter_robot_edges: bool = True, legend: bool = True,
                    outliers=None):
    """Draw the positions of ``poses`` as one polyline per robot, coloured by robot.

    ``ax`` is a 2D axes for d = 2 and a 3D axes (``projection="3d"``) for d = 3 (a 2D axes with 3D
    poses shows the x-y top view).  Consecutive pose indices owned by the same robot are joined;
    inter-robot edges (measurements between poses of different robots) are drawn as thin dashed
    black lines.  ``outliers`` (m,) bool: edges a robust loss rejected, drawn as thin solid red
    lines (and not among the inter-robot edges).  The legend lists at most 10 robots (then "…").
    Axis units are metres.
    """
    t = np.asarray(poses.t, dtype=np.float64)
    n, d = t.shape
    rop = np.asarray(robot_of_pose).reshape(-1)
    if rop.shape != (n,):
        raise ValueError(f"robot_of_pose must have shape ({n},), got {rop.shape}")
    three_d = _is_3d(ax) and d >= 3
    robots = np.unique(rop)
    colors = robot_colors(int(robots.max()) + 1 if len(robots) else 0)
    lw = 1.2 if n < 2000 else 0.8

    handles = []
    for a in robots:
        idx = np.flatnonzero(rop == a)
        for run in _runs(idx):
            if len(run) == 1:
                pts = t[run]
                if three_d:
                    ax.plot(pts[:, 0], pts[:, 1], pts[:, 2], ".", color=colors[a], ms=5)
                else:
                    ax.plot(pts[:, 0], pts[:, 1], ".", color=colors[a], ms=5)
            elif three_d:
                ax.plot(t[run, 0], t[run, 1], t[run, 2], "-", color=colors[a], lw=lw)
            else:
                ax.plot(t[run, 0], t[run, 1], "-", color=colors[a], lw=lw)
        label = f"robot {a} ({len(idx)} pose{'' if len(idx) == 1 else 's'})"
        handles.append(Line2D([], [], color=colors[a], lw=2, label=label))

    # start pose
    if three_d:
        ax.scatter(t[:1, 0], t[:1, 1], t[:1, 2], marker="o", s=30, color="k", zorder=5)
    else:
        ax.plot(t[:1, 0], t[:1, 1], "o", color="k", ms=5, zorder=5)
    start = Line2D([], [], marker="o", color="k", ls="", ms=5, label="pose 0")

    inter_handle = outlier_handle = None
    rejected = np.zeros(0 if graph is None else graph.num_edges, bool) if outliers is None else np.asarray(outliers)
    if inter_robot_edges and graph is not None:
        i = np.asarray(graph.i)
        j = np.asarray(graph.j)
        inter = (rop[i] != rop[j]) & ~rejected
        k = int(inter.sum())
        if k:
            # many inter-robot edges (e.g. city10000) would hide the trajectory: draw them fainter
            alpha, ew = (0.6, 0.5) if k < 500 else (0.35, 0.5) if k < 2000 else (0.2, 0.3)
            _draw_segments(ax, np.stack([t[i[inter]], t[j[inter]]], axis=1), three_d, colors="k", linestyles="--",
                           linewidths=ew, alpha=alpha)
            inter_handle = Line2D([], [], color="k", ls="--", lw=0.8, label=f"inter-robot edges ({k})")
    if graph is not None and rejected.any():
        i, j = np.asarray(graph.i)[rejected], np.asarray(graph.j)[rejected]
        _draw_segments(ax, np.stack([t[i], t[j]], axis=1), three_d, colors="tab:red", linewidths=0.5, alpha=0.5)
        outlier_handle = Line2D([], [], color="tab:red", lw=0.8, label=f"rejected edges ({int(rejected.sum())})")

    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    if three_d:
        ax.set_zlabel("z [m]")
        # true proportions, except that no axis is squashed below 30% of the longest one
        lo, hi = t.min(0)[:3], t.max(0)[:3]
        span = hi - lo
        span = np.maximum(span * 1.04, 0.3 * span.max()) if span.max() > 0 else np.ones(3)
        mid = 0.5 * (lo + hi)
        ax.set_xlim(mid[0] - span[0] / 2, mid[0] + span[0] / 2)
        ax.set_ylim(mid[1] - span[1] / 2, mid[1] + span[1] / 2)
        ax.set_zlim(mid[2] - span[2] / 2, mid[2] + span[2] / 2)
        ax.set_box_aspect(tuple(span), zoom=0.9)
    else:
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, lw=0.3, alpha=0.5)

    if legend:
        shown = handles
        if len(handles) > MAX_LEGEND_ROBOTS:
            rest = len(handles) - (MAX_LEGEND_ROBOTS - 1)
            shown = [*handles[:MAX_LEGEND_ROBOTS - 1], Line2D([], [], ls="", label=f"… (+{rest} more robots)")]
        extra = [start] + [h for h in (inter_handle, outlier_handle) if h is not None]
        items = shown + extra
        # below the axes, so that it never hides the trajectory
        ax.legend(handles=items, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.06 if three_d else -0.1),
                  ncol=min(4, len(items)), framealpha=0.85)
    return ax


# --------------------------------------------------------------------------------------------
# convergence
# --------------------------------------------------------------------------------------------


def printed_half_unit(value: float, digits: int) -> float:
    """Half a unit of the last of ``digits`` significant digits: a value printed with that many
    digits lies within this distance of the printed number."""
    if value == 0 or not math.isfinite(value):
        return 0.0
    return 0.5 * 10.0 ** (math.floor(math.log10(abs(value))) - (digits - 1))


def _raw_gap(f: np.ndarray, fstar: float, relative: bool) -> np.ndarray:
    g = np.asarray(f, dtype=np.float64) - fstar
    return g / abs(fstar) if relative else g


def _floor(gaps: list[np.ndarray], fstar: float, relative: bool) -> float:
    """Where values <= 0 are drawn: a power of ten below the smallest positive value, at least
    :data:`RELATIVE_FLOOR` (times |f*| for the absolute gap)."""
    lowest = RELATIVE_FLOOR * (1.0 if relative else max(abs(fstar), np.finfo(float).tiny))
    pos = np.concatenate([np.ravel(g)[np.ravel(g) > 0] for g in gaps]) if gaps else np.zeros(0)
    if len(pos) == 0:
        return lowest
    return max(lowest, 10.0 ** (math.floor(math.log10(pos.min())) - 1))


def _half_units(values: np.ndarray, digits: int | None) -> np.ndarray:
    return np.array([printed_half_unit(float(v), digits) if digits else 0.0 for v in np.ravel(values)])


def _reference_series(label, ks, fs, last, fstar, floor, relative, digits):
    """(label, legend label, iterations, y, yerr) of one set of reference points (see
    :func:`plot_convergence`): the points within the run, their gaps, the rounding bars."""
    outside = [int(k) for k in ks[ks > last]] if last is not None else []
    if last is not None:
        ks, fs = ks[ks <= last], fs[ks <= last]
    name, y, yerr = label, fs, None
    if fstar is not None:
        g = _raw_gap(fs, fstar, relative)
        if digits:
            half = _half_units(fs, digits)
            y = np.maximum(g, floor)
            lower = np.minimum(np.maximum(_raw_gap(fs - half, fstar, relative), floor), y)
            upper = np.maximum(_raw_gap(fs + half, fstar, relative), y)
            yerr = np.vstack([y - lower, upper - y])
            name = f"{label}, ± rounding"
        else:
            keep = g > 0
            ks, y = ks[keep], g[keep]
            if not keep.all():
                name = f"{label}; {int((~keep).sum())} pt(s) ≤ f* not shown"
    if outside:
        name += f"; k = {', '.join(map(str, outside))} after this run"
    return label, name, ks, y, yerr


def plot_convergence(
    ax,
    histories: Mapping[str, Any],
    fstar: float | None,
    relative: bool = True,
    *,
    references: Mapping[str, Mapping[int, float]] | None = None,
    tolerances: bool = True,
    printed_digits: int | None = None,
):
    """Plot convergence curves on ``ax``, one per ``label -> History`` (or f array) in ``histories``.

    * ``fstar`` given, ``relative=True``: (f - f*)/f* on a log axis, with the 1e-2/1e-3/1e-4 levels;
    * ``fstar`` given, ``relative=False``: f - f* on a log axis;
    * ``fstar`` None: f itself (log axis when all values are positive).

    Curve values <= 0 (an iterate at or below the reference f*) are drawn at a floor one decade
    below the smallest positive value (never below :data:`RELATIVE_FLOOR`), and the axis label
    says so.  The iteration axis ends with the longest curve.  ``references`` maps a label to
    ``{iteration: f}`` points (e.g. the paper's table), drawn as markers in the colour of the
    curve whose label is the longest prefix of the reference's label (e.g. "MM (paper)" takes the
    colour of "MM"), else black; points past the longest curve are left out and named in the
    legend.  With ``printed_digits`` (e.g. 4 for the paper's tables) a reference value is a
    rounded print: every point is drawn, with a bar over the values it may stand for (± half a
    unit of its last digit); a print at or below f* sits at the floor, its bar reaching up to
    the largest gap it allows.  Without it, points at or below f* are left out (the legend says
    how many).  Sets of reference points are drawn slightly apart in x, so that coinciding
    points (e.g. MM and AMM both printed as f*) stay visible.
    """
    curves = {label: _f_array(h) for label, h in histories.items()}
    refs = {}
    for label, pts in (references or {}).items():
        if pts:
            ks = sorted(pts)
            refs[label] = (np.asarray(ks, dtype=float), np.asarray([pts[k] for k in ks], dtype=np.float64))

    last = max((len(f) - 1 for f in curves.values()), default=None)
    if fstar is None:
        ys = dict(curves)
        floor, clipped_any = None, False
    else:
        fstar = float(fstar)
        raw = {label: _raw_gap(f, fstar, relative) for label, f in curves.items()}
        tops = [_raw_gap(fs + _half_units(fs, printed_digits), fstar, relative) for _, fs in refs.values()]
        floor = _floor([*raw.values(), *tops], fstar, relative)
        at_floor = [*raw.values()] + ([_raw_gap(fs[ks <= last], fstar, relative) for ks, fs in refs.values()]
                                      if printed_digits and last is not None else [])
        clipped_any = any(bool(np.any(g <= 0)) for g in at_floor)
        ys = {label: np.maximum(g, floor) for label, g in raw.items()}
    series = [_reference_series(label, ks, fs, last, fstar, floor, relative, printed_digits)
              for label, (ks, fs) in refs.items()]

    colors = {}
    for label, y in ys.items():
        (line,) = ax.plot(np.arange(len(y)), y, lw=1.5, label=label)
        colors[label] = line.get_color()
    markers = "osD^v"
    for n_ref, (prefix, label, ks, y, yerr) in enumerate(series):
        color = max(((len(lab), c) for lab, c in colors.items() if prefix.startswith(lab)), default=(0, "k"))[1]
        style = dict(fmt=markers[n_ref % len(markers)], ms=6, mfc="none", mew=1.5, color=color, label=label)
        dodge = (n_ref - (len(series) - 1) / 2) * 0.01 * (last or 0)  # side by side where points coincide
        ax.errorbar(ks + dodge, y, yerr=yerr, capsize=3, **style)
    if last:
        ax.set_xlim(0, 1.02 * last)  # a little room for markers at the last iteration
    ax.set_xlabel("iteration")
    if fstar is None:
        ax.set_ylabel("f = 2F")
        if all(np.all(f > 0) for f in curves.values()):
            ax.set_yscale("log")
    else:
        ax.set_yscale("log")
        floor_note = f"\n(values ≤ 0 shown at {floor:.0e})" if clipped_any else ""
        if relative:
            ax.set_ylabel("relative suboptimality (f − f*) / f*" + floor_note)
            if tolerances:
                for tol in _TOLERANCES:
                    ax.axhline(tol, color="0.6", lw=0.6, ls=":", zorder=0)
        else:
            ax.set_ylabel("suboptimality f − f*" + floor_note)
    ax.grid(True, which="major", lw=0.3, alpha=0.5)
    if ys or series:
        ax.legend(fontsize=8, loc="best", framealpha=0.85)
    return ax


def save_convergence_figure(
    path,
    curves: Mapping[str, Any],
    fstar: float | None,
    title: str = "",
    *,
    references: Mapping[str, Mapping[int, float]] | None = None,
    fstar_label: str | None = None,
    printed_digits: int | None = None,
) -> None:
    """PNG comparing convergence curves (e.g. MM vs AMM): f − f* and (f − f*)/f*, log scale.

    Without ``fstar`` a single panel shows f.  ``references``, ``printed_digits``: see
    :func:`plot_convergence`.
    ``fstar_label`` describes the reference in the title (default "f* = <value>"; e.g.
    "f* = 61.1541 (centralized)").
    """
    if fstar is None:
        fig = _new_figure((6.5, 4.5))
        ax = fig.add_subplot(1, 1, 1)
        plot_convergence(ax, curves, None, references=references, printed_digits=printed_digits)
        ax.set_title("objective f")
    else:
        fig = _new_figure((12, 4.6))
        ax1 = fig.add_subplot(1, 2, 1)
        ax2 = fig.add_subplot(1, 2, 2)
        plot_convergence(ax1, curves, fstar, relative=False, references=references, printed_digits=printed_digits)
        plot_convergence(ax2, curves, fstar, relative=True, references=references, printed_digits=printed_digits)
        ax1.set_title("suboptimality gap f − f*")
        ax2.set_title("relative suboptimality gap (f − f*) / f*")
    sup = title
    if fstar is not None:
        fstar_label = fstar_label or f"f* = {float(fstar):.9g}"
        sup = f"{title}  —  {fstar_label}" if title else fstar_label
    if sup:
        fig.suptitle(sup)
    _save_png(fig, path)


def save_solve_figure(path, graph, result, *, fstar: float | None = None, title: str = "",
                      fstar_label: str = "f*") -> None:
    """One PNG for a :class:`~mmpgo_jax.SolveResult`: trajectory (left), convergence (right).

    Left: the estimate's positions coloured by robot (top view for 2D, 3D axes for 3D) with the
    inter-robot edges, and in red the edges a robust loss rejected.  Right: f vs iteration and,
    when ``fstar`` is given, (f − f*)/f* below it.
    ``fstar_label`` names the reference in the legend and the gap's title (e.g. "certified f*",
    :attr:`~mmpgo_jax.FStarReference.label`).
    """
    d = int(np.asarray(result.poses.t).shape[-1])
    rop = np.asarray(result.partition.robot_of_pose)
    fig = _new_figure((13, 6.2))
    gs = fig.add_gridspec(2, 2, width_ratios=(1.25, 1.0))
    if d >= 3:
        import mpl_toolkits.mplot3d  # noqa: F401  (registers the 3d projection)

        ax_t = fig.add_subplot(gs[:, 0], projection="3d")
    else:
        ax_t = fig.add_subplot(gs[:, 0])
    plot_trajectory(ax_t, graph, result.poses, rop, outliers=getattr(result, "outliers", None))
    cfg = getattr(result, "config", None)
    method = f"{cfg.method.upper()}-PGO" if cfg is not None else "estimate"
    A = getattr(result.partition, "num_robots", len(np.unique(rop)))
    ax_t.set_title(f"{method} estimate, {A} robots, {result.poses.t.shape[0]} poses")

    label = method if cfg is None or cfg.method != "amm" else f"{method} (restart={cfg.restart})"
    f = _f_array(result)
    ax_f = fig.add_subplot(gs[:, 1]) if fstar is None else fig.add_subplot(gs[0, 1])
    plot_convergence(ax_f, {label: f}, None)
    ax_f.set_yscale("linear")
    if fstar is not None:
        ax_f.axhline(fstar, color="k", ls="--", lw=0.8, label=f"{fstar_label} = {fstar:.10g}")
        ax_f.legend(fontsize=8, loc="best")
        lo = min(float(fstar), float(f.min()))
        hi = float(f.max())
        pad = 0.05 * (hi - lo if hi > lo else max(abs(hi), 1.0))
        ax_f.set_ylim(lo - pad, hi + pad)
    ax_f.set_title(f"objective f = 2F: {f[0]:.6g} → {f[-1]:.6g} in {len(f) - 1} iterations")
    if fstar is not None:
        ax_g = fig.add_subplot(gs[1, 1], sharex=ax_f)
        plot_convergence(ax_g, {label: f}, fstar, relative=True)
        gap = (f[-1] - fstar) / abs(fstar)
        ax_g.set_title(f"relative gap to the {fstar_label} after {len(f) - 1} iterations: {gap:.3e}")
    if title:
        fig.suptitle(title)
    _save_png(fig, path)
