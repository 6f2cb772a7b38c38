"""Figures for the CLI (``solve --plot``, ``demo``, ``bench``): trajectories and convergence.

Everything is drawn on :class:`matplotlib.figure.Figure` objects with an explicit Agg canvas, so
importing this module neither imports :mod:`matplotlib.pyplot` nor switches the process-wide
backend (a Jupyter session keeps its own).  Files are written in the format their extension
names (any matplotlib writes: png, jpg, pdf, svg, ...; :func:`check_figure_path` refuses the
others), rendered into memory and written with :func:`~mmpgo_jax._io.atomic.atomic_write`, so a
reader never sees a half-written image.

Objective values are f = 2F (the paper's Tables I/II, docs/conventions.md §2).  Relative suboptimality is
(f - f*)/f*; values <= 0 (an iterate at or below the reference f*, which happens when f* is itself
only a tolerance-converged estimate) cannot be drawn on a log axis and are shown at a floor one
decade below the smallest positive value, which the axis label says.
"""

from __future__ import annotations

import functools
import io
import math
import os
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
    "check_figure_path",
    "draw_trajectory",
    "plot_convergence",
    "plot_trajectory",
    "printed_half_unit",
    "robot_colors",
    "save_convergence_figure",
    "save_figure",
    "save_solve_figure",
    "solve_figure",
    "solve_start",
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


@functools.cache
def _write_error(fmt: str) -> str | None:
    """Why matplotlib cannot write ``fmt`` here (None: it can), found by rendering a small figure
    with text: some formats need an outside tool (pgf: a LaTeX installation) that the list of
    supported extensions does not check.  Cached: one probe per format and process."""
    probe = _new_figure((1, 1))
    probe.text(0.5, 0.5, "f*")
    try:
        probe.savefig(io.BytesIO(), format=fmt)
    except Exception as err:  # whatever the backend raises (RuntimeError, OSError, ...) means "not here"
        return str(err)
    return None


def check_figure_path(path, what: str = "figure") -> str:
    """The format a figure is written to ``path`` in: its extension (any matplotlib writes, e.g.
    png, jpg, pdf, svg), or png for a name without one.  Raises ValueError, one line starting
    with ``what`` and ``path`` (e.g. "--plot x.xyz: ..."), for an extension matplotlib does not
    know or cannot write here; call it before a long computation whose result it will draw."""
    ext = os.path.splitext(os.fspath(path))[1][1:].lower()
    if not ext:
        return "png"
    supported = sorted(FigureCanvasAgg.get_supported_filetypes())
    if ext not in supported:
        raise ValueError(f"{what} {os.fspath(path)}: unsupported extension '.{ext}' "
                         f"(matplotlib writes {', '.join(supported)})")
    reason = _write_error(ext)
    if reason is not None:
        raise ValueError(f"{what} {os.fspath(path)}: matplotlib cannot write .{ext} files here: {reason}")
    return ext


def save_figure(fig: Figure, path, dpi: int = 120) -> None:
    """Write ``fig`` in the format of ``path``'s extension (:func:`check_figure_path`), atomically:
    rendered into memory first, so that a reader never sees a half-written file."""
    fmt = check_figure_path(path)
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt, dpi=dpi)
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

# Edges other than odometry, drawn thin over the trajectories (under them, the short ones between
# revisits of a place would be hidden); black for inter-robot edges, which no robot colour
# (tab10/tab20/turbo) is.  (label, colour, line style, mask key)
_EDGE_STYLES = (("loop closures", "0.45", "-", "loop"), ("inter-robot edges", "k", "--", "inter"),
                ("rejected edges", "tab:red", "-", "rejected"))
_RINGED_EDGES = 100


def _draw_segments(ax, segs, three_d: bool, **style):
    """Line segments (k, 2, d) on a 2D or 3D axes."""
    if three_d:
        from mpl_toolkits.mplot3d.art3d import Line3DCollection

        ax.add_collection3d(Line3DCollection(segs[..., :3], **style))
    else:
        ax.add_collection(LineCollection(segs[..., :2], **style), autolim=False)


def _edge_masks(graph, rop: np.ndarray, outliers) -> dict[str, np.ndarray]:
    """(m,) masks of the edges drawn as lines: loop closures (same robot, pose indices not
    consecutive: consecutive ones are the odometry the trajectory line already draws),
    inter-robot edges and the edges a robust loss rejected (drawn only as those)."""
    i, j = np.asarray(graph.i), np.asarray(graph.j)
    rejected = np.zeros(len(i), bool) if outliers is None else np.asarray(outliers, bool)
    same = rop[i] == rop[j]
    return {"loop": same & (np.abs(i - j) != 1) & ~rejected, "inter": ~same & ~rejected, "rejected": rejected}


def _coords(t: np.ndarray, idx, three_d: bool) -> tuple:
    """The x, y (and z on a 3D axes) columns of the positions ``t[idx]``, for ``ax.plot``."""
    return tuple(t[idx, c] for c in range(3 if three_d else 2))


def _draw_edges(ax, graph, t, rop, three_d, *, outliers, shown) -> list[Line2D]:
    """The edges of the classes in ``shown`` (keys of :func:`_edge_masks`) as thin lines, fainter
    the more there are (thousands, e.g. city10000's, would hide the trajectory); their legend items.
    Up to :data:`_RINGED_EDGES` of a class get a small ring at each end too: an edge between two
    visits of one place is shorter than the trajectory line is wide (MIT's), and the rings still
    show where it is (more rings would bury the trajectory: sphere2500's 459 inter-robot edges)."""
    i, j = np.asarray(graph.i), np.asarray(graph.j)
    masks = _edge_masks(graph, rop, outliers)
    handles = []
    for label, color, ls, key in _EDGE_STYLES:
        k = int(masks[key].sum())
        if key not in shown or k == 0:
            continue
        alpha, lw = (0.8, 0.7) if k < 500 else (0.45, 0.5) if k < 2000 else (0.25, 0.35)
        segs = np.stack([t[i[masks[key]]], t[j[masks[key]]]], axis=1)
        _draw_segments(ax, segs, three_d, colors=color, linestyles=ls, linewidths=lw, alpha=alpha, zorder=3)
        ring = dict(marker="o", ms=3.5, mfc="none", mec=color, mew=0.7) if k <= _RINGED_EDGES else {}
        if ring:
            ends = np.unique(np.concatenate([i[masks[key]], j[masks[key]]]))
            ax.plot(*_coords(t, ends, three_d), ls="", alpha=alpha, zorder=3, **ring)
        handles.append(Line2D([], [], color=color, ls=ls, lw=0.8, label=f"{label} ({k})", **ring))
    return handles


def _draw_robots(ax, t, rop, three_d) -> list[Line2D]:
    """One polyline per run of consecutive pose indices of a robot (its odometry chain), coloured
    by robot, and pose 0 as a black dot; the legend items (robots, then pose 0)."""
    robots = np.unique(rop)
    colors = robot_colors(int(robots.max()) + 1 if len(robots) else 0)
    lw = 1.2 if len(t) < 2000 else 0.8
    handles = []
    for a in robots:
        idx = np.flatnonzero(rop == a)
        for run in _runs(idx):
            ax.plot(*_coords(t, run, three_d), "." if len(run) == 1 else "-", color=colors[a], lw=lw, ms=5, zorder=2)
        poses = f"{len(idx)} pose{'s' * (len(idx) != 1)}"
        handles.append(Line2D([], [], color=colors[a], lw=2, label=f"robot {a} ({poses})"))
    if three_d:
        ax.scatter(*_coords(t, slice(0, 1), three_d), marker="o", s=30, color="k", zorder=5)
    else:
        ax.plot(*_coords(t, slice(0, 1), three_d), "o", color="k", ms=5, zorder=5)
    return [*handles, Line2D([], [], marker="o", color="k", ls="", ms=5, label="pose 0")]


def _fit_axes(ax, t, three_d) -> None:
    """Limits from the positions with a small margin, equal scale on every axis; 3D poses on a 2D
    axes are seen from above, which the x label says."""
    ax.set_xlabel("x [m]" if three_d or t.shape[1] < 3 else "x [m]   (x-y top view of the 3D poses)")
    ax.set_ylabel("y [m]")
    if three_d:
        ax.set_zlabel("z [m]")
        lo, hi = t.min(0)[:3], t.max(0)[:3]
        span = hi - lo
        # true proportions, except that no axis is squashed below 30% of the longest one
        span = np.maximum(span * 1.04, 0.3 * span.max()) if span.max() > 0 else np.ones(3)
        mid = 0.5 * (lo + hi)
        ax.set_xlim(mid[0] - span[0] / 2, mid[0] + span[0] / 2)
        ax.set_ylim(mid[1] - span[1] / 2, mid[1] + span[1] / 2)
        ax.set_zlim(mid[2] - span[2] / 2, mid[2] + span[2] / 2)
        ax.set_box_aspect(tuple(span), zoom=0.9)
        return
    # autoscaled to the positions (the lines drawn) with a small margin; fixed limits would fight the
    # equal aspect, which widens the shorter side to the box's shape
    ax.margins(0.03)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, lw=0.3, alpha=0.5)


def _legend_items(handles: list[Line2D]) -> list[Line2D]:
    """Robots first, at most :data:`MAX_LEGEND_ROBOTS` of them (then "…"), then the rest."""
    robots = [h for h in handles if h.get_label().startswith("robot ")]
    rest = [h for h in handles if h not in robots]
    if len(robots) > MAX_LEGEND_ROBOTS:
        more = len(robots) - (MAX_LEGEND_ROBOTS - 1)
        robots = [*robots[: MAX_LEGEND_ROBOTS - 1], Line2D([], [], ls="", label=f"… (+{more} more robots)")]
    return robots + rest


def draw_trajectory(ax, graph, poses, robot_of_pose, *, inter_robot_edges: bool = True,
                    loop_closures: bool = True, outliers=None) -> list[Line2D]:
    """:func:`plot_trajectory` without the legend; returns its items (for a legend of its own)."""
    t = np.asarray(poses.t, dtype=np.float64)
    rop = np.asarray(robot_of_pose).reshape(-1)
    if rop.shape != (len(t),):
        raise ValueError(f"robot_of_pose must have shape ({len(t)},), got {rop.shape}")
    three_d = _is_3d(ax) and t.shape[1] >= 3
    handles = _draw_robots(ax, t, rop, three_d)
    if graph is not None:
        shown = {"rejected"} | ({"inter"} if inter_robot_edges else set()) | ({"loop"} if loop_closures else set())
        handles += _draw_edges(ax, graph, t, rop, three_d, outliers=outliers, shown=shown)
    _fit_axes(ax, t, three_d)
    return _legend_items(handles)


def plot_trajectory(ax, graph, poses, robot_of_pose, *, inter_robot_edges: bool = True, legend: bool = True,
                    outliers=None, loop_closures: bool = True):
    """Draw the positions of ``poses`` as one polyline per robot, coloured by robot.

    ``ax`` is a 2D axes for d = 2 and a 3D axes (``projection="3d"``) for d = 3 (a 2D axes with 3D
    poses shows the x-y top view, and its x label says so).  Consecutive pose indices owned by the
    same robot are joined (the odometry); the other edges of ``graph`` are thin lines over them
    (with rings at their ends when there are few): loop closures (within a robot) grey,
    inter-robot edges (measurements between poses of different robots) dashed black.  ``outliers``
    (m,) bool: edges a robust loss rejected, drawn as thin red lines (and not among the others).
    The legend, below the axes, lists at most 10 robots (then "…").  Axis units are metres; limits fit the positions.
    """
    handles = draw_trajectory(ax, graph, poses, robot_of_pose, inter_robot_edges=inter_robot_edges,
                              loop_closures=loop_closures, outliers=outliers)
    if legend:  # below the axes, so that it never hides the trajectory
        ax.legend(handles=handles, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.06 if _is_3d(ax) else -0.1),
                  ncol=min(4, len(handles)), framealpha=0.85)
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


def _draw_tolerances(ax) -> None:
    """The 1e-2 / 1e-3 / 1e-4 levels of (f − f*)/f*, each labelled at its left end, where the
    curves, which start high, seldom are."""
    for tol in _TOLERANCES:
        ax.axhline(tol, color="0.5", lw=0.7, ls=":", zorder=0)
        ax.text(0.01, tol, f"{tol:.0e}".replace("e-0", "e-"), transform=ax.get_yaxis_transform(), ha="left",
                va="bottom", fontsize=8, color="0.3", bbox=dict(fc="white", ec="none", alpha=0.7, pad=0.5))


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

    * ``fstar`` given, ``relative=True``: (f - f*)/f* on a log axis, with the 1e-2/1e-3/1e-4 levels
      (labelled; ``tolerances=False``: without them);
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
                _draw_tolerances(ax)
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
    """A figure comparing convergence curves (e.g. MM vs AMM): f − f* and (f − f*)/f*, log scale;
    in the format of ``path``'s extension (:func:`check_figure_path`).

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
    save_figure(fig, path)


def solve_start(graph, robot_of_pose, *, init=None, initial=None, fixed=None, frame=None, loss="l2",
                loss_scale=None, gnc=None, **_solver_options):
    """The poses a ``solve(graph, robot_of_pose, **options)`` starts from, in the frame of its result,
    computed without solving (a solve's own start is ``SolveResult.start``).  Takes ``solve``'s
    keyword arguments; those that do not choose the start (method, iterations, ...) are ignored."""
    from .._init.start import initialize
    from .._mm.robust import as_loss
    from .._solve.build import start_for
    from .._solve.result import output_frame

    method, options = start_for(init, as_loss(loss, loss_scale, gnc))
    start = initialize(graph, method, initial=initial, robots=np.asarray(robot_of_pose), fixed=fixed, **options)
    return output_frame(start, fixed, frame)


def _benchmark_name(name: str, graph) -> str:
    """``name`` (a file name) with the registered benchmark's name, e.g. "MITb (MIT.g2o)", when the
    registry knows the file and the graph has its size; ``name`` itself otherwise."""
    from .._io.datasets import benchmark_info

    info = benchmark_info(name) if name else None
    if info is None or info.num_poses != graph.num_poses:
        return name
    return info.name if info.name.lower() == os.path.splitext(os.path.basename(name))[0].lower() \
        else f"{info.name} ({name})"


def _method_label(result) -> str:
    """The solver's label as tables print it ("AMM-PGO (restart=adaptive)", "RBCD++", "DGS")."""
    from .._solve.methods import method_label, method_name

    solver = getattr(result, "solver", None)
    if solver is None:
        return "estimate"
    label = method_label(method_name(solver))
    restart = getattr(getattr(solver, "config", None), "restart", None)
    return f"{label} (restart={restart})" if method_name(solver) == "amm" and restart else label


def _fit_gap_limits(ax, f: np.ndarray, fstar: float) -> None:
    """y limits of the relative gap panel: the curve and the three tolerance levels, with room."""
    g = _raw_gap(f, fstar, True)
    g = np.maximum(g, _floor([g], fstar, True))
    lo, hi = min(float(g.min()), _TOLERANCES[-1]), max(float(g.max()), _TOLERANCES[0])
    ax.set_ylim(lo / 3, hi * 3)


def _convergence_panel(ax, result, fstar, fstar_label) -> None:
    """(f − f*)/f* against the iteration, with the tolerance levels; f itself without ``fstar``."""
    f = _f_array(result)
    plot_convergence(ax, {_method_label(result): f}, fstar, relative=True)
    k = len(f) - 1
    if fstar is None:
        ax.set_title(f"objective f = 2F: {f[0]:.6g} → {f[-1]:.6g} in {k} iterations\n(no reference f* for this file)",
                     fontsize=10)
        return
    _fit_gap_limits(ax, f, fstar)
    gap = (f[-1] - fstar) / abs(fstar)
    ax.set_title(f"relative gap to the {fstar_label} = {fstar:.10g}\n{gap:.3e} after {k} iterations", fontsize=10)


def solve_figure(graph, result, *, start=None, fstar: float | None = None, title: str = "",
                 fstar_label: str = "f*") -> Figure:
    """The figure of :func:`save_solve_figure` (drawn, not written)."""
    f = _f_array(result)
    rop = np.asarray(result.partition.robot_of_pose)
    panels = [("start", start, f[0])] if start is not None else []
    panels.append(("result", result.poses, f[-1]))
    fig = _new_figure((5.6 * len(panels) + 5.8, 6.4))
    gs = fig.add_gridspec(1, len(panels) + 1)
    outliers = getattr(result, "outliers", None)
    for col, (name, poses, value) in enumerate(panels):
        ax = fig.add_subplot(gs[0, col])
        handles = draw_trajectory(ax, graph, poses, rop, outliers=outliers)
        ax.set_title(f"{name}: f = {value:.7g}", fontsize=10)
    _convergence_panel(fig.add_subplot(gs[0, -1]), result, fstar, fstar_label)
    fig.legend(handles=handles, loc="outside lower center", ncol=min(7, len(handles)), fontsize=8, framealpha=0.85)
    A = getattr(result.partition, "num_robots", len(np.unique(rop)))
    sub = f"{_method_label(result)}, {A} robots, {graph.num_poses} poses, {graph.num_edges} edges"
    head = _benchmark_name(title, graph)
    fig.suptitle(f"{head}\n{sub}" if head else sub)
    return fig


def save_solve_figure(path, graph, result, *, start=None, fstar: float | None = None, title: str = "",
                      fstar_label: str = "f*") -> None:
    """One figure of a :class:`~mmpgo_jax.SolveResult`, written in the format of ``path``'s
    extension (:func:`check_figure_path`: png, jpg, pdf, svg, ...).

    Side by side: the ``start`` poses (when given, e.g. :func:`solve_start`), the result, both
    coloured by robot with the loop closures, the inter-robot edges and, in red, the edges a robust
    loss rejected (2D: the plane; 3D: the x-y top view); then (f − f*)/f* against the iteration
    with the 1e-2 / 1e-3 / 1e-4 levels when ``fstar`` is given, else f.  ``fstar_label`` names the
    reference (e.g. "certified f*", :attr:`~mmpgo_jax.FStarReference.label`).  ``title``: the
    file's name (the registered benchmark's name is added when the registry knows it) or any text.
    """
    check_figure_path(path)  # before drawing
    save_figure(solve_figure(graph, result, start=start, fstar=fstar, title=title, fstar_label=fstar_label), path)
