"""What a solve prints and writes, shared by ``solve``, ``optimum`` and the sharded solve.

The output files (--out, --tum, --history, --plot, ...) are checked before anything is read or
solved (:func:`check_outputs`: folder exists and is writable, not a directory, no two the same
file), and written all-or-none: each to a temporary file, renamed into place only when all
succeeded. Writing through a symbolic link replaces the link's target and keeps the link.
"""

from __future__ import annotations

import contextlib
import os
from typing import TYPE_CHECKING

import numpy as np

from .._core.messages import join_items
from .errors import CLIError

if TYPE_CHECKING:
    from .inputs import LoadedInput

_OUTPUTS = (("out", "--out"), ("tum", "--tum"), ("history", "--history"), ("plot", "--plot"),
            ("edge_weights", "--edge-weights"), ("checkpoint", "--checkpoint"))


def check_outputs(args) -> None:
    """Refuse unusable output paths before any work: for each of --out, --tum, --history, --plot
    that is set, its folder must exist and be writable, the path must not be a directory (nor a
    device or other non-regular file), and no two may be the same file (symbolic links resolved)."""
    from .._io.atomic import resolve_target
    from .robots import check_output_dirs

    check_output_dirs(args)
    seen: dict = {}
    for attr, flag in _OUTPUTS:
        value = getattr(args, attr, None)
        if value is None:
            continue
        value = os.fspath(value)
        if value == "":
            raise CLIError(f"{flag}: empty file name")
        target = resolve_target(value)
        shown = f"{flag} {value}"
        if os.path.isdir(target):
            raise CLIError(f"{shown}: is a directory")
        if os.path.exists(target) and not os.path.isfile(target):
            raise CLIError(f"{shown}: not a regular file (outputs replace the file as a whole)")
        folder = os.path.dirname(target)
        named = folder if os.path.islink(value) else (os.path.dirname(value) or ".")
        if not os.path.exists(folder):
            raise CLIError(f"{shown}: folder {named!r} does not exist")
        if not os.path.isdir(folder):
            raise CLIError(f"{shown}: {named!r} is not a folder")
        if not os.access(folder, os.W_OK | os.X_OK):
            raise CLIError(f"{shown}: folder {named!r} is not writable")
        keys = [target]
        with contextlib.suppress(OSError):
            st = os.stat(target)
            keys.append((st.st_dev, st.st_ino))  # hard links to one file
        for key in keys:
            if key in seen:
                raise CLIError(f"{seen[key]} and {shown}: the same file")
            seen[key] = shown
    if getattr(args, "plot", None):  # an image format matplotlib cannot write is refused before the solve
        from .._experiments.plots import check_figure_path

        check_figure_path(args.plot, "--plot")


def print_certificate(data: LoadedInput, poses, *, hint: bool, graph=None) -> None:
    """SE-Sync's certificate of ``poses`` on ``graph`` (default the file's graph)."""
    from .._experiments.certificate import certify

    if data.fixed is not None and len(data.fixed) > 1:
        print(f"certificate not applicable: {len(data.fixed)} FIX poses constrain the problem "
              "(the dual certificate covers PGO with at most one fixed pose)")
        return
    cert = certify(data.graph if graph is None else graph, poses)
    note = "" if graph is None else " (of the graph without the closures --pcm removed)"
    print(f"certificate {cert.summary()}{note}")
    if hint and not cert.certified:
        print("            (the certificate decides only at a critical point: run to a tight --grad-tol, "
              "e.g. --robots 1)")


def write_estimate(args, data: LoadedInput, poses, inliers=None) -> list[str]:
    """--out (g2o, with the FIX lines), --tum, --tum-dir and --out-dir files of an estimate; returns
    the paths written. ``inliers`` (m,) bool: the edges to write (all when None)."""
    from .._io.g2o import write_g2o, write_tum
    from .._io.multi_robot import write_robot_folder, write_robot_tum

    written = []
    robots = dict(robot_of_pose=data.robot_of_pose, robot_names=data.robot_names, vertex_ids=data.vertex_ids)
    graph, information = data.graph, data.information
    if inliers is not None:  # --drop-outliers
        graph = graph.select_edges(inliers)
        information = None if information is None else np.asarray(information)[inliers]
    if getattr(args, "tum_dir", None):
        written += write_robot_tum(args.tum_dir, poses, **robots)
    if getattr(args, "out_dir", None):
        written += write_robot_folder(args.out_dir, graph, poses, information=information,
                                      fixed=data.fixed_mask, **robots)
    if args.out:
        write_g2o(args.out, graph, poses, vertex_ids=data.vertex_ids, information=information,
                  fixed=data.fixed_mask)
        written.append(args.out)
    if args.tum:
        write_tum(args.tum, poses, vertex_ids=data.vertex_ids)
        written.append(args.tum)
    return written


def finish_solve(args, data: LoadedInput, result, fstar) -> None:
    """After a solve (single- or multi-device): --certify, then the --out/--tum/--history/--plot
    files, all or none (:func:`~mmpgo_jax._io.atomic.atomic_group`). ``fstar``: the
    :class:`~mmpgo_jax.FStarReference` of the plot's gaps, or None."""
    from .._io.atomic import atomic_group

    fstar = comparable_fstar(result, fstar)
    if args.certify:
        prefiltered = getattr(result, "prefiltered", None)
        removed = prefiltered is not None and np.any(prefiltered)
        print_certificate(data, result.poses, hint=True,
                          graph=data.graph.select_edges(~prefiltered) if removed else None)
    keep = result.inliers if getattr(args, "drop_outliers", False) else None
    with atomic_group():
        written = write_estimate(args, data, result.poses, keep)
        if getattr(args, "edge_weights", None):
            write_edge_weights_csv(args.edge_weights, data, result)
            written.append(args.edge_weights)
        if args.history:
            write_history_csv(args.history, result)
            written.append(args.history)
        if args.plot:
            from .._experiments.plots import save_solve_figure

            save_solve_figure(args.plot, data.graph, result, fstar=None if fstar is None else fstar.value,
                              fstar_label="f*" if fstar is None else fstar.label, title=data.path.name,
                              start=result.start)
            written.append(args.plot)
    for path in written:  # only now are they in place
        print(f"wrote {path}")


def _rejected_lines(result, data: LoadedInput | None, mask=None, lead: str = "; ") -> str:
    """"; lines 12, 40 and 3 more of FILE" for the rejected edges (``mask``, default ``~inliers``),
    when they come from one file as read (``lead``: what goes before "lines")."""
    lines = None if data is None or data.keep is not None else getattr(data.g2o, "edge_line", None)
    mask = ~np.asarray(result.inliers) if mask is None else np.asarray(mask)
    rejected = np.flatnonzero(mask)
    if lines is None or len(rejected) == 0 or len(lines) != len(mask):
        return ""
    which = "line" if len(rejected) == 1 else "lines"
    return f"{lead}{which} {join_items(lines[rejected].tolist(), 60)} of {data.path.name}"


def _revisits_text(rounds) -> str:
    """How often a run overruled its distributed robust start and the start was made again without
    the overruled edge (``stats["starts"][k]["revisits"]``)."""
    if not rounds:
        return ""
    kept = sum(r["kept"] for r in rounds)
    return (f"; it overruled its start: made again without {len(rounds)} overruled edge"
            f"{'' if len(rounds) == 1 else 's'} in turn, {kept} of those runs kept (lower f)")


def _trials_text(result, rounds, data, edge: str, what: str) -> str:
    """How many inter-robot closures were tried in turn by a run from the result (``rounds``:
    ``stats["starts"][k]["readmissions"]``, ``edge`` "admitted": a list per round, or ``["removals"]``,
    "removed"), and the lines of those kept; ``what``: the closures tried, in words."""
    if not rounds:
        return ""
    kept = np.zeros(len(result.inliers), bool)
    kept[[e for r in rounds if r["kept"] for e in np.atleast_1d(r[edge])]] = True
    tried = len({int(e) for r in rounds for e in np.atleast_1d(r[edge])})
    count = int(kept.sum())
    tail = (f"{count} of those runs kept" if all(np.size(r[edge]) == 1 for r in rounds) else  # batches
            f"{count} of those kept, by {sum(r['kept'] for r in rounds)} of {len(rounds)} runs")
    return (f"; {tried} closure{'' if tried == 1 else 's'} {what} in turn from its result, {tail} (lower f)"
            f"{_rejected_lines(result, data, kept, lead=': ')}")


def _exchanges_text(result, rounds, data) -> str:
    """How many rounds of the exchange search (``stats["starts"][k]["exchanges"]``: closures the start
    accepted and the run rejected admitted, alone or in exchange for an accepted one, one move or
    several on disjoint robots per round) were tried by a run from the result, and the lines of the
    closures the kept ones admitted and left out."""
    if not rounds:
        return ""
    admitted = np.zeros(len(result.inliers), bool)
    left_out = np.zeros(len(result.inliers), bool)
    kept_moves = [m for r in rounds if r["kept"] for m in r["moves"]]
    admitted[[a for a, _ in kept_moves]] = True
    left_out[[out for _, out in kept_moves if out is not None]] = True
    kept = sum(r["kept"] for r in rounds)
    moves = sum(len(r["moves"]) for r in rounds)
    text = (f"; {len(rounds)} exchange trial{'' if len(rounds) == 1 else 's'} ({moves} "
            f"move{'' if moves == 1 else 's'}) of closures run in turn from its result, {kept} of those runs kept "
            "(lower f)")
    if kept:
        text += f"{_rejected_lines(result, data, admitted, lead=': admitted ')}"
        if left_out.any():
            text += f"{_rejected_lines(result, data, left_out, lead=', left out ')}"
    return text


def _noise_line(result, graph) -> str:
    """A robust run's line on the data's noise against their information matrices: the
    a-posteriori variance factor of the kept edges at the final poses (:func:`~mmpgo_jax.noise_level`)
    and what it means for the loss's scale c."""
    from .._core.noise import noise_level
    from .._mm.robust import chi2_scale

    level = noise_level(graph.select_edges(np.asarray(result.inliers, bool)), result.poses)
    if level.redundancy <= 0:
        return "noise       the kept edges have no redundancy: nothing to compare their information matrices with"
    c = float(result.loss.scale)
    if level.high < 1.0:
        meaning = ("the information matrices overstate the noise, so the scale c is loose for these data "
                   "(an outlier that bends the map slightly can cost less than c^2)")
    elif level.low > 1.0:
        meaning = ("the information matrices understate the noise, so the scale c is tight for these data "
                   f"(correct edges may be rejected; c for the kept edges' noise: --loss-scale "
                   f"{c * np.sqrt(level.low):.4g} or more)")
        if graph.dim == 2 and level.low < 2.0:  # SE-Sync's 2D kappa = I33 alone reads 1-2 (docs/conventions.md §10)
            meaning += ("; in 2D this is also what a file whose angle noise is exactly what its I33 states reads, "
                        "because SE-Sync's kappa = I33 counts the angle twice (that file's 0.99 quantile: "
                        f"--loss-scale {chi2_scale(2, noise='information'):.3g})")
    else:
        meaning = "consistent with the information matrices"
    return (f"noise       kept edges' residuals {level.factor:.3g}x what their information matrices predict "
            f"({100 * level.confidence:g} % interval {level.low:.3g}-{level.high:.3g}, a-posteriori variance "
            f"factor): {meaning}")


def _readmission_line(result, data: LoadedInput | None) -> str:
    """``--readmit``'s line: the loop closures re-admitted, f before and after the search, its
    Newton solves and seconds, and whether the run from there was kept."""
    info = result.stats["readmission"]
    edges = np.asarray(info["readmitted"], np.int64)
    mask = np.zeros(len(result.inliers), bool)
    mask[edges] = True
    kept = "the run from there kept" if info["kept"] else "the first run kept"
    return (f"readmit     {len(edges)} rejected loop closure{'' if len(edges) == 1 else 's'} re-admitted "
            f"(f {info['f_before']:.6f} -> {info['f_after']:.6f} at the kept edges' optimum, {info['solves']} "
            f"Newton solves, {info['seconds']:.1f} s; {kept}){_rejected_lines(result, data, mask)}")


def comparable_fstar(result, fstar):
    """``fstar``, or None when a pre-filter removed edges: f is then that of a smaller graph, and a
    gap to the whole file's f* would mean nothing (it can be negative)."""
    prefiltered = getattr(result, "prefiltered", None)
    return None if prefiltered is not None and np.any(prefiltered) else fstar


def print_summary(result, fstar, data: LoadedInput | None = None) -> None:
    """The result of a solve; ``fstar``: the :class:`~mmpgo_jax.FStarReference` of its gap, or None."""
    fstar = comparable_fstar(result, fstar)
    h = result.history
    split = f" ({data.robots_label})" if data is not None and data.robots_label else ""
    from .._solve.methods import method_label, method_name

    cfg = result.config  # MM / AMM's settings (None for another method)
    restart = f", restart={cfg.restart}" if cfg is not None and cfg.method == "amm" else ""  # MM has none
    label = method_label(method_name(result.solver))
    print(f"method      {label}, {result.partition.num_robots} robots{split}{restart}")
    print(f"iterations  {h.iterations} ({result.stop_description})")
    print(f"f = 2F      {h.f[0]:.6f} -> {h.f[-1]:.6f}")
    if fstar is not None:
        print(f"f*          {fstar.value:.12g} ({fstar.label})")
        print(f"gap         {fstar.gap(h.f[-1]):.3e} = (f - f*)/f*, relative to the {fstar.label}")
    print(f"|grad F|    {h.grad_norm[-1]:.3e}")
    prefiltered = getattr(result, "prefiltered", None)
    if prefiltered is not None:
        stats = result.stats
        print(f"pcm         {stats['pcm_rejected']} of {stats['pcm_closures']} inter-robot loop closures rejected "
              f"before the solve (confidence {stats['pcm_confidence']:g}){_rejected_lines(result, data, prefiltered)}")
        if stats["pcm_components"] > 1:
            print(f"            the graph without them has {stats['pcm_components']} connected components: each "
                  "is solved in its own frame (its first pose at the identity), not placed relative to the others")
    stages = result.stats.get("distributed_chordal")
    if stages is not None:
        how = " / ".join("sparse factors" if f == "sparse" else "dense inverses" for f in stages["factorizations"])
        print(f"start       distributed chordal: {stages['rotation_iterations']} + {stages['translation_iterations']} "
              f"CG iterations (rotations + translations), each robot's Gamma applied as {how}")
    for row in result.stats.get("starts", ()):
        kept = "kept" if row["kept"] else "not kept"
        count = row["rejected"]
        rejected = "" if count is None else f", {count} edge{'' if count == 1 else 's'} rejected"
        finished = ("" if row.get("finished") is None
                    else f" (f = {row['finished']:.6f} before it was finished from its kept edges)")
        polished = ("" if row.get("polished") is None
                    else f"; f = {row['polished']:.6f} before a last run from its kept edges' optimum")
        print(f"start       {row['start']}: f = {row['f']:.6f}{finished}{rejected}, {row['iterations']} iterations, "
              f"{row['seconds']:.2f} s ({kept}){_revisits_text(row.get('revisits', ()))}"
              f"{_trials_text(result, row.get('readmissions', ()), data, 'admitted', 'it had rejected tried')}"
              f"{_trials_text(result, row.get('removals', ()), data, 'removed', 'it had accepted left out')}"
              f"{_exchanges_text(result, row.get('exchanges', ()), data)}"
              f"{polished}")
    if result.loss is not None:
        robust = ~result.inliers if prefiltered is None else ~result.inliers & ~prefiltered
        used = len(result.inliers) - (0 if prefiltered is None else int(prefiltered.sum()))
        gnc = f", GNC {result.stats['gnc_stages']} stages" if bool(result.loss.use_gnc) else ""
        print(f"loss        {result.loss.name} (c = {float(result.loss.scale):.4g}{gnc}): {int(robust.sum())} of "
              f"{used} edges rejected (f = sum of rho(r^2)){_rejected_lines(result, data, robust)}")
    if result.loss is not None and data is not None:
        print(_noise_line(result, data.graph))
    if "readmission" in result.stats:
        print(_readmission_line(result, data))
    if result.accuracy is not None:
        a = result.accuracy
        print(f"ATE         {a.ate:.6g} RMSE, {a.ate_max:.6g} max (positions after rigid alignment); "
              f"rotation {a.rotation_deg:.4g} deg RMSE")
        print(f"RPE         {a.rpe_translation:.6g} translation, {a.rpe_rotation_deg:.4g} deg rotation "
              "(consecutive poses, RMSE)")


def print_timing(result, *, read: float, write: float) -> None:
    """The time line: every phase of the run, in the order it ran."""
    setup = f"initialize {result.initialize_seconds:.2f} s, build {result.build_seconds:.2f} s"
    mode = result.stats.get("compile_mode")
    compiled = f"compile {result.compile_seconds:.2f} s" + (f" ({mode})" if mode in ("fast", "optimized") else "")
    print(f"time        read {read:.2f} s, {setup}, {compiled}, "
          f"iterations {result.solve_seconds:.2f} s ({result.ms_per_iteration:.2f} ms/iteration), write {write:.2f} s")


def write_edge_weights_csv(path, data: LoadedInput, result) -> None:
    """One line per edge of a robust solve: original ids i, j, final weight, inlier 0/1; for GTSAM
    symbol keys also their names (i_symbol, j_symbol: "a67" for Symbol('a', 67))."""
    from .._io.atomic import atomic_write
    from .._io.multi_robot import symbol_names

    ids = np.asarray(data.vertex_ids)
    i, j = np.asarray(data.graph.i), np.asarray(data.graph.j)
    names = symbol_names(ids)
    rows = zip(ids[i].tolist(), ids[j].tolist(), result.weights, result.inliers, strict=True)
    lines = [f"{a},{b},{float(w)!r},{int(k)}" for a, b, w, k in rows]
    if names is not None:
        lines = [f"{line},{names[a]},{names[b]}" for line, a, b in zip(lines, i.tolist(), j.tolist(), strict=True)]
    with atomic_write(path) as fh:
        fh.write("i,j,weight,inlier" + (",i_symbol,j_symbol" if names is not None else "") + "\n")
        fh.writelines(line + "\n" for line in lines)


def write_history_csv(path, result) -> None:
    from .._io.atomic import atomic_write

    h = result.history
    with atomic_write(path) as fh:
        fh.write("iteration,f,grad_norm,restarts\n")
        for k in range(len(h.f)):
            fh.write(f"{k},{float(h.f[k])!r},{float(h.grad_norm[k])!r},{int(h.restarts[k].sum())}\n")
